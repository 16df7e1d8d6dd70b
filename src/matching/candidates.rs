//! Each query's candidates: which stage gives them for a setting (a baseline, the index, the
//! fused or the plain coarse stage, or the fine stage over the whole map), how long the lists
//! are, and the checks made before (labels, HOG); merging the lists of a map's shards.

use super::answer::{CandidateLists, MatchTimes};
use super::coarse::{indexed_topk, uses_index, FusedWeights};
use super::stages::Stages;
use super::{baseline, setting::Setting};
use crate::config::Config;
use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Remedy, Result};
use crate::util::ms_since;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::ssim_topk;
use std::time::Instant;

/// Length of the candidate lists of `setting`: K for the settings with a coarse stage, else the
/// longest recall@N asked for (at least K), since those lists are the final ranking.
pub fn list_len(setting: Setting, cfg: &Config) -> usize {
    match setting.uses_coarse() {
        true => cfg.matching.top_k,
        false => cfg.matching.top_k.max(cfg.eval.recall_at.iter().copied().max().unwrap_or(1)),
    }
}

/// Each query's candidates, best first, as (score, index in `refs`): the coarse K-list for the
/// settings with a coarse stage, else the final list of the fine stage or baseline ([`list_len`]
/// long). Fails if a segment of a stored map was damaged or the setting cannot run here.
pub fn candidates(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
) -> Result<(CandidateLists, MatchTimes)> {
    let mut times = MatchTimes::default();
    check_labels(refs, setting)?;
    if refs.is_empty() {
        return Ok((vec![vec![]; queries.len()], times));
    }
    let t = Instant::now();
    let len = list_len(setting, cfg);
    let lists = if setting.is_baseline() {
        baseline::topk(refs, queries, setting, len, cfg.matching.tile)?
    } else if setting.fuses_coarse(cfg.matching.coarse) && uses_index(refs, queries, cfg) {
        times.approximate = true;
        indexed_topk(refs, queries, cfg, setting, len)?
    } else if setting.fuses_coarse(cfg.matching.coarse) {
        fused_topk(stages, refs, queries, cfg, setting, len)?
    } else if setting.uses_coarse() {
        stages.coarse(refs, queries, &cfg.global.ssim_params(), len, cfg.matching.tile)?
    } else {
        let params = tree_params(cfg, setting, refs.neighbour_slots())?;
        stages.fine_topk(&params, refs, queries, len, cfg.matching.tile)?
    };
    match setting.uses_coarse() || setting.is_baseline() {
        true => times.coarse_ms = ms_since(t),
        false => times.fine_ms = ms_since(t),
    }
    // a stored map checks each segment on first read; one that failed was read as empty
    refs.check()?;
    Ok((lists, times))
}

/// Fails if `setting` needs semantic labels and `refs` were encoded without them (a map built
/// from photos with neither label maps nor a segmenter), or is the HOG baseline and `refs` store
/// no HOG descriptors: cheap, so callers check before encoding.
pub fn check_labels(refs: &dyn RefSource, setting: Setting) -> Result<()> {
    if setting == Setting::Hog && refs.hog_dim() == 0 {
        return Err(Error::refused(format!("setting {setting}"), "the map stores no HOG descriptors", Remedy::RebuildWithHog));
    }
    match setting.label_free() {
        Some(_) if !refs.labelled() => Err(Error::refused(
            format!("setting {setting}"),
            format!(
                "the map was built without semantic labels (its photos had neither label maps nor a segmenter), {}",
                if setting == Setting::Fused { "and without them fused is the appearance baseline" } else { "which this setting needs" }
            ),
            Remedy::RebuildWithLabels,
        )),
        _ => Ok(()),
    }
}

/// The tree-similarity parameters of `setting` under `cfg` (its class table's categories for
/// `similarity.class_match`).
pub fn tree_params(cfg: &Config, setting: Setting, neighbour_slots: usize) -> Result<TreeSimParams> {
    let table = crate::classes::ClassTable::from_config(&cfg.classes)?;
    Ok(cfg.similarity.tree_params_over(setting.uses_appearance(), neighbour_slots, &table.category_key()))
}

/// Merges per-shard candidate lists of the same queries (indices in the whole map's index space,
/// each shard's lists holding the K best of its references) into the whole map's lists: exactly the
/// lists one process computes, ties across shards included (the twin's fold,
/// [`ssim_topk::merge_lists`]). Fails if the shards disagree on the number of queries, or a list
/// holds one reference twice (an [`Error::Check`]).
pub fn merge_lists(parts: &[&[Vec<(f32, u32)>]], k: usize) -> Result<Vec<Vec<(f32, u32)>>> {
    ssim_topk::merge_lists(parts, k).map_err(|e| Error::check(e.0))
}

/// The fused coarse stage: for each query, the `k` references of highest
/// cos(whole-image appearance) + `matching.w_global` x SSIM(global descriptors). Descriptors
/// without appearance have no cosine term (the ranking is then the global descriptor's).
fn fused_topk(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    cfg: &Config,
    setting: Setting,
    k: usize,
) -> Result<CandidateLists> {
    let w = cfg.matching.w_global as f32;
    let weights = FusedWeights::of(refs, queries, cfg, setting);
    if baseline::unavailable(refs, queries, Setting::Appearance).is_some() && w > 0.0 && weights.embedding == 0.0 {
        // no cosine term: the global ranking, each score times w (as the fused scan computes it)
        let mut lists = stages.coarse(refs, queries, &cfg.global.ssim_params(), k, cfg.matching.tile)?;
        lists.iter_mut().flatten().for_each(|(s, _)| *s *= w);
        return Ok(lists);
    }
    stages.fused_coarse(refs, queries, &cfg.global.ssim_params(), weights, k, cfg.matching.tile)
}
