//! Structural similarity of global descriptors: the CPU path's reference (`ssim_pair`,
//! `ssim_stats`) that the twins `ssim_topk`, `ssim_block` and
//! `ssim_stats` are held to.
//!
//! SSIM (Wang, Bovik, Sheikh & Simoncelli, IEEE TIP 2004; paper ref. 26) with a uniform square
//! window over all valid window positions, as skimage's `structural_similarity` computes it. Each
//! descriptor carries its own window means and variances ("stats", computed once at encoding), so
//! a pair costs only the cross term: a product map, a separable box sum (in the pair order of
//! [`pair_order_sum`]), and the SSIM formula (grouped as [`ssim_window`] says).

use super::abi::SsimParams;

/// Window sums of `values` (gw x gh) into `out` (nw x nh), separably: rows into `rows`, then
/// columns, each sum in index order (the statistics' order).
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

/// The sum of the `win` values `at(j)` .. `at(j + win - 1)` of the window starting at `j`, in the
/// cross term's pair order: windows j and j + 1 (j even) share their `win - 1` common values,
/// summed first in index order, and then each adds its own end value (`at(j)` for an even j,
/// `at(j + win - 1)` for an odd one). Summed pair by pair, as the fast path's lanes do, two
/// windows cost `win` additions rather than `2 (win - 1)` (3.5 a window instead of 6 at the
/// default 7-wide window); the twins and the shaders sum in this order too, window by window.
/// `win` is at least 2 (the configuration allows 3 and up).
#[inline(always)]
pub fn pair_order_sum(j: usize, win: usize, at: impl Fn(usize) -> f32) -> f32 {
    debug_assert!(win >= 2, "pair_order_sum: window {win}");
    let (lo, own) = if j.is_multiple_of(2) { (j + 1, j) } else { (j, j + win - 1) };
    let mut s = at(lo);
    for k in 1..win - 1 {
        s += at(lo + k);
    }
    s + at(own)
}

/// Window sums of the product map `values` (gw x gh) into `out` (nw x nh), separably (rows into
/// `rows`, then columns), each in [`pair_order_sum`]'s order, written as loops that vectorise:
/// the shared sums of `win - 1` values (`inner`) first (in rows from every start, of which the
/// odd ones, the `lo` of both windows of a pair, are used; in columns from the odd starts only),
/// then each window's own value.
fn cross_box_sums(p: &SsimParams, values: &[f32], rows: &mut [f32], inner: &mut [f32], out: &mut [f32]) {
    let (gw, nw, nh, win) = (p.gw as usize, p.nw as usize, p.nh as usize, p.win as usize);
    let inner = &mut inner[..nw + 1];
    for r in 0..p.gh as usize {
        let src = &values[r * gw..(r + 1) * gw];
        // inner[a] for every a (the odd ones are used): src[a] + ... + src[a + win - 2]
        inner.copy_from_slice(&src[..nw + 1]);
        for k in 1..win - 1 {
            for (t, &v) in inner.iter_mut().zip(&src[k..]) {
                *t += v;
            }
        }
        for (c, d) in rows[r * nw..(r + 1) * nw].iter_mut().enumerate() {
            *d = if c % 2 == 0 { inner[c + 1] + src[c] } else { inner[c] + src[c + win - 1] };
        }
    }
    let inner = &mut inner[..nw];
    for a in (1..=nh).step_by(2) {
        inner.copy_from_slice(&rows[a * nw..(a + 1) * nw]);
        for k in 1..win - 1 {
            for (t, &v) in inner.iter_mut().zip(&rows[(a + k) * nw..(a + k + 1) * nw]) {
                *t += v;
            }
        }
        for (d, (&t, &v)) in out[(a - 1) * nw..a * nw].iter_mut().zip(inner.iter().zip(&rows[(a - 1) * nw..a * nw])) {
            *d = t + v;
        }
        if a < nh {
            let own = &rows[(a + win - 1) * nw..(a + win) * nw];
            for (d, (&t, &v)) in out[a * nw..(a + 1) * nw].iter_mut().zip(inner.iter().zip(own)) {
                *d = t + v;
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
    inner: Vec<f32>,
}

impl SsimScratch {
    fn fit(&mut self, p: &SsimParams) {
        self.product.resize(p.len(), 0.0);
        self.rows.resize(p.gh as usize * p.nw as usize, 0.0);
        self.sums.resize(p.windows(), 0.0);
        self.inner.resize(p.nw as usize + 1, 0.0);
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
/// ((2 μx μy + C1)(2 σxy + C2)) / ((μx² + μy² + C1)(σx² + σy² + C2)), grouped as
/// [`ssim_window`] says.
pub fn ssim_pair(p: &SsimParams, x: &[f32], xs: &[f32], y: &[f32], ys: &[f32], scratch: &mut SsimScratch) -> f32 {
    scratch.fit(p);
    let n = p.windows();
    for ((q, a), b) in scratch.product.iter_mut().zip(x).zip(y) {
        *q = a * b;
    }
    cross_box_sums(p, &scratch.product, &mut scratch.rows, &mut scratch.inner, &mut scratch.sums);
    let (mx, vx) = xs.split_at(n);
    let (my, vy) = ys.split_at(n);
    // The shader's reduction: lane l sums windows l, l + LANES, ...; then a tree over the lanes.
    // (Independent lanes also let this loop vectorise.)
    let mut acc = [0.0f32; LANES];
    for start in (0..n).step_by(LANES) {
        let m = LANES.min(n - start);
        for l in 0..m {
            let i = start + l;
            acc[l] += ssim_window(p, scratch.sums[i], mx[i], my[i], vx[i], vy[i]);
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

/// SSIM of one window from the sum of x*y over it, the two means and the two variances:
/// (2 a + C1) ((Σxy · (1 / win²) - a) 2cn + C2) / (((μx² + C1) + μy²) ((σx² + C2) + σy²)) with
/// a = μx μy and cn the covariance normalisation; in exact arithmetic the textbook
/// (2 μx μy + C1)(2 σxy + C2) / ((μx² + μy² + C1)(σx² + σy² + C2)). The numerator rounds as
/// the textbook order does (doubling is exact); the denominator is grouped so that what depends
/// on x alone ([`window_x_terms`]) is computed once per query rather than once per pair: 13
/// operations a window instead of 16, which the coarse scan's speed rests on. Every path (this
/// twin, the shaders, `global::ssim_fast`) evaluates exactly this grouping.
#[inline(always)]
pub fn ssim_window(p: &SsimParams, sum_xy: f32, mx: f32, my: f32, vx: f32, vy: f32) -> f32 {
    ssim_window_terms(p, window_factors(p), sum_xy, window_x_terms(p, mx, vx), my, vy)
}

/// The window formula's factors that depend on the parameters only: (1 / win², 2 cn), as the
/// shaders compute them.
#[inline(always)]
pub fn window_factors(p: &SsimParams) -> (f32, f32) {
    (1.0 / (p.win * p.win) as f32, 2.0 * p.cov_norm)
}

/// The terms of a window that depend on x (the query) alone: [μx, μx² + C1, σx² + C2].
#[inline(always)]
pub fn window_x_terms(p: &SsimParams, mx: f32, vx: f32) -> [f32; 3] {
    [mx, mx * mx + p.c1, vx + p.c2]
}

/// [`ssim_window`] from x's terms ([`window_x_terms`]) and the factors ([`window_factors`]).
#[inline(always)]
pub fn ssim_window_terms(p: &SsimParams, (inv, n2): (f32, f32), sum_xy: f32, x: [f32; 3], my: f32, vy: f32) -> f32 {
    let [mx, mmc1, vc2] = x;
    let a = mx * my;
    let num = (2.0 * a + p.c1) * ((sum_xy * inv - a) * n2 + p.c2);
    let den = (mmc1 + my * my) * (vc2 + vy);
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

#[cfg(test)]
mod tests {
    use super::pair_order_sum;

    /// Every window's pair-order sum adds each of its `win` values once and no other: with the
    /// values distinct powers of two every such sum is exact, so any other index set shows.
    #[test]
    fn pair_order_sum_adds_each_value_of_the_window_once() {
        let at = |i: usize| (1u32 << i) as f32;
        for win in [2, 3, 5, 7, 9, 15] {
            for j in 0..24 - win {
                let want: f32 = (j..j + win).map(at).sum();
                assert_eq!(pair_order_sum(j, win, at), want, "window {j}, {win} wide");
            }
        }
    }
}
