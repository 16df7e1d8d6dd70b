//! SSIM of one descriptor pair from precomputed per-descriptor terms: the kernel of the fast CPU
//! coarse path (`matching::coarse_cpu`), equal bit for bit to [`ssim_pair`](crate::kernels::ssim::ssim_pair).
//!
//! Algorithm: the twin's arithmetic in the twin's order (product map, direct `win`-tap
//! horizontal window sums, direct vertical sums, the SSIM window formula, the shader's 64-lane
//! strided mean), laid out for SIMD:
//! - window columns are processed a vector at a time (`pulp`'s native width: 8 lanes with AVX2),
//!   from rows padded to a multiple of [`W`]; `G` vectors side by side, so that independent
//!   addition chains hide the adders' latency;
//! - the image is streamed row by row: one product row, a ring of `win` rows of horizontal sums
//!   and the window values are all a pair writes, so its scratch stays in L1;
//! - what depends on one descriptor only is laid out once per descriptor ([`terms_from_stats`]:
//!   window means m and variances v in padded rows), not once per pair. Pre-adding the
//!   constants (m*m + C1/2, v + C2/2) would round differently from the twin, which adds C1 and
//!   C2 after summing the two descriptors' terms; pre-squaring m (a third plane) was measured
//!   and bought nothing, since the kernel is not bound by those multiplications;
//! - the per-window values go to a row-major buffer and are reduced as the twin reduces them.
//!
//! IEEE operations evaluated in the same order give the same bits (Rust neither contracts
//! a*b+c into a fused multiply-add nor reassociates, and only plain add/sub/mul/div are used), so
//! scores equal the twin's exactly (a zero may differ in sign only), on every instruction set.
//! Running-sum box filters would do fewer additions but round differently, and in the covariance
//! E\[xy\] - mx*my a rounding difference is amplified by up to 2 / C2 (~2200 at the defaults) in
//! windows of near-zero variance, so no tolerance like 1e-5 holds for every input; the direct
//! sums were kept for exact equality.

use crate::kernels::abi::SsimParams;
use crate::kernels::ssim::{ssim_stats, SsimScratch, LANES};
use pulp::Simd;

/// Row padding in f32 lanes: a multiple of every vector width the kernel is built for (8 for
/// AVX2, 4 for NEON, 1 for the scalar fallback), so every row holds whole vectors.
pub const W: usize = 8;

/// Lanes of the twin's reduction (the shader's workgroup size).
const RL: usize = LANES;

/// Sizes of the padded layout, derived from [`SsimParams`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FastLayout {
    gw: usize,
    gh: usize,
    win: usize,
    nw: usize,
    nh: usize,
    /// Window columns rounded up to a multiple of `W`: the row stride of sums and terms.
    stride: usize,
    /// Windows per descriptor (nw * nh).
    n: usize,
}

impl FastLayout {
    /// The padded layout of descriptors of `p`'s sizes.
    pub fn new(p: &SsimParams) -> Self {
        let (nw, nh) = (p.nw as usize, p.nh as usize);
        FastLayout { gw: p.gw as usize, gh: p.gh as usize, win: p.win as usize, nw, nh, stride: nw.next_multiple_of(W), n: nw * nh }
    }
    /// Floats of one descriptor's terms: m and v, each `nh` rows of `stride`.
    pub fn terms_len(&self) -> usize {
        2 * self.nh * self.stride
    }
}

/// The terms of one descriptor from its stats record ([means | variances], as `ssim_stats`
/// writes it). Padding columns are zero; they only ever produce lanes that are discarded.
pub fn terms_from_stats(l: &FastLayout, stats: &[f32], out: &mut [f32]) {
    let plane = l.nh * l.stride;
    let (means, vars) = stats[..2 * l.n].split_at(l.n);
    for (src, dst) in [means, vars].into_iter().zip(out[..2 * plane].chunks_exact_mut(plane)) {
        for (s, d) in src.chunks_exact(l.nw).zip(dst.chunks_exact_mut(l.stride)) {
            d[..l.nw].copy_from_slice(s);
            d[l.nw..].fill(0.0);
        }
    }
}

/// The terms of one descriptor from the descriptor itself, for stores that keep no stats: its
/// stats are computed into `stats` exactly as `ssim_stats` computes them (the same bits as stored
/// stats), then [`terms_from_stats`].
pub fn terms_from_descriptor(p: &SsimParams, l: &FastLayout, x: &[f32], stats: &mut [f32], scratch: &mut SsimScratch, out: &mut [f32]) {
    ssim_stats(p, x, stats, scratch);
    terms_from_stats(l, stats, out);
}

/// Per-thread scratch of the kernel (owned by the executor, reused for every pair). Everything
/// a pair writes stays in L1: one product row, `win` rows of horizontal sums, the window values.
#[derive(Debug, Clone)]
pub struct FastScratch {
    /// Products x*y of one row, zero past `gw` so every vector-wide horizontal read is in bounds.
    prod: Vec<f32>,
    /// Horizontal window sums of the last `win` rows, row r in slot r % win (`stride` each).
    ring: Vec<f32>,
    /// Per-window SSIM values, row-major as the twin numbers windows; zero from `n` to the next
    /// multiple of the reduction's lanes, then `W` of spill.
    vals: Vec<f32>,
    /// Window means in padded rows (`stride` each, zero padding): the statistics' second pass.
    means: Vec<f32>,
}

impl FastScratch {
    /// Scratch sized for descriptors of layout `l`.
    pub fn new(l: &FastLayout) -> Self {
        FastScratch {
            prod: vec![0.0; (l.stride + l.win - 1).max(l.gw).next_multiple_of(W)],
            ring: vec![0.0; l.win * l.stride],
            vals: vec![0.0; l.n.next_multiple_of(RL) + W],
            means: vec![0.0; l.nh * l.stride],
        }
    }
}

#[inline(always)]
fn ld<S: Simd>(s: &[f32], o: usize) -> S::f32s {
    S::as_simd_f32s(&s[o..o + S::F32_LANES]).0[0]
}

#[inline(always)]
fn st<S: Simd>(s: &mut [f32], o: usize, v: S::f32s) {
    S::as_mut_simd_f32s(&mut s[o..o + S::F32_LANES]).0[0] = v;
}

/// Vectors processed side by side (a window row of 64 columns is 8 AVX2 vectors): independent addition chains, enough to cover the latency of
/// an addition (3-4 cycles) on two adders, and with their temporaries within 16 vector registers.
const G: usize = 8;

/// The SSIM constants as vectors.
#[derive(Clone, Copy)]
struct Consts<V> {
    inv: V,
    cn: V,
    c1: V,
    c2: V,
    two: V,
}

/// SSIM of query `x` (terms `tx`) and reference `y` (terms `ty`): the twin's
/// `ssim_pair(p, x, xs, y, ys)`, with the vector instructions of `simd`.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn ssim_pair_fast<S: Simd>(simd: S, p: &SsimParams, l: &FastLayout, x: &[f32], tx: &[f32], y: &[f32], ty: &[f32], s: &mut FastScratch) -> f32 {
    let (gw, stw, win) = (l.gw, l.stride, l.win);
    let chunks = stw / S::F32_LANES;
    let k = Consts {
        inv: simd.splat_f32s(1.0 / (win * win) as f32),
        cn: simd.splat_f32s(p.cov_norm),
        c1: simd.splat_f32s(p.c1),
        c2: simd.splat_f32s(p.c2),
        two: simd.splat_f32s(2.0),
    };
    let FastScratch { prod, ring, vals, .. } = s;
    let (mut slot, mut first) = (0, 0);
    for (r, (xr, yr)) in x.chunks_exact(gw).zip(y.chunks_exact(gw)).take(l.gh).enumerate() {
        // products, then horizontal window sums ((p[c] + p[c+1]) + ...) + p[c+win-1], as the twin adds them
        let ((pv, pt), (xv, xt), (yv, yt)) = (S::as_mut_simd_f32s(&mut prod[..gw]), S::as_simd_f32s(xr), S::as_simd_f32s(yr));
        for ((d, a), b) in pv.iter_mut().zip(xv).zip(yv) {
            *d = simd.mul_f32s(*a, *b);
        }
        for ((d, a), b) in pt.iter_mut().zip(xt).zip(yt) {
            *d = a * b;
        }
        horizontal_row(simd, prod, &mut ring[slot * stw..(slot + 1) * stw], chunks, win);
        slot = if slot + 1 == win { 0 } else { slot + 1 };
        // the window row whose last image row this was: vertical sums in row order from slot
        // `first` on, then the window formula
        if r + 1 >= win {
            let wr = r + 1 - win;
            let mut j = 0;
            while j + G <= chunks {
                windows::<S, G>(simd, &k, l, tx, ty, ring, first, vals, wr, j);
                j += G;
            }
            while j < chunks {
                windows::<S, 1>(simd, &k, l, tx, ty, ring, first, vals, wr, j);
                j += 1;
            }
            first = if first + 1 == win { 0 } else { first + 1 };
        }
    }
    // the twin's reduction: lane j sums windows j, j + RL, ...; then a tree over the lanes
    // (the zeros past n leave the lanes they reach unchanged)
    let n = l.n;
    vals[n..n.next_multiple_of(RL)].fill(0.0);
    let mut acc = [0.0f32; RL];
    {
        let accv = S::as_mut_simd_f32s(&mut acc).0;
        for chunk in vals[..n.next_multiple_of(RL)].chunks_exact(RL) {
            for (a, v) in accv.iter_mut().zip(S::as_simd_f32s(chunk).0) {
                *a = simd.add_f32s(*a, *v);
            }
        }
    }
    let mut h = RL / 2;
    while h > 0 {
        for j in 0..h {
            acc[j] += acc[j + h];
        }
        h /= 2;
    }
    acc[0] / n as f32
}

/// The stats record of descriptor `x` ([means | variances], `p.stats_len()` values into `out`),
/// equal to [`ssim_stats`]'s (a zero may differ in sign only): the same box sums, in the same
/// order, of `x` and then of `x * x`, streamed row by row through the pair kernel's scratch like
/// [`ssim_pair_fast`]. Maps store no statistics, so a query batch recomputes every reference's:
/// for one query against a shortlist this costs more than the SSIM pairs did (the twin's loops
/// took 15 µs a descriptor on the development machine).
pub fn ssim_stats_fast<S: Simd>(simd: S, p: &SsimParams, l: &FastLayout, x: &[f32], out: &mut [f32], s: &mut FastScratch) {
    let n = l.n;
    let inv = simd.splat_f32s(1.0 / (l.win * l.win) as f32);
    let cn = simd.splat_f32s(p.cov_norm);
    // means: the window sums of x, times inv; kept in padded rows too for the second pass
    box_rows(simd, l, x, false, s, |simd, sum, _, _| simd.mul_f32s(sum, inv));
    out[..n].copy_from_slice(&s.vals[..n]);
    for (src, dst) in out[..n].chunks_exact(l.nw).zip(s.means.chunks_exact_mut(l.stride)) {
        dst[..l.nw].copy_from_slice(src);
    }
    // variances: (the window sums of x*x, times inv, less the mean squared) times cov_norm
    let means = std::mem::take(&mut s.means);
    box_rows(simd, l, x, true, s, |simd, sum, wr, c0| {
        let m = ld::<S>(&means, wr * l.stride + c0);
        simd.mul_f32s(simd.sub_f32s(simd.mul_f32s(sum, inv), simd.mul_f32s(m, m)), cn)
    });
    s.means = means;
    out[n..2 * n].copy_from_slice(&s.vals[..n]);
}

/// The stats records of descriptors `globals` (`p.len()` values each) into `stats`
/// (`p.stats_len()` each), in parallel, by [`ssim_stats_fast`] with the best vector instructions
/// `pulp` finds, or by the twin's [`ssim_stats`] where it finds none (the same values either way).
pub fn ssim_stats_batch(p: &SsimParams, globals: &[f32], stats: &mut [f32]) {
    use rayon::prelude::*;
    let (glen, slen, l) = (p.len(), p.stats_len(), FastLayout::new(p));
    let arch = pulp::Arch::new();
    if matches!(arch, pulp::Arch::Scalar) {
        stats.par_chunks_mut(slen).zip(globals.par_chunks(glen)).for_each_init(SsimScratch::default, |sc, (out, x)| ssim_stats(p, x, out, sc));
        return;
    }
    stats.par_chunks_mut(slen).zip(globals.par_chunks(glen)).for_each_init(
        || FastScratch::new(&l),
        |scratch, (out, x)| {
            struct One<'a> {
                p: &'a SsimParams,
                l: &'a FastLayout,
                x: &'a [f32],
                out: &'a mut [f32],
                s: &'a mut FastScratch,
            }
            impl pulp::WithSimd for One<'_> {
                type Output = ();
                #[inline(always)]
                fn with_simd<S: Simd>(self, simd: S) {
                    ssim_stats_fast(simd, self.p, self.l, self.x, self.out, self.s)
                }
            }
            arch.dispatch(One { p, l: &l, x, out, s: scratch })
        },
    );
}

/// The window sums of `x` (of `x * x` where `square`), each turned into a value by `f(simd, sum,
/// window row, first column)` and written to `s.vals` row-major (`nw` a row; a row's
/// padding lanes spill into the next row, which overwrites them, and the last row's past `n`).
#[inline(always)]
fn box_rows<S: Simd>(simd: S, l: &FastLayout, x: &[f32], square: bool, s: &mut FastScratch, f: impl Fn(S, S::f32s, usize, usize) -> S::f32s) {
    let (gw, stw, win, lanes) = (l.gw, l.stride, l.win, S::F32_LANES);
    let chunks = stw / lanes;
    let FastScratch { prod, ring, vals, .. } = s;
    let (mut slot, mut first) = (0, 0);
    for (r, xr) in x.chunks_exact(gw).take(l.gh).enumerate() {
        if square {
            let ((pv, pt), (xv, xt)) = (S::as_mut_simd_f32s(&mut prod[..gw]), S::as_simd_f32s(xr));
            for (d, a) in pv.iter_mut().zip(xv) {
                *d = simd.mul_f32s(*a, *a);
            }
            for (d, a) in pt.iter_mut().zip(xt) {
                *d = a * a;
            }
        } else {
            prod[..gw].copy_from_slice(xr);
        }
        horizontal_row(simd, prod, &mut ring[slot * stw..(slot + 1) * stw], chunks, win);
        slot = if slot + 1 == win { 0 } else { slot + 1 };
        if r + 1 >= win {
            let wr = r + 1 - win;
            for j in 0..chunks {
                let c0 = j * lanes;
                let mut sum = ld::<S>(&ring[first * stw..], c0);
                let mut k = first;
                for _ in 1..win {
                    k = if k + 1 == win { 0 } else { k + 1 };
                    sum = simd.add_f32s(sum, ld::<S>(&ring[k * stw..], c0));
                }
                let v = f(simd, sum, wr, c0);
                st::<S>(vals, wr * l.nw + c0, v);
            }
            first = if first + 1 == win { 0 } else { first + 1 };
        }
    }
}

/// Horizontal window sums of one product row into `dst` (`chunks` vectors), `G` vectors at a time.
#[inline(always)]
fn horizontal_row<S: Simd>(simd: S, prod: &[f32], dst: &mut [f32], chunks: usize, win: usize) {
    let mut j = 0;
    while j + G <= chunks {
        horizontal::<S, G>(simd, prod, dst, j, win);
        j += G;
    }
    while j < chunks {
        horizontal::<S, 1>(simd, prod, dst, j, win);
        j += 1;
    }
}

/// Horizontal window sums of `N` vectors of one product row, from vector `j` on.
#[inline(always)]
fn horizontal<S: Simd, const N: usize>(simd: S, prod: &[f32], dst: &mut [f32], j: usize, win: usize) {
    let lanes = S::F32_LANES;
    let c0 = j * lanes;
    let src = &prod[c0..c0 + N * lanes + win - 1];
    let mut acc: [S::f32s; N] = std::array::from_fn(|i| ld::<S>(src, i * lanes));
    for k in 1..win {
        // one bounds check per shift, none per load
        let shifted = &src[k..k + N * lanes];
        for (i, a) in acc.iter_mut().enumerate() {
            *a = simd.add_f32s(*a, ld::<S>(shifted, i * lanes));
        }
    }
    let dst = &mut dst[c0..c0 + N * lanes];
    for (i, a) in acc.into_iter().enumerate() {
        st::<S>(dst, i * lanes, a);
    }
}

/// Vertical sums and SSIM values of `N` vectors of window row `wr`, from vector `j` on; the
/// window's first row of horizontal sums is in ring slot `first`. A row's padding lanes spill
/// into the next row's first values, which that row then overwrites (the last row's spill is
/// overwritten with zeros before the reduction).
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn windows<S: Simd, const N: usize>(
    simd: S,
    k: &Consts<S::f32s>,
    l: &FastLayout,
    tx: &[f32],
    ty: &[f32],
    ring: &[f32],
    first: usize,
    vals: &mut [f32],
    wr: usize,
    j: usize,
) {
    let (lanes, stw, win, plane) = (S::F32_LANES, l.stride, l.win, l.nh * l.stride);
    let c0 = j * lanes;
    let row = |slot: usize| &ring[slot * stw + c0..slot * stw + c0 + N * lanes];
    let r0 = row(first);
    let mut sum: [S::f32s; N] = std::array::from_fn(|i| ld::<S>(r0, i * lanes));
    let mut slot = first;
    for _ in 1..win {
        slot = if slot + 1 == win { 0 } else { slot + 1 };
        let rk = row(slot);
        for (i, a) in sum.iter_mut().enumerate() {
            *a = simd.add_f32s(*a, ld::<S>(rk, i * lanes));
        }
    }
    let o = wr * stw + c0;
    let span = |i: usize| i * plane + o..i * plane + o + N * lanes;
    let (mx, my) = (&tx[span(0)], &ty[span(0)]);
    let (vx, vy) = (&tx[span(1)], &ty[span(1)]);
    let v0 = wr * l.nw + c0;
    let out = &mut vals[v0..v0 + N * lanes];
    for (i, sum) in sum.into_iter().enumerate() {
        let e = i * lanes;
        let (mx, my) = (ld::<S>(mx, e), ld::<S>(my, e));
        // ssim::ssim_window, operation for operation
        let cov = simd.mul_f32s(simd.sub_f32s(simd.mul_f32s(sum, k.inv), simd.mul_f32s(mx, my)), k.cn);
        let num = simd.mul_f32s(simd.add_f32s(simd.mul_f32s(simd.mul_f32s(k.two, mx), my), k.c1), simd.add_f32s(simd.mul_f32s(k.two, cov), k.c2));
        let den = simd.mul_f32s(
            simd.add_f32s(simd.add_f32s(simd.mul_f32s(mx, mx), simd.mul_f32s(my, my)), k.c1),
            simd.add_f32s(simd.add_f32s(ld::<S>(vx, e), ld::<S>(vy, e)), k.c2),
        );
        st::<S>(out, e, simd.div_f32s(num, den));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(200))]
        /// The vectorised statistics equal the twin's `ssim_stats` (a zero's sign aside), for every
        /// instruction set pulp offers here and the scalar one, on random descriptors of random
        /// shapes, some flat (near-zero variances: where a rounding difference would show).
        #[test]
        fn fast_stats_equal_the_twin(w in 3usize..40, h in 3usize..30, win in prop::sample::select(vec![3usize, 5, 7]), seed in any::<u64>(), flat in any::<bool>(), batch in 1usize..6) {
            prop_assume!(w >= win && h >= win);
            let cfg = crate::config::GlobalConfig { width: w, height: h, ssim_window: win, ..Default::default() };
            let p = SsimParams::new(&cfg);
            let mut rng = crate::util::SplitMix64::new(seed);
            let globals: Vec<f32> = (0..batch * p.len()).map(|_| if flat { 0.5 + 1e-4 * rng.next_f64() as f32 } else { rng.next_f64() as f32 }).collect();
            let mut want = vec![0.0f32; batch * p.stats_len()];
            let mut sc = SsimScratch::default();
            for (x, out) in globals.chunks(p.len()).zip(want.chunks_mut(p.stats_len())) {
                ssim_stats(&p, x, out, &mut sc);
            }
            let mut got = vec![f32::NAN; batch * p.stats_len()];
            ssim_stats_batch(&p, &globals, &mut got);
            prop_assert!(got.iter().zip(&want).all(|(a, b)| a == b), "batch differs from the twin");
            let l = FastLayout::new(&p);
            let mut scalar = vec![f32::NAN; p.stats_len()];
            ssim_stats_fast(pulp::Scalar::new(), &p, &l, &globals[..p.len()], &mut scalar, &mut FastScratch::new(&l));
            prop_assert!(scalar.iter().zip(&want).all(|(a, b)| a == b), "scalar fast path differs from the twin");
        }
    }

    /// An empty batch writes nothing.
    #[test]
    fn an_empty_batch_is_nothing_to_do() {
        let p = SsimParams::new(&crate::config::GlobalConfig::default());
        ssim_stats_batch(&p, &[], &mut []);
    }
}
