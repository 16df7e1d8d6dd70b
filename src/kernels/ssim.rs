//! Structural similarity of global descriptors: the CPU path's reference (`ssim_pair`,
//! `ssim_stats`) that the twins `kernels::ssim_topk`, `kernels::ssim_block` and
//! `kernels::ssim_stats` are held to.
//!
//! SSIM (Wang, Bovik, Sheikh & Simoncelli, IEEE TIP 2004; paper ref. 26) with a uniform square
//! window over all valid window positions, as skimage's `structural_similarity` computes it. Each
//! descriptor carries its own window means and variances ("stats", computed once at encoding), so
//! a pair costs only the cross term: a product map, a separable box sum, and the SSIM formula.

use super::abi::SsimParams;

/// Window sums of `values` (gw x gh) into `out` (nw x nh), separably: rows into `rows`, then columns.
fn box_sums(p: &SsimParams, values: &[f32], rows: &mut [f32], out: &mut [f32]) {
    let (gw, nw, nh, win) = (p.gw as usize, p.nw as usize, p.nh as usize, p.win as usize);
    for r in 0..p.gh as usize {
        let src = &values[r * gw..(r + 1) * gw];
        let dst = &mut rows[r * nw..(r + 1) * nw];
        dst.fill(0.0);
        for k in 0..win {
            for c in 0..nw {
                dst[c] += src[c + k];
            }
        }
    }
    for r in 0..nh {
        let dst = &mut out[r * nw..(r + 1) * nw];
        dst.fill(0.0);
        for k in 0..win {
            let src = &rows[(r + k) * nw..(r + k + 1) * nw];
            for c in 0..nw {
                dst[c] += src[c];
            }
        }
    }
}

/// Reusable scratch space for SSIM (an executor's buffers: no allocation per pair).
#[derive(Debug, Default, Clone)]
pub struct SsimScratch {
    product: Vec<f32>,
    rows: Vec<f32>,
    sums: Vec<f32>,
}

impl SsimScratch {
    fn fit(&mut self, p: &SsimParams) {
        self.product.resize(p.len(), 0.0);
        self.rows.resize(p.gh as usize * p.nw as usize, 0.0);
        self.sums.resize(p.windows(), 0.0);
    }
}

/// Window means and (sample) variances of one descriptor: `out` = [means | variances].
pub fn ssim_stats(p: &SsimParams, x: &[f32], out: &mut [f32], scratch: &mut SsimScratch) {
    scratch.fit(p);
    let n = p.windows();
    let inv = 1.0 / (p.win * p.win) as f32;
    box_sums(p, x, &mut scratch.rows, &mut scratch.sums);
    for (m, s) in out[..n].iter_mut().zip(&scratch.sums) {
        *m = s * inv;
    }
    for (q, v) in scratch.product.iter_mut().zip(x) {
        *q = v * v;
    }
    box_sums(p, &scratch.product, &mut scratch.rows, &mut scratch.sums);
    let (means, vars) = out.split_at_mut(n);
    for i in 0..n {
        vars[i] = (scratch.sums[i] * inv - means[i] * means[i]) * p.cov_norm;
    }
}

/// SSIM of descriptors `x` and `y` given their stats: the mean over windows of
/// ((2 μx μy + C1)(2 σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2)).
pub fn ssim_pair(p: &SsimParams, x: &[f32], xs: &[f32], y: &[f32], ys: &[f32], scratch: &mut SsimScratch) -> f32 {
    scratch.fit(p);
    let n = p.windows();
    let inv = 1.0 / (p.win * p.win) as f32;
    for ((q, a), b) in scratch.product.iter_mut().zip(x).zip(y) {
        *q = a * b;
    }
    box_sums(p, &scratch.product, &mut scratch.rows, &mut scratch.sums);
    let (mx, vx) = xs.split_at(n);
    let (my, vy) = ys.split_at(n);
    // The shader's reduction: lane l sums windows l, l + LANES, ...; then a tree over the lanes.
    // (Independent lanes also let this loop vectorise.)
    let mut acc = [0.0f32; LANES];
    for start in (0..n).step_by(LANES) {
        let m = LANES.min(n - start);
        for l in 0..m {
            let i = start + l;
            acc[l] += ssim_window(p, scratch.sums[i] * inv, mx[i], my[i], vx[i], vy[i]);
        }
    }
    let mut h = LANES / 2;
    while h > 0 {
        for l in 0..h {
            acc[l] += acc[l + h];
        }
        h /= 2;
    }
    acc[0] / n as f32
}

/// Lanes of the SSIM reduction: the workgroup size of `ssim_topk.wgsl`.
pub const LANES: usize = 64;

/// SSIM of one window from the mean of x*y, the two means and the two variances.
#[inline(always)]
pub fn ssim_window(p: &SsimParams, mean_xy: f32, mx: f32, my: f32, vx: f32, vy: f32) -> f32 {
    let cov = (mean_xy - mx * my) * p.cov_norm;
    let num = (2.0 * mx * my + p.c1) * (2.0 * cov + p.c2);
    let den = (mx * mx + my * my + p.c1) * (vx + vy + p.c2);
    num / den
}

/// Reference: SSIM straight from the definition in f64, window by window.
pub fn ssim_reference(p: &SsimParams, x: &[f32], y: &[f32]) -> f64 {
    let (gw, win) = (p.gw as usize, p.win as usize);
    let n = (win * win) as f64;
    let mut total = 0.0;
    for wy in 0..p.nh as usize {
        for wx in 0..p.nw as usize {
            let px: Vec<(f64, f64)> = (0..win * win)
                .map(|k| {
                    let i = (wy + k / win) * gw + wx + k % win;
                    (x[i] as f64, y[i] as f64)
                })
                .collect();
            let mx = px.iter().map(|v| v.0).sum::<f64>() / n;
            let my = px.iter().map(|v| v.1).sum::<f64>() / n;
            let c = p.cov_norm as f64;
            let vx = px.iter().map(|v| (v.0 - mx).powi(2)).sum::<f64>() / n * c;
            let vy = px.iter().map(|v| (v.1 - my).powi(2)).sum::<f64>() / n * c;
            let cxy = px.iter().map(|v| (v.0 - mx) * (v.1 - my)).sum::<f64>() / n * c;
            let (c1, c2) = (p.c1 as f64, p.c2 as f64);
            total += ((2.0 * mx * my + c1) * (2.0 * cxy + c2)) / ((mx * mx + my * my + c1) * (vx + vy + c2));
        }
    }
    total / (p.nw * p.nh) as f64
}
