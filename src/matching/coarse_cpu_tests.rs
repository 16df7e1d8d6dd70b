//! The fast coarse path against the twin: the same score bits for every pair, the same K-lists.

use super::*;
use crate::descriptors::DescriptorSet;
use crate::kernels::abi::TileParams;
use crate::kernels::ssim::SsimScratch;
use crate::kernels::ssim_topk::ssim_tile;
use crate::kernels::test_data::{params, shape};
use crate::matching::{coarse_topk, coarse_topk_twin};
use crate::util::SplitMix64;
use proptest::prelude::*;

/// [`crate::kernels::test_data::set`] as a descriptor set (the sources the coarse stage reads).
fn set(p: &SsimParams, n: usize, pool: usize, rng: &mut SplitMix64) -> DescriptorSet {
    let g = crate::kernels::test_data::set(p, n, pool, rng);
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

/// Terms derived from the descriptor alone (a store without stats) are the terms of the stored
/// stats, bit for bit, and both are the window means and sample variances of the descriptor,
/// computed here independently (each window's values summed in f64), at the layout the fast
/// kernel reads: a means plane, then a variances plane, rows of `stride` with zeros past `nw`.
#[test]
fn terms_from_the_descriptor_equal_terms_from_stats() {
    use crate::global::ssim_fast::{terms_from_descriptor, terms_from_stats, FastLayout};
    let p = params(64, 48, 7, true, (0.01, 0.03));
    let l = FastLayout::new(&p);
    let s = set(&p, 6, 6, &mut SplitMix64::new(4));
    let (gw, win, nw, nh) = (p.gw as usize, p.win as usize, p.nw as usize, p.nh as usize);
    let stride = l.terms_len() / (2 * nh);
    assert!(stride >= nw, "stride {stride} < nw {nw}");
    let (mut a, mut b, mut st) = (vec![0.0; l.terms_len()], vec![0.0; l.terms_len()], vec![0.0; p.stats_len()]);
    for i in 0..s.len() {
        terms_from_stats(&l, s.stats(i), &mut a);
        terms_from_descriptor(&p, &l, s.global(i), &mut st, &mut SsimScratch::default(), &mut b);
        assert_eq!(a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "descriptor {i}");
        let x = s.global(i);
        let mut expect = vec![0.0f64; l.terms_len()];
        let n2 = (win * win) as f64;
        for wy in 0..nh {
            for wx in 0..nw {
                let vals = (0..win).flat_map(|dy| (0..win).map(move |dx| x[(wy + dy) * gw + wx + dx] as f64));
                let (sum, sq) = vals.fold((0.0, 0.0), |(s, q), v| (s + v, q + v * v));
                let mean = sum / n2;
                expect[wy * stride + wx] = mean;
                expect[nh * stride + wy * stride + wx] = (sq / n2 - mean * mean) * p.cov_norm as f64;
            }
        }
        for (j, (&got, &want)) in b.iter().zip(&expect).enumerate() {
            assert!((got as f64 - want).abs() <= 1e-5 * want.abs().max(1.0), "descriptor {i}, term {j}: {got} vs {want}");
        }
    }
}
