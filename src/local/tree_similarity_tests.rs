//! The tree-set similarity twin (`kernels::tree_similarity`) on forests built here: the formula
//! term by term, assignment, normalisation, missing appearance.

use super::Forest;
use crate::config::{MissingAppearance, SimilarityConfig};
use crate::values::Values;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::tree_similarity::*;

fn forest(trees: &[(u8, f32, f32, f32)], nb: &[[i32; 3]]) -> Forest {
    Forest {
        classes: trees.iter().map(|t| t.0).collect(),
        areas: trees.iter().map(|t| t.1).collect(),
        centroids: trees.iter().flat_map(|t| [t.2, t.3]).collect(),
        neighbours: nb.iter().flatten().copied().collect(),
        neighbour_slots: 3,
        has_appearance: vec![0; trees.len()],
        descriptors: vec![0; trees.len()],
        ..Default::default()
    }
}

#[test]
fn identical_forests_score_one_and_class_gates() {
    let f =
        forest(&[(0, 0.3, 0.2, 0.5), (2, 0.2, 0.4, 0.2), (8, 0.1, 0.6, 0.3), (10, 0.2, 0.4, 0.05)], &[[1, 2, 3], [3, 2, 0], [1, 3, 0], [1, 2, 0]]);
    let p = SimilarityConfig::default().tree_params(false, 3);
    let mut s = TreeSimScratch::default();
    assert!((tree_similarity(&p, f.as_ref(), f.as_ref(), &mut s) - 1.0).abs() < 1e-6);
    let mut other = f.clone();
    other.classes = vec![11, 12, 13, 14];
    assert_eq!(tree_similarity(&p, f.as_ref(), other.as_ref(), &mut s), 0.0);
    // a missing object costs its share: 3 of 4 trees, divided by the larger forest
    let sub = forest(&[(0, 0.3, 0.2, 0.5), (2, 0.2, 0.4, 0.2), (8, 0.1, 0.6, 0.3)], &[[1, 2, -1], [2, 0, -1], [1, 0, -1]]);
    let v = tree_similarity(&p, f.as_ref(), sub.as_ref(), &mut s);
    assert!(v < 0.75 && v > 0.5, "{v}");
}

#[test]
fn neutral_appearance_when_missing() {
    let f = forest(&[(0, 0.3, 0.2, 0.5)], &[[-1, -1, -1]]);
    let p = SimilarityConfig::spec().tree_params(true, 3);
    let mut s = TreeSimScratch::default();
    // S_in = (1 + 1 + 0.5) / 3, S_N = 0  ->  S = 0.5 * 2.5 / 3
    assert!((tree_similarity(&p, f.as_ref(), f.as_ref(), &mut s) - 0.5 * 2.5 / 3.0).abs() < 1e-6);
    let drop = SimilarityConfig { missing_appearance: MissingAppearance::Drop, ..SimilarityConfig::spec() };
    let p = drop.tree_params(true, 3);
    assert!((tree_similarity(&p, f.as_ref(), f.as_ref(), &mut s) - 0.5).abs() < 1e-6);
}

#[test]
fn appearance_separates_same_geometry() {
    let mut a = forest(&[(2, 0.3, 0.2, 0.5), (8, 0.2, 0.5, 0.4)], &[[1, -1, -1], [0, -1, -1]]);
    let mut b = a.clone();
    a.set_appearance(2, vec![1.0, 0.0, 0.0, 1.0], vec![1, 1], 1).unwrap();
    b.set_appearance(2, vec![0.0, 1.0, 1.0, 0.0], vec![1, 1], 1).unwrap();
    assert!(a.clone().set_appearance(2, vec![1.0; 3], vec![1, 1], 1).is_err(), "3 values for 2 trees of 2");
    let mut s = TreeSimScratch::default();
    let forest_only = SimilarityConfig::default().tree_params(false, 3);
    let semlook = SimilarityConfig::default().tree_params(true, 3);
    let same = tree_similarity(&semlook, a.as_ref(), a.as_ref(), &mut s);
    let diff = tree_similarity(&semlook, a.as_ref(), b.as_ref(), &mut s);
    assert!(same > diff + 0.2, "{same} {diff}");
    assert_eq!(tree_similarity(&forest_only, a.as_ref(), a.as_ref(), &mut s), tree_similarity(&forest_only, a.as_ref(), b.as_ref(), &mut s));
}

/// A random forest of `n` trees over `classes` classes with `dim` appearance values (a fifth of
/// the trees without); `uniform`: every tree the same (every same-class cell ties).
fn random_forest(n: usize, dim: usize, classes: usize, uniform: bool, rng: &mut crate::util::SplitMix64) -> Forest {
    let mut f = Forest { neighbour_slots: 3, ..Default::default() };
    let first = (rng.below(classes) as u8, rng.range(0.001, 0.3) as f32, rng.next_f64() as f32, rng.next_f64() as f32);
    let mut app = vec![0.0f32; n * dim];
    let mut counts = vec![0u32; n];
    let v0: Vec<f32> = (0..dim).map(|_| rng.normal() as f32).collect();
    for t in 0..n {
        let (c, a, x, y) =
            if uniform { first } else { (rng.below(classes) as u8, rng.range(0.001, 0.3) as f32, rng.next_f64() as f32, rng.next_f64() as f32) };
        f.classes.push(c);
        f.areas.push(a);
        f.centroids.extend([x, y]);
        for _ in 0..3 {
            f.neighbours.push(if n > 1 && rng.chance(0.8) { ((t + 1 + rng.below(n - 1)) % n) as i32 } else { -1 });
        }
        if dim > 0 && rng.chance(0.8) {
            counts[t] = 1 + rng.below(40) as u32;
            let v: Vec<f32> = if uniform { v0.clone() } else { (0..dim).map(|_| rng.normal() as f32).collect() };
            let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            app[t * dim..(t + 1) * dim].iter_mut().zip(&v).for_each(|(o, x)| *o = x / norm);
        }
    }
    f.set_appearance(dim, app, counts, 1).unwrap();
    f
}

/// The similarity options the GPU tests cover (tests/gpu/main.rs), each with and without
/// appearance, the last pairing trees by Cityscapes category.
fn every_option() -> Vec<TreeSimParams> {
    use crate::config::*;
    let variants = [
        SimilarityConfig::default(),
        SimilarityConfig { position: PositionSimilarity::Gaussian, missing_appearance: MissingAppearance::Drop, ..Default::default() },
        SimilarityConfig { assignment: Assignment::BestMatch, ..Default::default() },
        SimilarityConfig { tree_weight: TreeWeight::Descriptors, normalise: Normalise::GeometricMean, ..Default::default() },
        SimilarityConfig { tree_weight: TreeWeight::SqrtArea, assignment: Assignment::BestMatch, ..Default::default() },
        SimilarityConfig {
            tree_weight: TreeWeight::Area,
            w_area: 0.0,
            w_position: 0.0,
            missing_appearance: MissingAppearance::Drop,
            ..Default::default()
        },
        SimilarityConfig { class_match: ClassMatch::Category, ..Default::default() },
    ];
    let table = crate::classes::ClassTable::cityscapes();
    variants.iter().flat_map(|sim| [false, true].map(|app| sim.tree_params_over(app, 3, &table.category_key()))).collect()
}

/// `tree_similarity_small` (several pairs a workgroup, the assignment parallel over pairs and
/// cells) gives `tree_similarity`'s score bit for bit for every pair that fits a round, and
/// leaves the others alone: forests of 0, 1, a few, tens of trees, up to and over the round's
/// pools, random and uniform (every cell tied: the tie rule decides), f32 and f16 appearance,
/// every similarity option, pairs in grid order (consecutive pairs share a query) and shuffled.
#[test]
fn the_small_kernels_twin_equals_the_pair_twin_bit_for_bit() {
    let mut rng = crate::util::SplitMix64::new(19);
    let sizes = [0usize, 1, 2, 3, 5, 8, 12, 17, 24, 31, 40, 48, 64, 65, 100, 127, 128];
    let dim = 8;
    let forests: Vec<Forest> =
        sizes.iter().enumerate().map(|(i, &n)| random_forest(n, dim, if i % 3 == 0 { 2 } else { 5 }, i % 4 == 1, &mut rng)).collect();
    // the f16 copies of the appearance (as a map built with f16 stores it)
    let halves: Vec<Vec<u16>> = forests.iter().map(|f| f.appearance.iter().map(|&v| half::f16::from_f32(v).to_bits()).collect()).collect();
    let as_ref = |i: usize, f16: bool| ForestRef {
        appearance: if f16 { Values::F16(&halves[i]) } else { Values::F32(&forests[i].appearance) },
        ..forests[i].as_ref()
    };
    // queries: every size; references: every size twice (f32 and f16), and the queries themselves
    let queries: Vec<ForestRef> = (0..forests.len()).map(|i| as_ref(i, false)).collect();
    let refs: Vec<ForestRef> = (0..forests.len()).flat_map(|i| [as_ref(i, false), as_ref(i, true)]).collect();
    let grid: Vec<[u32; 2]> = (0..queries.len() as u32).flat_map(|q| (0..refs.len() as u32).map(move |r| [q, r])).collect();
    let mut shuffled = grid.clone();
    for i in (1..shuffled.len()).rev() {
        shuffled.swap(i, rng.below(i + 1));
    }
    let mut scratch = TreeSimScratch::default();
    for (v, p) in every_option().iter().enumerate() {
        for (order, pairs) in [("grid", &grid), ("shuffled", &shuffled)] {
            let mut out = vec![f32::NAN; pairs.len()];
            let rounds = tree_similarity_small(p, &queries, &refs, pairs, &mut out, &mut scratch);
            let mut skipped = 0;
            for (j, &[q, r]) in pairs.iter().enumerate() {
                let (qf, rf) = (queries[q as usize], refs[r as usize]);
                if fits_small(qf.len(), rf.len()) {
                    let want = tree_similarity(p, qf, rf, &mut scratch);
                    assert_eq!(
                        out[j].to_bits(),
                        want.to_bits(),
                        "option {v}, {order}: pair {q}-{r} ({} x {} trees): {} vs {want}",
                        qf.len(),
                        rf.len(),
                        out[j]
                    );
                } else {
                    assert!(out[j].is_nan(), "option {v}: pair {q}-{r} ({} x {} trees) is not the small kernel's", qf.len(), rf.len());
                    skipped += 1;
                }
            }
            assert_eq!(rounds.skipped, skipped);
            assert_eq!(rounds.pairs + skipped, pairs.len());
            // small forests side by side: rounds of several pairs, in grid order of all eight
            assert!(rounds.shared_rounds > 0, "{order}: {rounds:?}");
            assert!(order != "grid" || rounds.most_pairs_in_a_round == PAIRS_PER_GROUP, "{rounds:?}");
            assert_eq!(rounds.workgroups, pairs.len().div_ceil(PAIRS_PER_GROUP));
        }
    }
}
