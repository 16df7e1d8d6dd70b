//! Dense layers on the CPU, as the transformer networks use them (LighterGlue's attention and
//! MLPs; the layers a new network of the kind takes too): the linear layer and the matrix products
//! under it (ndarray's strided views over matrixmultiply's kernels, nothing copied), and the row
//! operations (softmax, log-softmax, layer norm + GELU) compiled for the best vector instructions
//! the processor has, each giving the same bits on every instruction set. Their device forms are
//! the kernels of `shaders/lighterglue.wgsl` (`semlook_kernels::lighterglue`).

use crate::util::lane_sum;
use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2, ShapeBuilder};
use semlook_kernels::lighterglue::erf_with;

/// Layer norm's epsilon (PyTorch's default).
const LN_EPS: f32 = 1e-5;

/// `rows` rows of `n` values `ld` apart in `v`, as a matrix view (strides: no copy).
fn view(v: &[f32], rows: usize, n: usize, ld: usize) -> ArrayView2<'_, f32> {
    let len = if rows == 0 { 0 } else { (rows - 1) * ld + n };
    ArrayView2::from_shape((rows, n).strides((ld, 1)), &v[..len.min(v.len())]).expect("rows within the slice")
}

/// `a (m x k) b^T`, `b` being `n x k`: `m x n`.
pub(crate) fn gemm_nt(a: &[f32], b: &[f32], m: usize, n: usize, k: usize) -> Vec<f32> {
    gemm_nt_strided(a, k, b, k, m, n, k)
}

/// [`gemm_nt`] on rows `lda` and `ldb` apart (the first `k` values of each): ndarray's product
/// (matrixmultiply's kernels) on strided views, nothing copied.
pub(crate) fn gemm_nt_strided(a: &[f32], lda: usize, b: &[f32], ldb: usize, m: usize, n: usize, k: usize) -> Vec<f32> {
    let mut c = vec![0.0f32; m * n];
    if m > 0 && n > 0 {
        let mut cv = ArrayViewMut2::from_shape((m, n), &mut c).expect("m x n");
        general_mat_mul(1.0, &view(a, m, k, lda), &view(b, n, k, ldb).t(), 0.0, &mut cv);
    }
    c
}

/// `a (m x k) b (k x n)`: `m x n`, `b`'s rows `ldb` apart (the first `n` values of each).
pub(crate) fn gemm_nn_strided(a: &[f32], b: &[f32], ldb: usize, m: usize, k: usize, n: usize) -> Vec<f32> {
    let mut c = vec![0.0f32; m * n];
    if m > 0 && n > 0 {
        let mut cv = ArrayViewMut2::from_shape((m, n), &mut c).expect("m x n");
        general_mat_mul(1.0, &view(a, m, k, k), &view(b, k, n, ldb), 0.0, &mut cv);
    }
    c
}

/// A linear layer `y = x W^T + b`: `n_out` x `n_in` weights in PyTorch's layout.
pub struct Linear {
    w: Vec<f32>,
    b: Vec<f32>,
    n_in: usize,
    n_out: usize,
}

impl Linear {
    /// The layer of weights `w` (`n_out` x `n_in`, row-major) and bias `b`.
    pub fn new(w: Vec<f32>, b: Vec<f32>, n_in: usize, n_out: usize) -> Linear {
        assert_eq!((w.len(), b.len()), (n_out * n_in, n_out));
        Linear { w, b, n_in, n_out }
    }
    /// Weights (`n_out` x `n_in`, row-major).
    pub fn weights(&self) -> &[f32] {
        &self.w
    }
    /// Bias.
    pub fn bias(&self) -> &[f32] {
        &self.b
    }
    /// Input width.
    pub fn n_in(&self) -> usize {
        self.n_in
    }
    /// Output width.
    pub fn n_out(&self) -> usize {
        self.n_out
    }
    /// `rows` rows of `x` (each `n_in` long) through the layer.
    pub fn forward(&self, x: &[f32], rows: usize) -> Vec<f32> {
        let mut y = vec![0.0f32; rows * self.n_out];
        self.forward_into(x, self.n_in, rows, &mut y, self.n_out);
        y
    }
    /// The layer's outputs for `rows` rows of `x` (`lda` apart) into `y`'s rows (`ldy` apart; the
    /// first `n_out` values of each are written, the rest left as they are).
    pub fn forward_into(&self, x: &[f32], lda: usize, rows: usize, y: &mut [f32], ldy: usize) {
        let (k, n) = (self.n_in, self.n_out);
        if rows == 0 || n == 0 {
            return;
        }
        let len = (rows - 1) * ldy + n;
        let mut yv = ArrayViewMut2::from_shape((rows, n).strides((ldy, 1)), &mut y[..len]).expect("rows within y");
        yv.rows_mut().into_iter().for_each(|mut r| r.assign(&ndarray::ArrayView1::from(&self.b[..])));
        general_mat_mul(1.0, &view(x, rows, k, lda), &view(&self.w, n, k, k).t(), 1.0, &mut yv);
    }
}

/// `a` (`m x n`, row-major) transposed, by tiles of 16 x 16 (the cache lines of both
/// sides stay in use).
pub(crate) fn transpose(a: &[f32], m: usize, n: usize) -> Vec<f32> {
    const TILE: usize = 16;
    let mut t = vec![0.0f32; m * n];
    for i0 in (0..m).step_by(TILE) {
        for j0 in (0..n).step_by(TILE) {
            for i in i0..(i0 + TILE).min(m) {
                for j in j0..(j0 + TILE).min(n) {
                    t[j * m + i] = a[i * n + j];
                }
            }
        }
    }
    t
}

/// An operation on one row of values.
pub(crate) trait RowOp {
    /// Applies the operation to the row.
    fn apply(&self, r: &mut [f32]);
}

/// The softmax of the row times a scale.
pub(crate) struct Softmax(pub(crate) f32);
/// The log-softmax of the row.
pub(crate) struct LogSoftmax;
/// Layer norm (gain, shift), then GELU.
pub(crate) struct NormGelu<'a>(pub(crate) &'a [f32], pub(crate) &'a [f32]);

impl RowOp for Softmax {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        softmax(r, self.0);
    }
}

impl RowOp for LogSoftmax {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        log_softmax(r);
    }
}

impl RowOp for NormGelu<'_> {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        layer_norm(r, self.0, self.1);
        for v in r.iter_mut() {
            *v = gelu(*v);
        }
    }
}

/// `op` on each row (`n` values) of `x`, compiled for the best vector instructions the processor
/// has (AVX-512 where it is found, else what `pulp` finds): the row operations below are written
/// without calls into libm, with lane-wise sums and with `for` loops (a `for_each`'s `fold` is
/// not always inlined), and are inlined here, so that their loops vectorise for this instruction
/// set (they were half of the matcher's time as scalar code). Every instruction set computes
/// each value by the same operations in the same order (sums and maxima by eight lanes whatever
/// the vector width): the same bits.
pub(crate) fn each_row(x: &mut [f32], n: usize, op: impl RowOp) {
    debug_assert!(n > 0 && x.len().is_multiple_of(n), "{} values in rows of {n}", x.len());
    if n == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vl")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
    {
        // SAFETY: the processor has the features the function is compiled for (checked above).
        return unsafe { rows_avx512(x, n, op) };
    }
    each_row_portable(x, n, op)
}

/// [`each_row`] through `pulp`'s dispatch (AVX2 where the processor has it, else scalar code).
fn each_row_portable(x: &mut [f32], n: usize, op: impl RowOp) {
    struct Rows<'a, O>(&'a mut [f32], usize, O);
    impl<O: RowOp> pulp::WithSimd for Rows<'_, O> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) {
            for r in self.0.chunks_exact_mut(self.1) {
                self.2.apply(r);
            }
        }
    }
    pulp::Arch::new().dispatch(Rows(x, n, op));
}

/// [`each_row`]'s loop compiled for AVX-512 (16 lanes; 5 % off the matcher's time on the
/// development machine's Xeon).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn rows_avx512(x: &mut [f32], n: usize, op: impl RowOp) {
    for r in x.chunks_exact_mut(n) {
        op.apply(r);
    }
}

/// The largest value of `r` (`-inf` for none), by eight lanes as [`lane_sum`] sums.
#[inline(always)]
fn row_max(r: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 8];
    let chunks = r.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a = a.max(v);
        }
    }
    tail.iter().chain(&acc).fold(f32::NEG_INFINITY, |a, &v| a.max(v))
}

/// A softmax's terms below e^this of the largest are 0 (4e-31 of it: nothing in an f32 sum), so
/// that no weight is subnormal after the normalisation (rows up to 10^7 values).
const SOFTMAX_FLOOR: f32 = -70.0;

/// The softmax of `r` times `scale` (> 0): the largest scaled value is the scaled largest
/// (rounding is monotonic), so the scale is applied in the pass that takes the exponentials (the
/// same bits as scaling the row first). (Taking their sum in that pass too kept the loop from
/// vectorising: 30 % slower.)
#[inline(always)]
fn softmax(r: &mut [f32], scale: f32) {
    let max = row_max(r) * scale;
    for x in r.iter_mut() {
        let d = *x * scale - max;
        *x = if d < SOFTMAX_FLOOR { 0.0 } else { exp(d) };
    }
    let inv = 1.0 / lane_sum(r, |v| v);
    for x in r.iter_mut() {
        *x *= inv;
    }
}

#[inline(always)]
fn log_softmax(r: &mut [f32]) {
    let max = row_max(r);
    let lse = lane_sum(r, |x| exp(x - max)).ln() + max;
    for x in r.iter_mut() {
        *x -= lse;
    }
}

#[inline(always)]
fn layer_norm(x: &mut [f32], g: &[f32], b: &[f32]) {
    let n = x.len() as f32;
    let mean = lane_sum(x, |v| v) / n;
    let var = lane_sum(x, |v| (v - mean) * (v - mean)) / n;
    let inv = 1.0 / (var + LN_EPS).sqrt();
    for ((v, &g), &b) in x.iter_mut().zip(g).zip(b) {
        *v = (*v - mean) * inv * g + b;
    }
}

/// e^x, within 2 ulp of the exact value for x in [-87.3, 88.3]; 0 below (e^x is under 1.3e-38
/// there, where a softmax's terms no longer count, and products of such values with others would
/// be subnormal: slow), 88.3's value above. Cephes' `expf` (Moshier), a Cody-Waite reduction by
/// ln 2 and a degree-5 minimax polynomial, without branches or calls.
#[inline(always)]
#[allow(clippy::excessive_precision)]
fn exp(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5 x 2^23: adding it rounds to the nearest integer
    const LN2_HI: f32 = 0.693_359_375;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const LOW: f32 = -87.3;
    let below = x < LOW;
    let x = x.clamp(LOW, 88.3);
    let t = x * std::f32::consts::LOG2_E + ROUND;
    let n = t - ROUND; // round(x / ln 2), in [-126, 127]
    let k = t.to_bits().wrapping_sub(ROUND.to_bits()) as i32; // the same, as an integer
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = (((((1.987_569_150_0e-4 * r + 1.398_199_950_7e-3) * r + 8.333_451_907_3e-3) * r + 4.166_579_589_4e-2) * r + 1.666_666_545_9e-1) * r
        + 5.000_000_120_1e-1)
        * (r * r)
        + r
        + 1.0;
    let e = p * f32::from_bits(((k + 127) as u32) << 23);
    if below {
        0.0
    } else {
        e
    }
}

/// GELU in its erf form, as `nn.GELU()`; erf by Abramowitz and Stegun 7.1.26 (|error| <=
/// 1.5e-7, the device's form: [`erf_with`]) on [`exp`].
#[inline(always)]
fn gelu(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_with(x * std::f32::consts::FRAC_1_SQRT_2, exp))
}

/// The logistic function, as the matcher's heads use it.
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `ln sigmoid(x)` without overflow.
pub(crate) fn log_sigmoid(x: f32) -> f32 {
    x.min(0.0) - (-x.abs()).exp().ln_1p()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_operations_match_their_definitions() {
        let mut r = [1.0f32, 2.0, 3.0];
        softmax(&mut r, 1.0);
        let e: Vec<f32> = [1.0f32, 2.0, 3.0].iter().map(|x| x.exp()).collect();
        let s: f32 = e.iter().sum();
        for (a, b) in r.iter().zip(&e) {
            assert!((a - b / s).abs() < 1e-6);
        }
        assert!((log_sigmoid(-30.0) - (-30.0)).abs() < 1e-4 && (log_sigmoid(0.0) - 0.5f32.ln()).abs() < 1e-6);
        assert!((gelu(1.0) - 0.841_344_7).abs() < 1e-6);
        let a = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]; // 2 x 3
        assert_eq!(gemm_nt(&a, &a, 2, 2, 3), vec![14.0, 32.0, 32.0, 77.0]);
        assert_eq!(gemm_nn_strided(&a, &[1.0, 0.0, 0.0, 1.0, 1.0, 1.0], 2, 2, 3, 2), vec![4.0, 5.0, 10.0, 11.0]);
        // rows further apart than their values: the padding is never read
        let padded = [1.0f32, 0.0, 9.0, 0.0, 1.0, 9.0, 1.0, 1.0];
        assert_eq!(gemm_nn_strided(&a, &padded, 3, 2, 3, 2), vec![4.0, 5.0, 10.0, 11.0]);
        let a_padded = [1.0f32, 2.0, 3.0, 9.0, 4.0, 5.0, 6.0];
        assert_eq!(gemm_nt_strided(&a_padded, 4, &a_padded, 4, 2, 2, 3), vec![14.0, 32.0, 32.0, 77.0]);
    }

    #[test]
    fn exp_is_within_two_ulp_over_its_range() {
        let mut worst = 0.0f64;
        for i in 0..=2_000_000 {
            let x = -87.3 + (88.3 + 87.3) * i as f32 / 2_000_000.0;
            let exact = (x as f64).exp();
            let ulp = 2f64.powi(exact.log2().floor() as i32 - 23); // of an f32 at `exact`
            worst = worst.max((exp(x) as f64 - exact).abs() / ulp);
        }
        assert!(worst <= 2.0, "exp: worst {worst} ulp");
        // softmax weights are 0 or normal, never subnormal (a row reaching e^-100 of its largest)
        let mut r: Vec<f32> = (0..500).map(|i| -(i as f32) * 0.2).collect();
        each_row(&mut r, 500, Softmax(1.0));
        assert!(r.iter().all(|v| *v == 0.0 || v.is_normal()), "a subnormal softmax weight");
        // 0 below the range (never subnormal), finite above it
        assert!(exp(-87.4) == 0.0 && exp(-1000.0) == 0.0 && exp(f32::NEG_INFINITY) == 0.0 && exp(1000.0).is_finite());
    }

    #[test]
    fn row_operations_give_the_same_bits_on_every_instruction_set() {
        let mut g = crate::util::SplitMix64::new(11);
        let mut rnd = || g.range(-20.0, 20.0) as f32;
        for n in [1, 7, 8, 9, 31, 96, 192, 383] {
            let x: Vec<f32> = (0..3 * n).map(|_| rnd()).collect();
            let (g, b): (Vec<f32>, Vec<f32>) = (0..n).map(|_| (rnd(), rnd())).unzip();
            // each operation inlined into each loop (as the matcher runs them), against the same
            // operation applied row by row in this function (compiled for the baseline target)
            macro_rules! same_bits {
                ($op:expr) => {{
                    let (mut best, mut portable, mut plain) = (x.clone(), x.clone(), x.clone());
                    each_row(&mut best, n, $op);
                    each_row_portable(&mut portable, n, $op);
                    plain.chunks_exact_mut(n).for_each(|r| $op.apply(r));
                    assert_eq!(best, portable, "n {n}: {}", stringify!($op));
                    assert_eq!(best, plain, "n {n}: {}", stringify!($op));
                }};
            }
            same_bits!(Softmax(0.37));
            same_bits!(LogSoftmax);
            same_bits!(NormGelu(&g, &b));
        }
    }

    #[test]
    fn row_operations_match_their_definitions_at_every_length() {
        let mut g = crate::util::SplitMix64::new(7);
        let mut rnd = || g.range(-6.0, 6.0) as f32;
        for n in 1..=41 {
            let row: Vec<f32> = (0..n).map(|_| rnd()).collect();
            let max = row.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
            let sum: f64 = row.iter().map(|&v| (v as f64 - max).exp()).sum();
            // three rows through each_row: the row and two others (rows must not leak into each other)
            let three: Vec<f32> = row.iter().map(|v| v + 3.0).chain(row.iter().copied()).chain(row.iter().map(|v| -v)).collect();
            let (mut sm, mut lsm) = (three.clone(), three.clone());
            each_row(&mut sm, n, Softmax(1.0));
            each_row(&mut lsm, n, LogSoftmax);
            // a scale is folded into the exponentials: the same bits as the softmax of the scaled rows
            let s = 0.37f32;
            let (mut scaled_first, mut folded) = (three.iter().map(|v| v * s).collect::<Vec<f32>>(), three.clone());
            each_row(&mut scaled_first, n, Softmax(1.0));
            each_row(&mut folded, n, Softmax(s));
            assert_eq!(scaled_first, folded, "softmax with a scale, n {n}");
            let (sm, lsm) = (&sm[n..2 * n], &lsm[n..2 * n]); // the middle row; row + 3's softmax is the same: below
            for i in 0..n {
                let p = (row[i] as f64 - max).exp() / sum;
                assert!((sm[i] as f64 - p).abs() <= 1e-6 * p.max(1e-3), "softmax n {n} i {i}: {} vs {p}", sm[i]);
                assert!((lsm[i] as f64 - p.ln()).abs() <= 2e-6 * p.ln().abs().max(1.0), "log_softmax n {n} i {i}");
            }
            let (g, b): (Vec<f32>, Vec<f32>) = (0..n).map(|_| (rnd(), rnd())).unzip();
            let mut ln = three.clone();
            each_row(&mut ln, n, NormGelu(&g, &b));
            let mut first = three[..n].to_vec();
            each_row(&mut first, n, Softmax(1.0));
            assert!(first.iter().zip(sm).all(|(a, b)| (a - b).abs() <= 1e-6), "softmax of row + 3, n {n}");
            let mean = row.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
            let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n as f64;
            for i in 0..n {
                let norm = ((row[i] as f64 - mean) / (var + LN_EPS as f64).sqrt() * g[i] as f64 + b[i] as f64) as f32;
                let want = 0.5 * norm * (1.0 + semlook_kernels::lighterglue::lg_erf(norm * std::f32::consts::FRAC_1_SQRT_2));
                let got = ln[n + i];
                assert!((got - want).abs() <= 1e-5 * want.abs().max(1.0), "layer norm + GELU n {n} i {i}: {got} vs {want}");
            }
        }
        // GELU on the fast exp against the device's form on the standard one
        for i in -4000..=4000 {
            let x = i as f32 / 400.0;
            let want = 0.5 * x * (1.0 + semlook_kernels::lighterglue::lg_erf(x * std::f32::consts::FRAC_1_SQRT_2));
            assert!((gelu(x) - want).abs() <= 1e-6 * want.abs().max(1.0), "gelu({x}): {} vs {want}", gelu(x));
        }
    }
}
