//! Small shared helpers: a seeded random generator whose sequence never changes between releases
//! (synthetic data and codebooks must be reproducible from a seed), and timing.

pub use semlook_kernels::rng::SplitMix64;

/// The sum of `f` over `v` in eight interleaved partial sums, then the values past the last
/// whole eight: a fixed order (the same result on every machine) whose loop vectorises where it
/// is inlined into code compiled for vector instructions (the index's thumbnail SSIM, the
/// learned matcher's row operations).
#[inline(always)]
pub fn lane_sum(v: &[f32], f: impl Fn(f32) -> f32) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = v.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for (a, &x) in acc.iter_mut().zip(c) {
            *a += f(x);
        }
    }
    acc.iter().sum::<f32>() + tail.iter().map(|&x| f(x)).sum::<f32>()
}

/// Milliseconds elapsed since `t`.
pub fn ms_since(t: std::time::Instant) -> f64 {
    t.elapsed().as_secs_f64() * 1e3
}

/// Lower-case hex SHA-256 of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    use sha2::Digest;
    sha2::Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

/// SHA-256 of a file's contents.
pub fn sha256_file(path: &std::path::Path) -> crate::Result<String> {
    let bytes = std::fs::read(path).map_err(|e| crate::Error::io(path, e))?;
    Ok(sha256_hex(&bytes))
}

/// Memory this machine can give a new allocation without swapping: `MemAvailable` of
/// /proc/meminfo, or 4 GiB where that cannot be read (other systems).
pub fn available_memory_bytes() -> u64 {
    std::fs::read_to_string("/proc/meminfo")
        .ok()
        .and_then(|s| {
            s.lines().find(|l| l.starts_with("MemAvailable:")).and_then(|l| l.split_whitespace().nth(1)).and_then(|kb| kb.parse::<u64>().ok())
        })
        .map_or(4 << 30, |kb| kb * 1024)
}

/// Takes over the result of a once-per-process check of a file (`None`: sound, `Some(reason)`:
/// damaged) that `from` ran where `same` says both are the same file, unless `to` has its own.
pub(crate) fn take_over_check(to: &std::sync::OnceLock<Option<String>>, from: &std::sync::OnceLock<Option<String>>, same: bool) {
    if let (true, Some(found)) = (same, from.get()) {
        let _ = to.set(found.clone());
    }
}
