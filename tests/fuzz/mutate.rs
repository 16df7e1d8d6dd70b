//! The mutator: byte flips, random bytes, interesting values, truncations, extensions,
//! duplicated and deleted ranges, and splices of another seed; plus fix-ups that recompute
//! checksums (PNG chunk CRCs) so that mutations reach past them, and an entropy reader for
//! targets that build their input from the bytes (`arbitrary`-style).

use semlook::util::SplitMix64;

/// Values that often sit on a boundary of a length or a count.
const INTERESTING: [u32; 10] = [0, 1, 0x7f, 0x80, 0xff, 0x100, 0x7fff, 0xffff, 0x7fff_ffff, 0xffff_ffff];

/// One to four mutations of `input`; `others` are the seeds a splice may take from.
pub fn mutate(rng: &mut SplitMix64, input: &[u8], others: &[Vec<u8>]) -> Vec<u8> {
    let mut v = input.to_vec();
    for _ in 0..1 + rng.below(4) {
        let n = v.len();
        match rng.below(9) {
            0 if n > 0 => {
                let i = rng.below(n);
                v[i] ^= 1 << rng.below(8);
            }
            1 if n > 0 => {
                let i = rng.below(n);
                v[i] = rng.next_u64() as u8;
            }
            2 if n > 0 => {
                // an interesting value, little- or big-endian, 1, 2 or 4 bytes wide
                let width = [1, 2, 4][rng.below(3)];
                let at = rng.below(n);
                let val = INTERESTING[rng.below(INTERESTING.len())];
                let bytes = if rng.chance(0.5) { val.to_le_bytes() } else { val.to_be_bytes() };
                for (k, b) in bytes.iter().take(width).enumerate() {
                    if let Some(slot) = v.get_mut(at + k) {
                        *slot = *b;
                    }
                }
            }
            3 => v.truncate(rng.below(n + 1)),
            4 => {
                let extra = 1 + rng.below(64);
                v.extend((0..extra).map(|_| rng.next_u64() as u8));
            }
            5 if n > 0 => {
                // duplicate a range in place
                let a = rng.below(n);
                let b = (a + 1 + rng.below(256)).min(n);
                let chunk = v[a..b].to_vec();
                let at = rng.below(v.len() + 1);
                v.splice(at..at, chunk);
            }
            6 if n > 0 => {
                let a = rng.below(n);
                let b = (a + 1 + rng.below(64)).min(n);
                v.drain(a..b);
            }
            7 if !others.is_empty() => {
                // splice: our head, another seed's tail
                let o = &others[rng.below(others.len())];
                let cut = rng.below(v.len() + 1);
                let from = rng.below(o.len() + 1);
                v.truncate(cut);
                v.extend_from_slice(&o[from..]);
            }
            _ if n > 0 => {
                // a run of one byte value
                let a = rng.below(n);
                let b = (a + 1 + rng.below(32)).min(n);
                let byte = [0u8, 0xff, b'0', b'9', b'"', b'[', b'-'][rng.below(7)];
                v[a..b].fill(byte);
            }
            _ => v.push(rng.next_u64() as u8),
        }
    }
    v
}

/// CRC-32 (IEEE), as PNG and zip use it.
pub fn crc32(bytes: &[u8]) -> u32 {
    let mut c = !0u32;
    for &b in bytes {
        c ^= b as u32;
        for _ in 0..8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
        }
    }
    !c
}

/// Recomputes the CRC of every whole PNG chunk, so the decoder reads the mutated data.
pub fn png_fixup(v: &mut [u8]) {
    let mut at = 8;
    while at + 12 <= v.len() {
        let len = u32::from_be_bytes([v[at], v[at + 1], v[at + 2], v[at + 3]]) as usize;
        let Some(end) = (at + 8).checked_add(len).filter(|&e| e + 4 <= v.len()) else { break };
        let crc = crc32(&v[at + 4..end]);
        v[end..end + 4].copy_from_slice(&crc.to_be_bytes());
        at = end + 4;
    }
}

/// Reads choices from fuzz bytes; past the end every read is zero.
pub struct Entropy<'a> {
    bytes: &'a [u8],
    at: usize,
}

impl<'a> Entropy<'a> {
    pub fn new(bytes: &'a [u8]) -> Self {
        Entropy { bytes, at: 0 }
    }
    pub fn byte(&mut self) -> u8 {
        let b = self.bytes.get(self.at).copied().unwrap_or(0);
        self.at += 1;
        b
    }
    pub fn u32(&mut self) -> u32 {
        u32::from_le_bytes([self.byte(), self.byte(), self.byte(), self.byte()])
    }
    /// A number in 0..n (0 for n = 0).
    pub fn below(&mut self, n: usize) -> usize {
        if n == 0 {
            0
        } else {
            self.u32() as usize % n
        }
    }
    pub fn pick<'t, T>(&mut self, items: &'t [T]) -> &'t T {
        &items[self.below(items.len())]
    }
    /// True once in `one_in` reads; never on zero bytes, so all-zero input takes the default
    /// (valid) branch of every choice.
    pub fn chance(&mut self, one_in: u8) -> bool {
        let n = one_in.max(2);
        self.byte() % n == n - 1
    }
}

/// Random bytes, as seeds of the targets that read [`Entropy`].
pub fn random_seeds(seed: u64, count: usize, len: usize) -> Vec<Vec<u8>> {
    let mut rng = SplitMix64::new(seed);
    (0..count).map(|_| (0..len).map(|_| rng.next_u64() as u8).collect()).collect()
}

/// A JSON value changed where the fuzz bytes say: numbers, strings, booleans, nulls, emptied or
/// grown containers, keys dropped.
pub fn json_mutate(e: &mut Entropy, v: &mut serde_json::Value) {
    use serde_json::{json, Value};
    if e.chance(9) {
        *v = match e.below(9) {
            0 => json!(e.u32() as i64 - (1 << 31)),
            1 => json!(*e.pick(&[-1i64, 0, 1, 2, 3, 7, 255, 65536, i64::MAX, i64::MIN])),
            2 => json!(*e.pick(&[0.5f64, -3.25, 1e300, -1e-300, 7.0])),
            3 => json!(*e.pick(&[
                "",
                "day",
                "night",
                "imgs",
                "imgs/db",
                "imgs/q",
                "../",
                "/",
                "synthia",
                "folders",
                "explicit",
                "palette",
                "void",
                "road",
                "\u{e9}t\u{e9}-\u{1f6a6}-\u{5730}\u{56fe}"
            ])),
            4 => json!(e.chance(2)),
            5 => Value::Null,
            6 => json!([]),
            7 => json!({}),
            _ => json!([0, 1, [2, 3], "x"]),
        };
        return;
    }
    match v {
        Value::Array(items) => {
            if !items.is_empty() && e.chance(8) {
                let i = e.below(items.len());
                let dup = items[i].clone();
                items.push(dup);
            }
            for item in items.iter_mut() {
                json_mutate(e, item);
            }
        }
        Value::Object(map) => {
            let keys: Vec<String> = map.keys().cloned().collect();
            for k in keys {
                if e.chance(16) {
                    map.remove(&k);
                } else if let Some(item) = map.get_mut(&k) {
                    json_mutate(e, item);
                }
            }
        }
        _ => {}
    }
}
