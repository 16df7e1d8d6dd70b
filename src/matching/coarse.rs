//! The coarse stage on the CPU: SSIM of the global descriptors streamed over the map into top-K
//! lists (the fast path, [`coarse_topk`], and the twins' loop it is held to, [`coarse_topk_twin`]),
//! the fused score with the appearance and embedding cosines ([`FusedWeights`], [`fused_topk_cpu`]),
//! the search through the approximate index ([`indexed_topk`]) and the score of given pairs.

use super::answer::CandidateLists;
use super::coarse_cpu::{self, stream_topk};
use super::{baseline, setting::Setting};
use crate::config::{Config, IndexSearch};
use crate::descriptors::source::{self, GlobalSource, RefSource};
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Result};
use crate::values::Values;
use rayon::prelude::*;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::ssim_topk;

/// The weights of the fused coarse score's terms beside the appearance cosine.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct FusedWeights {
    /// Of the SSIM of the global descriptors (`matching.w_global`).
    pub global: f32,
    /// Of the cosine of the whole-image embeddings (`matching.w_embedding`; 0 where the setting
    /// has no embedding term or the queries and references do not both have embeddings of one
    /// width).
    pub embedding: f32,
}

impl FusedWeights {
    /// The weights `cfg` gives `setting` for `queries` against `refs`.
    pub fn of(refs: &dyn RefSource, queries: &DescriptorSet, cfg: &Config, setting: Setting) -> FusedWeights {
        // embeddings of one network on both sides (a record on each: a set of unknown origin has none)
        let same = match (&queries.embedding, refs.embedding_record()) {
            (Some(a), Some(b)) => a.same_network(b),
            _ => false,
        };
        let both = same && queries.embedding_dim > 0 && refs.embedding_dim() == queries.embedding_dim;
        let embedding = if setting.embeds() && both { cfg.matching.w_embedding as f32 } else { 0.0 };
        FusedWeights { global: cfg.matching.w_global as f32, embedding }
    }
    /// SSIM only (no embedding term).
    pub fn global_only(w_global: f32) -> FusedWeights {
        FusedWeights { global: w_global, embedding: 0.0 }
    }
    /// The fused score's terms other than the SSIM for query `q` and reference `r`: the appearance
    /// cosine (with `cosine`) plus `embedding` x the embeddings' cosine (both of length 1).
    #[inline]
    fn appearance(&self, refs: &dyn RefSource, queries: &DescriptorSet, q: usize, r: usize, cosine: bool) -> f32 {
        self.appearance_of(queries, q, &refs.image_appearance(r), &refs.image_embedding(r), cosine)
    }
    /// [`FusedWeights::appearance`] with the reference's vectors read once by the caller.
    #[inline]
    fn appearance_of(&self, queries: &DescriptorSet, q: usize, ra: &Values, re: &Values, cosine: bool) -> f32 {
        let a = if cosine { Values::F32(queries.image_appearance(q)).dot(ra) } else { 0.0 };
        match self.embedding {
            0.0 => a,
            w => a + w * Values::F32(queries.image_embedding(q)).dot(re),
        }
    }
}

/// Whether `cfg` has a search of `places` references go through their approximate index where
/// there is one (`index.search`; `auto`: from `index.min_places` references).
pub fn searches_index(cfg: &Config, places: usize) -> bool {
    match cfg.index.search {
        IndexSearch::Exact => false,
        IndexSearch::Approximate => true,
        IndexSearch::Auto => places >= cfg.index.min_places,
    }
}

/// Whether the fused coarse stage of `queries` against `refs` searches the approximate index:
/// `index.search` says so (`auto`: from `index.min_places` references), the source has one, and
/// the queries carry appearance vectors of its width.
pub fn uses_index(refs: &dyn RefSource, queries: &DescriptorSet, cfg: &Config) -> bool {
    searches_index(cfg, refs.len()) && refs.has_index() && queries.appearance_dim == refs.appearance_dim() && queries.appearance_dim > 0
}

/// The largest SSIM of two descriptors (each window's term is at most 1), with room for rounding.
const SSIM_MAX: f32 = 1.0 + 1e-4;
/// References of a shortlist whose SSIM is computed at a time (see [`indexed_topk`]).
const RESCORE_CHUNK: usize = 64;

/// The fused coarse stage through the approximate index: each query's shortlist
/// (`index.shortlist` references of its `index.probe` nearest lists) scored exactly as the full
/// scan scores it (the same appearance cosine, the fast SSIM path, the same sum: bit for bit the
/// scan's scores), the best `k` kept (ties to the lower reference). The SSIM, most of the cost,
/// is computed in order of falling cosine and stops where the next cosine plus `w_global` x the
/// largest SSIM cannot reach the k-th fused score so far: what is left out could not have entered
/// the top-K, so the result is that of scoring the whole shortlist.
pub fn indexed_topk(refs: &dyn RefSource, queries: &DescriptorSet, cfg: &Config, setting: Setting, k: usize) -> Result<CandidateLists> {
    let p = cfg.global.ssim_params();
    let (glen, slen) = (p.len(), p.stats_len());
    let w = FusedWeights::of(refs, queries, cfg, setting);
    let w_global = w.global;
    let cosine = baseline::unavailable(refs, queries, Setting::Appearance).is_none();
    let mut exec = coarse_cpu::CoarseCpu::new(&p);
    let (mut globals, mut stats, mut scores) = (Vec::new(), Vec::new(), Vec::new());
    let mut lists = Vec::with_capacity(queries.len());
    if k == 0 {
        return Ok(vec![vec![]; queries.len()]);
    }
    for q in 0..queries.len() {
        let iq = crate::index::IndexQuery {
            appearance: queries.image_appearance(q),
            global: queries.global(q),
            probe: cfg.index.probe,
            pool: cfg.index.pool,
            shortlist: cfg.index.shortlist,
            at_least: k,
            w_global,
            ssim: &cfg.global,
            embedding: queries.image_embedding(q),
            w_embedding: w.embedding,
        };
        let shortlist = match refs.index_shortlist(&iq) {
            Some(r) => r?,
            None => return Err(Error::invalid("coarse stage", "the references have no index")),
        };
        // exact cosines (and the embedding term), highest first
        let mut by_cos: Vec<(f32, u32)> = shortlist.par_iter().map(|&(_, r)| (w.appearance(refs, queries, q, r as usize, cosine), r)).collect();
        by_cos.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        exec.prepare(queries.stats(q), 1);
        let mut list: Vec<(f32, u32)> = Vec::with_capacity(by_cos.len());
        let mut kth = f32::NEG_INFINITY;
        for chunk in by_cos.chunks(RESCORE_CHUNK) {
            if list.len() >= k && chunk[0].0 + w_global * SSIM_MAX < kth {
                break;
            }
            let n = chunk.len();
            globals.clear();
            globals.resize(n * glen, 0.0);
            stats.clear();
            stats.resize(n * slen, 0.0);
            globals.par_chunks_mut(glen).zip(chunk.par_iter()).for_each_init(source::TileBuf::default, |buf, (g, &(_, r))| {
                g.copy_from_slice(refs.globals_tile(r as usize, r as usize + 1, buf));
            });
            crate::global::ssim_fast::ssim_stats_batch(&p, &globals, &mut stats);
            scores.clear();
            scores.resize(n, 0.0);
            exec.score_tile(queries.global(q), &globals, &stats, &mut scores);
            list.extend(chunk.iter().zip(&scores).map(|(&(cos, r), &ssim)| (cos + w_global * ssim, r)));
            if list.len() >= k {
                list.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
                list.truncate(k);
                kth = list[k - 1].0;
            }
        }
        list.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        list.truncate(k);
        lists.push(list);
    }
    Ok(lists)
}

/// The fused coarse stage on the CPU: per tile of references, the SSIM scores of the fast path
/// plus `w_global` x their appearance cosines, folded into the K-lists.
pub fn fused_topk_cpu(refs: &dyn RefSource, queries: &DescriptorSet, p: &SsimParams, w: FusedWeights, k: usize, tile: usize) -> Vec<Vec<(f32, u32)>> {
    let mut exec = coarse_cpu::CoarseCpu::new(p);
    exec.prepare(&queries.global_stats, queries.len());
    let mut buf = source::TileBuf::default();
    let nq = queries.len();
    let cosine = baseline::unavailable(refs, queries, Setting::Appearance).is_none();
    stream_topk(nq, refs.len(), k, tile, ssim_topk::topk_merge_ref_major, |tp, scores| {
        let (start, end) = (tp.tile_start as usize, (tp.tile_start + tp.tile_len) as usize);
        let (g, st) = refs.tile(start, end, &mut buf);
        exec.score_tile(&queries.globals, g, st, scores);
        scores.par_chunks_mut(nq).enumerate().for_each(|(j, row)| {
            let (ra, re) = (refs.image_appearance(start + j), refs.image_embedding(start + j));
            for (q, s) in row.iter_mut().enumerate() {
                *s = w.appearance_of(queries, q, &ra, &re, cosine) + w.global * *s;
            }
        });
    })
}

/// The score the coarse stage of `setting` gives each pair: SSIM of the global descriptors, plus
/// the appearance cosine where the stage fuses them (as [`fused_topk`] and [`coarse_topk`]).
pub(super) fn coarse_pair_scores(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config, pairs: &[(u32, u32)]) -> Vec<f32> {
    let p = cfg.global.ssim_params();
    let fw = FusedWeights::of(refs, queries, cfg, setting);
    let w = fw.global;
    let fused = setting.fuses_coarse(cfg.matching.coarse);
    let cosine = fused && baseline::unavailable(refs, queries, Setting::Appearance).is_none();
    pairs
        .par_iter()
        .map_init(
            || (source::TileBuf::default(), semlook_kernels::ssim::SsimScratch::default()),
            |(buf, scratch), &(q, r)| {
                let (q, r) = (q as usize, r as usize);
                let (g, st) = refs.tile(r, r + 1, buf);
                let ssim = semlook_kernels::ssim::ssim_pair(&p, queries.global(q), queries.stats(q), g, st, scratch);
                match (fused, cosine) {
                    (false, _) => ssim,
                    (true, true) => fw.appearance(refs, queries, q, r, true) + w * ssim,
                    (true, false) => fw.appearance(refs, queries, q, r, false) + w * ssim,
                }
            },
        )
        .collect()
}

/// Coarse stage on the CPU: for each query, the `k` references of highest SSIM, streamed over
/// tiles of `tile` references, scored by the fast path ([`coarse_cpu::CoarseCpu`]; the same
/// scores as the twin, bit for bit).
pub fn coarse_topk(refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Vec<Vec<(f32, u32)>> {
    let mut exec = coarse_cpu::CoarseCpu::new(p);
    exec.prepare(&queries.global_stats, queries.len());
    let mut buf = source::TileBuf::default();
    stream_topk(queries.len(), refs.len(), k, tile, ssim_topk::topk_merge_ref_major, |tp, scores| {
        let (start, end) = (tp.tile_start as usize, (tp.tile_start + tp.tile_len) as usize);
        let (g, st) = refs.tile(start, end, &mut buf);
        exec.score_tile(&queries.globals, g, st, scores);
    })
}

/// The coarse stage through the CPU twins of the kernels the GPU path runs (`ssim_block`, then
/// `topk_partial` and `topk_merge_lists`), in the GPU executor's loop: passes of at most `tile`
/// references (and at most what one merge takes), each scored into a queries x pass block,
/// selected per segment and merged into the ping-pong running lists. The reference the fast path
/// and the GPU path are held to. Descriptors too wide for `ssim_block`'s workgroup arrays (which
/// the GPU path refuses) are scored by the one-pair reference twins (`ssim_tile`, `topk_merge`).
pub fn coarse_topk_twin(refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Vec<Vec<(f32, u32)>> {
    use semlook_kernels::abi::{Entry, PassParams};
    use semlook_kernels::topk_select::{topk_merge_lists, topk_partial, MAX_LISTS, SEG};
    let (nq, n) = (queries.len(), refs.len());
    let mut buf = source::TileBuf::default();
    let Some((rb, qb)) = semlook_kernels::ssim_block::block_shape(p) else {
        return stream_topk(nq, n, k, tile, ssim_topk::topk_merge, |tp, scores| {
            let (start, end) = (tp.tile_start as usize, (tp.tile_start + tp.tile_len) as usize);
            let (g, st) = refs.tile(start, end, &mut buf);
            ssim_topk::ssim_tile(p, tp, &queries.globals, &queries.global_stats, g, st, scores);
        });
    };
    if nq == 0 || n == 0 || k == 0 {
        return vec![Vec::new(); nq];
    }
    let pass_refs = tile.clamp(1, (MAX_LISTS - 1) * SEG);
    let (mut top_a, mut top_b) = (vec![Entry::EMPTY; nq * k], vec![Entry::EMPTY; nq * k]);
    let mut parity = 0;
    for start in (0..n).step_by(pass_refs) {
        let len = pass_refs.min(n - start);
        let ps = PassParams {
            queries: nq as u32,
            refs: len as u32,
            ref_first: 0,
            ref_index: start as u32,
            rb,
            qb,
            k: k as u32,
            segs: len.div_ceil(SEG) as u32,
            parity,
            fresh: (start == 0) as u32,
            ..Default::default()
        };
        let (g, st) = refs.tile(start, start + len, &mut buf);
        let mut scores = vec![0.0; nq * len];
        semlook_kernels::ssim_block::ssim_block(p, &ps, &queries.globals, &queries.global_stats, &mut scores, g, st);
        let mut partial = vec![Entry::EMPTY; nq * ps.segs as usize * k];
        topk_partial(&ps, &scores, &mut partial);
        topk_merge_lists(&ps, &partial, &mut top_a, &mut top_b);
        parity ^= 1;
    }
    let top = if parity == 0 { top_a } else { top_b };
    let (s, i): (Vec<f32>, Vec<u32>) = top.iter().map(|e| (e.score, e.index)).unzip();
    ssim_topk::topk_lists(k, &s, &i)
}
