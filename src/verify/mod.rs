//! Stage 4c (beyond the paper): geometric verification of the coarse stage's candidates, as
//! Patch-NetVLAD (Hausler et al., CVPR 2021) and hloc (Sarlin et al., CVPR 2019) re-rank theirs.
//! Each image stores its best learned keypoints (`descriptors::keypoints`); for a (query, reference) pair
//! the keypoints are matched by mutual nearest neighbours above a cosine ([`semlook_kernels::mnn_match`]) or by
//! the learned matcher LighterGlue ([`lighterglue`], `verification.matcher`), and the
//! matches that one homography explains are counted by RANSAC ([`ransac`]). Optionally only inliers
//! whose semantic classes agree at both ends count: the labels decide which geometric evidence
//! is trusted.

pub mod best_columns;
pub mod homography;
pub mod pose;
pub mod ransac;

use crate::classes::{ClassTable, VOID};
use crate::config::{Matcher, SemanticCheck, VerificationConfig};
use crate::descriptors::keypoints::{KeypointsRef, DESCRIPTOR_SCALE};
use crate::error::Result;
use crate::networks::lighterglue::{self, GlueParams, LighterGlue};
use best_columns::BestColumns;
use ransac::RansacParams;
use std::sync::{Arc, Mutex};

/// The verification parameters of a config, in the units the stages use.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VerifyParams {
    /// Smallest integer dot product of a match (the cosine x DESCRIPTOR_SCALE^2).
    pub min_dot: i32,
    /// Parameters of the homography RANSAC.
    pub ransac: RansacParams,
    /// Which RANSAC inliers count towards the verified score.
    pub semantic: SemanticCheck,
    /// Per class index: whether its keypoints are left out of matching (`ignore_classes`).
    pub ignored: [bool; 256],
    /// Which matcher pairs keypoints up.
    pub matcher: Matcher,
    /// The learned matcher's parameters (`matcher = lighterglue`, or `w_glue` > 0).
    pub glue: GlueParams,
}

impl VerifyParams {
    /// The parameters of `cfg`.
    pub fn new(cfg: &VerificationConfig) -> Self {
        VerifyParams {
            min_dot: (cfg.min_cosine as f32 * DESCRIPTOR_SCALE * DESCRIPTOR_SCALE).ceil() as i32,
            ransac: RansacParams {
                threshold: cfg.threshold,
                max_iterations: cfg.max_iterations,
                confidence: cfg.confidence,
                seed: cfg.seed,
                refine: cfg.refine,
            },
            semantic: cfg.semantic,
            ignored: [false; 256],
            matcher: cfg.matcher,
            glue: GlueParams {
                filter_threshold: cfg.glue_threshold as f32,
                width_confidence: cfg.glue_width_confidence as f32,
                depth_confidence: cfg.glue_depth_confidence as f32,
            },
        }
    }
    /// The parameters of `cfg`'s verification with its `ignore_classes` resolved in `classes`;
    /// a name the table does not have is an error naming it.
    pub fn for_config(cfg: &VerificationConfig, classes: &ClassTable) -> Result<Self> {
        Ok(VerifyParams { ignored: classes.mask("verification.ignore_classes", &cfg.ignore_classes)?, ..VerifyParams::new(cfg) })
    }
}

/// What verification found for one pair.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, serde::Serialize)]
pub struct Verified {
    /// Mutual nearest-neighbour matches.
    pub matches: u32,
    /// Matches the best homography explains (those whose classes agree, with the semantic check).
    pub inliers: u32,
    /// With `w_glue` > 0 (and the MNN matcher): the inliers of LighterGlue's matches.
    pub glue_inliers: u32,
}

/// Verifies one pair from the best columns of its keypoints (the MNN kernel's, or the fast
/// path's output): mutual matches, then RANSAC. A side without keypoints scores 0.
pub fn verify_from_best(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef, best: &BestColumns) -> Verified {
    verify_matches(p, q, r, best_columns::mutual(best, p.min_dot))
}

/// The matches verification counts for one pair (query keypoint, reference keypoint): `p`'s
/// matcher's (mutual nearest neighbours above the cosine, or LighterGlue's), those on ignored
/// classes dropped; what [`pose::pair_pose`] estimates a relative pose from. A side without
/// keypoints has none.
pub fn pair_matches(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef) -> Result<Vec<(u32, u32)>> {
    if q.is_empty() || r.is_empty() || q.dim != r.dim {
        return Ok(vec![]);
    }
    let m = match p.matcher {
        Matcher::Mnn => best_columns::mutual(&best_columns::best_columns(q.descriptors, r.descriptors, q.dim, &mut Vec::new()), p.min_dot),
        Matcher::Lighterglue => shared_lighterglue()?.match_keypoints(&p.glue, q, r).into_iter().map(|(i, j, _)| (i, j)).collect(),
    };
    Ok(drop_ignored(p, q, r, m))
}

/// `m` without the matches on ignored classes.
fn drop_ignored(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef, mut m: Vec<(u32, u32)>) -> Vec<(u32, u32)> {
    if p.ignored.contains(&true) {
        let on_ignored = |classes: &[u8], i: u32| classes.get(i as usize).is_some_and(|&c| p.ignored[c as usize]);
        m.retain(|&(i, j)| !on_ignored(q.classes, i) && !on_ignored(r.classes, j));
    }
    m
}

/// Verifies one pair from its matches (query keypoint, reference keypoint): those on ignored
/// classes dropped, then RANSAC.
fn verify_matches(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef, m: Vec<(u32, u32)>) -> Verified {
    let m = drop_ignored(p, q, r, m);
    let mut out = Verified { matches: m.len() as u32, ..Verified::default() };
    if m.len() < 4 {
        return out;
    }
    let src: Vec<[f64; 2]> = m.iter().map(|&(i, _)| q.position(i as usize)).collect();
    let dst: Vec<[f64; 2]> = m.iter().map(|&(_, j)| r.position(j as usize)).collect();
    if let Some((_, inliers)) = ransac::ransac_homography(&src, &dst, &p.ransac) {
        out.inliers =
            m.iter().zip(&inliers).filter(|&(&(i, j), &inl)| inl && classes_agree(p.semantic, q.classes[i as usize], r.classes[j as usize])).count()
                as u32;
    }
    out
}

/// Whether an inlier between classes `a` and `b` counts under `check`.
#[inline]
pub fn classes_agree(check: SemanticCheck, a: u8, b: u8) -> bool {
    match check {
        SemanticCheck::Off => true,
        SemanticCheck::SameClass => a == b && a != VOID,
    }
}

/// Verifies one pair from the learned matcher's matches (the CPU's, or the device's:
/// `networks::lighterglue` (its device executor)): those on ignored classes dropped, then RANSAC.
pub fn verify_from_glue(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef, matches: &[lighterglue::GlueMatch]) -> Verified {
    verify_matches(p, q, r, matches.iter().map(|&(i, j, _)| (i, j)).collect())
}

/// The learned matcher, loaded once per process from `xfeat-lighterglue.pt` in the model folders
/// ([`crate::nn::onnx::model_dirs`], `$SEMLOOK_MODELS` first); a missing or unreadable file is an
/// error naming it (and is looked for again on the next call).
pub fn shared_lighterglue() -> Result<Arc<LighterGlue>> {
    static NET: Mutex<Option<Arc<LighterGlue>>> = Mutex::new(None);
    let mut slot = NET.lock().unwrap_or_else(|e| e.into_inner());
    if let Some(net) = slot.as_ref() {
        return Ok(net.clone());
    }
    let path = crate::nn::onnx::find_model(lighterglue::LIGHTERGLUE_WEIGHTS, None, "LighterGlue weights (verification.matcher = \"lighterglue\")")?;
    let net = Arc::new(LighterGlue::load(&path)?);
    *slot = Some(net.clone());
    Ok(net)
}

/// Verifies the (query, reference) pairs on the CPU with `p`'s matcher: the fast MNN path, or
/// LighterGlue, in parallel over pairs.
pub fn verify_pairs_cpu<'a>(
    p: &VerifyParams,
    q: &(dyn Fn(u32) -> KeypointsRef<'a> + Sync),
    r: &(dyn Fn(u32) -> KeypointsRef<'a> + Sync),
    pairs: &[(u32, u32)],
) -> Result<Vec<Verified>> {
    use rayon::prelude::*;
    Ok(match p.matcher {
        Matcher::Mnn => pairs.par_iter().map_init(Vec::new, |scratch, &(a, b)| verify_pair(p, q(a), r(b), scratch)).collect(),
        Matcher::Lighterglue => verify_pairs_glue(p, &*shared_lighterglue()?, q, r, pairs),
    })
}

/// Queries whose LighterGlue sides are held at once by [`verify_pairs_glue`] (about 0.3 MB each
/// at 384 keypoints; their pairs are shared among the threads).
const GLUE_QUERY_BLOCK: usize = 8;

/// Verifies the pairs with the learned matcher `net`, in parallel over pairs: what the network
/// computes from one image alone ([`LighterGlue::prepare`]) once per query for all its pairs, a
/// block of queries at a time (memory bounded by the block, not by the pairs), and once per pair
/// for the reference. The same matches as each pair through [`LighterGlue::match_keypoints`].
fn verify_pairs_glue<'a>(
    p: &VerifyParams,
    net: &LighterGlue,
    q: &(dyn Fn(u32) -> KeypointsRef<'a> + Sync),
    r: &(dyn Fn(u32) -> KeypointsRef<'a> + Sync),
    pairs: &[(u32, u32)],
) -> Vec<Verified> {
    use rayon::prelude::*;
    let mut order: Vec<usize> = (0..pairs.len()).collect();
    order.sort_by_key(|&i| pairs[i].0); // stable: a query's pairs keep their order
    let mut out = vec![Verified::default(); pairs.len()];
    let mut rest = &order[..];
    while !rest.is_empty() {
        // the next GLUE_QUERY_BLOCK queries' pairs
        let (mut end, mut seen) = (0, 0);
        while end < rest.len() && (seen < GLUE_QUERY_BLOCK || pairs[rest[end]].0 == pairs[rest[end - 1]].0) {
            if end == 0 || pairs[rest[end]].0 != pairs[rest[end - 1]].0 {
                seen += 1;
            }
            end += 1;
        }
        let (block, tail) = rest.split_at(end);
        let mut queries: Vec<u32> = block.iter().map(|&i| pairs[i].0).collect();
        queries.dedup();
        let sides: Vec<_> = queries.par_iter().map(|&a| net.prepare(q(a))).collect();
        let found: Vec<(usize, Verified)> = block
            .par_iter()
            .map(|&i| {
                let (a, b) = pairs[i];
                let side = &sides[queries.binary_search(&a).expect("the block's query")];
                let matches = match (side, net.prepare(r(b))) {
                    (Some(sa), Some(sb)) => net.match_prepared(&p.glue, sa, &sb),
                    _ => Vec::new(),
                };
                (i, verify_from_glue(p, q(a), r(b), &matches))
            })
            .collect();
        found.into_iter().for_each(|(i, v)| out[i] = v);
        rest = tail;
    }
    out
}

/// Verifies one pair on the CPU (fast MNN path).
pub fn verify_pair(p: &VerifyParams, q: KeypointsRef, r: KeypointsRef, scratch: &mut Vec<f32>) -> Verified {
    if q.is_empty() || r.is_empty() || q.dim != r.dim {
        return Verified::default();
    }
    let best = best_columns::best_columns(q.descriptors, r.descriptors, q.dim, scratch);
    verify_from_best(p, q, r, &best)
}
