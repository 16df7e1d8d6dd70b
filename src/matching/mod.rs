//! Stage 4: matching queries against a map (`docs/design/method.md` §2.7-2.9) in nine settings ([`Setting::ALL`]): two
//! baselines, the paper's coarse stage and four ablation settings (paper §4.3, method.md §6.1), `fused` and
//! `verified`.
//!
//! - coarse: SSIM of the query's global descriptor against every reference, streamed tile by tile
//!   into a top-K list (memory O(K) per query, never queries x map);
//! - fine: tree-set similarity of the query's forest against the K candidates (or against the
//!   whole map when the setting has no coarse stage), best first.

pub mod baseline;
pub mod coarse_cpu;
pub mod evidence;
pub mod null;
pub mod setting;

pub use evidence::{Evidence, PairScore};
pub use setting::{Setting, UnknownSetting};

use crate::classes::ClassTable;
use crate::config::{Config, IndexSearch, Matcher, ScoreFusion};
use crate::descriptors::source::{self, GlobalSource, RefSource};
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Remedy, Result};
use crate::util::ms_since;
use crate::values::Values;
use crate::verify::{verify_pairs_cpu, Verified, VerifyParams};
use coarse_cpu::stream_topk;
use rayon::prelude::*;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::ssim_topk;
use semlook_kernels::tree_similarity::{tree_similarity, TreeSimScratch};
use serde::Serialize;
use std::time::Instant;

/// One ranked reference for a query.
#[derive(Debug, Clone, Copy, PartialEq, Serialize)]
pub struct Candidate {
    /// Index of the reference in the map.
    pub reference: u32,
    /// SSIM of the global descriptors, when the coarse stage ran.
    pub coarse: Option<f32>,
    /// Tree-set similarity, when the fine stage ran.
    pub fine: Option<f32>,
    /// Keypoint matches the verification's homography explains, when it ran.
    pub inliers: Option<u32>,
    /// The score used for ranking and for the precision-recall curve.
    pub score: f32,
}

/// Ranked candidates of one query, best first (empty for an empty map, or a baseline that
/// could not run).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct QueryMatch {
    /// Candidates, best first.
    pub ranked: Vec<Candidate>,
    /// `verified`: how the candidates spread in each evidence term ([`score_pairs`] scores other
    /// references of the query against it).
    pub evidence: Option<Evidence>,
}

impl QueryMatch {
    /// The top-1 candidate, if any.
    pub fn best(&self) -> Option<&Candidate> {
        self.ranked.first()
    }
}

/// Wall-clock time of a batch, per stage.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct MatchTimes {
    /// Milliseconds of the candidate stage: coarse top-K, or a baseline's ranking.
    pub coarse_ms: f64,
    /// Milliseconds of the fine stage: re-ranking (with verification where it runs), or fine top-K over the whole map.
    pub fine_ms: f64,
    /// The coarse stage searched the map's approximate index (`index.search`), not every
    /// reference.
    pub approximate: bool,
}

/// The three heavy operations of matching, implemented by the CPU path ([`CpuStages`]) and by
/// the GPU path (`gpu::GpuStages`); [`match_with`] composes them the same way for both.
pub trait Stages {
    /// For each query, the `k` best references by SSIM (best first).
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
    /// Tree-set similarity of each (query, reference) pair.
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>>;
    /// For each query, the `k` best references of the whole map by tree-set similarity.
    fn fine_topk(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
    /// For each query, the `k` best references by cos(appearance) + `w.embedding` x
    /// cos(embeddings) + `w.global` x SSIM.
    fn fused_coarse(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        p: &SsimParams,
        w: FusedWeights,
        k: usize,
        tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>>;
    /// Geometric verification of each (query, reference) pair.
    fn verify_pairs(&mut self, p: &VerifyParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<Verified>>;
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
    fn fused_coarse(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        p: &SsimParams,
        w: FusedWeights,
        k: usize,
        tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(fused_topk_cpu(refs, queries, p, w, k, tile))
    }
    /// Mutual nearest neighbours by the fast path (a matrix product per pair), or LighterGlue; then RANSAC.
    fn verify_pairs(&mut self, p: &VerifyParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<Verified>> {
        verify_pairs_cpu(p, &|q| queries.keypoints(q as usize), &|r| refs.keypoints(r as usize), pairs)
    }
}

/// Matches every query of `queries` against `refs` with `setting` on the CPU; results in query
/// order. A baseline the descriptors lack (see [`baseline::unavailable`]), or a stored map with a
/// damaged segment, is an error (one fallible path, as `Engine::match_batch`).
pub fn match_batch(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Result<(Vec<QueryMatch>, MatchTimes)> {
    match_with(&mut CpuStages, refs, queries, setting, cfg)
}

/// Matches with the given stages: coarse top-K, fine re-ranking of the candidates (or fine
/// top-K over the whole map for settings without a coarse stage), best first. The same three
/// steps ([`candidates`], [`fine_scores`], [`rank`]) serve a map split into shards: each shard
/// gives its candidates, [`ssim_topk::merge_lists`] keeps the global K, the owners score the pairs.
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

/// Length of the candidate lists of `setting`: K for the settings with a coarse stage, else the
/// longest recall@N asked for (at least K), since those lists are the final ranking.
pub fn list_len(setting: Setting, cfg: &Config) -> usize {
    match setting.uses_coarse() {
        true => cfg.matching.top_k,
        false => cfg.matching.top_k.max(cfg.eval.recall_at.iter().copied().max().unwrap_or(1)),
    }
}

/// Per query, (score, reference) best first.
pub type CandidateLists = Vec<Vec<(f32, u32)>>;

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

/// The (query, reference) pairs of candidate lists, in list order.
pub fn pairs_of(lists: &[Vec<(f32, u32)>]) -> Vec<(u32, u32)> {
    lists.iter().enumerate().flat_map(|(q, l)| l.iter().map(move |&(_, r)| (q as u32, r))).collect()
}

/// The fine score of each (query, reference index in `refs`) pair under `setting` ([`PairScore`]):
/// the tree-set similarity, and for `verified` the part of the verified score that depends on the
/// pair alone and its evidence (inliers, compact HOGs' cosine); [`rank`] adds the coarse part and
/// weighs the evidence against the query's other candidates.
pub fn fine_scores(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
    pairs: &[(u32, u32)],
) -> Result<Vec<PairScore>> {
    Ok(pair_scores(stages, refs, queries, setting, cfg, pairs)?.0)
}

/// [`fine_scores`], with the verification of each pair for the settings that verify.
fn pair_scores(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
    pairs: &[(u32, u32)],
) -> Result<(Vec<PairScore>, Option<Vec<Verified>>)> {
    let terms = pair_terms(stages, refs, queries, setting, cfg, pairs)?;
    let verified = setting.verifies().then(|| terms.iter().map(|t| t.verified.unwrap_or_default()).collect());
    Ok((terms.iter().map(|t| t.score(&cfg.verification)).collect(), verified))
}

/// What the fine stage measures of one pair, before any weight: the tree-set similarity and, for
/// `verified`, the verification and the compact HOGs' cosine, with their tail probabilities
/// under the map's null where the score tests against it. [`PairTerms::score`] weighs them (a
/// sweep of the weights measures once, `semlook dev tune`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct PairTerms {
    /// Tree-set similarity.
    pub similarity: f32,
    /// `verified`: what verification found.
    pub verified: Option<Verified>,
    /// `verified`, where both images have compact HOGs: their cosine.
    pub compact_hog: Option<f32>,
    /// `verified` with `inliers = "significant"`: P(null pair shows as many inliers).
    pub p_inliers: Option<f32>,
    /// `verified` with `inliers = "significant"`, where both have compact HOGs: P(null pair's are
    /// as alike).
    pub p_compact_hog: Option<f32>,
}

impl PairTerms {
    /// The pair's [`PairScore`] under `v`'s weights: for `verified`, `w_fine` x the similarity +
    /// `w_glue` x ln(1 + LighterGlue's inliers), with the evidence for [`rank`] to weigh; else the
    /// similarity.
    pub fn score(&self, v: &crate::config::VerificationConfig) -> PairScore {
        match self.verified {
            None => PairScore { fine: self.similarity, ..PairScore::default() },
            Some(ver) => PairScore {
                fine: (v.w_glue * (ver.glue_inliers as f64).ln_1p() + v.w_fine * self.similarity as f64) as f32,
                inliers: Some(ver.inliers),
                compact_hog: self.compact_hog,
                p_inliers: self.p_inliers,
                p_compact_hog: self.p_compact_hog,
            },
        }
    }
}

/// The [`PairTerms`] of each (query, reference) pair under `setting`.
pub fn pair_terms(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
    pairs: &[(u32, u32)],
) -> Result<Vec<PairTerms>> {
    if let Some(&(q, r)) = pairs.iter().find(|&&(q, r)| q as usize >= queries.len() || r as usize >= refs.len()) {
        return Err(Error::invalid("fine stage", format!("pair ({q}, {r}) outside {} queries x {} references", queries.len(), refs.len())));
    }
    let params = tree_params(cfg, setting, refs.neighbour_slots())?;
    let similarity = stages.fine_pairs(&params, refs, queries, pairs)?;
    if similarity.len() != pairs.len() {
        return Err(Error::invalid("fine stage", format!("{} scores for {} pairs", similarity.len(), pairs.len())));
    }
    let mut terms: Vec<PairTerms> = similarity.iter().map(|&f| PairTerms { similarity: f, ..PairTerms::default() }).collect();
    if setting.verifies() {
        let vp = VerifyParams::for_config(&cfg.verification, &ClassTable::from_config(&cfg.classes)?)?;
        let mut v = stages.verify_pairs(&vp, refs, queries, pairs)?;
        if v.len() != pairs.len() {
            return Err(Error::invalid("verification", format!("{} results for {} pairs", v.len(), pairs.len())));
        }
        let w = &cfg.verification;
        if w.matcher == Matcher::Mnn && w.w_glue > 0.0 {
            // the learned matcher beside MNN, on every pair whose MNN inliers reach
            // `glue_min_inliers`: a rule of the pair alone, so its score never depends on which
            // other pairs are scored with it (shards, sequence neighbours)
            let gated: Vec<usize> = (0..pairs.len()).filter(|&i| v[i].inliers >= w.glue_min_inliers).collect();
            let sub: Vec<(u32, u32)> = gated.iter().map(|&i| pairs[i]).collect();
            let g = stages.verify_pairs(&VerifyParams { matcher: Matcher::Lighterglue, ..vp }, refs, queries, &sub)?;
            if g.len() != sub.len() {
                return Err(Error::invalid("verification", format!("{} results for {} pairs", g.len(), sub.len())));
            }
            gated.iter().zip(&g).for_each(|(&i, g)| v[i].glue_inliers = g.inliers);
        }
        // the compact HOGs' cosine where both sides have them (maps of small frames)
        let hog = queries.compact_hog_dim > 0 && refs.compact_hog_dim() == queries.compact_hog_dim;
        for ((t, v), &(q, r)) in terms.iter_mut().zip(&v).zip(pairs) {
            t.verified = Some(*v);
            t.compact_hog = hog.then(|| Values::F32(queries.image_compact_hog(q as usize)).dot(&refs.image_compact_hog(r as usize)));
        }
        // the evidence's tail probabilities under the map's null, where the score tests against it
        if w.inliers == crate::config::InlierEvidence::Significant && !pairs.is_empty() {
            let null = null::kept_or(refs, cfg, || measure_null(stages, refs, cfg))?;
            let inliers: Vec<Option<u32>> = terms.iter().map(|t| t.verified.map(|v| v.inliers)).collect();
            let hogs: Vec<Option<f32>> = terms.iter().map(|t| t.compact_hog).collect();
            let (pi, ph) = null.p_values(&inliers, &hogs);
            for ((t, pi), ph) in terms.iter_mut().zip(pi).zip(ph) {
                (t.p_inliers, t.p_compact_hog) = (pi, ph);
            }
        }
    }
    refs.check()?;
    Ok(terms)
}

/// Measures the null of `verified`'s evidence over `refs` under `cfg` ([`null`]'s docs): the
/// `null_sources` references matched by `verified`'s coarse stage against the map, their
/// candidates of other places verified.
pub fn measure_null(stages: &mut dyn Stages, refs: &dyn RefSource, cfg: &Config) -> Result<null::NullEvidence> {
    let v = &cfg.verification;
    let src = null::sources(refs.len(), v.null_sources as usize);
    if src.is_empty() || refs.keypoint_dim() == 0 {
        return Ok(null::NullEvidence::from_pairs(null::key(cfg), src.len(), std::iter::empty(), vec![]));
    }
    let queries = refs.gather(&src)?;
    // each source's K candidates of other places: enough candidates asked for that the gap's
    // own references (at most 2 gap + 1 of them) leave K
    let mut wide = cfg.clone();
    wide.matching.top_k = cfg.matching.top_k + 2 * v.null_gap as usize + 1;
    let (lists, _) = candidates(stages, refs, &queries, Setting::Verified, &wide)?;
    let pairs = null::null_pairs(refs, &src, &lists, v.null_gap, cfg.matching.top_k);
    let vp = VerifyParams::for_config(v, &ClassTable::from_config(&cfg.classes)?)?;
    let verified = stages.verify_pairs(&vp, refs, &queries, &pairs)?;
    let hog = queries.compact_hog_dim > 0 && refs.compact_hog_dim() == queries.compact_hog_dim;
    let compact_hog: Vec<f32> = match hog {
        true => pairs.iter().map(|&(q, r)| Values::F32(queries.image_compact_hog(q as usize)).dot(&refs.image_compact_hog(r as usize))).collect(),
        false => vec![],
    };
    refs.check()?;
    Ok(null::NullEvidence::from_pairs(null::key(cfg), src.len(), verified.iter().map(|r| r.inliers), compact_hog))
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

/// The final ranking from candidate lists and, for settings with both stages, the fine score of
/// every candidate in list order (as [`pairs_of`] lists them): the score is the fine one (or fine
/// x SSIM, `matching.score`; for `verified`, fine + `verification.w_coarse` x the fused coarse
/// score + the evidence terms against the query's candidates, [`Evidence::terms`]), best first,
/// ties keeping the coarse order (stable sort).
pub fn rank(setting: Setting, lists: &[Vec<(f32, u32)>], fine: Option<&[PairScore]>, cfg: &Config) -> Result<Vec<QueryMatch>> {
    let total: usize = lists.iter().map(Vec::len).sum();
    let two_stages = setting.reranks();
    match (two_stages, fine) {
        (true, Some(f)) if f.len() == total => {}
        (false, None) => {}
        (true, got) => {
            return Err(Error::invalid("ranking", format!("setting {setting} needs {total} fine scores, got {}", got.map_or(0, <[PairScore]>::len))))
        }
        (false, Some(_)) => return Err(Error::invalid("ranking", format!("setting {setting} takes no fine scores for its candidates"))),
    }
    let fine = fine.unwrap_or(&[]);
    let mut at = 0;
    Ok(lists
        .iter()
        .map(|l| {
            let mine = if two_stages { &fine[at..at + l.len()] } else { &[][..] };
            at += mine.len();
            let evidence = setting.verifies().then(|| Evidence::of(mine));
            let mut ranked: Vec<Candidate> =
                l.iter().enumerate().map(|(k, &(s, r))| candidate(setting, cfg, s, r, mine.get(k), evidence.as_ref())).collect();
            // best first; ties keep the coarse order (stable sort)
            ranked.sort_by(|a, b| b.score.total_cmp(&a.score));
            QueryMatch { ranked, evidence }
        })
        .collect())
}

/// A ranked reference from the score `s` of its candidate list and, for settings with both
/// stages, its fine score `f` (for `verified` weighed against its query's candidates, `e`): what
/// [`rank`] and [`score_pairs`] give.
fn candidate(setting: Setting, cfg: &Config, s: f32, r: u32, f: Option<&PairScore>, e: Option<&Evidence>) -> Candidate {
    match (setting.is_baseline(), setting.uses_coarse(), f) {
        (true, _, _) => Candidate { reference: r, coarse: None, fine: None, inliers: None, score: s },
        (_, true, None) => Candidate { reference: r, coarse: Some(s), fine: None, inliers: None, score: s },
        (_, true, Some(p)) => {
            let f = p.fine;
            let score = match (setting.verifies(), cfg.matching.score) {
                (true, _) => {
                    let v = &cfg.verification;
                    let terms = e.map_or(0.0, |e| e.terms(p, v));
                    // tested against the null, the fine stage speaks only for a candidate whose
                    // evidence is significant: elsewhere the coarse order stands
                    let fine = match v.inliers == crate::config::InlierEvidence::Significant && terms <= 0.0 {
                        true => 0.0,
                        false => f,
                    };
                    fine + v.w_coarse as f32 * s + terms
                }
                (false, ScoreFusion::Fine) => f,
                (false, ScoreFusion::FineTimesGlobal) => f * s,
            };
            Candidate { reference: r, coarse: Some(s), fine: Some(f), inliers: p.inliers, score }
        }
        (_, false, _) => Candidate { reference: r, coarse: None, fine: Some(s), inliers: None, score: s },
    }
}

/// What `setting` scores each (query, reference) pair, as if the reference had been one of the
/// query's candidates: the coarse score its coarse stage gives the pair (or the baseline's
/// cosine), the fine score and inliers where the setting has them, and the final score [`rank`]
/// would rank it by, the evidence of `verified` weighed against `evidence[q]` (the spread of the
/// query's candidates, [`QueryMatch::evidence`]; `None`, or a query it has none for: against the
/// pairs given for that query). For pairs that were candidates, with their query's evidence, the
/// same values as [`match_with`] (sequence matching scores the neighbours of each frame's
/// candidates with it).
pub fn score_pairs(
    stages: &mut dyn Stages,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    setting: Setting,
    cfg: &Config,
    pairs: &[(u32, u32)],
    evidence: Option<&[Option<Evidence>]>,
) -> Result<Vec<Candidate>> {
    check_labels(refs, setting)?;
    if let Some(&(q, r)) = pairs.iter().find(|&&(q, r)| q as usize >= queries.len() || r as usize >= refs.len()) {
        return Err(Error::invalid("pair scores", format!("pair ({q}, {r}) outside {} queries x {} references", queries.len(), refs.len())));
    }
    if pairs.is_empty() {
        return Ok(vec![]);
    }
    let first: Vec<f32> = if setting.is_baseline() {
        if let Some(why) = baseline::unavailable(refs, queries, setting) {
            return Err(Error::invalid(format!("setting {setting}"), why));
        }
        pairs.par_iter().map(|&(q, r)| baseline::pair_cosine(refs, queries, setting, q as usize, r as usize)).collect()
    } else if setting.uses_coarse() {
        coarse_pair_scores(refs, queries, setting, cfg, pairs)
    } else {
        let params = tree_params(cfg, setting, refs.neighbour_slots())?;
        stages.fine_pairs(&params, refs, queries, pairs)?
    };
    let fine = match setting.reranks() {
        true => Some(pair_scores(stages, refs, queries, setting, cfg, pairs)?.0),
        false => None,
    };
    refs.check()?;
    // each query's evidence: given, else the spread of its pairs here
    let mut own: std::collections::HashMap<u32, Evidence> = std::collections::HashMap::new();
    if let (true, Some(f)) = (setting.verifies(), &fine) {
        let mut by_query: std::collections::BTreeMap<u32, Vec<PairScore>> = Default::default();
        for (&(q, _), p) in pairs.iter().zip(f) {
            if evidence.and_then(|e| e.get(q as usize).copied().flatten()).is_none() {
                by_query.entry(q).or_default().push(*p);
            }
        }
        own = by_query.into_iter().map(|(q, v)| (q, Evidence::of(&v))).collect();
    }
    Ok(pairs
        .iter()
        .enumerate()
        .map(|(k, &(q, r))| {
            let e = evidence.and_then(|e| e.get(q as usize).copied().flatten()).or_else(|| own.get(&q).copied());
            candidate(setting, cfg, first[k], r, fine.as_ref().map(|f| &f[k]), e.as_ref())
        })
        .collect())
}

/// The score the coarse stage of `setting` gives each pair: SSIM of the global descriptors, plus
/// the appearance cosine where the stage fuses them (as [`fused_topk`] and [`coarse_topk`]).
fn coarse_pair_scores(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config, pairs: &[(u32, u32)]) -> Vec<f32> {
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
