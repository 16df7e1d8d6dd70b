//! SSIM window statistics of a batch of descriptors: the CPU twins of `shaders/ssim_stats.wgsl`
//! (`stats_row_sums`, `stats_windows`), same bindings and loop shape. Their values equal
//! [`super::ssim::ssim_stats`]'s (the CPU path's) bit for bit: the same separable sums, in the
//! same order (tested below).

use super::abi::{Dims, SsimParams};

/// Row sums of x and x*x over every window column of every row of `dims.frames` descriptors from
/// descriptor `dims.first` of `desc` (gw x gh each) into `rows` ([x sums | x*x sums] of gh x nw
/// per frame of the run). One invocation per (row, window column) and frame.
pub fn stats_row_sums(p: &SsimParams, dims: &Dims, desc: &[f32], rows: &mut [f32]) {
    let (gw, gh, nw, win) = (p.gw as usize, p.gh as usize, p.nw as usize, p.win as usize);
    let n = gh * nw;
    for f in 0..dims.frames as usize {
        for i in 0..n {
            let (r, c) = (i / nw, i % nw);
            let src = (dims.first as usize + f) * gw * gh + r * gw + c;
            let (mut s, mut s2) = (0.0f32, 0.0f32);
            for k in 0..win {
                let v = desc[src + k];
                s += v;
                s2 += v * v;
            }
            rows[2 * f * n + i] = s;
            rows[(2 * f + 1) * n + i] = s2;
        }
    }
}

/// Window means and (sample) variances of the run's descriptors from their row sums into `stats`
/// ([means | variances] per descriptor, from descriptor `dims.first`). One invocation per window
/// and frame.
pub fn stats_windows(p: &SsimParams, dims: &Dims, rows: &[f32], stats: &mut [f32]) {
    let (gh, nw, win) = (p.gh as usize, p.nw as usize, p.win as usize);
    let (n, rn) = (p.windows(), gh * nw);
    let inv = 1.0 / (p.win * p.win) as f32;
    for f in 0..dims.frames as usize {
        for i in 0..n {
            let (r, c) = (i / nw, i % nw);
            let (mut s, mut s2) = (0.0f32, 0.0f32);
            for k in 0..win {
                s += rows[2 * f * rn + (r + k) * nw + c];
                s2 += rows[(2 * f + 1) * rn + (r + k) * nw + c];
            }
            let m = s * inv;
            let at = 2 * (dims.first as usize + f) * n;
            stats[at + i] = m;
            stats[at + n + i] = (s2 * inv - m * m) * p.cov_norm;
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::rng::SplitMix64;
    use crate::ssim::{ssim_stats, SsimScratch};
    use crate::test_data::{set, shape};
    use proptest::prelude::*;

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(48))]

        /// The batch twins give `ssim_stats`'s bits for every frame, every shape and kind of
        /// descriptor (smooth, noise, flat windows, constants).
        #[test]
        fn the_batch_twins_equal_the_cpu_stats_bit_for_bit(p in shape(), frames in 1usize..5, seed in any::<u64>()) {
            let g = set(&p, frames, frames, &mut SplitMix64::new(seed));
            let mut stats = vec![0.0; frames * p.stats_len()];
            // in runs of up to two frames, as a stored map's chunk is computed
            for first in (0..frames).step_by(2) {
                let dims = Dims { frames: 2.min(frames - first) as u32, first: first as u32, ..Default::default() };
                let mut rows = vec![0.0; 2 * 2 * p.gh as usize * p.nw as usize];
                stats_row_sums(&p, &dims, &g.globals, &mut rows);
                stats_windows(&p, &dims, &rows, &mut stats);
            }
            for f in 0..frames {
                let mut want = vec![0.0; p.stats_len()];
                ssim_stats(&p, &g.globals[f * p.len()..(f + 1) * p.len()], &mut want, &mut SsimScratch::default());
                let got = &stats[f * p.stats_len()..(f + 1) * p.stats_len()];
                prop_assert!(got.iter().zip(&want).all(|(a, b)| a.to_bits() == b.to_bits()), "frame {f}");
            }
        }
    }
}
