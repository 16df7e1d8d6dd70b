//! The fast coarse path against the twin: the same score bits for every pair, the same K-lists.

use super::*;
use crate::descriptors::DescriptorSet;
use crate::matching::{coarse_topk, coarse_topk_twin};
use crate::util::SplitMix64;
use proptest::prelude::*;
use semlook_kernels::abi::TileParams;
use semlook_kernels::ssim_topk::ssim_tile;
use semlook_kernels::test_data::{params, shape};

/// [`semlook_kernels::test_data::set`] as a descriptor set (the sources the coarse stage reads).
fn set(p: &SsimParams, n: usize, pool: usize, rng: &mut SplitMix64) -> DescriptorSet {
    let g = semlook_kernels::test_data::set(p, n, pool, rng);
    let mut s = DescriptorSet::new(p, 1, 0, 0);
    for i in 0..n {
        s.push(&crate::descriptors::EncodedImage {
            id: format!("d{i}"),
            width: 1,
            height: 1,
            global: g.globals[i * p.len()..(i + 1) * p.len()].to_vec(),
            global_stats: g.global_stats[i * p.stats_len()..(i + 1) * p.stats_len()].to_vec(),
            forest: crate::local::Forest { neighbour_slots: 1, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: Default::default(),
            pose: None,
        })
        .unwrap();
    }
    s
}

/// Fast scores of every pair (query-major), with the given instruction set.
fn fast_scores(p: &SsimParams, simd: Simd, q: &DescriptorSet, r: &DescriptorSet) -> Vec<f32> {
    let mut x = CoarseCpu::with_simd(p, simd);
    x.prepare(&q.global_stats, q.len());
    let mut by_ref = vec![0.0; q.len() * r.len()];
    x.score_tile(&q.globals, &r.globals, &r.global_stats, &mut by_ref);
    (0..q.len() * r.len()).map(|i| by_ref[(i % r.len()) * q.len() + i / r.len()]).collect()
}

fn same(a: f32, b: f32) -> bool {
    a == b || (a.is_nan() && b.is_nan())
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(48))]

    /// Every pair's fast score has the twin's bits (both instruction sets), whatever the sizes,
    /// window, covariance normalisation and constants (C1 = C2 = 0 gives NaN windows).
    #[test]
    fn fast_scores_equal_the_twin_bit_for_bit(p in shape(), nq in 1usize..5, nr in 1usize..20, seed in any::<u64>()) {
        let mut rng = SplitMix64::new(seed);
        let (q, r) = (set(&p, nq, nq, &mut rng), set(&p, nr, 6, &mut rng));
        let tp = TileParams { queries: nq as u32, tile_len: nr as u32, tile_start: 0, k: 1 };
        let mut twin = vec![0.0; nq * nr];
        ssim_tile(&p, &tp, &q.globals, &q.global_stats, &r.globals, &r.global_stats, &mut twin);
        for simd in [Simd::Best, Simd::Scalar, Simd::Twin] {
            let fast = fast_scores(&p, simd, &q, &r);
            for (i, (a, b)) in fast.iter().zip(&twin).enumerate() {
                prop_assert!(same(*a, *b), "{simd:?} pair {i}: fast {a:e} ({:#x}) twin {b:e} ({:#x})", a.to_bits(), b.to_bits());
            }
        }
    }

    /// The production coarse stage (fast path) returns exactly the twin path's K-lists: same
    /// references in the same order (ties to the lower index; the maps repeat descriptors) and
    /// the same scores, for any K and tile size.
    #[test]
    fn fast_top_k_equals_the_twin(nq in 1usize..5, nr in 1usize..60, k in 1usize..12, tile in 1usize..70, pool in 1usize..8, seed in any::<u64>()) {
        let p = params(16, 12, 5, true, (0.01, 0.03));
        let mut rng = SplitMix64::new(seed);
        let (q, r) = (set(&p, nq, nq, &mut rng), set(&p, nr, pool, &mut rng));
        prop_assert_eq!(coarse_topk(&r, &q, &p, k, tile), coarse_topk_twin(&r, &q, &p, k, tile));
    }
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(24))]

    /// Descriptors wider than 64 windows a row (which `shape()` never makes): the reduction's
    /// lanes then hold windows of two rows' columns, and the fast path still adds them in the
    /// twin's order, bit for bit.
    #[test]
    fn wide_descriptors_equal_the_twin_bit_for_bit(nw in 55usize..150, dh in 0usize..5, win in prop::sample::select(vec![3usize, 5, 7]), nr in 1usize..12, seed in any::<u64>()) {
        let p = params(win + nw - 1, win + dh, win, true, (0.01, 0.03));
        let mut rng = SplitMix64::new(seed);
        let (q, r) = (set(&p, 2, 2, &mut rng), set(&p, nr, 4, &mut rng));
        let tp = TileParams { queries: 2, tile_len: nr as u32, tile_start: 0, k: 1 };
        let mut twin = vec![0.0; 2 * nr];
        ssim_tile(&p, &tp, &q.globals, &q.global_stats, &r.globals, &r.global_stats, &mut twin);
        for simd in [Simd::Best, Simd::Scalar] {
            let fast = fast_scores(&p, simd, &q, &r);
            for (i, (a, b)) in fast.iter().zip(&twin).enumerate() {
                prop_assert!(same(*a, *b), "{simd:?} nw {nw} pair {i}: fast {a:e} ({:#x}) twin {b:e} ({:#x})", a.to_bits(), b.to_bits());
            }
        }
    }
}

/// A batch larger than one query pass (and a block count that does not divide the tile):
/// scores still equal the twin's.
#[test]
fn several_query_passes_equal_the_twin() {
    let p = params(12, 10, 3, true, (0.01, 0.03));
    let mut rng = SplitMix64::new(9);
    let (q, r) = (set(&p, QUERIES_PER_PASS + 3, 40, &mut rng), set(&p, 2 * REFS_PER_BLOCK + 3, 19, &mut rng));
    let tp = TileParams { queries: q.len() as u32, tile_len: r.len() as u32, tile_start: 0, k: 1 };
    let mut twin = vec![0.0; q.len() * r.len()];
    ssim_tile(&p, &tp, &q.globals, &q.global_stats, &r.globals, &r.global_stats, &mut twin);
    assert_eq!(fast_scores(&p, Simd::Best, &q, &r), twin);
    assert_eq!(coarse_topk(&r, &q, &p, 5, 7), coarse_topk_twin(&r, &q, &p, 5, 7));
}
