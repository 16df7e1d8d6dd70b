//! A dense layer's product `y = x W^T + b` with the weights packed once, for the learned
//! matcher's linear layers (`verify::lighterglue`): a register-blocked micro-kernel in the manner
//! of BLIS and matrixmultiply (Goto and van de Geijn, "Anatomy of high-performance matrix
//! multiplication", TOMS 2008), with the weights in panels of 32 output columns laid out once at
//! load (a general product packs both operands on every call: an eighth of the matcher's time) and
//! the inputs read in place. Where the processor lacks AVX-512, or for widths that are not a
//! multiple of 32, matrixmultiply does the product.
//!
//! Each output is `fma(x[k], w[k], acc)` over k in order from 0, then plus its bias: the
//! arithmetic of matrixmultiply's AVX-512 kernel at these depths (one block of k), so both paths
//! give the same bits (`tests::the_kernel_gives_matrixmultiplys_bits`).

use matrixmultiply::sgemm;

/// Output columns of one panel (two AVX-512 vectors).
const PANEL: usize = 32;
/// Rows of one micro-kernel call (16 accumulators).
const ROWS: usize = 8;

/// A dense layer: `n_out` x `n_in` weights (PyTorch's layout), bias, and the weights in panels.
pub struct Dense {
    w: Vec<f32>,
    b: Vec<f32>,
    n_in: usize,
    n_out: usize,
    /// For each panel of 32 outputs, `n_in` rows of its 32 weights; empty where the kernel is not used.
    panels: Vec<f32>,
}

impl Dense {
    /// The layer of weights `w` (`n_out` x `n_in`, row-major) and bias `b`.
    pub fn new(w: Vec<f32>, b: Vec<f32>, n_in: usize, n_out: usize) -> Dense {
        assert_eq!((w.len(), b.len()), (n_out * n_in, n_out));
        let mut panels = Vec::new();
        if n_out.is_multiple_of(PANEL) && n_in > 0 {
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
        let mut y = Vec::with_capacity(rows * self.n_out);
        self.write(x, self.n_in, rows, y.spare_capacity_mut().as_mut_ptr().cast(), self.n_out, rows * self.n_out);
        // SAFETY: `write` stored every one of the rows x n_out outputs.
        unsafe { y.set_len(rows * self.n_out) };
        y
    }

    /// The layer's outputs for `rows` rows of `x` (`lda` apart) into `y`'s rows (`ldy` apart;
    /// the first `n_out` values of each are written, the rest left as they are).
    pub fn forward_into(&self, x: &[f32], lda: usize, rows: usize, y: &mut [f32], ldy: usize) {
        assert!(rows == 0 || y.len() >= (rows - 1) * ldy + self.n_out);
        self.write(x, lda, rows, y.as_mut_ptr(), ldy, y.len());
    }

    /// Writes the outputs through `y` (`len` values from it may be written).
    fn write(&self, x: &[f32], lda: usize, rows: usize, y: *mut f32, ldy: usize, len: usize) {
        let (k, n) = (self.n_in, self.n_out);
        assert!(rows == 0 || (lda >= k && x.len() >= (rows - 1) * lda + k && ldy >= n && len >= (rows - 1) * ldy + n));
        if rows == 0 || n == 0 {
            return;
        }
        #[cfg(target_arch = "x86_64")]
        if !self.panels.is_empty() && std::arch::is_x86_feature_detected!("avx512f") {
            // SAFETY: the processor has AVX-512F (checked); x holds rows rows of k values lda
            // apart, y rows of n values ldy apart (asserted), the panels n x k values.
            return unsafe { kernel::product(x.as_ptr(), lda, rows, &self.panels, &self.b, k, n, y, ldy) };
        }
        for r in 0..rows {
            // SAFETY: row r's n outputs are within the asserted extent of y.
            unsafe { std::ptr::copy_nonoverlapping(self.b.as_ptr(), y.add(r * ldy), n) };
        }
        // SAFETY: as asserted; C holds the bias, added to (beta 1).
        unsafe { sgemm(rows, k, n, 1.0, x.as_ptr(), lda as isize, 1, self.w.as_ptr(), 1, k as isize, 1.0, y, ldy as isize, 1) }
    }
}

#[cfg(target_arch = "x86_64")]
mod kernel {
    use super::{PANEL, ROWS};
    use std::arch::x86_64::*;

    /// Every row block and panel.
    #[target_feature(enable = "avx512f")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn product(x: *const f32, lda: usize, rows: usize, panels: &[f32], b: &[f32], k: usize, n: usize, y: *mut f32, ldy: usize) {
        for p in 0..n / PANEL {
            let (w, bias) = (panels.as_ptr().add(p * k * PANEL), b.as_ptr().add(p * PANEL));
            let mut r = 0;
            while r + ROWS <= rows {
                block::<ROWS>(x.add(r * lda), lda, w, bias, k, y.add(r * ldy + p * PANEL), ldy);
                r += ROWS;
            }
            while r < rows {
                block::<1>(x.add(r * lda), lda, w, bias, k, y.add(r * ldy + p * PANEL), ldy);
                r += 1;
            }
        }
    }

    /// `R` rows by one panel: 2R accumulators over k, then the bias.
    #[target_feature(enable = "avx512f")]
    #[inline]
    unsafe fn block<const R: usize>(x: *const f32, lda: usize, w: *const f32, bias: *const f32, k: usize, y: *mut f32, ldy: usize) {
        let mut acc = [[_mm512_setzero_ps(); 2]; R];
        for kk in 0..k {
            let w0 = _mm512_loadu_ps(w.add(kk * PANEL));
            let w1 = _mm512_loadu_ps(w.add(kk * PANEL + 16));
            for (r, a) in acc.iter_mut().enumerate() {
                let v = _mm512_set1_ps(*x.add(r * lda + kk));
                a[0] = _mm512_fmadd_ps(v, w0, a[0]);
                a[1] = _mm512_fmadd_ps(v, w1, a[1]);
            }
        }
        let (b0, b1) = (_mm512_loadu_ps(bias), _mm512_loadu_ps(bias.add(16)));
        for (r, a) in acc.iter().enumerate() {
            _mm512_storeu_ps(y.add(r * ldy), _mm512_add_ps(a[0], b0));
            _mm512_storeu_ps(y.add(r * ldy + 16), _mm512_add_ps(a[1], b1));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn random(n: usize, seed: u64) -> Vec<f32> {
        let mut s = seed;
        (0..n)
            .map(|_| {
                s = s.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                (s >> 40) as f32 / (1u64 << 24) as f32 - 0.5
            })
            .collect()
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
