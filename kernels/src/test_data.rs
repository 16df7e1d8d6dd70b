//! Global descriptors for the coarse kernels' property tests: every kind of input the kernels
//! must score alike (smooth fields, noise, flat windows and exact ties, constants).

use crate::abi::SsimParams;
use crate::rng::SplitMix64;
use crate::ssim::{ssim_stats, SsimScratch};
use proptest::prelude::*;

/// A descriptor of one of four kinds: a smooth field (like a distance map), uniform noise,
/// three levels only (flat windows, exact ties), or a constant.
pub fn descriptor(p: &SsimParams, rng: &mut SplitMix64) -> Vec<f32> {
    let (w, len) = (p.gw as usize, p.len());
    match rng.below(4) {
        0 => {
            let (fx, fy, ph) = (rng.range(0.05, 0.6), rng.range(0.05, 0.6), rng.range(0.0, 6.0));
            (0..len).map(|k| (0.5 + 0.5 * (fx * (k % w) as f64 + ph).sin() * (fy * (k / w) as f64).cos()) as f32).collect()
        }
        1 => (0..len).map(|_| rng.next_f64() as f32).collect(),
        2 => (0..len).map(|_| rng.below(3) as f32 * 0.5).collect(),
        _ => vec![rng.next_f64() as f32; len],
    }
}

/// `n` global descriptors and their SSIM statistics, concatenated as the kernels read them.
pub struct Globals {
    /// The descriptors, concatenated.
    pub globals: Vec<f32>,
    /// Their SSIM statistics, concatenated.
    pub global_stats: Vec<f32>,
}

/// `n` descriptors drawn (with repeats, so some references tie exactly) from a pool of `pool`.
pub fn set(p: &SsimParams, n: usize, pool: usize, rng: &mut SplitMix64) -> Globals {
    let pool: Vec<Vec<f32>> = (0..pool.max(1)).map(|_| descriptor(p, rng)).collect();
    let mut out = Globals { globals: Vec::with_capacity(n * p.len()), global_stats: vec![0.0; n * p.stats_len()] };
    let mut scratch = SsimScratch::default();
    for i in 0..n {
        let g = &pool[rng.below(pool.len())];
        ssim_stats(p, g, &mut out.global_stats[i * p.stats_len()..(i + 1) * p.stats_len()], &mut scratch);
        out.globals.extend_from_slice(g);
    }
    out
}

/// The parameters of a `w` x `h` descriptor, window `win`, covariance and constants as given.
pub fn params(w: usize, h: usize, win: usize, sample: bool, k: (f64, f64)) -> SsimParams {
    SsimParams::new(w, h, win, k, sample)
}

/// Descriptor sizes from one window to 40 x 30 past it, odd windows 3..=11, both covariance
/// normalisations, the default constants, zero constants (NaN windows) and large ones.
pub fn shape() -> impl Strategy<Value = SsimParams> {
    (3usize..12, 0usize..40, 0usize..30, any::<bool>(), prop::sample::select(vec![(0.01, 0.03), (0.0, 0.0), (0.1, 0.2)])).prop_map(
        |(win, dw, dh, sample, k)| {
            let win = win | 1; // odd, 3..=11
            params(win + dw, win + dh, win, sample, k)
        },
    )
}
