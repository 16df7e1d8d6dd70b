//! Borrowed arrays of stored real values: `f32`, or `f16` (IEEE half precision, kept as its bits)
//! that is widened to `f32` as it is read. Maps may store global descriptors and appearance vectors
//! in f16 to halve their size; every computation stays in f32 (a stored f16 value widens exactly).

use half::slice::{HalfBitsSliceExt, HalfFloatSliceExt};
use serde::{Deserialize, Serialize};

/// How a map stores its global descriptors and appearance vectors.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum ValueType {
    /// 4 bytes per value: the encoder's values bit for bit.
    #[default]
    F32,
    /// 2 bytes per value, rounded to nearest (relative error below 2^-11 in the normal range).
    F16,
}

impl ValueType {
    /// Bytes per stored value: 4 or 2.
    pub fn bytes(self) -> usize {
        match self {
            ValueType::F32 => 4,
            ValueType::F16 => 2,
        }
    }
    /// The type's name, "f32" or "f16", as a map's manifest writes it.
    pub fn name(self) -> &'static str {
        match self {
            ValueType::F32 => "f32",
            ValueType::F16 => "f16",
        }
    }
}

/// Largest finite f16 value: stored values beyond it would become infinite.
pub const F16_MAX: f32 = 65504.0;

/// A borrowed run of values of either storage type.
#[derive(Debug, Clone, Copy)]
pub enum Values<'a> {
    /// f32 values.
    F32(&'a [f32]),
    /// f16 bit patterns.
    F16(&'a [u16]),
    /// Vectors stored as their non-zero blocks of int8 values (appearance in a map).
    Blocks(Blocks<'a>),
}

/// Vectors of `dim` values in blocks of `block` (VLAD: one block per centre), stored as the
/// blocks that are not all zero: per stored block its index in the vector, a power-of-two scale
/// (value = q x 2^exponent) and `block` int8 values. Vector v holds stored blocks
/// `offsets[v]..offsets[v + 1]` (indices into `ids`, `exponents` and `values` / `block`).
#[derive(Debug, Clone, Copy)]
pub struct Blocks<'a> {
    /// Values per vector.
    pub dim: usize,
    /// Values per block.
    pub block: usize,
    /// Where each vector's stored blocks start in `ids`, then where the last one's end (vectors + 1
    /// entries).
    pub offsets: &'a [u32],
    /// Per stored block, its index in its vector.
    pub ids: &'a [u8],
    /// Per stored block, its scale exponent e (value = q x 2^e).
    pub exponents: &'a [i8],
    /// The stored blocks' int8 values q, `block` per stored block.
    pub values: &'a [i8],
}

impl<'a> Blocks<'a> {
    /// The number of vectors.
    pub fn vectors(&self) -> usize {
        self.offsets.len().saturating_sub(1)
    }
    /// Vectors `a..b`.
    pub fn vectors_range(&self, a: usize, b: usize) -> Blocks<'a> {
        Blocks { offsets: &self.offsets[a..=b], ..*self }
    }
    /// Writes the vectors, zeros where no block is stored, into `dst` (vectors x dim values). A
    /// stored block whose index or range lies outside is skipped (a damaged segment is refused by
    /// its checks before it is served; reading it must still not panic).
    pub fn write_to(&self, dst: &mut [f32]) {
        dst.fill(0.0);
        let (d, b) = (self.dim, self.block.max(1));
        for v in 0..self.vectors() {
            let (s, e) = (self.offsets[v] as usize, self.offsets[v + 1] as usize);
            for j in s..e.min(self.ids.len()).min(self.exponents.len()) {
                let at = v * d + self.ids[j] as usize * b;
                let (Some(out), Some(q)) = (dst.get_mut(at..at + b), self.values.get(j * b..(j + 1) * b)) else { continue };
                if at + b > (v + 1) * d {
                    continue;
                }
                let scale = exp2(self.exponents[j]);
                for (o, &x) in out.iter_mut().zip(q) {
                    *o = x as f32 * scale;
                }
            }
        }
    }
}

/// 2^e as f32 (exact for the exponents int8 block scales use).
#[inline]
fn exp2(e: i8) -> f32 {
    f32::powi(2.0, e as i32)
}

/// Largest magnitude of a block's int8 values.
pub const BLOCK_Q: f32 = 127.0;

/// The power-of-two scale exponent of a block whose largest magnitude is `max` (> 0): the smallest
/// e with max / 2^e <= 127, so the largest value keeps 7 to 8 significant bits.
fn block_exponent(max: f32) -> i8 {
    let mut e = (max / BLOCK_Q).log2().ceil() as i32;
    // guard the float rounding of log2 at exact powers of two
    while max / (2.0f32).powi(e) > BLOCK_Q {
        e += 1;
    }
    while e > -126 && max / (2.0f32).powi(e - 1) <= BLOCK_Q {
        e -= 1;
    }
    e.clamp(-126, 127) as i8
}

/// Rounds every block of `v` (blocks of `block` values) to the grid blocks are stored on: q x 2^e
/// with int8 q. A vector so rounded is stored and read back exactly ([`to_blocks`]).
pub fn round_to_blocks(v: &mut [f32], block: usize) {
    for chunk in v.chunks_mut(block.max(1)) {
        let max = chunk.iter().fold(0.0f32, |m, x| m.max(x.abs()));
        if !(max > 0.0) || !max.is_finite() {
            continue;
        }
        let scale = exp2(block_exponent(max));
        for x in chunk.iter_mut() {
            // through the integer, as a stored block is read (no negative zero)
            *x = ((*x / scale).round().clamp(-BLOCK_Q, BLOCK_Q) as i8) as f32 * scale;
        }
    }
}

/// Stored blocks of vectors (`dense`, `dim` values each): offsets, block indices, exponents and
/// int8 values. Values not on the block grid are rounded to it ([`round_to_blocks`]); vectors
/// already on it come back exactly. `base` is added to the offsets.
pub fn to_blocks(dense: &[f32], dim: usize, block: usize, base: u32) -> (Vec<u32>, Vec<u8>, Vec<i8>, Vec<i8>) {
    let (mut offsets, mut ids, mut exps, mut vals) = (vec![base], vec![], vec![], vec![]);
    for vector in dense.chunks(dim.max(1)) {
        for (i, chunk) in vector.chunks(block.max(1)).enumerate() {
            let max = chunk.iter().fold(0.0f32, |m, x| m.max(x.abs()));
            if !(max > 0.0) || !max.is_finite() {
                continue;
            }
            let e = block_exponent(max);
            let scale = exp2(e);
            ids.push(i as u8);
            exps.push(e);
            vals.extend(chunk.iter().map(|x| (x / scale).round().clamp(-BLOCK_Q, BLOCK_Q) as i8));
        }
        offsets.push(base + ids.len() as u32);
    }
    (offsets, ids, exps, vals)
}

impl<'a> Values<'a> {
    /// No values.
    pub const EMPTY: Values<'static> = Values::F32(&[]);

    /// The number of values (for blocks: vectors x dim, the zeros included).
    pub fn len(&self) -> usize {
        match self {
            Values::F32(v) => v.len(),
            Values::F16(v) => v.len(),
            Values::Blocks(b) => b.vectors() * b.dim,
        }
    }
    /// Whether there are no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Values `a..b` (panics outside the run, like a slice; blocks slice by whole vectors, so
    /// `a` and `b` are multiples of their dimension).
    pub fn slice(&self, a: usize, b: usize) -> Values<'a> {
        match self {
            Values::F32(v) => Values::F32(&v[a..b]),
            Values::F16(v) => Values::F16(&v[a..b]),
            Values::Blocks(k) => {
                assert!(k.dim > 0 && a.is_multiple_of(k.dim) && b.is_multiple_of(k.dim) && a <= b, "blocks slice by whole vectors");
                Values::Blocks(k.vectors_range(a / k.dim, b / k.dim))
            }
        }
    }
    /// The f32 slice itself when the values are stored as f32.
    pub fn as_f32(&self) -> Option<&'a [f32]> {
        match self {
            Values::F32(v) => Some(v),
            _ => None,
        }
    }
    /// Widens the values into `dst` (of the same length).
    pub fn write_to(&self, dst: &mut [f32]) {
        match self {
            Values::F32(v) => dst.copy_from_slice(v),
            Values::F16(v) => v.reinterpret_cast::<half::f16>().convert_to_f32_slice(dst),
            Values::Blocks(b) => b.write_to(dst),
        }
    }
    /// Appends the values, widened, to `out`.
    pub fn extend_into(&self, out: &mut Vec<f32>) {
        let at = out.len();
        out.resize(at + self.len(), 0.0);
        self.write_to(&mut out[at..]);
    }
    /// The values, widened, in a new vector.
    pub fn to_vec(&self) -> Vec<f32> {
        let mut v = Vec::with_capacity(self.len());
        self.extend_into(&mut v);
        v
    }
    /// The first value (index and value, widened) for which `pred` holds.
    pub fn position(&self, pred: impl Fn(f32) -> bool) -> Option<(usize, f32)> {
        match self {
            Values::F32(v) => v.iter().copied().enumerate().find(|&(_, x)| pred(x)),
            Values::F16(v) => v.iter().map(|&b| half::f16::from_bits(b).to_f32()).enumerate().find(|&(_, x)| pred(x)),
            Values::Blocks(_) => self.to_vec().into_iter().enumerate().find(|&(_, x)| pred(x)),
        }
    }
    /// The values as an f32 slice: borrowed when stored as f32, else widened into `buf`.
    pub fn widened<'s>(&self, buf: &'s mut Vec<f32>) -> &'s [f32]
    where
        'a: 's,
    {
        match *self {
            Values::F32(v) => v,
            _ => {
                buf.clear();
                buf.resize(self.len(), 0.0);
                self.write_to(buf);
                buf
            }
        }
    }
    /// Sum of products with `other`, in order, accumulated in f32: exactly
    /// `a.iter().zip(b).map(|(x, y)| x * y).sum()` over the widened values (f16 runs are widened
    /// a block at a time with the processor's conversion instructions, not value by value).
    pub fn dot(&self, other: &Values) -> f32 {
        if let (Values::F32(a), Values::F32(b)) = (self, other) {
            return a.iter().zip(*b).map(|(x, y)| x * y).sum();
        }
        if matches!(self, Values::Blocks(_)) || matches!(other, Values::Blocks(_)) {
            // widened whole (blocks slice by vectors only), then the f32 dot
            return WIDE.with_borrow_mut(|(x, y)| {
                let (a, b) = (self.widened(x), other.widened(y));
                a.iter().zip(b).map(|(p, q)| p * q).sum()
            });
        }
        const BLOCK: usize = 256;
        let n = self.len().min(other.len());
        let (mut x, mut y) = ([0.0f32; BLOCK], [0.0f32; BLOCK]);
        // the neutral element `sum` starts from, so that the fold below gives the same bits
        let mut acc: f32 = std::iter::empty::<f32>().sum();
        for a in (0..n).step_by(BLOCK) {
            let b = (a + BLOCK).min(n);
            self.slice(a, b).write_to(&mut x[..b - a]);
            other.slice(a, b).write_to(&mut y[..b - a]);
            acc = x[..b - a].iter().zip(&y[..b - a]).fold(acc, |s, (p, q)| s + p * q);
        }
        acc
    }
}

thread_local! {
    /// Scratch of [`Values::dot`] for block vectors.
    static WIDE: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// f32 values as f16 bit patterns (round to nearest even).
pub fn to_f16_bits(src: &[f32]) -> Vec<u16> {
    let mut out = vec![half::f16::ZERO; src.len()];
    out.convert_from_f32_slice(src);
    out.reinterpret_cast().to_vec()
}

/// Each value rounded through f16 and back: what an f16 map returns for `v`.
pub fn round_through_f16(v: &mut [f32]) {
    let bits = to_f16_bits(v);
    Values::F16(&bits).write_to(v);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn f16_round_trip_and_dot() {
        let x = [0.0f32, 1.0, 0.5, 0.333_333_34, -0.25, 1e-3];
        let bits = to_f16_bits(&x);
        let back = Values::F16(&bits).to_vec();
        for (a, b) in x.iter().zip(&back) {
            assert!((a - b).abs() <= a.abs() * 1e-3 + 1e-7, "{a} -> {b}");
        }
        // widening is exact, so narrowing again gives the same bits
        assert_eq!(to_f16_bits(&back), bits);
        let f = Values::F32(&x);
        assert_eq!(f.dot(&f), x.iter().map(|v| v * v).sum::<f32>());
        assert_eq!(Values::F16(&bits).dot(&f), back.iter().zip(&x).map(|(a, b)| a * b).sum::<f32>());
        assert_eq!(Values::F16(&bits).slice(1, 3).to_vec(), vec![1.0, 0.5]);
        // longer than one conversion block, f16 on either side or both: the widened f32 dot, bit for bit
        let long: Vec<f32> = (0..1000).map(|i| ((i * 37 % 101) as f32 - 50.0) / 64.0).collect();
        let lb = to_f16_bits(&long);
        let wide = Values::F16(&lb).to_vec();
        let reference = |a: &[f32], b: &[f32]| a.iter().zip(b).map(|(x, y)| x * y).sum::<f32>();
        assert_eq!(Values::F16(&lb).dot(&Values::F32(&long)).to_bits(), reference(&wide, &long).to_bits());
        assert_eq!(Values::F32(&long).dot(&Values::F16(&lb)).to_bits(), reference(&long, &wide).to_bits());
        assert_eq!(Values::F16(&lb).dot(&Values::F16(&lb)).to_bits(), reference(&wide, &wide).to_bits());
        let mut buf = Vec::new();
        assert_eq!(Values::F16(&lb).widened(&mut buf), &wide[..]);
        assert_eq!(Values::F32(&long).widened(&mut buf).as_ptr(), long.as_ptr(), "f32 values are borrowed");
    }

    #[test]
    fn blocks_store_rounded_vectors_exactly_and_skip_zero_blocks() {
        // 3 vectors of 4 blocks of 5: zero blocks, tiny and large values, negative values near 0
        let mut v: Vec<f32> =
            (0..60).map(|i| if (i / 5) % 3 == 1 { 0.0 } else { ((i * 37 % 23) as f32 - 11.0) * 10f32.powi(-(i % 4)) / 7.0 }).collect();
        v[3] = -1e-9;
        let original = v.clone();
        round_to_blocks(&mut v, 5);
        for (a, b) in v.iter().zip(&original) {
            let block_max = 11.0f32 / 7.0;
            assert!((a - b).abs() <= block_max / 127.0, "{a} vs {b}");
        }
        let (o, ids, e, q) = to_blocks(&v, 20, 5, 0);
        assert_eq!(o.len(), 4);
        assert!(ids.len() < 12, "all-zero blocks are not stored: {ids:?}");
        let b = Values::Blocks(Blocks { dim: 20, block: 5, offsets: &o, ids: &ids, exponents: &e, values: &q });
        assert_eq!(b.len(), 60);
        let back = b.to_vec();
        assert_eq!(back.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), v.iter().map(|x| x.to_bits()).collect::<Vec<_>>(), "read back bit for bit");
        assert_eq!(b.slice(20, 40).to_vec(), v[20..40].to_vec());
        // rounding again changes nothing; the dot equals the f32 one on the widened values
        let mut again = v.clone();
        round_to_blocks(&mut again, 5);
        assert_eq!(again, v);
        let other: Vec<f32> = (0..20).map(|i| i as f32 / 20.0).collect();
        assert_eq!(b.slice(40, 60).dot(&Values::F32(&other)).to_bits(), v[40..60].iter().zip(&other).map(|(x, y)| x * y).sum::<f32>().to_bits());
    }
}
