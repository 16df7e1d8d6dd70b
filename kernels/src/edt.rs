//! Exact Euclidean distance transform (CPU twin of `shaders/edt.wgsl`).
//!
//! Algorithm: Meijster, Roerdink & Hesselink, "A general algorithm for computing distance
//! transforms in linear time" (ISMM 2000). Phase 1 scans each column for the distance to the
//! nearest edge pixel in that column; phase 2 takes, per row, the lower envelope of the parabolas
//! (x - i)^2 + g(i)^2 with integer separators. Everything is 32-bit integer arithmetic, so the GPU
//! twin reproduces the squared distances bit for bit. This is the exact transform that Shih & Wu's
//! two-scan 3x3 propagation (paper ref. 24, `docs/design/method.md` §2.3) approximates.
//!
//! Pixels of an image without any edge get squared distances >= (w + h)^2 (the "infinity" of the
//! paper), which the pooling stage truncates like any other far pixel.

/// Largest image side the 32-bit arithmetic supports: (2 * 8192)^2 + 8192^2 < 2^31.
pub const MAX_SIDE: usize = 8192;

/// Phase 1. Bindings: `edges` (1 = edge pixel), `g` (out: column distance, in pixels).
/// One invocation per column x.
pub fn edt_columns(edges: &[u32], g: &mut [i32], width: usize, height: usize) {
    for x in 0..width {
        edt_column(edges, g, width, height, x);
    }
}

/// Phase 1 for column `x`: one invocation of [`edt_columns`].
#[inline]
pub fn edt_column(edges: &[u32], g: &mut [i32], width: usize, height: usize, x: usize) {
    let inf = (width + height) as i32;
    g[x] = if edges[x] != 0 { 0 } else { inf };
    for y in 1..height {
        let i = y * width + x;
        g[i] = if edges[i] != 0 { 0 } else { (g[i - width] + 1).min(inf) };
    }
    for y in (0..height.saturating_sub(1)).rev() {
        let i = y * width + x;
        if g[i + width] < g[i] {
            g[i] = g[i + width] + 1;
        }
    }
}

/// Floor division for a positive divisor (WGSL's `/` truncates, so both twins spell it out).
#[inline]
fn floor_div(a: i32, b: i32) -> i32 {
    let q = a / b;
    if a % b != 0 && a < 0 {
        q - 1
    } else {
        q
    }
}

/// Phase 2. Bindings: `g` (phase 1 output), `s`, `t` (scratch, one row each per invocation),
/// `d2` (out: squared distance). One invocation per row y.
pub fn edt_rows(g: &[i32], s: &mut [i32], t: &mut [i32], d2: &mut [u32], width: usize, height: usize) {
    for y in 0..height {
        edt_row(g, s, t, d2, width, y);
    }
}

/// Phase 2 for row `y`: one invocation of [`edt_rows`].
#[inline]
pub fn edt_row(g: &[i32], s: &mut [i32], t: &mut [i32], d2: &mut [u32], width: usize, y: usize) {
    let row = y * width..(y + 1) * width;
    let (g, s, t, d2) = (&g[row.clone()], &mut s[row.clone()], &mut t[row.clone()], &mut d2[row]);
    let f = |x: i32, i: i32| (x - i) * (x - i) + g[i as usize] * g[i as usize];
    let sep = |i: i32, u: i32| {
        let (gu, gi) = (g[u as usize], g[i as usize]);
        floor_div(u * u - i * i + gu * gu - gi * gi, 2 * (u - i))
    };
    let w = width as i32;
    let mut q: i32 = 0;
    s[0] = 0;
    t[0] = 0;
    for u in 1..w {
        while q >= 0 && f(t[q as usize], s[q as usize]) > f(t[q as usize], u) {
            q -= 1;
        }
        if q < 0 {
            q = 0;
            s[0] = u;
        } else {
            let wsep = 1 + sep(s[q as usize], u);
            if wsep < w {
                q += 1;
                s[q as usize] = u;
                t[q as usize] = wsep;
            }
        }
    }
    for u in (0..w).rev() {
        d2[u as usize] = f(u, s[q as usize]) as u32;
        if u == t[q as usize] {
            q -= 1;
        }
    }
}

/// Brute-force reference: for every pixel, the minimum squared distance to any edge pixel
/// (u32::MAX where the image has no edge). O(pixels x edges); for tests only.
pub fn edt_brute_force(edges: &[u32], width: usize, height: usize) -> Vec<u32> {
    let pts: Vec<(i64, i64)> = (0..width * height).filter(|&i| edges[i] != 0).map(|i| ((i % width) as i64, (i / width) as i64)).collect();
    (0..width * height)
        .map(|i| {
            let (x, y) = ((i % width) as i64, (i / width) as i64);
            pts.iter().map(|&(px, py)| ((px - x).pow(2) + (py - y).pow(2)) as u32).min().unwrap_or(u32::MAX)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn run(edges: &[u32], w: usize, h: usize) -> Vec<u32> {
        let mut g = vec![0; w * h];
        let (mut s, mut t, mut d2) = (vec![0; w * h], vec![0; w * h], vec![0; w * h]);
        edt_columns(edges, &mut g, w, h);
        edt_rows(&g, &mut s, &mut t, &mut d2, w, h);
        d2
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        /// The transform is exact: it equals the brute-force minimum on random sparse edge maps.
        #[test]
        fn equals_brute_force(w in 1usize..40, h in 1usize..40, density in 0.0f64..0.2, seed in any::<u64>()) {
            let mut rng = crate::rng::SplitMix64::new(seed);
            let edges: Vec<u32> = (0..w * h).map(|_| (rng.next_f64() < density) as u32).collect();
            let fast = run(&edges, w, h);
            let slow = edt_brute_force(&edges, w, h);
            let inf2 = ((w + h) * (w + h)) as u32;
            for i in 0..w * h {
                if slow[i] == u32::MAX {
                    prop_assert!(fast[i] >= inf2, "pixel {i}: no edge but {}", fast[i]);
                } else {
                    prop_assert_eq!(fast[i], slow[i], "pixel {}", i);
                }
            }
        }
    }

    #[test]
    fn single_point_and_far_corner() {
        let (w, h) = (300, 200);
        let mut e = vec![0; w * h];
        e[0] = 1;
        let d2 = run(&e, w, h);
        assert_eq!(d2[w * h - 1], (299 * 299 + 199 * 199) as u32);
        assert_eq!(d2[5 * w + 12], 12 * 12 + 25);
    }
}
