//! Coarse stage on one tile of the map (CPU twin of `shaders/ssim_topk.wgsl`):
//! `ssim_tile` scores every (query, reference) pair of the tile, `topk_merge` folds a tile's
//! scores into each query's running top-K list. Over all tiles this is a streaming top-K: memory
//! is O(queries x (K + tile)), never queries x map.

use crate::global::ssim::{ssim_pair, SsimParams, SsimScratch};
use rayon::prelude::*;

/// Score of an empty top-K slot (below any SSIM, which lies in [-1, 1]).
pub const EMPTY_SCORE: f32 = -3.0e38;
/// Index of an empty top-K slot.
pub const EMPTY_INDEX: u32 = u32::MAX;

/// Uniform parameters of a tile, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct TileParams {
    pub queries: u32,
    pub tile_len: u32,
    /// Map index of the tile's first reference.
    pub tile_start: u32,
    pub k: u32,
}

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
            *slot = ssim_pair(p, &queries[q * len..(q + 1) * len], &query_stats[q * slen..(q + 1) * slen], &refs[r * len..(r + 1) * len], &ref_stats[r * slen..(r + 1) * slen], scratch);
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

/// Folds the scores of references `tile_start, tile_start + 1, ...` into one K-list (best first):
/// insertion of every score above the last kept one; equal scores keep the earlier reference.
fn fold(tile_start: u32, scores: impl Iterator<Item = f32>, ts: &mut [f32], ti: &mut [u32]) {
    let k = ts.len();
    for (j, s) in scores.enumerate() {
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
        ti[pos] = tile_start + j as u32;
    }
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
    }
}
