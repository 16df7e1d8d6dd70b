//! Coarse stage on one tile of the map (CPU twin of `shaders/ssim_topk.wgsl`):
//! `ssim_tile` scores every (query, reference) pair of the tile, `topk_merge` folds a tile's
//! scores into each query's running top-K list. Over all tiles this is a streaming top-K: memory
//! is O(queries x (K + tile)), never queries x map.

use super::abi::{TileParams, EMPTY_INDEX, EMPTY_SCORE};
use crate::abi::SsimParams;
use crate::ssim::{ssim_pair, SsimScratch};
use rayon::prelude::*;

/// Pairs per parallel task of the CPU twin: enough work to amortise scheduling, small enough
/// to keep both cores busy when a batch holds a single query.
const PAIRS_PER_TASK: usize = 64;

/// Bindings: `p`, `tp`, `queries`, `query_stats`, `refs` (the tile), `ref_stats`, `scores` (out,
/// queries x tile_len). One shader workgroup per pair; here pairs run in query-major order, in
/// parallel chunks.
#[allow(clippy::too_many_arguments)]
pub fn ssim_tile(p: &SsimParams, tp: &TileParams, queries: &[f32], query_stats: &[f32], refs: &[f32], ref_stats: &[f32], scores: &mut [f32]) {
    let (len, slen, t) = (p.len(), p.stats_len(), tp.tile_len as usize);
    scores[..tp.queries as usize * t].par_chunks_mut(PAIRS_PER_TASK).enumerate().for_each_init(SsimScratch::default, |scratch, (chunk, out)| {
        for (j, slot) in out.iter_mut().enumerate() {
            let pair = chunk * PAIRS_PER_TASK + j;
            let (q, r) = (pair / t, pair % t);
            *slot = ssim_pair(
                p,
                &queries[q * len..(q + 1) * len],
                &query_stats[q * slen..(q + 1) * slen],
                &refs[r * len..(r + 1) * len],
                &ref_stats[r * slen..(r + 1) * slen],
                scratch,
            );
        }
    });
}

/// Bindings: `tp`, `scores`, `topk_scores`, `topk_index` (queries x k, best first, initialised to
/// EMPTY_SCORE / EMPTY_INDEX). One invocation per query: insertion of every better score, ties
/// kept in favour of the lower (earlier) reference index; NaN scores are skipped.
pub fn topk_merge(tp: &TileParams, scores: &[f32], topk_scores: &mut [f32], topk_index: &mut [u32]) {
    let (k, t) = (tp.k as usize, tp.tile_len as usize);
    topk_scores.par_chunks_mut(k).zip(topk_index.par_chunks_mut(k)).enumerate().take(tp.queries as usize).for_each(|(q, (ts, ti))| {
        fold(tp.tile_start, (0..t).map(|j| scores[q * t + j]), ts, ti);
    });
}

/// `topk_merge` for scores laid out reference-major (`scores[j * queries + q]`), as the fast CPU
/// coarse path writes them (CPU only).
pub fn topk_merge_ref_major(tp: &TileParams, scores: &[f32], topk_scores: &mut [f32], topk_index: &mut [u32]) {
    let (k, t, nq) = (tp.k as usize, tp.tile_len as usize, tp.queries as usize);
    topk_scores.par_chunks_mut(k).zip(topk_index.par_chunks_mut(k)).enumerate().take(nq).for_each(|(q, (ts, ti))| {
        fold(tp.tile_start, (0..t).map(|j| scores[j * nq + q]), ts, ti);
    });
}

/// Folds the scores of references `tile_start, tile_start + 1, ...` into one K-list (best first).
fn fold(tile_start: u32, scores: impl Iterator<Item = f32>, ts: &mut [f32], ti: &mut [u32]) {
    fold_indexed(scores.enumerate().map(|(j, s)| (s, tile_start + j as u32)), ts, ti)
}

/// Folds (score, reference) pairs, in ascending reference order, into one K-list (best first):
/// insertion of every score above the last kept one; equal scores keep the earlier reference;
/// NaN is skipped. The list after a prefix is the K best of that prefix under (score descending,
/// index ascending), which is what makes [`merge_lists`] exact.
fn fold_indexed(items: impl Iterator<Item = (f32, u32)>, ts: &mut [f32], ti: &mut [u32]) {
    let k = ts.len();
    for (s, r) in items {
        if s <= ts[k - 1] || s.is_nan() {
            continue;
        }
        let mut pos = k - 1;
        while pos > 0 && ts[pos - 1] < s {
            ts[pos] = ts[pos - 1];
            ti[pos] = ti[pos - 1];
            pos -= 1;
        }
        ts[pos] = s;
        ti[pos] = r;
    }
}

/// Why [`merge_lists`] refused its parts.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct MergeError(pub String);

impl std::fmt::Display for MergeError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(&self.0)
    }
}

impl std::error::Error for MergeError {}

/// Merges per-part K-lists of the same queries (indices already in one global index space, each
/// part's list holding the K best of its references) into the global K-lists: candidates sorted
/// by index go through the same fold as one pass over the whole map, so the result is the one a
/// single process computes, ties across parts included. Fails if the parts disagree on the
/// number of queries, or a list holds one reference twice.
pub fn merge_lists(parts: &[&[Vec<(f32, u32)>]], k: usize) -> Result<Vec<Vec<(f32, u32)>>, MergeError> {
    let nq = parts.first().map_or(0, |p| p.len());
    if let Some(p) = parts.iter().find(|p| p.len() != nq) {
        return Err(MergeError(format!("parts hold {} and {nq} queries", p.len())));
    }
    if k == 0 {
        return Ok(vec![vec![]; nq]);
    }
    (0..nq)
        .map(|q| {
            let mut all: Vec<(f32, u32)> = parts.iter().flat_map(|p| p[q].iter().copied()).collect();
            all.sort_by_key(|&(_, r)| r);
            if let Some(w) = all.windows(2).find(|w| w[0].1 == w[1].1) {
                return Err(MergeError(format!("reference {} is a candidate of query {q} twice", w[0].1)));
            }
            let (mut ts, mut ti) = (vec![EMPTY_SCORE; k], vec![EMPTY_INDEX; k]);
            fold_indexed(all.into_iter(), &mut ts, &mut ti);
            Ok(topk_lists(k, &ts, &ti).remove(0))
        })
        .collect()
}

/// Reads K-lists back into (score, map index) lists, dropping empty slots.
pub fn topk_lists(k: usize, topk_scores: &[f32], topk_index: &[u32]) -> Vec<Vec<(f32, u32)>> {
    topk_scores
        .chunks(k)
        .zip(topk_index.chunks(k))
        .map(|(s, i)| s.iter().zip(i).filter(|(_, &i)| i != EMPTY_INDEX).map(|(&s, &i)| (s, i)).collect())
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    proptest! {
        /// Streaming tiles through topk_merge keeps exactly the K best of a full sort, ties to the
        /// lower index, whatever the tile size.
        #[test]
        fn streaming_equals_full_sort(scores in prop::collection::vec(0u8..20, 1..200), k in 1usize..15, tile in 1usize..50) {
            let n = scores.len();
            let (mut ts, mut ti) = (vec![EMPTY_SCORE; k], vec![EMPTY_INDEX; k]);
            let mut start = 0;
            while start < n {
                let end = (start + tile).min(n);
                let block: Vec<f32> = scores[start..end].iter().map(|&s| s as f32).collect();
                let tp = TileParams { queries: 1, tile_len: (end - start) as u32, tile_start: start as u32, k: k as u32 };
                topk_merge(&tp, &block, &mut ts, &mut ti);
                start = end;
            }
            let mut all: Vec<(f32, u32)> = scores.iter().enumerate().map(|(i, &s)| (s as f32, i as u32)).collect();
            all.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
            all.truncate(k);
            prop_assert_eq!(topk_lists(k, &ts, &ti).remove(0), all);
        }

        /// Merging the K-lists of contiguous parts (any split, dense ties) equals one pass over
        /// the whole list.
        #[test]
        fn merging_parts_equals_one_pass(scores in prop::collection::vec(0u8..20, 1..200), k in 1usize..15, cuts in prop::collection::vec(0usize..200, 0..6)) {
            let n = scores.len();
            let one_pass = |a: usize, b: usize| {
                let (mut ts, mut ti) = (vec![EMPTY_SCORE; k], vec![EMPTY_INDEX; k]);
                let tp = TileParams { queries: 1, tile_len: (b - a) as u32, tile_start: a as u32, k: k as u32 };
                let block: Vec<f32> = scores[a..b].iter().map(|&s| s as f32).collect();
                topk_merge(&tp, &block, &mut ts, &mut ti);
                topk_lists(k, &ts, &ti)
            };
            let mut bounds: Vec<usize> = cuts.into_iter().map(|c| c % (n + 1)).chain([0, n]).collect();
            bounds.sort();
            let parts: Vec<Vec<Vec<(f32, u32)>>> = bounds.windows(2).map(|w| one_pass(w[0], w[1])).collect();
            let refs: Vec<&[Vec<(f32, u32)>]> = parts.iter().map(|p| p.as_slice()).collect();
            prop_assert_eq!(merge_lists(&refs, k).unwrap(), one_pass(0, n));
        }
    }
}
