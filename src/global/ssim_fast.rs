//! The kernels of the fast CPU coarse path (`matching::coarse_cpu`): SSIM of one query against a
//! group of references ([`ssim_lanes_fast`], equal bit for bit to
//! [`ssim_pair`](semlook_kernels::ssim::ssim_pair) for each pair) and the SSIM statistics of a
//! descriptor ([`ssim_stats_fast`], equal to [`ssim_stats`]).
//!
//! Algorithm: the twin's arithmetic in the twin's order (product map, direct `win`-tap
//! horizontal window sums, direct vertical sums, both in `ssim::pair_order_sum`'s order, the
//! SSIM window formula as `ssim::ssim_window` groups it, the shader's 64-lane strided mean), laid
//! out for SIMD:
//! - pairs: one reference per vector lane (`pulp`'s native width: 8 with AVX2), the references'
//!   descriptors and stats [`interleave`]d, the query's values broadcast. No vector straddles
//!   windows, so there is no padding and no shifted load; the image is streamed row by row (one
//!   product row and a ring of `win + 1` rows of horizontal sums, in L1), `G` columns side by side
//!   for independent addition chains, and each window's value goes straight to its lane of the
//!   twin's reduction. What depends on the query only (`ssim::window_x_terms`:
//!   [`query_lane_terms`]) is computed once per query. Two neighbouring windows share `win - 1`
//!   of their values, in columns and in rows: the pair order sums those once for both.
//!   (Measured against the former one-pair kernel, whose vectors ran along window columns padded
//!   to 64: 1.5-1.65 against 2.5 µs a pair on one Zen 4 core, `cargo bench --bench coarse_kernel`;
//!   the pair order and the regrouped window formula then took it to 1.31-1.47 µs.)
//! - statistics: window columns a vector at a time, from rows padded to a multiple of [`W`].
//!
//! IEEE operations evaluated in the same order give the same bits (Rust neither contracts
//! a*b+c into a fused multiply-add nor reassociates, and only plain add/sub/mul/div are used), so
//! scores equal the twin's exactly (a zero may differ in sign only), on every instruction set.
//! Running-sum box filters would do fewer additions still, but each sum would then depend on
//! every earlier one (a shader's invocations compute theirs independently), and in the
//! covariance E\[xy\] - mx*my a rounding difference is amplified by up to 2 / C2 (~2200 at the
//! defaults) in windows of near-zero variance, so no tolerance like 1e-5 would hold between them
//! for every input; direct sums in a fixed order keep every path exactly equal.

use pulp::Simd;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::ssim::{ssim_stats, window_factors, window_x_terms, SsimScratch, LANES};

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
}

/// Per-thread scratch of the statistics kernel (reused for every descriptor). Everything it
/// writes stays in L1: one product row, `win` rows of horizontal sums, the window values.
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

/// Vectors (or lane groups) processed side by side: independent addition chains, enough to cover
/// the latency of an addition (3-4 cycles) on two adders, within 16 vector registers.
const G: usize = 8;

#[inline(always)]
fn ld<S: Simd>(s: &[f32], o: usize) -> S::f32s {
    S::as_simd_f32s(&s[o..o + S::F32_LANES]).0[0]
}

#[inline(always)]
fn st<S: Simd>(s: &mut [f32], o: usize, v: S::f32s) {
    S::as_mut_simd_f32s(&mut s[o..o + S::F32_LANES]).0[0] = v;
}

/// The stats record of descriptor `x` ([means | variances], `p.stats_len()` values into `out`),
/// equal to [`ssim_stats`]'s (a zero may differ in sign only): the same box sums, in the same
/// order, of `x` and then of `x * x`, streamed row by row (window columns a vector at a time, in
/// padded rows). Maps store no statistics, so a query batch recomputes every reference's:
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

/// Scratch of [`ssim_lanes_fast`] (one per worker, reused for every call): one row of products,
/// a ring of `win + 1` rows of horizontal sums, the reduction's accumulators; `lanes` floats per
/// position. Everything a call writes stays in L1 (about 19 KiB at the default size with AVX2).
#[derive(Debug, Clone, Default)]
pub struct LaneScratch {
    prod: Vec<f32>,
    ring: Vec<f32>,
    acc: Vec<f32>,
    /// Offsets in `ring` of the rows of the window rows being summed, oldest first.
    slots: Vec<usize>,
}

impl LaneScratch {
    fn fit(&mut self, p: &SsimParams, lanes: usize) {
        let (gw, nw, win) = (p.gw as usize, p.nw as usize, p.win as usize);
        self.prod.resize(gw * lanes, 0.0);
        self.ring.resize((win + 1) * nw * lanes, 0.0);
        self.acc.resize(RL * lanes, 0.0);
        self.slots.resize(win + 1, 0);
    }
}

/// Floats of a query's lane terms ([`query_lane_terms`]): three planes of one value per window.
pub fn query_lane_terms_len(p: &SsimParams) -> usize {
    3 * p.windows()
}

/// The query-side terms [`ssim_lanes_fast`] reads, from the query's stats record: per window
/// `ssim::window_x_terms` (m, m * m + C1, v + C2, rounded as the twin rounds them), as three
/// planes. Computed once per query, not once per window and reference block.
pub fn query_lane_terms(p: &SsimParams, stats: &[f32], out: &mut [f32]) {
    let n = p.windows();
    let (means, vars) = stats[..2 * n].split_at(n);
    let (m, rest) = out[..3 * n].split_at_mut(n);
    let (mmc1, vc2) = rest.split_at_mut(n);
    for (i, (&mx, &vx)) in means.iter().zip(vars).enumerate() {
        [m[i], mmc1[i], vc2[i]] = window_x_terms(p, mx, vx);
    }
}

/// Floats of a group's reference lane terms ([`ref_lane_terms`]) for `lanes` lanes.
pub fn ref_lane_terms_len(p: &SsimParams, lanes: usize) -> usize {
    p.stats_len() * lanes
}

/// The reference-side terms [`ssim_lanes_fast`] reads, from the stats records of `count`
/// references (`stats`, record-major): the records [`interleave`]d `lanes` side by side (a plane
/// of means, then one of variances). (A third plane of squared means was measured and bought
/// nothing in the kernel while adding a third to this preparation.)
pub fn ref_lane_terms(p: &SsimParams, stats: &[f32], count: usize, lanes: usize, out: &mut [f32]) {
    interleave(stats, p.stats_len(), count, lanes, out);
}

/// `count` records of `len` floats each (record-major in `src`) into `out` position-major,
/// `lanes` records side by side (`out[i * lanes + j]` = record j's float i); lanes past `count`
/// repeat the last record, so that they hold valid values (their results are discarded). `lanes`
/// is at most 16.
pub fn interleave(src: &[f32], len: usize, count: usize, lanes: usize, out: &mut [f32]) {
    debug_assert!(count >= 1 && lanes <= 16, "interleave: {count} records into {lanes} lanes");
    let mut recs = [&src[..0]; 16];
    for (j, r) in recs[..lanes].iter_mut().enumerate() {
        *r = &src[j.min(count - 1) * len..][..len];
    }
    let out = &mut out[..len * lanes];
    #[cfg(target_arch = "x86_64")]
    if lanes == 8 && std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: AVX is present (checked above); `transpose8_avx` reads and writes in bounds only.
        let done = unsafe { transpose8_avx(&recs, out) };
        for (i, o) in out.chunks_exact_mut(8).enumerate().skip(done) {
            for (o, r) in o.iter_mut().zip(&recs) {
                *o = r[i];
            }
        }
        return;
    }
    // sequential writes, one read stream per lane
    for (i, o) in out.chunks_exact_mut(lanes).enumerate() {
        for (o, r) in o.iter_mut().zip(&recs[..lanes]) {
            *o = r[i];
        }
    }
}

/// [`interleave`] of 8 records by 8 x 8 transposes in AVX registers (the scalar loop takes three
/// times as long as scoring the group once, which a single query pays for every group): the
/// positions of whole blocks of 8; returns how many positions it wrote.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn transpose8_avx(recs: &[&[f32]; 16], out: &mut [f32]) -> usize {
    use std::arch::x86_64::*;
    let len = recs[0].len();
    let blocks = len / 8;
    for b in 0..blocks {
        let i = b * 8;
        let r: [__m256; 8] = std::array::from_fn(|j| _mm256_loadu_ps(recs[j][i..i + 8].as_ptr()));
        let t0 = _mm256_unpacklo_ps(r[0], r[1]);
        let t1 = _mm256_unpackhi_ps(r[0], r[1]);
        let t2 = _mm256_unpacklo_ps(r[2], r[3]);
        let t3 = _mm256_unpackhi_ps(r[2], r[3]);
        let t4 = _mm256_unpacklo_ps(r[4], r[5]);
        let t5 = _mm256_unpackhi_ps(r[4], r[5]);
        let t6 = _mm256_unpacklo_ps(r[6], r[7]);
        let t7 = _mm256_unpackhi_ps(r[6], r[7]);
        let u0 = _mm256_shuffle_ps::<0x44>(t0, t2);
        let u1 = _mm256_shuffle_ps::<0xEE>(t0, t2);
        let u2 = _mm256_shuffle_ps::<0x44>(t1, t3);
        let u3 = _mm256_shuffle_ps::<0xEE>(t1, t3);
        let u4 = _mm256_shuffle_ps::<0x44>(t4, t6);
        let u5 = _mm256_shuffle_ps::<0xEE>(t4, t6);
        let u6 = _mm256_shuffle_ps::<0x44>(t5, t7);
        let u7 = _mm256_shuffle_ps::<0xEE>(t5, t7);
        let rows = [
            _mm256_permute2f128_ps::<0x20>(u0, u4),
            _mm256_permute2f128_ps::<0x20>(u1, u5),
            _mm256_permute2f128_ps::<0x20>(u2, u6),
            _mm256_permute2f128_ps::<0x20>(u3, u7),
            _mm256_permute2f128_ps::<0x31>(u0, u4),
            _mm256_permute2f128_ps::<0x31>(u1, u5),
            _mm256_permute2f128_ps::<0x31>(u2, u6),
            _mm256_permute2f128_ps::<0x31>(u3, u7),
        ];
        let dst = &mut out[i * 8..i * 8 + 64];
        for (k, v) in rows.iter().enumerate() {
            _mm256_storeu_ps(dst[k * 8..k * 8 + 8].as_mut_ptr(), *v);
        }
    }
    blocks * 8
}

/// SSIM of query `x` (lane terms `xt`, [`query_lane_terms`]) against `S::F32_LANES`
/// references at once, one per vector lane: `y` holds the references' descriptors
/// [`interleave`]d, `yt` their [`ref_lane_terms`]; their scores go to `out[..lanes]`. Each lane evaluates the
/// twin's `ssim_pair` operation for operation (product map, direct `win`-tap
/// horizontal then vertical window sums in `ssim::pair_order_sum`'s order, `ssim_window_terms`,
/// the 64-lane strided mean and its tree), so scores equal the twin's bit for bit (a zero may
/// differ in sign only). Since every lane is another pair, no vector straddles windows: no
/// padding, shifted loads or lane shuffles. Columns are summed a few at a time (independent
/// addition chains, each product loaded once for the default 7-wide window), window rows two at
/// a time; a pair of columns or of window rows sums its `win - 1` shared values once.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
pub fn ssim_lanes_fast<S: Simd>(simd: S, p: &SsimParams, x: &[f32], xt: &[f32], y: &[f32], yt: &[f32], s: &mut LaneScratch, out: &mut [f32]) {
    let lanes = S::F32_LANES;
    s.fit(p, lanes);
    let (gw, gh, nw, nh, win, n) = (p.gw as usize, p.gh as usize, p.nw as usize, p.nh as usize, p.win as usize, p.windows());
    let (inv, n2) = window_factors(p);
    let sp = |v: f32| simd.splat_f32s(v);
    let k = LaneConsts { inv: sp(inv), n2: sp(n2), two: sp(2.0), c1: sp(p.c1), c2: sp(p.c2) };
    let q = QueryTerms { m: &xt[..n], mmc1: &xt[n..2 * n], vc2: &xt[2 * n..3 * n] };
    let yt = S::as_simd_f32s(&yt[..2 * n * lanes]).0;
    let rt = RefTerms { m: &yt[..n], v: &yt[n..2 * n] };
    let y = S::as_simd_f32s(&y[..gw * gh * lanes]).0;
    let LaneScratch { prod, ring, acc, slots } = s;
    let prod = S::as_mut_simd_f32s(&mut prod[..gw * lanes]).0;
    let ring = S::as_mut_simd_f32s(&mut ring[..(win + 1) * nw * lanes]).0;
    let acc = S::as_mut_simd_f32s(&mut acc[..RL * lanes]).0;
    acc.fill(simd.splat_f32s(0.0));
    // ring capacity: the rows of two window rows
    let cap = win + 1;
    let pairs = nw <= RL;
    let mut slot = 0;
    for r in 0..gh {
        for ((d, &a), &b) in prod.iter_mut().zip(&x[r * gw..(r + 1) * gw]).zip(&y[r * gw..(r + 1) * gw]) {
            *d = simd.mul_f32s(simd.splat_f32s(a), b);
        }
        let dst = &mut ring[slot * nw..(slot + 1) * nw];
        let mut c = 0;
        if win == 7 {
            while c + GH <= nw {
                lanes_horizontal_7::<S, GH>(simd, prod, dst, c);
                c += GH;
            }
        }
        while c + G <= nw {
            lanes_horizontal::<S, G>(simd, prod, dst, c, win);
            c += G;
        }
        while c < nw {
            lanes_horizontal::<S, 1>(simd, prod, dst, c, win);
            c += 1;
        }
        slot = if slot + 1 == cap { 0 } else { slot + 1 };
        // window rows in pairs (sharing the sum of their `win - 1` common rows),
        // the last alone where their count is odd. Pairs add a row's values to the reduction's
        // lanes before the end of the row above, which keeps the twin's order of each lane's
        // additions only while a row has at most 64 windows (no lane holds two windows of the
        // same row pair's columns out of order); wider descriptors take their rows one at a time.
        let Some(wr) = (r + 1).checked_sub(win) else { continue };
        let two = pairs && wr % 2 == 1;
        if pairs && !two && wr + 1 < nh {
            continue;
        }
        let lo = if two { wr - 1 } else { wr };
        // the ring rows of window rows lo (and lo + 1), oldest first
        let rows = &mut slots[..win + two as usize];
        for (i, o) in rows.iter_mut().enumerate() {
            *o = (lo + i) % cap * nw;
        }
        let mut c = 0;
        while c + GW <= nw {
            lanes_windows::<S, GW>(simd, two, lo % 2 == 1, &k, ring, rows, c, &q, &rt, acc, lo * nw + c, nw);
            c += GW;
        }
        while c < nw {
            lanes_windows::<S, 1>(simd, two, lo % 2 == 1, &k, ring, rows, c, &q, &rt, acc, lo * nw + c, nw);
            c += 1;
        }
    }
    // the twin's tree over its 64 lanes, then the mean
    let mut h = RL / 2;
    while h > 0 {
        for j in 0..h {
            acc[j] = simd.add_f32s(acc[j], acc[j + h]);
        }
        h /= 2;
    }
    let nf = n as f32;
    for (o, a) in out[..lanes].iter_mut().zip(bytemuck::cast_slice::<S::f32s, f32>(&acc[..1])) {
        *o = a / nf;
    }
}

/// A query's lane terms as planes (`ssim::window_x_terms`).
struct QueryTerms<'a> {
    m: &'a [f32],
    mmc1: &'a [f32],
    vc2: &'a [f32],
}

/// Window columns whose SSIM values [`ssim_lanes_fast`] computes side by side.
const GW: usize = 4;

/// The constants of [`ssim_lanes_fast`] as vectors.
#[derive(Clone, Copy)]
struct LaneConsts<V> {
    inv: V,
    n2: V,
    two: V,
    c1: V,
    c2: V,
}

/// Horizontal sums of `N` window columns from `c` on, in `ssim::pair_order_sum`'s order: from an
/// even column on, a pair of columns shares its `win - 1` common products (one addition chain for
/// two sums); otherwise column by column.
#[inline(always)]
fn lanes_horizontal<S: Simd, const N: usize>(simd: S, prod: &[S::f32s], dst: &mut [S::f32s], c: usize, win: usize) {
    let src = &prod[c..c + N + win - 1];
    let mut a: [S::f32s; N] = [src[0]; N];
    if c.is_multiple_of(2) && N.is_multiple_of(2) {
        let mut inner: [S::f32s; N] = std::array::from_fn(|j| src[(2 * j + 1).min(N - 1)]);
        for t in 2..win {
            for (j, v) in inner[..N / 2].iter_mut().enumerate() {
                *v = simd.add_f32s(*v, src[2 * j + t]);
            }
        }
        for (j, &v) in inner[..N / 2].iter().enumerate() {
            a[2 * j] = simd.add_f32s(v, src[2 * j]);
            a[2 * j + 1] = simd.add_f32s(v, src[2 * j + win]);
        }
    } else {
        for (i, a) in a.iter_mut().enumerate() {
            let (lo, own) = if (c + i).is_multiple_of(2) { (i + 1, i) } else { (i, i + win - 1) };
            let mut v = src[lo];
            for t in 1..win - 1 {
                v = simd.add_f32s(v, src[lo + t]);
            }
            *a = simd.add_f32s(v, src[own]);
        }
    }
    dst[c..c + N].copy_from_slice(&a);
}

/// Window columns whose horizontal sums [`lanes_horizontal_7`] computes side by side.
const GH: usize = 4;

/// [`lanes_horizontal`] for 7-column windows (the default) from an even column `c`, `N` even:
/// the `N + 6` products each loaded once and kept in registers, rather than loaded for each pair.
#[inline(always)]
fn lanes_horizontal_7<S: Simd, const N: usize>(simd: S, prod: &[S::f32s], dst: &mut [S::f32s], c: usize) {
    debug_assert!(c.is_multiple_of(2) && N.is_multiple_of(2));
    let src = &prod[c..c + N + 6];
    let mut v = [src[0]; 16];
    v[..N + 6].copy_from_slice(src);
    let mut a = [src[0]; N];
    for i in (0..N).step_by(2) {
        let mut inner = v[i + 1];
        for t in 2..7 {
            inner = simd.add_f32s(inner, v[i + t]);
        }
        a[i] = simd.add_f32s(inner, v[i]);
        a[i + 1] = simd.add_f32s(inner, v[i + 7]);
    }
    dst[c..c + N].copy_from_slice(&a);
}

/// Vertical sums of `N` window columns from `c` on, in `ssim::pair_order_sum`'s order, of one
/// window row (`rows`: its `win` ring rows, oldest first; `odd`: whether its index is odd) or of
/// an even one and the next (`win + 1` rows, sharing the `win - 1` rows they have in common), and
/// their SSIM values, added to the reduction's lanes; `w` is the first window's index, `nw` the
/// windows of a row; `two` says which.
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn lanes_windows<S: Simd, const N: usize>(
    simd: S,
    two: bool,
    odd: bool,
    k: &LaneConsts<S::f32s>,
    ring: &[S::f32s],
    rows: &[usize],
    c: usize,
    q: &QueryTerms,
    r: &RefTerms<S::f32s>,
    acc: &mut [S::f32s],
    w: usize,
    nw: usize,
) {
    let row = |t: usize| &ring[rows[t] + c..rows[t] + c + N];
    let win = if two { rows.len() - 1 } else { rows.len() };
    // the rows the window row shares with its partner: 1..win of an even one, 0..win - 1 of an odd one
    let lo = if odd { 0 } else { 1 };
    let mut inner: [S::f32s; N] = std::array::from_fn(|i| row(lo)[i]);
    for t in lo + 1..lo + win - 1 {
        for (a, &v) in inner.iter_mut().zip(row(t)) {
            *a = simd.add_f32s(*a, v);
        }
    }
    let own = |t: usize| -> [S::f32s; N] { std::array::from_fn(|i| simd.add_f32s(inner[i], row(t)[i])) };
    if !two {
        lanes_values(simd, k, own(if odd { win - 1 } else { 0 }), q, r, acc, w);
        return;
    }
    lanes_values(simd, k, own(0), q, r, acc, w);
    lanes_values(simd, k, own(win), q, r, acc, w + nw);
}

/// The SSIM values of `N` consecutive windows from window `w` on, given their sums of x * y,
/// added to the reduction's lanes `w % 64`, ....
#[inline(always)]
fn lanes_values<S: Simd, const N: usize>(
    simd: S,
    k: &LaneConsts<S::f32s>,
    sum: [S::f32s; N],
    q: &QueryTerms,
    r: &RefTerms<S::f32s>,
    acc: &mut [S::f32s],
    w: usize,
) {
    let (mx, mmc1, vc2) = (&q.m[w..w + N], &q.mmc1[w..w + N], &q.vc2[w..w + N]);
    let (my, vy) = (&r.m[w..w + N], &r.v[w..w + N]);
    let mut vals = sum;
    for (i, val) in vals.iter_mut().enumerate() {
        // ssim::ssim_window_terms, operation for operation
        let (rm, sp) = (my[i], |v: f32| simd.splat_f32s(v));
        let a = simd.mul_f32s(sp(mx[i]), rm);
        let cross = simd.add_f32s(simd.mul_f32s(simd.sub_f32s(simd.mul_f32s(sum[i], k.inv), a), k.n2), k.c2);
        let num = simd.mul_f32s(simd.add_f32s(simd.mul_f32s(k.two, a), k.c1), cross);
        let den = simd.mul_f32s(simd.add_f32s(sp(mmc1[i]), simd.mul_f32s(rm, rm)), simd.add_f32s(sp(vc2[i]), vy[i]));
        *val = simd.div_f32s(num, den);
    }
    let j = w % RL;
    if j + N <= RL {
        for (a, v) in acc[j..j + N].iter_mut().zip(vals) {
            *a = simd.add_f32s(*a, v);
        }
    } else {
        for (i, v) in vals.into_iter().enumerate() {
            let j = (w + i) % RL;
            acc[j] = simd.add_f32s(acc[j], v);
        }
    }
}

/// A reference group's lane terms as planes.
struct RefTerms<'a, V> {
    m: &'a [V],
    v: &'a [V],
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
            let p = cfg.ssim_params();
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

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(100))]
        /// `interleave` puts record j's float i at i * lanes + j, repeating the last record in
        /// lanes past `count`, whichever way it runs (the AVX transposes of 8 x 8 blocks and their
        /// tail, or the plain loop for other lane counts).
        #[test]
        fn interleave_transposes_records(len in 1usize..100, count in 1usize..=8, lanes in prop::sample::select(vec![1usize, 4, 8, 16]), seed in any::<u64>()) {
            let count = count.min(lanes);
            let mut rng = crate::util::SplitMix64::new(seed);
            let src: Vec<f32> = (0..count * len).map(|_| rng.next_f64() as f32).collect();
            let mut out = vec![f32::NAN; len * lanes];
            interleave(&src, len, count, lanes, &mut out);
            for i in 0..len {
                for j in 0..lanes {
                    prop_assert_eq!(out[i * lanes + j], src[j.min(count - 1) * len + i], "float {} of lane {}", i, j);
                }
            }
        }
    }

    /// An empty batch writes nothing.
    #[test]
    fn an_empty_batch_is_nothing_to_do() {
        let p = crate::config::GlobalConfig::default().ssim_params();
        ssim_stats_batch(&p, &[], &mut []);
    }
}
