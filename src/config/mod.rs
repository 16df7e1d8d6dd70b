//! Every tunable of the engine, with the defaults of the design reference (`docs/design/method.md` §3).
//! Choices the paper does not state (\[R\] in method.md) are all here, so that a user can change them
//! in a TOML file. `semlook config` prints this struct's defaults.
//!
//! Sections split in two groups: the *encoding* sections ([`EncodingConfig`]: `input`, `classes`,
//! `objects`, `global`, `local`, `appearance`, `keypoints`, `segmentation`) change what is stored
//! in a map, so a map records them and refuses queries encoded differently; the *matching*
//! sections (`similarity`, `matching`, `verification`, `eval`) may change at query time.

mod encoding;
mod index;
mod matching;
mod networks;
mod stream;

pub use encoding::*;
pub use index::*;
pub use matching::*;
pub use networks::*;
pub use stream::*;

use crate::error::{Error, Result};
use serde::{Deserialize, Serialize};
use std::path::Path;

/// Defines [`Config`] and [`EncodingConfig`] from one list of sections, with the two functions that
/// move the encoding sections between them: a new encoding section is added once, here.
macro_rules! config_sections {
    (encoding { $($e:ident: $et:ty,)* } other { $($o:ident: $ot:ty,)* }) => {
        /// Every section: the encoding ones ([`EncodingConfig`]), then those that may change at
        /// query time.
        #[derive(Debug, Clone, PartialEq, Serialize, Deserialize, Default)]
        #[serde(default, deny_unknown_fields)]
        pub struct Config {
            $(#[allow(missing_docs)] pub $e: $et,)*
            $(#[allow(missing_docs)] pub $o: $ot,)*
        }

        /// The sections that determine stored descriptors; a map and its queries must agree on them.
        #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
        pub struct EncodingConfig {
            $(#[allow(missing_docs)] pub $e: $et,)*
        }

        impl Config {
            /// The encoding sections, as a map records them.
            pub fn encoding(&self) -> EncodingConfig {
                EncodingConfig { $($e: self.$e.clone(),)* }
            }

            /// Replaces the encoding sections with those a map was built with.
            pub fn with_encoding(mut self, enc: &EncodingConfig) -> Config {
                $(self.$e = enc.$e.clone();)*
                self
            }
        }
    };
}

config_sections! {
    encoding {
        input: InputConfig,
        classes: ClassesConfig,
        objects: ObjectsConfig,
        global: GlobalConfig,
        local: LocalConfig,
        appearance: AppearanceConfig,
        keypoints: KeypointsConfig,
        segmentation: SegmentationConfig,
    }
    other {
        models: ModelPaths,
        similarity: SimilarityConfig,
        matching: MatchingConfig,
        verification: VerificationConfig,
        sequence: SequenceConfig,
        stream: StreamConfig,
        index: IndexConfig,
        eval: EvalConfig,
        embedding: EmbeddingConfig,
    }
}

/// The sections of a config that say how a map is searched, not what it stores: a map built with
/// a profile (`map build --config configs/stream-realtime.toml`) keeps those that differ from the
/// defaults ([`crate::map::Manifest::profile`]), and its queries and streams take them as their
/// defaults (a `--config` replaces them all).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct QueryProfile {
    #[allow(missing_docs)]
    pub similarity: SimilarityConfig,
    #[allow(missing_docs)]
    pub matching: MatchingConfig,
    #[allow(missing_docs)]
    pub verification: VerificationConfig,
    #[allow(missing_docs)]
    pub sequence: SequenceConfig,
    #[allow(missing_docs)]
    pub stream: StreamConfig,
    #[allow(missing_docs)]
    pub index: IndexConfig,
}

impl Config {
    /// The query sections ([`QueryProfile`]) where any differs from the defaults; `None` where
    /// none does (a map built so follows the defaults of the code that queries it).
    pub fn profile(&self) -> Option<QueryProfile> {
        let of = |c: &Config| QueryProfile {
            similarity: c.similarity.clone(),
            matching: c.matching.clone(),
            verification: c.verification.clone(),
            sequence: c.sequence.clone(),
            stream: c.stream.clone(),
            index: c.index.clone(),
        };
        let p = of(self);
        (p != of(&Config::default())).then_some(p)
    }

    /// Replaces the query sections with a map's profile.
    pub fn with_profile(mut self, p: &QueryProfile) -> Config {
        self.similarity = p.similarity.clone();
        self.matching = p.matching.clone();
        self.verification = p.verification.clone();
        self.sequence = p.sequence.clone();
        self.stream = p.stream.clone();
        self.index = p.index.clone();
        self
    }

    /// Parses and validates a TOML config; `source_name` names it in errors.
    pub fn from_toml(text: &str, source_name: &str) -> Result<Config> {
        let cfg: Config = toml::from_str(text).map_err(|e| Error::InvalidConfig { source_name: source_name.into(), reason: e.to_string() })?;
        cfg.validate(source_name)?;
        Ok(cfg)
    }

    /// Reads, parses and validates the TOML config at `path`.
    pub fn load(path: &Path) -> Result<Config> {
        let text = std::fs::read_to_string(path).map_err(|e| Error::io(path, e))?;
        Config::from_toml(&text, &path.display().to_string())
    }

    /// The configuration as TOML; fails only for values TOML cannot hold (an integer above
    /// i64::MAX set in code), which [`Config::validate`] refuses.
    pub fn to_toml(&self) -> Result<String> {
        toml::to_string_pretty(self).map_err(|e| Error::InvalidConfig { source_name: "(in memory)".into(), reason: e.to_string() })
    }

    /// SHA-256 of the configuration's TOML: names exactly what ran in reports.
    pub fn sha256(&self) -> Result<String> {
        Ok(crate::util::sha256_hex(self.to_toml()?.as_bytes()))
    }

    /// The defaults for CamVid's 11 classes: label files hold CamVid ids (11 = void), and a
    /// Cityscapes segmenter's channels map to CamVid classes (`classes::CITYSCAPES_TO_CAMVID`).
    pub fn camvid() -> Config {
        let classes = ClassesConfig {
            table: TableSpec::Builtin("camvid".into()),
            label_ids: LabelIds::Named("camvid".into()),
            void_ids: vec![],
            exclude: vec![],
        };
        let mut c = Config { classes, ..Config::default() };
        c.segmentation.class_map = crate::classes::CITYSCAPES_TO_CAMVID.iter().map(|s| s.to_string()).collect();
        c
    }

    /// The defaults without appearance (label maps alone suffice to encode).
    pub fn without_appearance() -> Config {
        Config { appearance: AppearanceConfig { model: AppearanceModelKind::None, ..Default::default() }, ..Default::default() }
    }

    /// Checks that every value is in its range (numbers finite) and that the class table
    /// resolves; the error names the field.
    pub fn validate(&self, source_name: &str) -> Result<()> {
        let v = Check(source_name);
        let table = crate::classes::ClassTable::from_config(&self.classes).map_err(|e| match e {
            Error::InvalidConfig { reason, .. } => v.err(format!("[classes] {reason}")),
            other => other,
        })?;
        for (key, names) in
            [("appearance.ignore_classes", &self.appearance.ignore_classes), ("verification.ignore_classes", &self.verification.ignore_classes)]
        {
            table.mask(key, names).map_err(|e| match e {
                Error::InvalidConfig { reason, .. } => v.err(reason),
                other => other,
            })?;
        }
        self.input.validate(&v)?;
        self.objects.validate(&v)?;
        self.global.validate(&v)?;
        self.local.validate(&v)?;
        self.appearance.validate(&v)?;
        self.segmentation.validate(&v)?;
        self.similarity.validate(&v)?;
        self.matching.validate(&v)?;
        self.embedding.validate(&v)?;
        self.keypoints.validate(&v)?;
        self.verification.validate(&v, self.appearance.model)?;
        self.sequence.validate(&v)?;
        self.index.validate(&v)?;
        self.stream.validate(&v)?;
        self.eval.validate(&v)
    }
}

/// Range checks whose errors name the config source and the field.
struct Check<'a>(&'a str);

impl Check<'_> {
    fn err(&self, reason: String) -> Error {
        Error::InvalidConfig { source_name: self.0.into(), reason }
    }
    fn real(&self, name: &str, v: f64, lo: f64, hi: f64) -> Result<()> {
        if v.is_finite() && (lo..=hi).contains(&v) {
            return Ok(());
        }
        Err(self.err(format!("{name} = {v} must be a finite number in [{lo}, {hi}]")))
    }
    fn int(&self, name: &str, v: usize, lo: usize, hi: usize) -> Result<()> {
        if (lo..=hi).contains(&v) {
            return Ok(());
        }
        Err(self.err(format!("{name} = {v} must be in {lo}..={hi}")))
    }
}

/// Names the first field where two encodings differ, with both values, or `None` if equal.
pub fn first_difference(a: &EncodingConfig, b: &EncodingConfig) -> Option<(String, String, String)> {
    fn walk(path: String, a: &serde_json::Value, b: &serde_json::Value) -> Option<(String, String, String)> {
        use serde_json::Value::Object;
        match (a, b) {
            (Object(ma), Object(mb)) => {
                for (k, va) in ma {
                    let vb = mb.get(k).unwrap_or(&serde_json::Value::Null);
                    let p = if path.is_empty() { k.clone() } else { format!("{path}.{k}") };
                    if let Some(d) = walk(p, va, vb) {
                        return Some(d);
                    }
                }
                None
            }
            _ if a == b => None,
            _ => Some((path, a.to_string(), b.to_string())),
        }
    }
    // JSON holds every value of these structs; should it ever fail, the configs count as different
    match (serde_json::to_value(a), serde_json::to_value(b)) {
        (Ok(va), Ok(vb)) => walk(String::new(), &va, &vb),
        _ => (a != b).then(|| ("(encoding)".into(), format!("{a:?}"), format!("{b:?}"))),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn defaults_round_trip_through_toml() {
        let cfg = Config::default();
        let back = Config::from_toml(&cfg.to_toml().unwrap(), "test").unwrap();
        assert_eq!(cfg, back);
    }

    #[test]
    fn partial_file_keeps_other_defaults() {
        let cfg = Config::from_toml("[matching]\ntop_k = 20\n[classes]\nexclude = [\"car\"]\n", "t").unwrap();
        assert_eq!(cfg.matching.top_k, 20);
        assert_eq!(cfg.global, GlobalConfig::default());
    }

    #[test]
    fn rejects_bad_values_naming_the_field() {
        for (text, field) in [
            ("[global]\ntruncation = nan\n", "global.truncation"),
            ("[global]\nssim_window = 4\n", "ssim_window"),
            ("[matching]\ntop_k = 0\n", "top_k"),
            ("[verification]\nmatcher = \"lighterglue\"\n[appearance]\nmodel = \"onnx\"\n", "matches XFeat keypoints"),
            ("[verification]\nw_glue = 0.5\n[appearance]\nmodel = \"none\"\n", "matches XFeat keypoints"),
            ("[verification]\nmatcher = \"lighterglue\"\nw_glue = 0.5\n", "w_glue adds LighterGlue beside"),
            ("[verification]\nglue_min_inliers = 5\n", "without w_glue > 0"),
            ("[objects]\nmin_area = 1\n", "min_area"),
            ("[classes]\nexclude = [\"dragon\"]\n", "dragon"),
            ("[eval]\nrecall_at = [1, 100000]\n", "eval.recall_at[1]"),
            ("[matching]\ntile = 100000000\n", "matching.tile"),
            ("[appearance]\nnms_radius = 1000000\n", "appearance.nms_radius"),
            ("[appearance]\ncodebook_seed = 9223372036854775807\ncodebook_iterations = 99999\n", "appearance.codebook_iterations"),
            ("[segmentation]\ninput_width = 100000\n", "segmentation.input_width"),
            ("[segmentation]\nstd = [1.0, 0.0, 1.0]\n", "segmentation.std[1]"),
        ] {
            let err = Config::from_toml(text, "x.toml").unwrap_err().to_string();
            assert!(err.contains(field) && err.contains("x.toml"), "{err}");
        }
    }

    #[test]
    fn difference_names_the_field() {
        let a = Config::default().encoding();
        let mut b = a.clone();
        b.global.width = 32;
        let (field, va, vb) = first_difference(&a, &b).unwrap();
        assert_eq!((field.as_str(), va.as_str(), vb.as_str()), ("global.width", "64", "32"));
        assert!(first_difference(&a, &a).is_none());
    }
}
