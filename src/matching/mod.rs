//! Stage 4: matching queries against a map (spec §2.7-2.9) in the four ablation settings of the
//! paper (§4.3, spec §6.1), plus the coarse stage alone.
//!
//! - coarse: SSIM of the query's global descriptor against every reference, streamed tile by tile
//!   into a top-K list (memory O(K) per query, never queries x map);
//! - fine: tree-set similarity of the query's forest against the K candidates (or against the
//!   whole map when the setting has no coarse stage), best first.

pub mod baseline;
pub mod coarse_cpu;
pub mod source;
pub mod ssim_block;
pub mod ssim_topk;
#[cfg(test)]
pub(crate) mod test_data;
pub mod topk_select;

use crate::config::{Config, ScoreFusion};
use crate::error::{Error, Result};
use crate::global::ssim::SsimParams;
use crate::local::tree_similarity::{tree_similarity, TreeSimParams, TreeSimScratch};
use crate::descriptors::DescriptorSet;
use crate::util::ms_since;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;
use source::{GlobalSource, RefSource};

/// A matching setting: which stages run and whether appearance takes part.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Setting {
    /// Baseline: VPR-Bench's HOG (grey 512 x 512, cosine), the floor any VPR method must beat.
    Hog,
    /// Baseline: the VLAD of all the image's appearance descriptors with the map's codebook (cosine).
    Appearance,
    /// Coarse stage only: rank by SSIM of the global descriptors ("Edge (Coarse)").
    Global,
    /// §6.1 (1): Forest descriptors only, against the whole map, no appearance.
    Forest,
    /// §6.1 (2): SemLook local descriptors (Forest + appearance), against the whole map.
    Local,
    /// §6.1 (3): global descriptor selects K candidates, Forest re-ranks them.
    GlobalForest,
    /// §6.1 (4): the full method: global top-K, SemLook local re-ranking.
    Semlook,
}

impl Setting {
    /// Every setting: the two baselines, then the coarse stage and the paper's four.
    pub const ALL: [Setting; 7] = [Setting::Hog, Setting::Appearance, Setting::Global, Setting::Forest, Setting::Local, Setting::GlobalForest, Setting::Semlook];
    /// The coarse stage and the paper's four settings (no baselines).
    pub const SEMLOOK: [Setting; 5] = [Setting::Global, Setting::Forest, Setting::Local, Setting::GlobalForest, Setting::Semlook];

    /// A baseline, not a SemLook setting: one whole-image vector per image, cosine similarity.
    pub fn is_baseline(self) -> bool {
        matches!(self, Setting::Hog | Setting::Appearance)
    }
    pub fn uses_coarse(self) -> bool {
        matches!(self, Setting::Global | Setting::GlobalForest | Setting::Semlook)
    }
    pub fn uses_fine(self) -> bool {
        !self.is_baseline() && self != Setting::Global
    }
    pub fn uses_appearance(self) -> bool {
        matches!(self, Setting::Local | Setting::Semlook)
    }
    pub fn name(self) -> &'static str {
        match self {
            Setting::Hog => "hog",
            Setting::Appearance => "appearance",
            Setting::Global => "global",
            Setting::Forest => "forest",
            Setting::Local => "local",
            Setting::GlobalForest => "global-forest",
            Setting::Semlook => "semlook",
        }
    }
    pub fn describe(self) -> &'static str {
        match self {
            Setting::Hog => "baseline: VPR-Bench HOG",
            Setting::Appearance => "baseline: whole-image VLAD",
            Setting::Global => "global SSIM only",
            Setting::Forest => "Forest, whole map",
            Setting::Local => "Forest+appearance, whole map",
            Setting::GlobalForest => "global top-K -> Forest",
            Setting::Semlook => "global top-K -> Forest+appearance",
        }
    }
}

impl std::fmt::Display for Setting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

/// One ranked reference for a query.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Candidate {
    /// Index of the reference in the map.
    pub reference: u32,
    /// SSIM of the global descriptors, when the coarse stage ran.
    pub coarse: Option<f32>,
    /// Tree-set similarity, when the fine stage ran.
    pub fine: Option<f32>,
    /// The score used for ranking and for the precision-recall curve.
    pub score: f32,
}

/// Ranked candidates of one query, best first (empty for an empty map, or a baseline that
/// could not run).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct QueryMatch {
    pub ranked: Vec<Candidate>,
}

impl QueryMatch {
    pub fn best(&self) -> Option<&Candidate> {
        self.ranked.first()
    }
}

/// Wall-clock time of a batch, per stage.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct MatchTimes {
    pub coarse_ms: f64,
    pub fine_ms: f64,
}

/// The three heavy operations of matching, implemented by the CPU path ([`CpuStages`]) and by
/// the GPU path (`engine::GpuStages`); [`match_with`] composes them the same way for both.
pub trait Stages {
    /// For each query, the `k` best references by SSIM (best first).
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
    /// Tree-set similarity of each (query, reference) pair.
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>>;
    /// For each query, the `k` best references of the whole map by tree-set similarity.
    fn fine_topk(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
}

/// The CPU reference path (rayon over queries or pairs).
pub struct CpuStages;

impl Stages for CpuStages {
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(coarse_topk(refs, queries, p, k, tile))
    }
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>> {
        Ok(pairs
            .par_iter()
            .map_init(TreeSimScratch::default, |s, &(q, r)| tree_similarity(p, queries.forest(q as usize), refs.forest(r as usize), s))
            .collect())
    }
    /// Tree similarities of all queries against one tile of references at a time, folded into
    /// the per-query top-K by `topk_merge`, as the GPU path does.
    fn fine_topk(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(stream_topk(queries.len(), refs.len(), k, tile, ssim_topk::topk_merge, |tp, scores| {
            let (start, t) = (tp.tile_start as usize, tp.tile_len as usize);
            scores.par_iter_mut().enumerate().for_each_init(TreeSimScratch::default, |scratch, (i, s)| {
                *s = tree_similarity(p, queries.forest(i / t), refs.forest(start + i % t), scratch);
            });
        }))
    }
}

/// Matches every query of `queries` against `refs` with `setting` on the CPU; results in query
/// order. A baseline the descriptors lack (see [`baseline::unavailable`]), or a stored map with a
/// damaged segment, ranks nothing (a warning is logged); [`try_match_batch`] returns either as an
/// error instead.
pub fn match_batch(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> (Vec<QueryMatch>, MatchTimes) {
    try_match_batch(refs, queries, setting, cfg).unwrap_or_else(|e| {
        log::warn!("{e}");
        (vec![QueryMatch { ranked: vec![] }; queries.len()], MatchTimes::default())
    })
}

/// [`match_batch`], failing when `setting` cannot run on these descriptors.
pub fn try_match_batch(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Result<(Vec<QueryMatch>, MatchTimes)> {
    match_with(&mut CpuStages, refs, queries, setting, cfg)
}

/// Matches with the given stages: coarse top-K, fine re-ranking of the candidates (or fine
/// top-K over the whole map for settings without a coarse stage), best first.
pub fn match_with(stages: &mut dyn Stages, refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Result<(Vec<QueryMatch>, MatchTimes)> {
    let k = cfg.matching.top_k;
    let list_len = k.max(cfg.eval.recall_at.iter().copied().max().unwrap_or(1));
    let mut times = MatchTimes::default();
    let params = TreeSimParams::new(&cfg.similarity, setting.uses_appearance(), refs.neighbour_slots());
    if refs.is_empty() {
        return Ok((vec![QueryMatch { ranked: vec![] }; queries.len()], times));
    }
    let ranked: Vec<Vec<Candidate>> = if setting.is_baseline() {
        let t = Instant::now();
        let lists = baseline::topk(refs, queries, setting, list_len, cfg.matching.tile)?;
        times.coarse_ms = ms_since(t);
        lists.iter().map(|l| l.iter().map(|&(s, r)| Candidate { reference: r, coarse: None, fine: None, score: s }).collect()).collect()
    } else if setting.uses_coarse() {
        let t = Instant::now();
        let lists = stages.coarse(refs, queries, &SsimParams::new(&cfg.global), k, cfg.matching.tile)?;
        times.coarse_ms = ms_since(t);
        if setting.uses_fine() {
            let t = Instant::now();
            let pairs: Vec<(u32, u32)> = lists.iter().enumerate().flat_map(|(q, l)| l.iter().map(move |&(_, r)| (q as u32, r))).collect();
            let fine = stages.fine_pairs(&params, refs, queries, &pairs)?;
            times.fine_ms = ms_since(t);
            if fine.len() != pairs.len() {
                return Err(Error::invalid("fine stage", format!("{} scores for {} pairs", fine.len(), pairs.len())));
            }
            let mut it = fine.into_iter();
            lists
                .iter()
                .map(|l| {
                    l.iter()
                        .map(|&(s, r)| {
                            // as many scores as pairs, checked above
                            let f = it.next().unwrap_or(f32::NAN);
                            let score = match cfg.matching.score {
                                ScoreFusion::Fine => f,
                                ScoreFusion::FineTimesGlobal => f * s,
                            };
                            Candidate { reference: r, coarse: Some(s), fine: Some(f), score }
                        })
                        .collect()
                })
                .collect()
        } else {
            lists.iter().map(|l| l.iter().map(|&(s, r)| Candidate { reference: r, coarse: Some(s), fine: None, score: s }).collect()).collect()
        }
    } else {
        let t = Instant::now();
        let lists = stages.fine_topk(&params, refs, queries, list_len, cfg.matching.tile)?;
        times.fine_ms = ms_since(t);
        lists.iter().map(|l| l.iter().map(|&(s, r)| Candidate { reference: r, coarse: None, fine: Some(s), score: s }).collect()).collect()
    };
    // a stored map checks each segment on first read; one that failed was read as empty
    refs.check()?;
    let results = ranked
        .into_iter()
        .map(|mut c| {
            // best first; ties keep the coarse order (stable sort)
            c.sort_by(|a, b| b.score.total_cmp(&a.score));
            QueryMatch { ranked: c }
        })
        .collect();
    Ok((results, times))
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

/// The coarse stage through the GPU kernels' CPU twins (`ssim_tile`, `topk_merge`), tile by
/// tile: the reference the fast path and the GPU path are held to.
pub fn coarse_topk_twin(refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Vec<Vec<(f32, u32)>> {
    let mut buf = source::TileBuf::default();
    stream_topk(queries.len(), refs.len(), k, tile, ssim_topk::topk_merge, |tp, scores| {
        let (start, end) = (tp.tile_start as usize, (tp.tile_start + tp.tile_len) as usize);
        let (g, st) = refs.tile(start, end, &mut buf);
        ssim_topk::ssim_tile(p, tp, &queries.globals, &queries.global_stats, g, st, scores);
    })
}

/// A function folding one tile's scores into the K-lists (`topk_merge` or its reference-major form).
type Merge = fn(&ssim_topk::TileParams, &[f32], &mut [f32], &mut [u32]);

/// The CPU streaming top-K over a map of `n` references: per tile of at most `tile` references,
/// `score` fills the queries x tile scores, which `merge` folds into each query's K-list.
pub(crate) fn stream_topk(nq: usize, n: usize, k: usize, tile: usize, merge: Merge, mut score: impl FnMut(&ssim_topk::TileParams, &mut [f32])) -> Vec<Vec<(f32, u32)>> {
    let tile = tile.max(1).min(n.max(1));
    let mut scores = vec![0.0f32; nq * tile];
    let mut top_s = vec![ssim_topk::EMPTY_SCORE; nq * k];
    let mut top_i = vec![ssim_topk::EMPTY_INDEX; nq * k];
    let mut start = 0;
    while start < n {
        let end = (start + tile).min(n);
        let tp = ssim_topk::TileParams { queries: nq as u32, tile_len: (end - start) as u32, tile_start: start as u32, k: k as u32 };
        score(&tp, &mut scores[..nq * (end - start)]);
        merge(&tp, &scores[..nq * (end - start)], &mut top_s, &mut top_i);
        start = end;
    }
    ssim_topk::topk_lists(k, &top_s, &top_i)
}
