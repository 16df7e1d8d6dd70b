//! The null sample of `verified`'s evidence as a source carries it: what verification found
//! between references of one map that look alike but are other places (and, for the compact
//! HOGs' likelihood ratio, how alike references of one place are). [`crate::matching::null`]
//! measures it and tests evidence against it; the map store keeps the one measured at build in its
//! manifest ([`StoredNull`]), so every process, and every shard of the map, tests against the same
//! null. It lives here, below both, as the data they share.

use serde::{Deserialize, Serialize};

/// Fewer null pairs than this: no null (a map of a handful of references), so no evidence counts.
pub const MIN_NULL_PAIRS: usize = 20;

/// The null sample of one map under one measurement config (`matching::null::key`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NullEvidence {
    /// What it was measured under (`matching::null::key`).
    pub key: String,
    /// References matched against the map.
    pub sources: u32,
    /// Pairs verified (each a source and one of its candidates of another place).
    pub pairs: u32,
    /// `inliers[k]`: null pairs with exactly k inliers.
    pub inliers: Vec<u32>,
    /// The null pairs' compact-HOG cosines, ascending (empty where the map holds none).
    pub compact_hog: Vec<f32>,
    /// The compact-HOG cosines of the same sources with their neighbours one position away along
    /// their traversal (what the map shows of one place), ascending: the other side of the
    /// compact HOGs' likelihood ratio. Empty where the map holds no compact HOGs or no
    /// neighbours (then the ratio is 1 and the term silent). A null stored before this sample
    /// was measured has another key (`matching::null::key`) and is measured again.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub compact_hog_near: Vec<f32>,
}

impl NullEvidence {
    /// Whether this null, measured on `then` references of a map, still serves the map of `now`
    /// references of the same lineage: until the map has doubled or halved (a stream that commits
    /// every few frames measures it again as the map doubles, not at every commit), and a null too
    /// small to test against only at the size it was measured at.
    pub fn serves_size(&self, then: usize, now: usize) -> bool {
        let usable = self.pairs as usize >= MIN_NULL_PAIRS;
        now == then || (usable && now <= 2 * then && 2 * now >= then)
    }
}

/// The null a stored map keeps in its manifest: measured when it was built (or when an add or
/// removal took it past [`NullEvidence::serves_size`]), with the live images it had then. A
/// commit that takes the map past that size drops it (`map::manifest::write`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct StoredNull {
    /// Live images of the map when it was measured.
    pub images: usize,
    /// The sample.
    pub evidence: NullEvidence,
}
