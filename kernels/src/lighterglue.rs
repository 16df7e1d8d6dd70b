//! The CPU twins of `shaders/lighterglue.wgsl` (LighterGlue, XFeat's LightGlue, on the device):
//! the same entry points under the same names, the same bindings (arguments, in binding order)
//! and the same loop shape: an outer loop over the dispatch's workgroups, then the shader's phases
//! (between its barriers) each as a loop over the workgroup's invocations, every sum in the
//! shader's order. The CPU path runs `networks::lighterglue` (matrix products by sgemm, softmax in
//! two passes), which the tests hold to these twins on real pairs; the device is held to them by
//! `tests/gpu/lighterglue.rs`.
//!
//! Source of the network: Lindenberger, Sarlin and Pollefeys, "LightGlue: Local Feature Matching
//! at Light Speed", ICCV 2023, in XFeat's configuration (Potje et al., CVPR 2024): see
//! `networks::lighterglue`. The online softmax of `lg_attention` and `lg_row_lse` is Milakov and
//! Gimelshein, "Online normalizer calculation for softmax", 2018.
//!
//! Rows and partners: every point of every pair in a batch is one row; `table` gives each row its
//! partners as (first row, count). Values a pass does not cover are left as they are.

use super::abi::LgParams;

/// Invocations of the row kernels' workgroups, and partners per chunk.
pub const LANES: usize = 128;
/// `lg_linear`'s tile: TILE x TILE outputs, TILE values of k at a time.
pub const TILE: usize = 16;
/// Rows per `lg_layer_norm` workgroup.
pub const LN_ROWS: usize = 64;
/// `lg_linear`: add to the output.
pub const FLAG_ACCUMULATE: u32 = 1;
/// `lg_layer_norm`: GELU after the norm.
pub const FLAG_GELU: u32 = 1;
/// `lg_assignment_best`: a row without partners.
pub const NO_PARTNER: u32 = u32::MAX;
/// Layer norm's epsilon (PyTorch's default).
pub const LN_EPS: f32 = 1e-5;
/// The score of a row without partners.
pub const LOWEST: f32 = -3.402823e38;
/// A grid of `groups` workgroups (x at most `max_x`, the rest folded into y), as the row kernels'
/// `row_of` reads it.
pub fn row_grid(groups: usize, max_x: u32) -> [u32; 3] {
    let x = groups.clamp(1, max_x.max(1) as usize);
    [x as u32, groups.div_ceil(x).max(1) as u32, 1]
}

/// The grid of each entry point for `p`, at most `max_x` workgroups in x (`lg_linear`'s y is
/// rows / TILE and `lg_layer_norm`'s x rows / LN_ROWS: the executor keeps batches within them).
pub fn grid(entry: &str, p: &LgParams, max_x: u32) -> [u32; 3] {
    let (rows, n_in) = (p.rows as usize, p.n_in as usize);
    match entry {
        "lg_linear" => [(p.n_out as usize).div_ceil(TILE) as u32, rows.div_ceil(TILE) as u32, 1],
        "lg_layer_norm" => [rows.div_ceil(LN_ROWS) as u32, 1, 1],
        "lg_rotary" => row_grid((rows * (n_in / 2)).div_ceil(LANES), max_x),
        "lg_gather" => row_grid((rows * n_in).div_ceil(LANES), max_x),
        _ => row_grid(rows, max_x),
    }
}

/// `lg_linear`: `out[o_off + r n_out + o] (+)= (sum_k x[r, k] W[o, k] + bias[o]) scale` for `rows`
/// rows, x's columns below `split` from `a` (rows of `split`), the rest from `b` (rows of
/// `n_in - split`); W (`n_out` x `n_in`) at `w_off`, the bias at `b_off` of `weights`.
pub fn lg_linear(p: &LgParams, a: &[f32], b: &[f32], weights: &[f32], out: &mut [f32]) {
    let (rows, n_in, n_out, split) = (p.rows as usize, p.n_in as usize, p.n_out as usize, p.split as usize);
    let lin_in = |r: usize, i: usize| if i < split { a[r * split + i] } else { b[r * (n_in - split) + (i - split)] };
    for wy in 0..rows.div_ceil(TILE) {
        for wx in 0..n_out.div_ceil(TILE) {
            let mut acc = [0.0f32; TILE * TILE];
            let (mut xs, mut ws) = ([0.0f32; TILE * TILE], [0.0f32; TILE * TILE]);
            for k0 in (0..n_in).step_by(TILE) {
                for ly in 0..TILE {
                    for lx in 0..TILE {
                        let (kk, ri, oi) = (k0 + lx, wy * TILE + ly, wx * TILE + ly);
                        xs[ly * TILE + lx] = if ri < rows && kk < n_in { lin_in(ri, kk) } else { 0.0 };
                        ws[ly * TILE + lx] = if oi < n_out && kk < n_in { weights[p.w_off as usize + oi * n_in + kk] } else { 0.0 };
                    }
                }
                let n = TILE.min(n_in - k0);
                for ly in 0..TILE {
                    for lx in 0..TILE {
                        for j in 0..n {
                            acc[ly * TILE + lx] += xs[ly * TILE + j] * ws[lx * TILE + j];
                        }
                    }
                }
            }
            for ly in 0..TILE {
                for lx in 0..TILE {
                    let (r, o) = (wy * TILE + ly, wx * TILE + lx);
                    if r < rows && o < n_out {
                        let y = (acc[ly * TILE + lx] + weights[p.b_off as usize + o]) * p.scale;
                        let at = p.o_off as usize + r * n_out + o;
                        out[at] = if p.flags & FLAG_ACCUMULATE != 0 { out[at] + y } else { y };
                    }
                }
            }
        }
    }
}

/// erf by Abramowitz and Stegun 7.1.26 (|error| <= 1.5e-7), as the shader computes it (the
/// same decimal constants, so the same f32 values).
pub fn lg_erf(x: f32) -> f32 {
    erf_with(x, f32::exp)
}

/// Abramowitz and Stegun 7.1.26 on the exponential `exp`: [`lg_erf`]'s form, which the CPU
/// matcher (`networks::lighterglue`) also computes, on its vectorising `exp`.
#[inline(always)]
#[allow(clippy::excessive_precision)]
pub fn erf_with(x: f32, exp: impl Fn(f32) -> f32) -> f32 {
    let z = x.abs();
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = ((((1.061405429 * t - 1.453152027) * t + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t;
    let y = 1.0 - poly * exp(-z * z);
    if x < 0.0 {
        -y
    } else {
        y
    }
}

/// `lg_layer_norm`: each of `rows` rows of `n_in` values at `o_off` of `out` normalised (mean,
/// biased variance, `LN_EPS`), times the gain at `g_off` plus the shift at `b_off`, then GELU
/// where `flags` has FLAG_GELU; in place.
pub fn lg_layer_norm(p: &LgParams, weights: &[f32], out: &mut [f32]) {
    let (rows, w) = (p.rows as usize, p.n_in as usize);
    for wg in 0..rows.div_ceil(LN_ROWS) {
        for lane in 0..LN_ROWS {
            let r = wg * LN_ROWS + lane;
            if r >= rows {
                continue;
            }
            let row = &mut out[p.o_off as usize + r * w..][..w];
            let mut s = 0.0f32;
            for &v in row.iter() {
                s += v;
            }
            let mean = s / w as f32;
            let mut v = 0.0f32;
            for &x in row.iter() {
                let c = x - mean;
                v += c * c;
            }
            let inv = 1.0 / (v / w as f32 + LN_EPS).sqrt();
            for (i, x) in row.iter_mut().enumerate() {
                let mut y = (*x - mean) * inv * weights[p.g_off as usize + i] + weights[p.b_off as usize + i];
                if p.flags & FLAG_GELU != 0 {
                    y = 0.5 * y * (1.0 + lg_erf(y * std::f32::consts::FRAC_1_SQRT_2));
                }
                *x = y;
            }
        }
    }
}

/// `lg_rotary`: `a` holds Wqkv's output (rows of 3 `n_in`, q, k and v interleaved), `b` each
/// row's encoding (`n_in / 2` (cos, sin) pairs); writes the rotated queries at `q_off`, the
/// rotated keys at `k_off` and the values at `v_off` of `out` (rows of `n_in`).
pub fn lg_rotary(p: &LgParams, a: &[f32], b: &[f32], out: &mut [f32]) {
    let d = p.n_in as usize;
    let h = d / 2;
    let total = p.rows as usize * h;
    let (q, k, v) = (p.q_off as usize, p.k_off as usize, p.v_off as usize);
    for wg in 0..total.div_ceil(LANES) {
        for lane in 0..LANES {
            let i = wg * LANES + lane;
            if i >= total {
                continue;
            }
            let (r, kk) = (i / h, i % h);
            let t = r * 3 * d + 6 * kk;
            let e = r * d + 2 * kk;
            let (c, s) = (b[e], b[e + 1]);
            let o = r * d + 2 * kk;
            out[q + o] = a[t] * c - a[t + 3] * s;
            out[q + o + 1] = a[t + 3] * c + a[t] * s;
            out[k + o] = a[t + 1] * c - a[t + 4] * s;
            out[k + o + 1] = a[t + 4] * c + a[t + 1] * s;
            out[v + o] = a[t + 2];
            out[v + o + 1] = a[t + 5];
        }
    }
}

/// One row kernel's workgroup memory.
struct Shared {
    qs: [f32; LANES],
    ss: [f32; LANES],
    ps: [f32; LANES],
}

impl Shared {
    fn new() -> Shared {
        Shared { qs: [0.0; LANES], ss: [0.0; LANES], ps: [0.0; LANES] }
    }
    /// The row's query into `qs` (the shader's `load_query`).
    fn load_query(&mut self, p: &LgParams, a: &[f32], r: usize) {
        let d = p.n_in as usize;
        self.qs[..d].copy_from_slice(&a[p.q_off as usize + r * d..][..d]);
    }
    /// The scores of partners `c0 .. c0 + n` into `ss` (the shader's `chunk_scores`).
    fn chunk_scores(&mut self, p: &LgParams, a: &[f32], bias: Option<&[f32]>, start: usize, c0: usize, n: usize) {
        let d = p.n_in as usize;
        for lane in 0..n {
            let kr = p.k_off as usize + (start + c0 + lane) * d;
            let mut s = 0.0f32;
            for j in 0..d {
                s += self.qs[j] * a[kr + j];
            }
            s *= p.scale;
            if let Some(bias) = bias {
                s += bias[start + c0 + lane];
            }
            self.ss[lane] = s;
        }
    }
    /// The chunk's largest score (every invocation computes it, in the same order).
    fn chunk_max(&self, n: usize) -> f32 {
        let mut m = self.ss[0];
        for j in 1..n {
            m = m.max(self.ss[j]);
        }
        m
    }
    /// One chunk of the online softmax: `ps` = exp(score - new maximum), the running maximum
    /// and sum updated; the factor the running values are rescaled by is returned.
    fn online_step(&mut self, c0: usize, n: usize, m: &mut f32, l: &mut f32) -> f32 {
        let cm = self.chunk_max(n);
        let nm = if c0 == 0 { cm } else { m.max(cm) };
        let alpha = if c0 == 0 { 0.0 } else { (*m - nm).exp() };
        for lane in 0..n {
            self.ps[lane] = (self.ss[lane] - nm).exp();
        }
        let mut cs = 0.0f32;
        for j in 0..n {
            cs += self.ps[j];
        }
        *l = *l * alpha + cs;
        *m = nm;
        alpha
    }
}

/// `lg_attention`: row r's output (`n_in` values at `o_off + r n_in` of `out`) is
/// softmax_j(scale q_r . k_j) v_j over its partners j (`table`), q at `q_off`, k at `k_off`, v at
/// `v_off` of `a`; zeros for a row without partners.
pub fn lg_attention(p: &LgParams, a: &[f32], out: &mut [f32], table: &[u32]) {
    let d = p.n_in as usize;
    let mut sh = Shared::new();
    for r in 0..p.rows as usize {
        let (start, len) = (table[2 * r] as usize, table[2 * r + 1] as usize);
        sh.load_query(p, a, r);
        let (mut m, mut l) = (0.0f32, 0.0f32);
        let mut acc = vec![0.0f32; d];
        for c0 in (0..len).step_by(LANES) {
            let n = LANES.min(len - c0);
            sh.chunk_scores(p, a, None, start, c0, n);
            let alpha = sh.online_step(c0, n, &mut m, &mut l);
            for (lane, acc) in acc.iter_mut().enumerate() {
                let mut t = 0.0f32;
                for j in 0..n {
                    t += sh.ps[j] * a[p.v_off as usize + (start + c0 + j) * d + lane];
                }
                *acc = *acc * alpha + t;
            }
        }
        for (lane, acc) in acc.iter().enumerate() {
            out[p.o_off as usize + r * d + lane] = if len > 0 { acc / l } else { 0.0 };
        }
    }
}

/// `ln sigmoid(z)` as the shader computes it.
pub fn lg_log_sigmoid(z: f32) -> f32 {
    z.min(0.0) - (1.0 + (-z.abs()).exp()).ln()
}

/// `lg_row_lse`: row r's bias `out[r]` = log sigmoid(`b[r]`) - logsumexp_j(scale q_r . k_j) over
/// its partners (q at `q_off`, k at `k_off` of `a`); LOWEST for a row without partners.
pub fn lg_row_lse(p: &LgParams, a: &[f32], b: &[f32], out: &mut [f32], table: &[u32]) {
    let mut sh = Shared::new();
    for r in 0..p.rows as usize {
        let (start, len) = (table[2 * r] as usize, table[2 * r + 1] as usize);
        sh.load_query(p, a, r);
        let (mut m, mut l) = (0.0f32, 0.0f32);
        for c0 in (0..len).step_by(LANES) {
            let n = LANES.min(len - c0);
            sh.chunk_scores(p, a, None, start, c0, n);
            sh.online_step(c0, n, &mut m, &mut l);
        }
        out[r] = if len > 0 { lg_log_sigmoid(b[r]) - (l.ln() + m) } else { LOWEST };
    }
}

/// `lg_assignment_best`: row r's best partner (`best[r]`, its index within the row's range, the
/// lowest among equals; NO_PARTNER without any) by scale q_r . k_j + `b[j]`, and that score plus
/// `b[r]` (`out[r]`; LOWEST without partners).
pub fn lg_assignment_best(p: &LgParams, a: &[f32], b: &[f32], out: &mut [f32], table: &[u32], best: &mut [u32]) {
    let mut sh = Shared::new();
    for r in 0..p.rows as usize {
        let (start, len) = (table[2 * r] as usize, table[2 * r + 1] as usize);
        sh.load_query(p, a, r);
        let (mut bv, mut bj) = (LOWEST, NO_PARTNER);
        for c0 in (0..len).step_by(LANES) {
            let n = LANES.min(len - c0);
            sh.chunk_scores(p, a, Some(b), start, c0, n);
            for j in 0..n {
                if bj == NO_PARTNER || sh.ss[j] > bv {
                    bv = sh.ss[j];
                    bj = (c0 + j) as u32;
                }
            }
        }
        best[r] = bj;
        out[r] = if len > 0 { bv + b[r] } else { LOWEST };
    }
}

/// `lg_gather`: row i of `out` (`n_in` values) is row `table[i]` of `a`, for `rows` rows.
pub fn lg_gather(p: &LgParams, a: &[f32], out: &mut [f32], table: &[u32]) {
    let w = p.n_in as usize;
    let total = p.rows as usize * w;
    for wg in 0..total.div_ceil(LANES) {
        for lane in 0..LANES {
            let i = wg * LANES + lane;
            if i >= total {
                continue;
            }
            let (r, c) = (i / w, i % w);
            out[r * w + c] = a[table[r] as usize * w + c];
        }
    }
}
