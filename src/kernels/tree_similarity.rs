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

use super::abi::TreeSimParams;
use crate::values::Values;

/// A borrowed forest: a slice of a map's concatenated arrays or of one `local::Forest`. Appearance
/// vectors may be stored f16 (a map built with `--f16`); they are widened where they are scored.
#[derive(Debug, Clone, Copy)]
pub struct ForestRef<'a> {
    pub classes: &'a [u8],
    pub areas: &'a [f32],
    pub centroids: &'a [f32],
    pub neighbours: &'a [i32],
    pub neighbour_slots: usize,
    pub appearance: Values<'a>,
    pub has_appearance: &'a [u8],
    pub descriptors: &'a [u32],
    pub dim: usize,
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
pub(crate) fn greedy_assignment(
    scores: &[f32],
    nq: usize,
    nr: usize,
    wq: &[f32],
    wr: &[f32],
    row_used: &mut Vec<bool>,
    col_used: &mut Vec<bool>,
) -> f32 {
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
