//! The block kernel's twin against the pair twin: the same bits for every pair, whatever the
//! block shape; and the reason the kernel keeps direct window sums.

use super::*;
use crate::abi::TileParams;
use crate::rng::SplitMix64;
use crate::ssim::{ssim_pair, ssim_stats, SsimScratch};
use crate::ssim_topk::ssim_tile;
use crate::test_data::{params, set, shape};
use proptest::prelude::*;

fn same(a: f32, b: f32) -> bool {
    a.to_bits() == b.to_bits() || (a.is_nan() && b.is_nan())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Every score of `ssim_block` has `ssim_tile`'s bits, for every block shape that fits, with
    /// the pass starting inside the chunk and partial blocks on both edges.
    #[test]
    fn block_scores_equal_the_pair_twin_bit_for_bit(p in shape(), nq in 1usize..7, nr in 1usize..12, first in 0usize..3, seed in any::<u64>(), shrink in 0u32..3) {
        let mut rng = SplitMix64::new(seed);
        let (q, r) = (set(&p, nq, nq, &mut rng), set(&p, nr + first, 5, &mut rng));
        let tp = TileParams { queries: nq as u32, tile_len: nr as u32, tile_start: 0, k: 1 };
        let (len, sl) = (p.len(), p.stats_len());
        let mut twin = vec![0.0; nq * nr];
        ssim_tile(&p, &tp, &q.globals, &q.global_stats, &r.globals[first * len..], &r.global_stats[first * sl..], &mut twin);
        let (rb, qb) = block_shape(&p).unwrap();
        // the chosen shape, and smaller ones
        let (rb, qb) = (rb.saturating_sub(shrink).max(1), qb.saturating_sub(shrink).max(1));
        let ps = PassParams { queries: nq as u32, refs: nr as u32, ref_first: first as u32, rb, qb, ..Default::default() };
        let mut block = vec![f32::NAN; nq * nr];
        ssim_block(&p, &ps, &q.globals, &q.global_stats, &mut block, &r.globals, &r.global_stats);
        for (i, (a, b)) in block.iter().zip(&twin).enumerate() {
            prop_assert!(same(*a, *b), "{rb}x{qb} pair {i}: block {a:e} twin {b:e}");
        }
    }
}

/// The default descriptor size takes blocks of 2 references x 3 queries (the ring is the limit);
/// small descriptors take the full 8 pairs; descriptors wider than the product row take none.
#[test]
fn block_shapes_fit_the_workgroup_arrays() {
    assert_eq!(block_shape(&params(64, 48, 7, true, (0.01, 0.03))), Some((2, 3)));
    assert_eq!(block_shape(&params(16, 12, 7, true, (0.01, 0.03))), Some((2, 4)));
    assert_eq!(block_shape(&params(600, 8, 3, true, (0.01, 0.03))), None);
}

/// Running-sum box filters: each window sum from its neighbour's, one addition and one
/// subtraction (what the kernel would do instead of `win` additions).
fn ssim_running(p: &SsimParams, x: &[f32], xs: &[f32], y: &[f32], ys: &[f32]) -> f32 {
    let (gw, gh, win, nw, nh) = (p.gw as usize, p.gh as usize, p.win as usize, p.nw as usize, p.nh as usize);
    let prod: Vec<f32> = x.iter().zip(y).map(|(a, b)| a * b).collect();
    let mut rows = vec![0.0f32; gh * nw];
    for r in 0..gh {
        let src = &prod[r * gw..(r + 1) * gw];
        let mut s: f32 = src[..win].iter().sum();
        rows[r * nw] = s;
        for c in 1..nw {
            s = s + src[c + win - 1] - src[c - 1];
            rows[r * nw + c] = s;
        }
    }
    let n = nw * nh;
    let mut total = 0.0f64;
    for c in 0..nw {
        let mut s: f32 = (0..win).map(|k| rows[k * nw + c]).sum();
        for r in 0..nh {
            if r > 0 {
                s = s + rows[(r + win - 1) * nw + c] - rows[(r - 1) * nw + c];
            }
            let w = r * nw + c;
            total += ssim_window(p, s, xs[w], ys[w], xs[n + w], ys[n + w]) as f64;
        }
    }
    (total / n as f64) as f32
}

/// Why the kernel keeps direct sums: on near-flat descriptors (values around 0.9, noise 1e-4, as
/// in a distance map far from every edge) running sums miss the twin by more than 1e-5, because
/// the covariance E[xy] - mx*my amplifies their rounding by up to 2 / C2.
#[test]
fn running_sums_miss_the_twin_on_near_flat_descriptors() {
    let p = params(64, 48, 7, true, (0.01, 0.03));
    let mut rng = SplitMix64::new(1);
    let mut flat = || -> (Vec<f32>, Vec<f32>) {
        let g: Vec<f32> = (0..p.len()).map(|_| 0.9 + 1e-4 * rng.next_f64() as f32).collect();
        let mut st = vec![0.0; p.stats_len()];
        ssim_stats(&p, &g, &mut st, &mut SsimScratch::default());
        (g, st)
    };
    let ((x, xs), (y, ys)) = (flat(), flat());
    let twin = ssim_pair(&p, &x, &xs, &y, &ys, &mut SsimScratch::default());
    let running = ssim_running(&p, &x, &xs, &y, &ys);
    assert!((running - twin).abs() > 1e-5, "running {running} twin {twin}");
}
