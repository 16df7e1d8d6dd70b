//! Parallel top-K (CPU twin of `shaders/topk_select.wgsl`): `topk_partial` selects each
//! segment's K best by rounds of arg-max, `topk_merge_lists` merges a query's running list with
//! the segments' lists. Over all passes this keeps exactly what the streaming fold
//! [`ssim_topk::topk_merge`](super::ssim_topk::topk_merge) keeps: the K best, ties to the lower
//! reference index, NaN skipped (tested below).

use super::abi::Entry;
use crate::abi::PassParams;
use crate::abi::{EMPTY_INDEX, EMPTY_SCORE};

/// References per segment, one workgroup's share of a pass: the shader's `SEG`. Large enough that
/// a pass of a few thousand references has few partial lists to merge; the workgroup holds the
/// segment's scores (4 KiB).
pub const SEG: usize = 1024;
/// Lists one merge takes (the running list and up to `MAX_LISTS - 1` segments): the shader's
/// `MAX_LISTS`, the size of each invocation's array of list heads. A pass therefore covers at
/// most (MAX_LISTS - 1) x SEG references.
pub const MAX_LISTS: usize = 64;
/// Lanes of a `topk_partial` workgroup.
pub const LANES: usize = 64;

fn is_candidate(s: f32) -> bool {
    !s.is_nan() && s > EMPTY_SCORE
}

/// (s, i) ranks before (t, j): a higher score, or an equal one with a lower index; `None` ranks
/// after everything.
fn before(a: Option<(f32, u32)>, b: Option<(f32, u32)>) -> bool {
    match (a, b) {
        (None, _) => false,
        (Some(_), None) => true,
        (Some((s, i)), Some((t, j))) => s > t || (s == t && i < j),
    }
}

/// Bindings: `ps`, `scores` (queries x refs), `partial` (out, queries x segs x k). One workgroup
/// per (segment, query): K rounds; in each, every lane takes its best candidate ranking after
/// the last winner, and the lanes' best is the next entry.
pub fn topk_partial(ps: &PassParams, scores: &[f32], partial: &mut [Entry]) {
    let (k, refs) = (ps.k as usize, ps.refs as usize);
    for q in 0..ps.queries as usize {
        for seg in 0..ps.segs as usize {
            let base = seg * SEG;
            let seg_scores = &scores[q * refs + base..q * refs + base + SEG.min(refs - base)];
            let out = &mut partial[(q * ps.segs as usize + seg) * k..][..k];
            let mut prev: Option<(f32, u32)> = None;
            let mut t = 0;
            while t < k {
                let mut winner: Option<(f32, u32)> = None;
                for lane in 0..LANES {
                    let mut best: Option<(f32, u32)> = None;
                    for j in (lane..seg_scores.len()).step_by(LANES) {
                        let c = Some((seg_scores[j], j as u32));
                        if is_candidate(seg_scores[j]) && (prev.is_none() || before(prev, c)) && before(c, best) {
                            best = c;
                        }
                    }
                    if before(best, winner) {
                        winner = best;
                    }
                }
                let Some((s, j)) = winner else { break };
                out[t] = Entry { score: s, index: ps.ref_index + (base as u32) + j };
                prev = winner;
                t += 1;
            }
            out[t..].fill(Entry::EMPTY);
        }
    }
}

/// Bindings: `ps`, `partial`, and the running lists `top_a`, `top_b` (queries x k; the input is
/// `top_a` when `parity` is 0, the output the other). One invocation per query: K steps, each
/// taking the best head of the running list and the `segs` partial lists.
pub fn topk_merge_lists(ps: &PassParams, partial: &[Entry], top_a: &mut [Entry], top_b: &mut [Entry]) {
    let (k, segs) = (ps.k as usize, ps.segs as usize);
    let (input, output) = if ps.parity == 0 { (&*top_a, top_b) } else { (&*top_b, top_a) };
    for q in 0..ps.queries as usize {
        let list = |l: usize, h: usize| if l == 0 { input[q * k + h] } else { partial[(q * segs + l - 1) * k + h] };
        let mut heads = [0usize; MAX_LISTS];
        // a chunk's first pass has no running list to read
        let first = (ps.fresh != 0) as usize;
        for t in 0..k {
            let mut best: Option<(usize, Entry)> = None;
            for (l, &h) in heads.iter().enumerate().take(segs + 1).skip(first) {
                if h < k {
                    let c = list(l, h);
                    if c.index != EMPTY_INDEX && before(Some((c.score, c.index)), best.map(|b| (b.1.score, b.1.index))) {
                        best = Some((l, c));
                    }
                }
            }
            output[q * k + t] = match best {
                Some((l, e)) => {
                    heads[l] += 1;
                    e
                }
                None => Entry::EMPTY,
            };
        }
    }
}

#[cfg(test)]
#[path = "topk_select_tests.rs"]
mod tests;
