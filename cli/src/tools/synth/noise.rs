//! Deterministic hash noise for procedural textures and label jitter.

#[inline]
pub fn hash(a: i64, b: i64, c: i64, seed: u64) -> u64 {
    let mut h = seed ^ 0x9E37_79B9_7F4A_7C15;
    for v in [a, b, c] {
        h ^= v as u64;
        h = h.wrapping_mul(0xBF58_476D_1CE4_E5B9);
        h ^= h >> 29;
        h = h.wrapping_mul(0x94D0_49BB_1331_11EB);
        h ^= h >> 32;
    }
    h
}

/// Uniform in [0, 1) from integer coordinates.
#[inline]
pub fn hash01(a: i64, b: i64, c: i64, seed: u64) -> f32 {
    (hash(a, b, c, seed) >> 40) as f32 / (1u64 << 24) as f32
}

#[inline]
fn smooth(t: f64) -> f64 {
    t * t * (3.0 - 2.0 * t)
}

/// 2-D value noise in [0, 1), lattice spacing 1.
pub fn value2(x: f64, y: f64, seed: u64) -> f32 {
    let (xf, yf) = (x.floor(), y.floor());
    let (xi, yi) = (xf as i64, yf as i64);
    let (tx, ty) = (smooth(x - xf) as f32, smooth(y - yf) as f32);
    let h = |dx: i64, dy: i64| hash01(xi + dx, yi + dy, 0, seed);
    let a = h(0, 0) + (h(1, 0) - h(0, 0)) * tx;
    let b = h(0, 1) + (h(1, 1) - h(0, 1)) * tx;
    a + (b - a) * ty
}

/// Two octaves of value noise, in [0, 1).
pub fn fbm2(x: f64, y: f64, seed: u64) -> f32 {
    (value2(x, y, seed) * 2.0 + value2(x * 2.7, y * 2.7, seed ^ 0x55)) / 3.0
}
