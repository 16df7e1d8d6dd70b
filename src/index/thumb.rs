//! Thumbnails of the global descriptors, kept in the index so that its shortlist can follow the
//! fused coarse score (appearance cosine + `w_global` x SSIM) and not the appearance alone.
//!
//! Method: the global descriptor (an `h` x `w` map in [0, 1]) average-pooled over `f` x `f` blocks
//! and quantised to 8 bits (error at most 1/510 a value); two thumbnails are compared by the
//! coarse stage's own SSIM (`kernels::ssim`, its fast path `global::ssim_fast`: the same
//! constants `global.ssim_k1`, `ssim_k2`, `ssim_sample_covariance`) with a 3 x 3 window over the
//! thumbnail's values. Measured on the three real dev sets' 180 queries against their 481
//! references (docs/approximate-index.md): the SSIM of thumbnails pooled by 2 follows the exact SSIM at
//! r = 0.990 (within-query rank correlation 0.987), by 4 at 0.951; a cosine of the descriptors
//! only at 0.563.

use crate::config::GlobalConfig;
use semlook_kernels::abi::SsimParams;

/// The side of the SSIM window over thumbnails.
pub const WINDOW: usize = 3;

/// What a thumbnail is: the global descriptor's size, the pooling factor and the SSIM constants.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThumbSpec {
    /// Global descriptor width.
    pub width: usize,
    /// Global descriptor height.
    pub height: usize,
    /// Pooling factor (blocks of `pool` x `pool`); 0: no thumbnails.
    pub pool: usize,
}

impl ThumbSpec {
    /// Thumbnails of the global descriptors `g` describes, pooled by `pool` (0: none).
    pub fn new(g: &GlobalConfig, pool: usize) -> ThumbSpec {
        ThumbSpec { width: g.width, height: g.height, pool }
    }
    /// Thumbnail width and height (trailing columns and rows that fill no block are left out);
    /// (0, 0) where there are none or they would be smaller than one window.
    pub fn dims(&self) -> (usize, usize) {
        if self.pool == 0 {
            return (0, 0);
        }
        let (w, h) = (self.width / self.pool, self.height / self.pool);
        if w < WINDOW || h < WINDOW {
            (0, 0)
        } else {
            (w, h)
        }
    }
    /// Bytes a thumbnail (0: none).
    pub fn len(&self) -> usize {
        let (w, h) = self.dims();
        w * h
    }
    /// The SSIM of thumbnails: the coarse stage's constants `g` over the thumbnail's size with a
    /// [`WINDOW`] window (only meaningful where there are thumbnails).
    pub fn ssim_params(&self, g: &GlobalConfig) -> SsimParams {
        let (width, height) = self.dims();
        (GlobalConfig { width: width.max(WINDOW), height: height.max(WINDOW), ssim_window: WINDOW, ..g.clone() }).ssim_params()
    }
    /// Whether thumbnails are off (or too small to compare).
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    /// The thumbnail of a global descriptor (`width` x `height` values, row-major), appended to
    /// `out` (nothing where thumbnails are off).
    pub fn thumbnail(&self, global: &[f32], out: &mut Vec<u8>) {
        let (tw, th) = self.dims();
        let f = self.pool;
        let inv = 1.0 / (f * f) as f32;
        for ty in 0..th {
            for tx in 0..tw {
                let mut s = 0.0f32;
                for y in ty * f..(ty + 1) * f {
                    for x in tx * f..(tx + 1) * f {
                        s += global.get(y * self.width + x).copied().unwrap_or(0.0);
                    }
                }
                out.push(quantise(s * inv));
            }
        }
    }
}

/// A value in [0, 1] as 8 bits (rounded; outside values clamped, NaN as 0).
fn quantise(v: f32) -> u8 {
    if v.is_nan() {
        return 0;
    }
    (v.clamp(0.0, 1.0) * 255.0).round() as u8
}

/// Thumbnail bytes as the values they stand for (v / 255), appended to `out`.
#[inline(always)]
pub fn widen(thumb: &[u8], out: &mut Vec<f32>) {
    out.extend(thumb.iter().map(|&v| value(v)));
}

/// The value a thumbnail byte stands for.
#[inline(always)]
fn value(b: u8) -> f32 {
    b as f32 / 255.0
}

/// One query's thumbnail against many, as the index's pool re-ranking scores them: the SSIM of
/// `kernels::ssim` (the coarse stage's twin; constants `global.ssim_k1`, `ssim_k2`,
/// `ssim_sample_covariance`; mean over the valid 3 x 3 windows) by a path for small images: the
/// query's window terms once; each reference's window sums separable over the thumbnail as one
/// flat array (three neighbours, then three rows apart), so every loop is long and contiguous,
/// the windows that straddle a row's end computed and masked out; in f32 without fused
/// multiply-adds. Held to the twin within 1e-5 (tests). The scratch is kept between calls.
pub struct ThumbScorer {
    spec: ThumbSpec,
    p: SsimParams,
    /// Thumbnail width and height.
    w: usize,
    h: usize,
    /// The query's values, and per flat window position: its mean, 2 x mean, mean² + c1,
    /// variance + c2 (1 where the position is no window), and 1 or 0 (no window).
    x: Vec<f32>,
    mx: Vec<f32>,
    two_mx: Vec<f32>,
    mx2_c1: Vec<f32>,
    vx_c2: Vec<f32>,
    valid: Vec<f32>,
    /// Per reference: values, squares, products with the query; neighbour sums; window sums.
    y: [Vec<f32>; 3],
    rows: Vec<f32>,
    sums: [Vec<f32>; 3],
    terms: Vec<f32>,
    scores: Vec<f32>,
}

/// Window sums of a `w`-wide flat image `v` at every flat position that has three rows below it
/// (`out[i]`, `i` < (h - 2) w - 2; a window where `i % w < w - 2`), through `rows`.
#[inline(always)]
fn window_sums(v: &[f32], w: usize, rows: &mut Vec<f32>, out: &mut Vec<f32>) {
    debug_assert!(w >= WINDOW && v.len() >= WINDOW * w, "a thumbnail smaller than one window");
    let n = v.len() - 2;
    rows.resize(n, 0.0);
    let (a, b, c, r) = (&v[..n], &v[1..n + 1], &v[2..n + 2], &mut rows[..n]);
    for i in 0..n {
        r[i] = a[i] + b[i] + c[i];
    }
    let m = n - 2 * w;
    out.resize(m, 0.0);
    let (a, b, c, o) = (&rows[..m], &rows[w..w + m], &rows[2 * w..2 * w + m], &mut out[..m]);
    for i in 0..m {
        o[i] = a[i] + b[i] + c[i];
    }
}

impl ThumbScorer {
    /// A scorer for thumbnails `spec` with the coarse stage's constants `g`.
    pub fn new(spec: &ThumbSpec, g: &GlobalConfig) -> ThumbScorer {
        let (w, h) = spec.dims();
        ThumbScorer {
            spec: *spec,
            p: spec.ssim_params(g),
            w,
            h,
            x: vec![],
            mx: vec![],
            two_mx: vec![],
            mx2_c1: vec![],
            vx_c2: vec![],
            valid: vec![],
            y: Default::default(),
            rows: vec![],
            sums: Default::default(),
            terms: vec![],
            scores: vec![],
        }
    }

    /// Sets the query: the thumbnail of its global descriptor (the scorer's size).
    pub fn set_query(&mut self, global: &[f32]) {
        let mut bytes = Vec::with_capacity(self.spec.len());
        self.spec.thumbnail(global, &mut bytes);
        self.x.clear();
        widen(&bytes, &mut self.x);
        for v in [&mut self.mx, &mut self.two_mx, &mut self.mx2_c1, &mut self.vx_c2, &mut self.valid] {
            v.clear();
        }
        if self.w == 0 || self.x.len() != self.w * self.h {
            return;
        }
        let (inv_n, p, w) = (1.0 / (WINDOW * WINDOW) as f32, self.p, self.w);
        let [sx, sxx, _] = &mut self.sums;
        let xx: Vec<f32> = self.x.iter().map(|v| v * v).collect();
        window_sums(&self.x, w, &mut self.rows, sx);
        window_sums(&xx, w, &mut self.rows, sxx);
        for (i, (&a, &b)) in sx.iter().zip(sxx.iter()).enumerate() {
            let (m, window) = (a * inv_n, i % w < w + 1 - WINDOW);
            self.mx.push(if window { m } else { 0.0 });
            self.two_mx.push(if window { 2.0 * m } else { 0.0 });
            self.mx2_c1.push(if window { m * m + p.c1 } else { 1.0 });
            self.vx_c2.push(if window { (b * inv_n - m * m) * p.cov_norm + p.c2 } else { 1.0 });
            self.valid.push(if window { 1.0 } else { 0.0 });
        }
    }

    /// The SSIM of the query's thumbnail against each of `thumbs` (0 for one of another size,
    /// or where there are no thumbnails), with the best vector instructions `pulp` finds (the
    /// same operations in the same order on every instruction set).
    pub fn score<'a>(&mut self, thumbs: impl ExactSizeIterator<Item = &'a [u8]>) -> &[f32] {
        self.scores.clear();
        let mut scores = std::mem::take(&mut self.scores);
        pulp::Arch::new().dispatch(Run { s: self, thumbs, out: &mut scores });
        self.scores = scores;
        &self.scores
    }
}

/// One call of [`ThumbScorer::score`], compiled for an instruction set.
struct Run<'s, I> {
    s: &'s mut ThumbScorer,
    thumbs: I,
    out: &'s mut Vec<f32>,
}

impl<'a, I: Iterator<Item = &'a [u8]>> pulp::WithSimd for Run<'_, I> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let s = self.s;
        let (w, len) = (s.w, s.w * s.h);
        // one division a window: the window means by a multiplication (within 1e-7 of a division)
        let (inv_n, p) = (1.0 / (WINDOW * WINDOW) as f32, s.p);
        let windows = p.windows() as f32;
        for t in self.thumbs {
            if s.valid.is_empty() || t.len() != len {
                self.out.push(0.0);
                continue;
            }
            let [y, yy, xy] = &mut s.y;
            for v in [&mut *y, &mut *yy, &mut *xy] {
                v.resize(len, 0.0);
            }
            let (y, yy, xy, x, t) = (&mut y[..len], &mut yy[..len], &mut xy[..len], &s.x[..len], &t[..len]);
            for i in 0..len {
                let v = value(t[i]);
                y[i] = v;
                yy[i] = v * v;
                xy[i] = v * x[i];
            }
            let [sy, syy, sxy] = &mut s.sums;
            window_sums(y, w, &mut s.rows, sy);
            window_sums(yy, w, &mut s.rows, syy);
            window_sums(xy, w, &mut s.rows, sxy);
            let m = sy.len();
            s.terms.resize(m, 0.0);
            let (sy, syy, sxy, terms) = (&sy[..m], &syy[..m], &sxy[..m], &mut s.terms[..m]);
            let (mx, two_mx, mx2_c1, vx_c2, valid) = (&s.mx[..m], &s.two_mx[..m], &s.mx2_c1[..m], &s.vx_c2[..m], &s.valid[..m]);
            for i in 0..m {
                let my = sy[i] * inv_n;
                let vy = (syy[i] * inv_n - my * my) * p.cov_norm;
                let cxy = (sxy[i] * inv_n - mx[i] * my) * p.cov_norm;
                terms[i] = valid[i] * (((two_mx[i] * my + p.c1) * (2.0 * cxy + p.c2)) / ((mx2_c1[i] + my * my) * (vx_c2[i] + vy)));
            }
            self.out.push(crate::util::lane_sum(&s.terms, |v| v) / windows);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;
    use semlook_kernels::ssim::{ssim_pair, ssim_stats, SsimScratch};

    #[test]
    fn thumbnails_compare_by_the_coarse_stages_ssim_fast_path_as_its_twin() {
        let g = GlobalConfig::default();
        let mut rng = SplitMix64::new(3);
        for (w, h, pool) in [(64, 48, 2), (64, 48, 4), (13, 9, 3), (9, 9, 3)] {
            let spec = ThumbSpec { width: w, height: h, pool };
            let p = spec.ssim_params(&g);
            assert_eq!((p.gw as usize, p.gh as usize, p.win as usize), (spec.dims().0, spec.dims().1, WINDOW));
            let n = spec.len();
            // a query and 19 references: noise, a near copy, a flat one
            let thumbs: Vec<Vec<u8>> = (0..20)
                .map(|t| match t {
                    1 => (0..n).map(|_| (rng.next_u64() % 256) as u8).collect(),
                    2 => vec![77; n],
                    _ => (0..n).map(|i| ((i * 7 + t * 13) % 200) as u8 + (rng.next_u64() % 40) as u8).collect(),
                })
                .collect();
            let mut vals = Vec::new();
            thumbs.iter().for_each(|t| widen(t, &mut vals));
            // the query: a thumbnail made from a descriptor whose pooling gives thumbs[0]
            let global: Vec<f32> = (0..w * h)
                .map(|i| {
                    let (x, y) = (i % w, i / w);
                    if x / pool < spec.dims().0 && y / pool < spec.dims().1 {
                        thumbs[0][(y / pool) * spec.dims().0 + x / pool] as f32 / 255.0
                    } else {
                        0.0
                    }
                })
                .collect();
            let mut scorer = ThumbScorer::new(&spec, &g);
            scorer.set_query(&global);
            let fast = scorer.score(thumbs.iter().map(Vec::as_slice)).to_vec();
            let mut sc = SsimScratch::default();
            let (mut xs, mut ys) = (vec![0.0; p.stats_len()], vec![0.0; p.stats_len()]);
            ssim_stats(&p, &vals[..n], &mut xs, &mut sc);
            for r in 0..20 {
                ssim_stats(&p, &vals[r * n..(r + 1) * n], &mut ys, &mut sc);
                let twin = ssim_pair(&p, &vals[..n], &xs, &vals[r * n..(r + 1) * n], &ys, &mut sc);
                assert!((fast[r] - twin).abs() <= 1e-5, "{w}x{h}/{pool} reference {r}: fast {} vs twin {twin}", fast[r]);
            }
            assert!((fast[0] - 1.0).abs() < 1e-5, "a thumbnail is its own best match");
        }
    }

    #[test]
    fn thumbnails_pool_and_quantise_and_refuse_what_does_not_fit() {
        let spec = ThumbSpec { width: 7, height: 6, pool: 2 };
        assert_eq!(spec.dims(), (3, 3));
        let g: Vec<f32> = (0..42).map(|i| (i % 7) as f32 / 6.0).collect();
        let mut t = Vec::new();
        spec.thumbnail(&g, &mut t);
        // block (0, 0): columns 0 and 1 -> (0 + 1/6) / 2 = 1/12
        assert_eq!(t.len(), 9);
        assert_eq!(t[0], (255.0f32 / 12.0).round() as u8);
        assert_eq!(t[2], (255.0f32 * 9.0 / 12.0).round() as u8);
        // rounded to the nearest step (error at most half a step), not truncated
        assert_eq!((quantise(0.5), quantise(0.6 / 255.0), quantise(0.4 / 255.0)), (128, 1, 0));
        assert_eq!(quantise(f32::NAN), 0);
        assert_eq!(quantise(2.0), 255);
        // too small for one window, or off: no thumbnails
        for s in [ThumbSpec { width: 5, height: 48, pool: 2 }, ThumbSpec { width: 64, height: 48, pool: 0 }] {
            assert!(s.is_empty());
            let mut t = Vec::new();
            s.thumbnail(&g, &mut t);
            assert!(t.is_empty());
        }
    }
}
