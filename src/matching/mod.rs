//! Stage 4: matching queries against a map (`docs/design/method.md` §2.7-2.9) in nine settings ([`Setting::ALL`]): two
//! baselines, the paper's coarse stage and four ablation settings (paper §4.3, method.md §6.1), `fused` and
//! `verified`.
//!
//! - coarse: SSIM of the query's global descriptor against every reference, streamed tile by tile
//!   into a top-K list (memory O(K) per query, never queries x map);
//! - fine: tree-set similarity of the query's forest against the K candidates (or against the
//!   whole map when the setting has no coarse stage), best first.
//!
//! The files follow the query's walk: [`candidates`] (which stage gives a setting's lists, their
//! length, the checks made first) on [`Stages`] (the three heavy operations; [`CpuStages`] here,
//! `gpu::GpuStages` on the device), whose CPU coarse scans are in `coarse.rs` (the fast path, the
//! fused score, the approximate index) and `coarse_cpu.rs` (the tile executor); then [`rank`]
//! (each pair's terms and score, the ranking); what a query gets back is `answer.rs`'s
//! ([`QueryMatch`]). [`match_with`] composes them.

mod answer;
pub mod baseline;
mod candidates;
mod coarse;
pub mod coarse_cpu;
pub mod evidence;
pub mod null;
mod rank;
pub mod setting;
mod stages;

pub use answer::{pairs_of, Candidate, CandidateLists, MatchTimes, QueryMatch};
pub use candidates::{candidates, check_labels, list_len, merge_lists, tree_params};
pub use coarse::{coarse_topk, coarse_topk_twin, fused_topk_cpu, indexed_topk, searches_index, uses_index, FusedWeights};
pub use evidence::{Evidence, PairScore};
pub use rank::{fine_scores, measure_null, pair_terms, rank, score_pairs, PairTerms};
pub use setting::{Setting, UnknownSetting};
pub use stages::{CpuStages, Stages};

use crate::config::Config;
use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::error::Result;
use crate::util::ms_since;
use rank::pair_scores;
use std::time::Instant;

/// Matches every query of `queries` against `refs` with `setting` on the CPU; results in query
/// order. A baseline the descriptors lack (see [`baseline::unavailable`]), or a stored map with a
/// damaged segment, is an error (one fallible path, as `Engine::match_batch`).
pub fn match_batch(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Result<(Vec<QueryMatch>, MatchTimes)> {
    match_with(&mut CpuStages, refs, queries, setting, cfg)
}

/// Matches with the given stages: coarse top-K, fine re-ranking of the candidates (or fine
/// top-K over the whole map for settings without a coarse stage), best first. The same three
/// steps ([`candidates`], [`fine_scores`], [`rank`]) serve a map split into shards: each shard
/// gives its candidates, [`merge_lists`] keeps the global K, the owners score the pairs.
pub fn match_with(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
) -> Result<(Vec<QueryMatch>, MatchTimes)> {
    let (lists, mut times) = candidates(stages, refs, queries, setting, cfg)?;
    let fine = match setting.reranks() {
        true => {
            let t = Instant::now();
            let (f, _) = pair_scores(stages, refs, queries, setting, cfg, &pairs_of(&lists))?;
            times.fine_ms = ms_since(t);
            Some(f)
        }
        false => None,
    };
    Ok((rank(setting, &lists, fine.as_deref(), cfg)?, times))
}
