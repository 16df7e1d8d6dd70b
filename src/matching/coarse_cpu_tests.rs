//! The fast coarse path against the twin: the same score bits for every pair, the same K-lists.

use super::*;
use crate::config::GlobalConfig;
use crate::descriptors::EncodedImage;
use crate::global::ssim::{ssim_stats, SsimScratch};
use crate::local::Forest;
use crate::descriptors::DescriptorSet;
use crate::matching::ssim_topk::{ssim_tile, TileParams};
use crate::matching::{coarse_topk, coarse_topk_twin};
use crate::util::SplitMix64;
use proptest::prelude::*;

/// A descriptor of one of four kinds: a smooth field (like a distance map), uniform noise,
/// three levels only (flat windows, exact ties), or a constant.
fn descriptor(p: &SsimParams, rng: &mut SplitMix64) -> Vec<f32> {
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

/// A set of `n` descriptors drawn (with repeats, so some references tie exactly) from a pool of `pool`.
fn set(p: &SsimParams, n: usize, pool: usize, rng: &mut SplitMix64) -> DescriptorSet {
    let pool: Vec<Vec<f32>> = (0..pool.max(1)).map(|_| descriptor(p, rng)).collect();
    let mut s = DescriptorSet::new(p, 1, 0, 0);
    let mut scratch = SsimScratch::default();
    for i in 0..n {
        let g = pool[rng.below(pool.len())].clone();
        let mut stats = vec![0.0; p.stats_len()];
        ssim_stats(p, &g, &mut stats, &mut scratch);
        s.push(&EncodedImage { id: format!("d{i}"), width: 1, height: 1, global: g, global_stats: stats, forest: Forest { neighbour_slots: 1, ..Default::default() }, appearance: vec![], hog: vec![] }).unwrap();
    }
    s
}

fn params(w: usize, h: usize, win: usize, sample: bool, k: (f64, f64)) -> SsimParams {
    SsimParams::new(&GlobalConfig { width: w, height: h, ssim_window: win, ssim_sample_covariance: sample, ssim_k1: k.0, ssim_k2: k.1, ..Default::default() })
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

fn shape() -> impl Strategy<Value = SsimParams> {
    (3usize..12, 0usize..40, 0usize..30, any::<bool>(), prop::sample::select(vec![(0.01, 0.03), (0.0, 0.0), (0.1, 0.2)]))
        .prop_map(|(win, dw, dh, sample, k)| {
            let win = win | 1; // odd, 3..=11
            params(win + dw, win + dh, win, sample, k)
        })
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
/// stats, bit for bit.
#[test]
fn terms_from_the_descriptor_equal_terms_from_stats() {
    use crate::global::ssim_fast::{terms_from_descriptor, terms_from_stats, FastLayout};
    let p = params(64, 48, 7, true, (0.01, 0.03));
    let l = FastLayout::new(&p);
    let s = set(&p, 6, 6, &mut SplitMix64::new(4));
    let (mut a, mut b, mut st) = (vec![0.0; l.terms_len()], vec![0.0; l.terms_len()], vec![0.0; p.stats_len()]);
    for i in 0..s.len() {
        terms_from_stats(&l, s.stats(i), &mut a);
        terms_from_descriptor(&p, &l, s.global(i), &mut st, &mut SsimScratch::default(), &mut b);
        assert_eq!(a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(), "descriptor {i}");
    }
}
