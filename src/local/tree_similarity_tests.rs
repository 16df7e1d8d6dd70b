//! The tree-set similarity twin (`kernels::tree_similarity`) on forests built here: the formula
//! term by term, assignment, normalisation, missing appearance.

use super::Forest;
use crate::config::{MissingAppearance, SimilarityConfig};
use crate::kernels::abi::TreeSimParams;
use crate::kernels::tree_similarity::*;
use proptest::prelude::*;

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
    let p = TreeSimParams::new(&SimilarityConfig::default(), false, 3);
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
    let p = TreeSimParams::new(&SimilarityConfig::spec(), true, 3);
    let mut s = TreeSimScratch::default();
    // S_in = (1 + 1 + 0.5) / 3, S_N = 0  ->  S = 0.5 * 2.5 / 3
    assert!((tree_similarity(&p, f.as_ref(), f.as_ref(), &mut s) - 0.5 * 2.5 / 3.0).abs() < 1e-6);
    let drop = SimilarityConfig { missing_appearance: MissingAppearance::Drop, ..SimilarityConfig::spec() };
    let p = TreeSimParams::new(&drop, true, 3);
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
    let forest_only = TreeSimParams::new(&SimilarityConfig::default(), false, 3);
    let semlook = TreeSimParams::new(&SimilarityConfig::default(), true, 3);
    let same = tree_similarity(&semlook, a.as_ref(), a.as_ref(), &mut s);
    let diff = tree_similarity(&semlook, a.as_ref(), b.as_ref(), &mut s);
    assert!(same > diff + 0.2, "{same} {diff}");
    assert_eq!(tree_similarity(&forest_only, a.as_ref(), a.as_ref(), &mut s), tree_similarity(&forest_only, a.as_ref(), b.as_ref(), &mut s));
}

proptest! {
    /// Repeated-argmax greedy (the GPU loop shape) equals the sort-based greedy of the spec.
    #[test]
    fn greedy_matches_sorting_reference(nq in 1usize..12, nr in 1usize..12, seed in any::<u64>()) {
        let mut rng = crate::util::SplitMix64::new(seed);
        // few distinct values, so ties happen
        let scores: Vec<f32> = (0..nq * nr).map(|_| if rng.chance(0.3) { NOT_A_PAIR } else { (rng.below(5) as f32) / 4.0 }).collect();
        let (mut r, mut c) = (vec![], vec![]);
        let fast = greedy_assignment(&scores, nq, nr, &vec![1.0; nq], &vec![1.0; nr], &mut r, &mut c);
        prop_assert_eq!(fast, greedy_assignment_reference(&scores, nq, nr));
    }
}
