//! Forest-to-forest similarity (CPU twin of `shaders/tree_similarity.wgsl`; `docs/design/method.md` §2.8, whose
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
//!    total tree weight of the two forests (method.md §2.8: the larger forest size, for unit weights)
//!    or by the geometric mean of the totals.
//!
//! Two entry points share these phases: [`tree_similarity`] is one pair (the shader's
//! `tree_similarity`: one workgroup per pair, its matrices in global scratch), and
//! [`tree_similarity_small`] scores several pairs of small forests per workgroup, their trees and
//! matrices in workgroup memory, the assignment parallel over the pairs and their cells. Both give
//! the same scores bit for bit on the CPU (tested); a pair too large for one round of the second
//! ([`fits_small`]) is left to the first.

use super::abi::TreeSimParams;
use crate::values::Values;

/// A borrowed forest: a slice of a map's concatenated arrays or of one `local::Forest`. Appearance
/// vectors may be stored f16 (a map built with `--f16`); they are widened where they are scored.
#[derive(Debug, Clone, Copy)]
pub struct ForestRef<'a> {
    /// Class of each tree.
    pub classes: &'a [u8],
    /// Area of each tree's object, as a fraction of the image.
    pub areas: &'a [f32],
    /// (x, y) per tree, in image diagonals.
    pub centroids: &'a [f32],
    /// `neighbour_slots` entries per tree: indices into this forest, or -1 for an empty slot.
    pub neighbours: &'a [i32],
    /// Neighbour slots per tree.
    pub neighbour_slots: usize,
    /// `dim` values per tree (zeros where `has_appearance` is 0).
    pub appearance: Values<'a>,
    /// 1 where a tree has an appearance vector, else 0.
    pub has_appearance: &'a [u8],
    /// Appearance descriptors each tree's vector was aggregated from.
    pub descriptors: &'a [u32],
    /// Length of an appearance vector (0: no appearance).
    pub dim: usize,
}

impl<'a> ForestRef<'a> {
    /// Number of trees.
    pub fn len(&self) -> usize {
        self.classes.len()
    }
    /// Whether the forest has no trees.
    pub fn is_empty(&self) -> bool {
        self.classes.is_empty()
    }
    /// Neighbour indices of tree `k` (filled slots only).
    pub fn neighbours_of(&self, k: usize) -> impl Iterator<Item = usize> + 'a {
        let n = self.neighbour_slots;
        self.neighbours[k * n..(k + 1) * n].iter().filter(|&&j| j >= 0).map(|&j| j as usize)
    }
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
    /// [`tree_similarity_small`]: a round's slots, widened appearance per slot, the pool's
    /// cosines and scores, its row and column flags, the lanes' candidates.
    slots: Vec<Slot>,
    wide: Vec<(Vec<f32>, Vec<f32>)>,
    pool_cos: Vec<f32>,
    pool_score: Vec<f32>,
    flags: Vec<bool>,
    lanes: Vec<(f32, u32)>,
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
/// accept each whose row and column are free, as method.md §2.8 writes it (unit weights).
#[cfg(test)]
fn greedy_assignment_reference(scores: &[f32], nq: usize, nr: usize) -> f32 {
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

/// Invocations of a `tree_similarity_small` workgroup: the shader's `LANES`.
pub const LANES: usize = 64;
/// Pairs one `tree_similarity_small` workgroup takes (consecutive pairs of the dispatch), and the
/// most it scores in one round: the shader's `PAIRS_PER_GROUP`.
pub const PAIRS_PER_GROUP: usize = 8;
/// Cells (query tree x reference tree) of a round's pairs together: the length of each of the
/// workgroup's two matrices (cosines, pair scores), the shader's `SMALL_CELLS`.
pub const SMALL_CELLS: usize = 1536;
/// Trees of a round's forests together (a query forest shared by consecutive pairs counted once):
/// the shader's `SMALL_TREES`.
pub const SMALL_TREES: usize = 128;

/// Whether a pair of forests of `nq` and `nr` trees fits one round of [`tree_similarity_small`]
/// alone; a pair that does not is scored by [`tree_similarity`] (one workgroup per pair).
pub const fn fits_small(nq: usize, nr: usize) -> bool {
    nq * nr <= SMALL_CELLS && nq + nr <= SMALL_TREES
}

/// One pair of a round: where its matrices, flags and trees lie in the workgroup's pools.
#[derive(Debug, Clone, Copy, Default)]
struct Slot {
    /// Index of the pair in the dispatch (its output).
    j: usize,
    q: usize,
    r: usize,
    nq: usize,
    nr: usize,
    /// First cell in the pools of cosines and scores, first row flag (column flags follow).
    cell: usize,
    flag: usize,
    /// First query tree in the tree pool (the reference's follow the round's trees so far).
    qt: usize,
}

/// How [`tree_similarity_small`] shared its workgroups: rounds, pairs scored, pairs left to
/// [`tree_similarity`], and the rounds that held several pairs.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct SmallRounds {
    /// Workgroups of the dispatch.
    pub workgroups: usize,
    /// Rounds run over all workgroups.
    pub rounds: usize,
    /// Pairs scored.
    pub pairs: usize,
    /// Pairs left to [`tree_similarity`] (they do not [`fits_small`]).
    pub skipped: usize,
    /// Rounds that held more than one pair.
    pub shared_rounds: usize,
    /// Most pairs any round held.
    pub most_pairs_in_a_round: usize,
}

/// Bindings: `queries` and `refs` (the forests), `pairs` (query, reference) of the dispatch and
/// `out` (one score per pair; a pair that does not [`fits_small`] is left as it is). Workgroup w
/// takes pairs `w * PAIRS_PER_GROUP..` (at most [`PAIRS_PER_GROUP`]) and scores them in rounds:
/// lane 0 fills a round with the next pairs while their cells, trees and flags fit the pools
/// (a query forest shared with the previous pair is loaded once); the lanes then load the round's
/// trees, compute the cosines and pair scores of all its cells together, and run the assignment
/// with `LANES / next_power_of_two(pairs)` lanes per pair: each greedy step, every lane takes the
/// best free cell of its stride of its pair, a tree reduction per pair finds the pair's best
/// (ties to the lower cell), and the pair's first lane accepts it; for best-match, the lanes of a
/// pair take its rows. The first lane of each pair sums its accepted scores, then the tree
/// weights, in order, and writes the score: the arithmetic of [`tree_similarity`], operation for
/// operation.
pub fn tree_similarity_small(
    p: &TreeSimParams,
    queries: &[ForestRef],
    refs: &[ForestRef],
    pairs: &[[u32; 2]],
    out: &mut [f32],
    scratch: &mut TreeSimScratch,
) -> SmallRounds {
    let mut stats = SmallRounds::default();
    let TreeSimScratch { slots, wide, pool_cos, pool_score, flags, lanes, wq, wr, .. } = scratch;
    pool_cos.resize(SMALL_CELLS, 0.0);
    pool_score.resize(SMALL_CELLS, 0.0);
    flags.resize(SMALL_CELLS, false);
    lanes.resize(LANES, (NOT_A_PAIR, u32::MAX));
    wide.resize(PAIRS_PER_GROUP, Default::default());
    for wg in 0..pairs.len().div_ceil(PAIRS_PER_GROUP) {
        stats.workgroups += 1;
        let end = ((wg + 1) * PAIRS_PER_GROUP).min(pairs.len());
        let mut cursor = wg * PAIRS_PER_GROUP;
        loop {
            // lane 0: the round's pairs
            slots.clear();
            let (mut cells, mut trees, mut nflags, mut steps) = (0, 0, 0, 0);
            while cursor < end && slots.len() < PAIRS_PER_GROUP {
                let [q, r] = pairs[cursor].map(|v| v as usize);
                let (nq, nr) = (queries[q].len(), refs[r].len());
                if !fits_small(nq, nr) {
                    stats.skipped += 1;
                    cursor += 1;
                    continue;
                }
                let shared = slots.last().filter(|s| s.q == q).map(|s| s.qt);
                let new_trees = if shared.is_some() { nr } else { nq + nr };
                if cells + nq * nr > SMALL_CELLS || trees + new_trees > SMALL_TREES || nflags + nq + nr > SMALL_CELLS {
                    break;
                }
                slots.push(Slot { j: cursor, q, r, nq, nr, cell: cells, flag: nflags, qt: shared.unwrap_or(trees) });
                (cells, trees, nflags) = (cells + nq * nr, trees + new_trees, nflags + nq + nr);
                steps = steps.max(nq.min(nr));
                cursor += 1;
            }
            let n = slots.len();
            if n == 0 {
                break;
            }
            stats.rounds += 1;
            stats.pairs += n;
            stats.shared_rounds += (n > 1) as usize;
            stats.most_pairs_in_a_round = stats.most_pairs_in_a_round.max(n);
            let steps = if p.greedy != 0 { steps } else { 0 };
            // the round's trees into the pool (here: each pair's appearance, widened)
            for (s, w) in slots.iter().zip(wide.iter_mut()) {
                w.0.clear();
                queries[s.q].appearance.extend_into(&mut w.0);
                w.1.clear();
                refs[s.r].appearance.extend_into(&mut w.1);
            }
            let slot_of = |idx: usize| {
                let mut s = 0;
                while s + 1 < n && slots[s + 1].cell <= idx {
                    s += 1;
                }
                s
            };
            // phase 1: appearance cosines of every cell of the round
            if p.use_appearance != 0 {
                for lane in 0..LANES {
                    for idx in (lane..cells).step_by(LANES) {
                        let si = slot_of(idx);
                        let s = slots[si];
                        let (t, u) = ((idx - s.cell) / s.nr, (idx - s.cell) % s.nr);
                        let (qf, rf) = (&queries[s.q], &refs[s.r]);
                        let (dq, dr) = (qf.dim, rf.dim);
                        pool_cos[idx] = match (dq > 0 && qf.has_appearance[t] != 0, dr > 0 && rf.has_appearance[u] != 0) {
                            (true, true) => Values::F32(&wide[si].0[t * dq..(t + 1) * dq]).dot(&Values::F32(&wide[si].1[u * dr..(u + 1) * dr])),
                            _ => MISSING,
                        };
                    }
                }
            }
            // phase 2: pair scores of every cell
            for lane in 0..LANES {
                for idx in (lane..cells).step_by(LANES) {
                    let s = slots[slot_of(idx)];
                    let (t, u) = ((idx - s.cell) / s.nr, (idx - s.cell) % s.nr);
                    let (qf, rf) = (&queries[s.q], &refs[s.r]);
                    pool_score[idx] = if p.key(qf.classes[t]) == p.key(rf.classes[u]) {
                        pair_score(p, qf, rf, &pool_cos[s.cell..s.cell + s.nq * s.nr], t, u)
                    } else {
                        NOT_A_PAIR
                    };
                }
            }
            flags[..nflags].fill(false);
            // phase 3: lanes per pair, a power of two
            let per = LANES / n.next_power_of_two();
            let mut totals = [0.0f32; PAIRS_PER_GROUP];
            for _ in 0..steps {
                for (lane, l) in lanes.iter_mut().enumerate() {
                    *l = (NOT_A_PAIR, u32::MAX);
                    let Some(s) = slots.get(lane / per) else { continue };
                    for idx in (lane % per..s.nq * s.nr).step_by(per) {
                        let v = pool_score[s.cell + idx];
                        if !flags[s.flag + idx / s.nr] && !flags[s.flag + s.nq + idx % s.nr] && v > l.0 {
                            *l = (v, idx as u32);
                        }
                    }
                }
                let mut h = per / 2;
                while h > 0 {
                    for lane in 0..LANES {
                        if lane % per < h {
                            let (o, m) = (lanes[lane + h], lanes[lane]);
                            if o.0 > m.0 || (o.0 == m.0 && o.1 < m.1) {
                                lanes[lane] = o;
                            }
                        }
                    }
                    h /= 2;
                }
                for (si, s) in slots.iter().enumerate() {
                    let (v, idx) = lanes[si * per];
                    if idx != u32::MAX {
                        let (t, u) = (idx as usize / s.nr, idx as usize % s.nr);
                        flags[s.flag + t] = true;
                        flags[s.flag + s.nq + u] = true;
                        let (qf, rf) = (&queries[s.q], &refs[s.r]);
                        totals[si] += v * (p.tree_weight(qf.areas[t], qf.descriptors[t]) * p.tree_weight(rf.areas[u], rf.descriptors[u])).sqrt();
                    }
                }
            }
            for (si, s) in slots.iter().enumerate() {
                let (qf, rf) = (&queries[s.q], &refs[s.r]);
                wq.clear();
                wq.extend((0..s.nq).map(|t| p.tree_weight(qf.areas[t], qf.descriptors[t])));
                wr.clear();
                wr.extend((0..s.nr).map(|u| p.tree_weight(rf.areas[u], rf.descriptors[u])));
                if p.greedy == 0 {
                    // best match: the pair's lanes take its rows, the first lane sums them in order
                    let mut contrib = [-1.0f32; SMALL_TREES];
                    for lane in 0..per {
                        for t in (lane..s.nq).step_by(per) {
                            let mut best = (0.0f32, usize::MAX);
                            for u in 0..s.nr {
                                let v = pool_score[s.cell + t * s.nr + u];
                                if v > best.0 {
                                    best = (v, u);
                                }
                            }
                            if best.1 != usize::MAX {
                                contrib[t] = best.0 * (wq[t] * wr[best.1]).sqrt();
                            }
                        }
                    }
                    for &c in &contrib[..s.nq] {
                        if c >= 0.0 {
                            totals[si] += c;
                        }
                    }
                }
                let (sq, sr) = (wq.iter().sum::<f32>(), wr.iter().sum::<f32>());
                let norm = if p.geometric_norm != 0 { (sq * sr).sqrt() } else { sq.max(sr) };
                out[s.j] = if s.nq > 0 && s.nr > 0 && norm > 0.0 { totals[si] / norm } else { 0.0 };
            }
        }
    }
    stats
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Repeated-argmax greedy (the GPU loop shape) equals the sort-based greedy of method.md §2.8.
        #[test]
        fn greedy_matches_sorting_reference(nq in 1usize..12, nr in 1usize..12, seed in any::<u64>()) {
            let mut rng = crate::rng::SplitMix64::new(seed);
            // few distinct values, so ties happen
            let scores: Vec<f32> = (0..nq * nr).map(|_| if rng.chance(0.3) { NOT_A_PAIR } else { (rng.below(5) as f32) / 4.0 }).collect();
            let (mut r, mut c) = (vec![], vec![]);
            let fast = greedy_assignment(&scores, nq, nr, &vec![1.0; nq], &vec![1.0; nr], &mut r, &mut c);
            prop_assert_eq!(fast, greedy_assignment_reference(&scores, nq, nr));
        }
    }
}
