//! Stage 4: matching queries against a map (spec §2.7-2.9) in the four ablation settings of the
//! paper (§4.3, spec §6.1), plus the coarse stage alone.
//!
//! - coarse: SSIM of the query's global descriptor against every reference, streamed tile by tile
//!   into a top-K list (memory O(K) per query, never queries x map);
//! - fine: tree-set similarity of the query's forest against the K candidates (or against the
//!   whole map when the setting has no coarse stage), best first.

pub mod topk;

use crate::config::{Config, ScoreFusion};
use crate::global::ssim::{ssim_pair, SsimParams, SsimScratch};
use crate::local::tree_similarity::{tree_similarity, TreeSimParams, TreeSimScratch};
use crate::map::DescriptorSet;
use crate::util::ms_since;
use rayon::prelude::*;
use serde::{Deserialize, Serialize};
use std::time::Instant;
use topk::TopK;

/// A matching setting: which stages run and whether appearance takes part.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "kebab-case")]
pub enum Setting {
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
    pub const ALL: [Setting; 5] = [Setting::Global, Setting::Forest, Setting::Local, Setting::GlobalForest, Setting::Semlook];
    /// The four settings of the paper's ablation.
    pub const ABLATION: [Setting; 4] = [Setting::Forest, Setting::Local, Setting::GlobalForest, Setting::Semlook];

    pub fn uses_coarse(self) -> bool {
        matches!(self, Setting::Global | Setting::GlobalForest | Setting::Semlook)
    }
    pub fn uses_fine(self) -> bool {
        self != Setting::Global
    }
    pub fn uses_appearance(self) -> bool {
        matches!(self, Setting::Local | Setting::Semlook)
    }
    pub fn name(self) -> &'static str {
        match self {
            Setting::Global => "global",
            Setting::Forest => "forest",
            Setting::Local => "local",
            Setting::GlobalForest => "global-forest",
            Setting::Semlook => "semlook",
        }
    }
    pub fn describe(self) -> &'static str {
        match self {
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

/// Ranked candidates of one query, best first (empty only for an empty map).
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

/// Matches every query of `queries` against `refs` with `setting`; results in query order.
/// `list_len` is how many ranked candidates to keep when there is no coarse stage (at least K).
pub fn match_batch(refs: &DescriptorSet, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> (Vec<QueryMatch>, MatchTimes) {
    let k = cfg.matching.top_k;
    let list_len = k.max(cfg.eval.recall_at.iter().copied().max().unwrap_or(1));
    let mut times = MatchTimes::default();
    let nq = queries.len();
    let coarse_lists: Vec<Vec<(f32, u32)>> = if setting.uses_coarse() {
        let t = Instant::now();
        let lists = coarse_topk(refs, queries, &SsimParams::new(&cfg.global), k, cfg.matching.tile);
        times.coarse_ms = ms_since(t);
        lists
    } else {
        vec![vec![]; nq]
    };
    let t = Instant::now();
    let params = TreeSimParams::new(&cfg.similarity, setting.uses_appearance(), refs.neighbour_slots);
    let results: Vec<QueryMatch> = (0..nq)
        .into_par_iter()
        .map_init(TreeSimScratch::default, |scratch, q| {
            let qf = queries.forest(q);
            let mut ranked: Vec<Candidate> = if !setting.uses_fine() {
                coarse_lists[q].iter().map(|&(s, r)| Candidate { reference: r, coarse: Some(s), fine: None, score: s }).collect()
            } else if setting.uses_coarse() {
                coarse_lists[q]
                    .iter()
                    .map(|&(s, r)| {
                        let fine = tree_similarity(&params, qf, refs.forest(r as usize), scratch);
                        let score = match cfg.matching.score {
                            ScoreFusion::Fine => fine,
                            ScoreFusion::FineTimesGlobal => fine * s,
                        };
                        Candidate { reference: r, coarse: Some(s), fine: Some(fine), score }
                    })
                    .collect()
            } else {
                let mut top = TopK::new(list_len);
                for r in 0..refs.len() {
                    top.push(tree_similarity(&params, qf, refs.forest(r), scratch), r as u32);
                }
                top.into_items().into_iter().map(|(s, r)| Candidate { reference: r, coarse: None, fine: Some(s), score: s }).collect()
            };
            // best first; ties keep the coarse order (stable sort)
            ranked.sort_by(|a, b| b.score.total_cmp(&a.score));
            QueryMatch { ranked }
        })
        .collect();
    if setting.uses_fine() {
        times.fine_ms = ms_since(t);
    }
    (results, times)
}

/// Coarse stage: for each query, the `k` references of highest SSIM, streamed over tiles of
/// `tile` references. Tiles are the outer loop so a tile stays in cache for the whole batch.
pub fn coarse_topk(refs: &DescriptorSet, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Vec<Vec<(f32, u32)>> {
    let mut state: Vec<(TopK, SsimScratch)> = (0..queries.len()).map(|_| (TopK::new(k), SsimScratch::default())).collect();
    let mut start = 0;
    while start < refs.len() {
        let end = (start + tile).min(refs.len());
        state.par_iter_mut().enumerate().for_each(|(q, (top, scratch))| {
            let (qg, qs) = (queries.global(q), queries.stats(q));
            for r in start..end {
                top.push(ssim_pair(p, qg, qs, refs.global(r), refs.stats(r), scratch), r as u32);
            }
        });
        start = end;
    }
    state.into_iter().map(|(t, _)| t.into_items()).collect()
}
