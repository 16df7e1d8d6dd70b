//! A dense layer's product `y = x W^T + b` with the weights packed once, for the learned
//! matcher's linear layers (`verify::lighterglue`): a register-blocked micro-kernel in the manner
//! of BLIS and matrixmultiply (Goto and van de Geijn, "Anatomy of high-performance matrix
//! multiplication", TOMS 2008), with the weights in panels of 32 output columns laid out once at
//! load (a general product packs both operands on every call: an eighth of the matcher's time) and
//! the inputs read in place. Where the processor lacks AVX-512, or for widths that are not a
//! multiple of 32, matrixmultiply does the product.
//!
//! [`product`] runs the same kernel on a second operand read in place (the attention's weighted
//! sums of values).
//!
//! Each output is `fma(x[k], w[k], acc)` over k in order from 0 within each block of 256 of k,
//! each block's sum added to the bias (or 0) or to the blocks before: the arithmetic of
//! matrixmultiply 0.3.11's FMA kernels (AVX2 + FMA, AVX-512), so the paths give the same bits
//! (`tests::the_kernel_gives_matrixmultiplys_bits`, `tests::products_give_matrixmultiplys_bits`;
//! Cargo.toml pins the version). Its kernels without FMA round differently: on such processors
//! results differ from these in the last bits, as they did before this module.

use matrixmultiply::sgemm;

/// Output columns of one panel (two AVX-512 vectors).
const PANEL: usize = 32;
/// Rows of one micro-kernel call (16 accumulators).
#[cfg(target_arch = "x86_64")]
const ROWS: usize = 8;
/// Depth of one block of k: matrixmultiply's `S_KC` (its products over more are sums of blocks'
/// partial products, which the kernel adds in the same order).
#[cfg(target_arch = "x86_64")]
const KC: usize = 256;

/// `(rows - 1) ld + n`: the values that `rows` rows of `n`, `ld` apart, span (0 for no rows);
/// panics on overflow.
fn extent(rows: usize, ld: usize, n: usize) -> usize {
    match rows {
        0 => 0,
        _ => (rows - 1).checked_mul(ld).and_then(|v| v.checked_add(n)).expect("matrix extent overflows"),
    }
}

/// A dense layer: `n_out` x `n_in` weights (PyTorch's layout), bias, and the weights in panels.
pub struct Dense {
    w: Vec<f32>,
    b: Vec<f32>,
    n_in: usize,
    n_out: usize,
    /// For each panel of 32 outputs, `n_in` rows of its 32 weights; empty where the kernel is not used.
    #[cfg_attr(not(target_arch = "x86_64"), allow(dead_code))]
    panels: Vec<f32>,
}

impl Dense {
    /// The layer of weights `w` (`n_out` x `n_in`, row-major) and bias `b`.
    pub fn new(w: Vec<f32>, b: Vec<f32>, n_in: usize, n_out: usize) -> Dense {
        assert_eq!((w.len(), b.len()), (n_out * n_in, n_out));
        let mut panels = Vec::new();
        if cfg!(target_arch = "x86_64") && n_out.is_multiple_of(PANEL) && n_in > 0 {
            panels.reserve(n_out * n_in);
            for p in 0..n_out / PANEL {
                for k in 0..n_in {
                    panels.extend((0..PANEL).map(|j| w[(p * PANEL + j) * n_in + k]));
                }
            }
        }
        Dense { w, b, n_in, n_out, panels }
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
        let len = extent(rows, self.n_out, self.n_out);
        let mut y = Vec::with_capacity(len);
        self.write(x, self.n_in, rows, y.spare_capacity_mut().as_mut_ptr().cast(), self.n_out, len);
        // SAFETY: `write` stored every one of the rows x n_out outputs.
        unsafe { y.set_len(len) };
        y
    }

    /// The layer's outputs for `rows` rows of `x` (`lda` apart) into `y`'s rows (`ldy` apart;
    /// the first `n_out` values of each are written, the rest left as they are).
    pub fn forward_into(&self, x: &[f32], lda: usize, rows: usize, y: &mut [f32], ldy: usize) {
        self.write(x, lda, rows, y.as_mut_ptr(), ldy, y.len());
    }

    /// Writes the outputs through `y` (`len` values from it may be written).
    fn write(&self, x: &[f32], lda: usize, rows: usize, y: *mut f32, ldy: usize, len: usize) {
        let (k, n) = (self.n_in, self.n_out);
        assert!(lda >= k && ldy >= n && x.len() >= extent(rows, lda, k) && len >= extent(rows, ldy, n));
        if rows == 0 || n == 0 {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if !self.panels.is_empty() && std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the processor has AVX-512F (checked); x holds rows rows of k values lda
            // apart, y rows of n values ldy apart (asserted), the panels n x k values.
            return unsafe { kernel::product(x.as_ptr(), lda, rows, self.panels.as_ptr(), k * PANEL, PANEL, self.b.as_ptr(), k, n, y, ldy) };
        }
        for r in 0..rows {
            // SAFETY: row r's n outputs are within the asserted extent of y.
            unsafe { std::ptr::copy_nonoverlapping(self.b.as_ptr(), y.add(r * ldy), n) };
        }
        // SAFETY: as asserted; C holds the bias, added to (beta 1).
        unsafe { sgemm(rows, k, n, 1.0, x.as_ptr(), lda as isize, 1, self.w.as_ptr(), 1, k as isize, 1.0, y, ldy as isize, 1) }
    }
}

/// `a (rows x k, rows lda apart) b (k x n, rows ldb apart)`: `rows x n`, as matrixmultiply's
/// `sgemm` gives it (the same bits: the kernel where the processor has AVX-512 and `n` is a
/// multiple of 32, reading `b` in place; matrixmultiply otherwise).
pub fn product(a: &[f32], lda: usize, rows: usize, k: usize, b: &[f32], ldb: usize, n: usize) -> Vec<f32> {
    assert!(lda >= k && ldb >= n && a.len() >= extent(rows, lda, k) && b.len() >= extent(k, ldb, n));
    let len = extent(rows, n, n);
    if k == 0 {
        return vec![0.0; len]; // (matrixmultiply's zeros; the kernel would not read b, but address it)
    }
    let mut y: Vec<f32> = Vec::with_capacity(len);
    let out = y.spare_capacity_mut().as_mut_ptr().cast::<f32>();
    if rows > 0 && n > 0 {
        #[cfg(target_arch = "x86_64")]
        let kernel = n.is_multiple_of(PANEL) && std::arch::is_x86_feature_detected!("avx512f");
        #[cfg(not(target_arch = "x86_64"))]
        let kernel = false;
        if kernel {
            #[cfg(target_arch = "x86_64")]
            // SAFETY: AVX-512F present (checked); a, b and y within the asserted extents (b's
            // panel p is columns 32p.. of its rows).
            unsafe {
                kernel::product(a.as_ptr(), lda, rows, b.as_ptr(), PANEL, ldb, std::ptr::null(), k, n, out, n)
            }
        } else {
            // SAFETY: as asserted; beta 0 writes every element of C.
            unsafe { sgemm(rows, k, n, 1.0, a.as_ptr(), lda as isize, 1, b.as_ptr(), ldb as isize, 1, 0.0, out, n as isize, 1) }
        }
    }
    // SAFETY: every one of the rows x n outputs was written above (or there are none).
    unsafe { y.set_len(len) };
    y
}

#[cfg(target_arch = "x86_64")]
mod kernel {
    use crate::verify::dense::{KC, PANEL, ROWS};
    use std::arch::x86_64::*;

    /// Every row block and panel of `x (rows x k) W`: panel p's row kk (its 32 columns) at
    /// `w + p * panel_step + kk * row_step`; plus `bias` (32 a panel) where it is not null.
    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn product(
        x: *const f32,
        lda: usize,
        rows: usize,
        w: *const f32,
        panel_step: usize,
        row_step: usize,
        bias: *const f32,
        k: usize,
        n: usize,
        y: *mut f32,
        ldy: usize,
    ) {
        for p in 0..n / PANEL {
            let (w, bias) = (w.add(p * panel_step), if bias.is_null() { bias } else { bias.add(p * PANEL) });
            let mut r = 0;
            while r + ROWS <= rows {
                block::<ROWS>(x.add(r * lda), lda, w, row_step, bias, k, y.add(r * ldy + p * PANEL), ldy);
                r += ROWS;
            }
            while r < rows {
                block::<1>(x.add(r * lda), lda, w, row_step, bias, k, y.add(r * ldy + p * PANEL), ldy);
                r += 1;
            }
        }
    }

    /// `R` rows by one panel: for each block of `KC` of k, 2R accumulators from zero, added to
    /// the bias (first block; 0 without one) or to the sum so far.
    #[target_feature(enable = "avx512f")]
    #[inline]
    #[allow(clippy::too_many_arguments)]
    unsafe fn block<const R: usize>(x: *const f32, lda: usize, w: *const f32, row_step: usize, bias: *const f32, k: usize, y: *mut f32, ldy: usize) {
        let mut k0 = 0;
        loop {
            let k1 = (k0 + KC).min(k);
            let mut acc = [[_mm512_setzero_ps(); 2]; R];
            for kk in k0..k1 {
                let w0 = _mm512_loadu_ps(w.add(kk * row_step));
                let w1 = _mm512_loadu_ps(w.add(kk * row_step + 16));
                for (r, a) in acc.iter_mut().enumerate() {
                    let v = _mm512_set1_ps(*x.add(r * lda + kk));
                    a[0] = _mm512_fmadd_ps(v, w0, a[0]);
                    a[1] = _mm512_fmadd_ps(v, w1, a[1]);
                }
            }
            for (r, a) in acc.iter().enumerate() {
                let out = y.add(r * ldy);
                let (c0, c1) = match (k0, bias.is_null()) {
                    (0, true) => (a[0], a[1]),
                    (0, false) => (_mm512_add_ps(a[0], _mm512_loadu_ps(bias)), _mm512_add_ps(a[1], _mm512_loadu_ps(bias.add(16)))),
                    _ => (_mm512_add_ps(a[0], _mm512_loadu_ps(out)), _mm512_add_ps(a[1], _mm512_loadu_ps(out.add(16)))),
                };
                _mm512_storeu_ps(out, c0);
                _mm512_storeu_ps(out.add(16), c1);
            }
            if k1 >= k {
                break;
            }
            k0 = k1;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut g = crate::util::SplitMix64::new(seed);
        (0..n).map(|_| g.range(-0.5, 0.5) as f32).collect()
    }

    /// [`product`] against matrixmultiply at the attention's shapes: depths past one block of
    /// k (summed in matrixmultiply's order), rows around the kernel's blocks, `b` read in place
    /// from wider rows; widths that are not a multiple of 32 go to matrixmultiply.
    #[test]
    fn products_give_matrixmultiplys_bits() {
        for (k, n) in [(0, 96), (1, 32), (96, 96), (255, 96), (256, 96), (257, 96), (384, 96), (600, 64), (384, 40)] {
            for rows in [0, 1, 9, 300] {
                let (a, b) = (random(rows * k, 5 + k as u64), random((k + 1) * (2 * n + 1), 6));
                let got = product(&a, k, rows, k, &b[n + 1..], 2 * n + 1, n);
                let mut want = vec![0.0f32; rows * n];
                if rows > 0 {
                    // SAFETY: a is rows x k, b's rows from n + 1 hold n values 2n + 1 apart.
                    unsafe {
                        sgemm(
                            rows,
                            k,
                            n,
                            1.0,
                            a.as_ptr(),
                            k as isize,
                            1,
                            b[n + 1..].as_ptr(),
                            (2 * n + 1) as isize,
                            1,
                            0.0,
                            want.as_mut_ptr(),
                            n as isize,
                            1,
                        )
                    }
                }
                assert_eq!(got, want, "{rows} x {k} x {n}");
            }
        }
    }

    /// The kernel (where the processor has AVX-512) and matrixmultiply give the same bits at
    /// every shape the matcher uses and at row counts around the kernel's blocks; outputs within
    /// 1e-5 of the f64 product; `forward_into` leaves the rest of each row alone.
    #[test]
    fn the_kernel_gives_matrixmultiplys_bits() {
        #[cfg(target_arch = "x86_64")]
        if !std::arch::is_x86_feature_detected!("avx512f") {
            eprintln!("no AVX-512 on this processor: the kernel is not run, matrixmultiply is held to the f64 product only");
        }
        for (n_in, n_out) in [(96, 96), (96, 288), (96, 192), (192, 192), (192, 96), (64, 96), (96, 1), (96, 40)] {
            let (w, b) = (random(n_in * n_out, 1), random(n_out, 2));
            let dense = Dense::new(w.clone(), b.clone(), n_in, n_out);
            for rows in [0, 1, 7, 8, 9, 17, 300] {
                let x = random(rows * n_in, 3 + rows as u64);
                let got = dense.forward(&x, rows);
                let mut want = b.repeat(rows);
                if rows > 0 {
                    // SAFETY: x is rows x n_in, w n_out x n_in read transposed, want rows x n_out.
                    unsafe {
                        sgemm(
                            rows,
                            n_in,
                            n_out,
                            1.0,
                            x.as_ptr(),
                            n_in as isize,
                            1,
                            w.as_ptr(),
                            1,
                            n_in as isize,
                            1.0,
                            want.as_mut_ptr(),
                            n_out as isize,
                            1,
                        )
                    }
                }
                assert_eq!(got, want, "{rows} x {n_in} -> {n_out}");
                for r in 0..rows {
                    for j in 0..n_out {
                        let exact: f64 = b[j] as f64 + (0..n_in).map(|k| x[r * n_in + k] as f64 * w[j * n_in + k] as f64).sum::<f64>();
                        assert!((got[r * n_out + j] as f64 - exact).abs() < 1e-5, "{rows} x {n_in} -> {n_out} at ({r}, {j})");
                    }
                }
                // into every other row of a wider buffer, from inputs two rows apart
                let mut wide = vec![-7.0f32; rows * (n_out + 3)];
                let spread: Vec<f32> = x.chunks_exact(n_in.max(1)).flat_map(|row| row.iter().copied().chain(std::iter::repeat_n(9.0, 5))).collect();
                dense.forward_into(&spread, n_in + 5, rows, &mut wide, n_out + 3);
                for r in 0..rows {
                    assert_eq!(&wide[r * (n_out + 3)..r * (n_out + 3) + n_out], &want[r * n_out..(r + 1) * n_out]);
                    assert_eq!(&wide[r * (n_out + 3) + n_out..(r + 1) * (n_out + 3)], &[-7.0; 3]);
                }
            }
        }
    }
}
