//! The matching settings: which stages run, and whether appearance takes part.

use crate::config::CoarseStage;
use serde::{Deserialize, Serialize};

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
    /// §6.1 (3): global descriptor selects K candidates, Forest re-ranks them
    /// (`matching.coarse`: the edge descriptor alone, or fused with the whole-image appearance).
    GlobalForest,
    /// §6.1 (4): the full method: global top-K, SemLook local re-ranking (`matching.coarse` as
    /// for setting 3).
    Semlook,
    /// Beyond the paper, coarse stage only: rank by cos(whole-image appearance) + w_global x SSIM
    /// of the global descriptors (`matching.w_global`).
    Fused,
    /// Beyond the paper, the recommended pipeline: the fused coarse top-K, re-ranked by SemLook
    /// local similarity and geometric verification (`verification`).
    Verified,
}

impl Setting {
    /// Every setting: the two baselines, the coarse stage and the paper's four, then the fused
    /// coarse stage and the recommended pipeline.
    pub const ALL: [Setting; 9] = [
        Setting::Hog,
        Setting::Appearance,
        Setting::Global,
        Setting::Forest,
        Setting::Local,
        Setting::GlobalForest,
        Setting::Semlook,
        Setting::Fused,
        Setting::Verified,
    ];
    /// The setting `query`, `eval` and the Python API use when none is named.
    pub const RECOMMENDED: Setting = Setting::Verified;
    /// The coarse stage and the paper's four settings (no baselines).
    pub const SEMLOOK: [Setting; 5] = [Setting::Global, Setting::Forest, Setting::Local, Setting::GlobalForest, Setting::Semlook];

    /// A baseline, not a SemLook setting: one whole-image vector per image, cosine similarity.
    /// `None` where the setting runs on frames without labels (encoded with void label maps,
    /// [`crate::encode::Encoder::without_labels`]); else why it cannot.
    pub fn label_free(self) -> Option<&'static str> {
        match self {
            // verified: the coarse stage's SSIM term is the same for every pair, so it ranks by
            // the appearance cosine; verification checks geometry (its semantic check is off)
            Setting::Hog | Setting::Appearance | Setting::Verified => None,
            Setting::Fused => Some("without labels its SSIM term is the same for every pair: it is the appearance baseline"),
            _ => Some("needs semantic labels: give label maps, or install the default segmenter (`semlook models`)"),
        }
    }
    pub fn is_baseline(self) -> bool {
        matches!(self, Setting::Hog | Setting::Appearance)
    }
    pub fn uses_coarse(self) -> bool {
        matches!(self, Setting::Global | Setting::GlobalForest | Setting::Semlook | Setting::Fused | Setting::Verified)
    }
    /// Whether the coarse stage fuses the global descriptor with the whole-image appearance:
    /// always for `fused` and `verified`, for the paper's two-stage settings (3 and 4) when
    /// `matching.coarse` says so, never for `global` (the edge descriptor alone).
    pub fn fuses_coarse(self, coarse: CoarseStage) -> bool {
        match self {
            Setting::Fused | Setting::Verified => true,
            Setting::GlobalForest | Setting::Semlook => coarse == CoarseStage::Fused,
            _ => false,
        }
    }
    pub fn uses_fine(self) -> bool {
        !self.is_baseline() && !matches!(self, Setting::Global | Setting::Fused)
    }
    /// The fine stage adds geometric verification.
    pub fn verifies(self) -> bool {
        self == Setting::Verified
    }
    /// Both stages: the fine stage re-ranks the coarse stage's candidates.
    pub fn reranks(self) -> bool {
        self.uses_coarse() && self.uses_fine()
    }
    pub fn uses_appearance(self) -> bool {
        matches!(self, Setting::Local | Setting::Semlook | Setting::Fused | Setting::Verified)
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
            Setting::Fused => "fused",
            Setting::Verified => "verified",
        }
    }
    pub fn describe(self) -> &'static str {
        match self {
            Setting::Hog => "baseline: VPR-Bench HOG",
            Setting::Appearance => "baseline: whole-image VLAD",
            Setting::Global => "global SSIM only",
            Setting::Forest => "Forest, whole map",
            Setting::Local => "Forest+appearance, whole map",
            Setting::GlobalForest => "coarse top-K -> Forest",
            Setting::Semlook => "coarse top-K -> Forest+appearance",
            Setting::Fused => "global+appearance top-K only",
            Setting::Verified => "fused top-K -> local + verification",
        }
    }
}

impl std::fmt::Display for Setting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}
