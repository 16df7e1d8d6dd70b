//! The fine stage and the final ranking: the terms of each candidate pair (tree similarity,
//! verification, compact HOG, what they weigh against the map's null: the inliers' tail
//! probability, the compact HOGs' likelihood ratio), the pair's score,
//! the ranking of each query's candidates, and the same scores for any given pairs.

use super::answer::{Candidate, QueryMatch};
use super::candidates::{candidates, check_labels, tree_params};
use super::coarse::coarse_pair_scores;
use super::evidence::{Evidence, PairScore};
use super::stages::Stages;
use super::{baseline, null, setting::Setting};
use crate::classes::ClassTable;
use crate::config::{Config, Matcher, ScoreFusion};
use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Result};
use crate::values::Values;
use crate::verify::{Verified, VerifyParams};
use rayon::prelude::*;

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
pub(super) fn pair_scores(
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
/// `verified`, the verification and the compact HOGs' cosine, weighed against the map's null
/// where the score tests against it (the inliers' tail probability, the compact HOGs' likelihood
/// ratio). [`PairTerms::score`] weighs them (a
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
    /// `verified` with `inliers = "significant"`, where both have compact HOGs: P(a same-place
    /// pair of the map is as alike) / P(a null pair is).
    pub compact_hog_ratio: Option<f32>,
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
                compact_hog_ratio: self.compact_hog_ratio,
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
        let hogs = compact_hog_cosines(refs, queries, pairs);
        for (i, (t, v)) in terms.iter_mut().zip(&v).enumerate() {
            t.verified = Some(*v);
            t.compact_hog = hogs.as_ref().map(|h| h[i]);
        }
        // the evidence weighed against the map's null, where the score tests against it: the
        // inliers' tail probabilities, the compact HOGs' likelihood ratios
        if w.inliers == crate::config::InlierEvidence::Significant && !pairs.is_empty() {
            let null = null::kept_or(refs, cfg, || measure_null(stages, refs, cfg))?;
            let inliers: Vec<Option<u32>> = terms.iter().map(|t| t.verified.map(|v| v.inliers)).collect();
            let hogs: Vec<Option<f32>> = terms.iter().map(|t| t.compact_hog).collect();
            let (pi, ph) = null.tail_and_ratio(&inliers, &hogs);
            for ((t, pi), ph) in terms.iter_mut().zip(pi).zip(ph) {
                (t.p_inliers, t.compact_hog_ratio) = (pi, ph);
            }
        }
    }
    refs.check()?;
    Ok(terms)
}

/// The compact HOGs' cosine of each (query, reference) pair, where both sides have compact HOGs
/// of one size (maps of small frames); `None` where they do not.
fn compact_hog_cosines(refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Option<Vec<f32>> {
    let hog = queries.compact_hog_dim > 0 && refs.compact_hog_dim() == queries.compact_hog_dim;
    hog.then(|| pairs.iter().map(|&(q, r)| Values::F32(queries.image_compact_hog(q as usize)).dot(&refs.image_compact_hog(r as usize))).collect())
}

/// Measures the null of `verified`'s evidence over `refs` under `cfg` ([`null`]'s docs): the
/// `null_sources` references matched by `verified`'s coarse stage against the map, their
/// candidates of other places verified; where the map holds compact HOGs, their cosines and the
/// sources' cosines with their neighbours along their traversal (the same-place sample).
pub fn measure_null(stages: &mut dyn Stages, refs: &dyn RefSource, cfg: &Config) -> Result<null::NullEvidence> {
    let v = &cfg.verification;
    let src = null::sources(refs.len(), v.null_sources as usize);
    if src.is_empty() || refs.keypoint_dim() == 0 {
        return Ok(null::NullEvidence::from_pairs(null::key(cfg), src.len(), std::iter::empty(), vec![], vec![]));
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
    // the compact HOGs' cosines of the null pairs and of the sources' same-place pairs
    let cosines = |pairs: &[(u32, u32)]| compact_hog_cosines(refs, &queries, pairs).unwrap_or_default();
    let (compact_hog, compact_hog_near) = (cosines(&pairs), cosines(&null::near_pairs(refs, &src)));
    refs.check()?;
    Ok(null::NullEvidence::from_pairs(null::key(cfg), src.len(), verified.iter().map(|r| r.inliers), compact_hog, compact_hog_near))
}

/// The final ranking from candidate lists and, for settings with both stages, the fine score of
/// every candidate in list order (as [`pairs_of`](super::pairs_of) lists them): the score is the fine one (or fine
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
/// same values as [`match_with`](super::match_with) (sequence matching scores the neighbours of each frame's
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
