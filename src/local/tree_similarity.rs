//! Forest-to-forest similarity (CPU twin of `shaders/tree_similarity.wgsl`; spec §2.8, whose
//! Eqs. (11)-(14) are reconstructions, all weights configurable).
//!
//! For one (query forest, reference forest) pair, in three phases:
//! 1. appearance cosines between every query tree and every reference tree (when appearance is used);
//! 2. tree similarity S(t, u) for every same-class pair:
//!    S_in = weighted mean of S_A = min(A)/max(A), S_P = max(0, 1 - ||ΔP||) (or a Gaussian),
//!    S_V = max(0, cos) (neutral, or dropped, where appearance is missing);
//!    S_N = (1/n) Σ over t's neighbours of the best unused same-class neighbour of u, scored by
//!    its appearance cosine (1 without appearance: the fraction of matching categories);
//!    S = w_in S_in + w_N S_N;
//! 3. image similarity: greedy one-to-one assignment (repeatedly the largest remaining S, ties to
//!    the lowest (t, u)); an accepted pair adds S(t, u) sqrt(w_t w_u), with w the tree weight
//!    (1, the area, its square root, or the descriptor count + 1); the sum is divided by the larger
//!    total tree weight of the two forests (spec §2.8: the larger forest size, for unit weights)
//!    or by the geometric mean of the totals.

use super::ForestRef;
use crate::config::{Assignment, ClassMatch, MissingAppearance, Normalise, PositionSimilarity, SimilarityConfig, TreeWeight};
use crate::values::Values;

/// Uniform parameters of the kernel, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct TreeSimParams {
    pub w_area: f32,
    pub w_position: f32,
    pub w_appearance: f32,
    pub w_intrinsic: f32,
    pub w_neighbours: f32,
    pub position_sigma: f32,
    pub neutral: f32,
    /// 1: Gaussian position similarity, 0: linear.
    pub gaussian_position: u32,
    /// 1: drop a missing appearance term and renormalise, 0: score it `neutral`.
    pub drop_missing: u32,
    /// 1: appearance takes part (SemLook local), 0: Forest only.
    pub use_appearance: u32,
    /// 1: greedy one-to-one, 0: best match per query tree.
    pub greedy: u32,
    /// Neighbour slots per tree (the S_N denominator).
    pub neighbour_slots: u32,
    /// Tree weight: 0 uniform, 1 area, 2 sqrt(area), 3 descriptor count + 1.
    pub tree_weight: u32,
    /// 1: divide by the geometric mean of the forests' total weights, 0: by the larger total.
    pub geometric_norm: u32,
    pub _pad: [u32; 2],
    /// Per class, the key trees pair by (the class itself, or its category), four u8 to a word:
    /// two trees may pair when their classes' keys are equal.
    pub class_key: [u32; 64],
}

impl TreeSimParams {
    /// Parameters of `cfg`; the intrinsic and neighbour weights are normalised to sum to 1, so
    /// identical forests score 1 whatever the weights.
    pub fn new(cfg: &SimilarityConfig, use_appearance: bool, neighbour_slots: usize) -> Self {
        let wsum = (cfg.w_intrinsic + cfg.w_neighbours).max(f64::MIN_POSITIVE);
        TreeSimParams {
            w_area: cfg.w_area as f32,
            w_position: cfg.w_position as f32,
            w_appearance: cfg.w_appearance as f32,
            w_intrinsic: (cfg.w_intrinsic / wsum) as f32,
            w_neighbours: (cfg.w_neighbours / wsum) as f32,
            position_sigma: cfg.position_sigma as f32,
            neutral: cfg.neutral_appearance as f32,
            gaussian_position: (cfg.position == PositionSimilarity::Gaussian) as u32,
            drop_missing: (cfg.missing_appearance == MissingAppearance::Drop) as u32,
            use_appearance: use_appearance as u32,
            greedy: (cfg.assignment == Assignment::Greedy) as u32,
            neighbour_slots: neighbour_slots as u32,
            // settings without appearance never see descriptor counts: they weigh by area instead
            tree_weight: match cfg.tree_weight {
                TreeWeight::Uniform => 0,
                TreeWeight::Area => 1,
                TreeWeight::SqrtArea => 2,
                TreeWeight::Descriptors if use_appearance => 3,
                TreeWeight::Descriptors => 1,
            },
            geometric_norm: (cfg.normalise == Normalise::GeometricMean) as u32,
            _pad: [0; 2],
            class_key: pack_key(&std::array::from_fn(|i| i as u8)),
        }
    }

    /// The parameters with the pairing rule of `cfg.class_match` over `table`'s categories.
    pub fn with_classes(mut self, cfg: &SimilarityConfig, table: &crate::classes::ClassTable) -> Self {
        let categories = match cfg.class_match {
            ClassMatch::Class => false,
            ClassMatch::Category => true,
            ClassMatch::CategoryWithAppearance => self.use_appearance != 0,
        };
        if categories {
            self.class_key = pack_key(&table.category_key());
        }
        self
    }

    /// The pairing key of class `c`.
    #[inline]
    pub fn key(&self, c: u8) -> u32 {
        (self.class_key[c as usize / 4] >> (8 * (c as u32 % 4))) & 0xff
    }

    /// The weight of a tree of relative area `area` aggregated from `descriptors` descriptors.
    #[inline]
    pub fn tree_weight(&self, area: f32, descriptors: u32) -> f32 {
        match self.tree_weight {
            1 => area,
            2 => area.max(0.0).sqrt(),
            3 => descriptors as f32 + 1.0,
            _ => 1.0,
        }
    }
}

/// 256 u8 keys, four to a little-endian word (as the kernel reads them).
fn pack_key(key: &[u8; 256]) -> [u32; 64] {
    std::array::from_fn(|w| (0..4).fold(0u32, |acc, l| acc | (key[4 * w + l] as u32) << (8 * l)))
}

/// Value of a cosine slot whose pair lacks appearance on either side.
pub const MISSING: f32 = -2.0;
/// Value of a pair-score slot whose trees differ in class (never assigned).
pub const NOT_A_PAIR: f32 = -1.0;

/// Scratch space reused across pairs.
#[derive(Debug, Default, Clone)]
pub struct TreeSimScratch {
    cosines: Vec<f32>,
    /// The forests' appearance vectors widened to f32 (maps storing f16).
    q_wide: Vec<f32>,
    r_wide: Vec<f32>,
    scores: Vec<f32>,
    wq: Vec<f32>,
    wr: Vec<f32>,
    row_used: Vec<bool>,
    col_used: Vec<bool>,
}

/// Image similarity of forests `q` and `r`.
pub fn tree_similarity(p: &TreeSimParams, q: ForestRef, r: ForestRef, scratch: &mut TreeSimScratch) -> f32 {
    let (nq, nr) = (q.len(), r.len());
    if nq == 0 || nr == 0 {
        return 0.0;
    }
    scratch.cosines.resize(nq * nr, MISSING);
    scratch.scores.resize(nq * nr, NOT_A_PAIR);
    // phase 1: appearance cosines (f16 vectors widened once per forest, not once per pair of trees)
    if p.use_appearance != 0 {
        let TreeSimScratch { cosines, q_wide, r_wide, .. } = scratch;
        let (qa, ra) = (q.appearance.widened(q_wide), r.appearance.widened(r_wide));
        let (dq, dr) = (q.dim, r.dim);
        for t in 0..nq {
            for u in 0..nr {
                cosines[t * nr + u] = match (dq > 0 && q.has_appearance[t] != 0, dr > 0 && r.has_appearance[u] != 0) {
                    (true, true) => Values::F32(&qa[t * dq..(t + 1) * dq]).dot(&Values::F32(&ra[u * dr..(u + 1) * dr])),
                    _ => MISSING,
                };
            }
        }
    }
    // phase 2: tree similarities
    for t in 0..nq {
        for u in 0..nr {
            scratch.scores[t * nr + u] =
                if p.key(q.classes[t]) == p.key(r.classes[u]) { pair_score(p, &q, &r, &scratch.cosines, t, u) } else { NOT_A_PAIR };
        }
    }
    // phase 3: assignment, weighted sum, normalisation
    scratch.wq.clear();
    scratch.wq.extend((0..nq).map(|t| p.tree_weight(q.areas[t], q.descriptors[t])));
    scratch.wr.clear();
    scratch.wr.extend((0..nr).map(|u| p.tree_weight(r.areas[u], r.descriptors[u])));
    let total = if p.greedy != 0 {
        greedy_assignment(&scratch.scores, nq, nr, &scratch.wq, &scratch.wr, &mut scratch.row_used, &mut scratch.col_used)
    } else {
        best_match(&scratch.scores, nq, nr, &scratch.wq, &scratch.wr)
    };
    let (sq, sr) = (scratch.wq.iter().sum::<f32>(), scratch.wr.iter().sum::<f32>());
    let norm = if p.geometric_norm != 0 { (sq * sr).sqrt() } else { sq.max(sr) };
    if norm > 0.0 {
        total / norm
    } else {
        0.0
    }
}

/// Each query tree takes its best reference tree (first of equal scores), weighted.
fn best_match(scores: &[f32], nq: usize, nr: usize, wq: &[f32], wr: &[f32]) -> f32 {
    let mut total = 0.0f32;
    for t in 0..nq {
        let mut best = (0.0f32, usize::MAX);
        for u in 0..nr {
            if scores[t * nr + u] > best.0 {
                best = (scores[t * nr + u], u);
            }
        }
        if best.1 != usize::MAX {
            total += best.0 * (wq[t] * wr[best.1]).sqrt();
        }
    }
    total
}

/// Appearance term of a pair from its cosine slot: max(0, cos), or `neutral` when missing.
#[inline]
fn cos_plus(p: &TreeSimParams, c: f32) -> f32 {
    if c == MISSING {
        p.neutral
    } else {
        c.max(0.0)
    }
}

/// S(t, u) for a same-class pair.
fn pair_score(p: &TreeSimParams, q: &ForestRef, r: &ForestRef, cosines: &[f32], t: usize, u: usize) -> f32 {
    let nr = r.len();
    let (aq, ar) = (q.areas[t], r.areas[u]);
    let s_area = if aq.max(ar) > 0.0 { aq.min(ar) / aq.max(ar) } else { 1.0 };
    let dx = q.centroids[2 * t] - r.centroids[2 * u];
    let dy = q.centroids[2 * t + 1] - r.centroids[2 * u + 1];
    let d = (dx * dx + dy * dy).sqrt();
    let s_pos = if p.gaussian_position != 0 { (-(d * d) / (2.0 * p.position_sigma * p.position_sigma)).exp() } else { (1.0 - d).max(0.0) };
    let mut num = p.w_area * s_area + p.w_position * s_pos;
    let mut den = p.w_area + p.w_position;
    if p.use_appearance != 0 {
        let c = cosines[t * nr + u];
        if c != MISSING || p.drop_missing == 0 {
            num += p.w_appearance * cos_plus(p, c);
            den += p.w_appearance;
        }
    }
    let s_in = if den > 0.0 { num / den } else { 0.0 };
    // neighbours: each of t's neighbours takes the best unused same-class neighbour of u
    let slots = p.neighbour_slots as usize;
    let mut used = [false; 8];
    let mut s_nb = 0.0f32;
    for a_slot in 0..slots {
        let a = q.neighbours[t * slots + a_slot];
        if a < 0 {
            continue;
        }
        let mut best = -1.0f32;
        let mut best_slot = usize::MAX;
        for (b_slot, is_used) in used.iter().enumerate().take(slots) {
            let b = r.neighbours[u * slots + b_slot];
            if b < 0 || *is_used || p.key(q.classes[a as usize]) != p.key(r.classes[b as usize]) {
                continue;
            }
            let v = if p.use_appearance != 0 { cos_plus(p, cosines[a as usize * nr + b as usize]) } else { 1.0 };
            if v > best {
                best = v;
                best_slot = b_slot;
            }
        }
        if best_slot != usize::MAX {
            used[best_slot] = true;
            s_nb += best;
        }
    }
    let s_nb = if slots > 0 { s_nb / slots as f32 } else { 0.0 };
    p.w_intrinsic * s_in + p.w_neighbours * s_nb
}

/// Repeatedly accepts the largest remaining pair score (ties: lowest t, then lowest u) whose row
/// and column are both free; returns the sum of accepted scores, each times sqrt(w_t w_u).
fn greedy_assignment(scores: &[f32], nq: usize, nr: usize, wq: &[f32], wr: &[f32], row_used: &mut Vec<bool>, col_used: &mut Vec<bool>) -> f32 {
    row_used.clear();
    row_used.resize(nq, false);
    col_used.clear();
    col_used.resize(nr, false);
    let mut total = 0.0f32;
    for _ in 0..nq.min(nr) {
        let mut best = NOT_A_PAIR;
        let mut best_i = usize::MAX;
        for t in 0..nq {
            if row_used[t] {
                continue;
            }
            for u in 0..nr {
                let s = scores[t * nr + u];
                if !col_used[u] && s > best {
                    best = s;
                    best_i = t * nr + u;
                }
            }
        }
        if best_i == usize::MAX {
            break;
        }
        let (t, u) = (best_i / nr, best_i % nr);
        row_used[t] = true;
        col_used[u] = true;
        total += best * (wq[t] * wr[u]).sqrt();
    }
    total
}

/// Reference for phase 3: sort all same-class pairs by score (descending, stable in (t, u)) and
/// accept each whose row and column are free, as spec §2.8 writes it (unit weights).
pub fn greedy_assignment_reference(scores: &[f32], nq: usize, nr: usize) -> f32 {
    let mut pairs: Vec<usize> = (0..nq * nr).filter(|&i| scores[i] > NOT_A_PAIR).collect();
    pairs.sort_by(|&a, &b| scores[b].total_cmp(&scores[a]).then(a.cmp(&b)));
    let (mut rows, mut cols) = (vec![false; nq], vec![false; nr]);
    let mut total = 0.0;
    for i in pairs {
        let (t, u) = (i / nr, i % nr);
        if !rows[t] && !cols[u] {
            rows[t] = true;
            cols[u] = true;
            total += scores[i];
        }
    }
    total
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::SimilarityConfig;
    use crate::local::Forest;
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
        let f = forest(
            &[(0, 0.3, 0.2, 0.5), (2, 0.2, 0.4, 0.2), (8, 0.1, 0.6, 0.3), (10, 0.2, 0.4, 0.05)],
            &[[1, 2, 3], [3, 2, 0], [1, 3, 0], [1, 2, 0]],
        );
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
}
