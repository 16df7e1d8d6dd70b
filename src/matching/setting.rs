//! The matching settings: which stages run, and whether appearance takes part.

use crate::config::CoarseStage;
use serde::{Deserialize, Serialize};

/// A matching setting: which stages run and whether appearance takes part.
///
/// Its names are [`Setting::name`]'s: serde writes and reads them (JSON, TOML, the map's files),
/// and the command line's ([`crate::Choice`]) are the same. Every predicate below
/// matches every variant, so a new one is decided for each, not counted false by default.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Setting {
    /// Baseline: VPR-Bench's HOG (grey 512 x 512, cosine), the floor any VPR method must beat.
    Hog,
    /// Baseline: the VLAD of all the image's appearance descriptors with the map's codebook (cosine).
    Appearance,
    /// Coarse stage only: rank by SSIM of the global descriptors ("Edge (Coarse)").
    Global,
    /// method.md §6.1 (1): Forest descriptors only, against the whole map, no appearance.
    Forest,
    /// method.md §6.1 (2): SemLook local descriptors (Forest + appearance), against the whole map.
    Local,
    /// method.md §6.1 (3): global descriptor selects K candidates, Forest re-ranks them
    /// (`matching.coarse`: the edge descriptor alone, or fused with the whole-image appearance).
    GlobalForest,
    /// method.md §6.1 (4): the full method: global top-K, SemLook local re-ranking (`matching.coarse` as
    /// for setting 3).
    Semlook,
    /// Beyond the paper, coarse stage only: rank by cos(whole-image appearance) + w_embedding x
    /// cos(whole-image embeddings) + w_global x SSIM of the global descriptors
    /// (`matching.w_embedding`, `matching.w_global`).
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
            // the appearance cosine (and the embeddings'); verification checks geometry (its
            // semantic check is off)
            Setting::Hog | Setting::Appearance | Setting::Verified => None,
            Setting::Fused => {
                Some("without labels its SSIM term is the same for every pair: `verified` ranks by the same coarse stage and verifies it")
            }
            Setting::Global | Setting::Forest | Setting::Local | Setting::GlobalForest | Setting::Semlook => {
                Some("needs semantic labels: give label maps, or install the default segmenter (`semlook models`)")
            }
        }
    }
    /// The settings a map built without semantic labels serves, in [`Setting::ALL`]'s order:
    /// those [`Setting::label_free`] lets run, `hog` only when the map stores HOG descriptors.
    pub fn served_without_labels(hog: bool) -> impl Iterator<Item = Setting> {
        Setting::ALL.into_iter().filter(move |&s| s.label_free().is_none() && (hog || s != Setting::Hog))
    }
    /// A baseline (one whole-image vector per image, cosine), not a SemLook setting.
    pub fn is_baseline(self) -> bool {
        use Setting::*;
        match self {
            Hog | Appearance => true,
            Global | Forest | Local | GlobalForest | Semlook | Fused | Verified => false,
        }
    }
    /// The coarse stage (global SSIM, fused or not) ranks the map.
    pub fn uses_coarse(self) -> bool {
        use Setting::*;
        match self {
            Global | GlobalForest | Semlook | Fused | Verified => true,
            Hog | Appearance | Forest | Local => false,
        }
    }
    /// Whether the coarse stage fuses the global descriptor with the whole-image appearance:
    /// always for `fused` and `verified`, for the paper's two-stage settings (3 and 4) when
    /// `matching.coarse` says so, never for `global` (the edge descriptor alone).
    pub fn fuses_coarse(self, coarse: CoarseStage) -> bool {
        use Setting::*;
        match self {
            Fused | Verified => true,
            GlobalForest | Semlook => coarse == CoarseStage::Fused,
            Hog | Appearance | Global | Forest | Local => false,
        }
    }
    /// Its fused coarse stage adds the whole-image embeddings' cosine (`matching.w_embedding`):
    /// the settings beyond the paper (the paper's two-stage settings keep their coarse stage).
    pub fn embeds(self) -> bool {
        matches!(self, Setting::Fused | Setting::Verified)
    }
    /// The fine stage (forest similarity, with appearance where the setting has it) runs.
    pub fn uses_fine(self) -> bool {
        use Setting::*;
        match self {
            Forest | Local | GlobalForest | Semlook | Verified => true,
            Hog | Appearance | Global | Fused => false,
        }
    }
    /// The fine stage adds geometric verification.
    pub fn verifies(self) -> bool {
        use Setting::*;
        match self {
            Verified => true,
            Hog | Appearance | Global | Forest | Local | GlobalForest | Semlook | Fused => false,
        }
    }
    /// Both stages: the fine stage re-ranks the coarse stage's candidates.
    pub fn reranks(self) -> bool {
        self.uses_coarse() && self.uses_fine()
    }
    /// Appearance (XFeat VLAD) takes part in the ranking.
    pub fn uses_appearance(self) -> bool {
        use Setting::*;
        match self {
            Local | Semlook | Fused | Verified => true,
            Hog | Appearance | Global | Forest | GlobalForest => false,
        }
    }
    /// The setting's one name: the command line's, the JSON's, the config's and Python's.
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
    /// The setting named by [`Setting::name`], if any.
    pub fn from_name(name: &str) -> Option<Setting> {
        Setting::ALL.into_iter().find(|s| s.name() == name)
    }
    /// [`Setting::from_name`], or [`UnknownSetting`] naming the settings there are.
    pub fn parse(name: &str) -> Result<Setting, UnknownSetting> {
        Setting::from_name(name).ok_or_else(|| UnknownSetting { name: name.to_string() })
    }
    /// A short description for tables.
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

/// A name that is no [`Setting`]; displays as "\"x\" is not one of hog, appearance, ...".
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownSetting {
    /// The name given.
    pub name: String,
}

impl std::fmt::Display for UnknownSetting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{:?} is not one of {}", self.name, Setting::ALL.map(Setting::name).join(", "))
    }
}

impl std::error::Error for UnknownSetting {}

/// [`Setting::ALL`] holds each variant once, in the order of the enum.
const _: () = {
    let mut i = 0;
    while i < Setting::ALL.len() {
        assert!(Setting::ALL[i] as usize == i, "Setting::ALL is out of order or lacks a variant");
        i += 1;
    }
};

impl Serialize for Setting {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        s.serialize_str(self.name())
    }
}

impl<'de> Deserialize<'de> for Setting {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        let name = String::deserialize(d)?;
        Setting::parse(&name).map_err(|reason| serde::de::Error::custom(format!("unknown setting {reason}")))
    }
}

impl std::fmt::Display for Setting {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(self.name())
    }
}

#[cfg(test)]
mod tests {
    use super::Setting;

    /// One name per setting: the command line's, serde's and Python's are `Setting::name`,
    /// and `ALL` is the command line's list of variants.
    #[test]
    fn setting_names_are_one() {
        for s in Setting::ALL {
            assert_eq!(serde_json::to_string(&s).ok(), Some(format!("\"{}\"", s.name())));
            assert_eq!(serde_json::from_str::<Setting>(&format!("\"{}\"", s.name())).ok(), Some(s));
            assert_eq!(Setting::from_name(s.name()), Some(s));
        }
        let err = serde_json::from_str::<Setting>("\"verify\"").unwrap_err().to_string();
        assert!(err.contains("unknown setting \"verify\"") && err.contains("global-forest"), "{err}");
        assert_eq!(
            Setting::parse("verify").unwrap_err().to_string(),
            "\"verify\" is not one of hog, appearance, global, forest, local, global-forest, semlook, fused, verified"
        );
    }
}
