//! What matching answers: each query's ranked candidates ([`QueryMatch`], [`Candidate`]), the
//! candidate lists the stages pass on ([`CandidateLists`]) and the time each stage took.

use super::evidence::Evidence;
use serde::Serialize;

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
    /// `verified`: how the candidates spread in each evidence term ([`score_pairs`](super::score_pairs) scores other
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

/// Per query, (score, reference) best first.
pub type CandidateLists = Vec<Vec<(f32, u32)>>;

/// The (query, reference) pairs of candidate lists, in list order.
pub fn pairs_of(lists: &[Vec<(f32, u32)>]) -> Vec<(u32, u32)> {
    lists.iter().enumerate().flat_map(|(q, l)| l.iter().map(move |&(_, r)| (q as u32, r))).collect()
}
