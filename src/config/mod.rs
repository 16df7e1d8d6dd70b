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
        let i = &self.input;
        v.int("input.compact_hog_long_side", i.compact_hog_long_side, 0, 8192)?;
        if i.working_long_side != 0 {
            v.int("input.working_long_side", i.working_long_side, 32, 8192)?;
        }
        v.real("objects.min_area_fraction", self.objects.min_area_fraction, 0.0, 0.5)?;
        v.int("objects.max_objects", self.objects.max_objects, 1, 256)?;
        let g = &self.global;
        v.real("global.truncation", g.truncation, 1e-3, 1.0)?;
        v.int("global.ssim_window", g.ssim_window, 3, 1023)?;
        if g.ssim_window.is_multiple_of(2) {
            return Err(v.err(format!("global.ssim_window = {} must be odd", g.ssim_window)));
        }
        v.int("global.width", g.width, g.ssim_window, 1024)?;
        v.int("global.height", g.height, g.ssim_window, 1024)?;
        v.real("global.ssim_k1", g.ssim_k1, 1e-6, 1.0)?;
        v.real("global.ssim_k2", g.ssim_k2, 1e-6, 1.0)?;
        v.int("local.neighbours", self.local.neighbours, 0, 8)?;
        v.real("local.tie_tolerance", self.local.tie_tolerance, 0.0, 1.0)?;
        let a = &self.appearance;
        v.int("appearance.nms_radius", a.nms_radius, 0, 64)?;
        v.real("appearance.score_threshold", a.score_threshold, 0.0, 1.0)?;
        v.int("appearance.max_keypoints", a.max_keypoints, 1, 1 << 20)?;
        v.int("appearance.border", a.border, 0, 4096)?;
        v.int("appearance.vlad_centres", a.vlad_centres, 1, 64)?;
        v.int("appearance.min_descriptors", a.min_descriptors, 0, 1_000_000)?;
        v.int("appearance.codebook_images", a.codebook_images, 1, 100_000)?;
        v.int("appearance.codebook_samples_per_image", a.codebook_samples_per_image, 1, 100_000)?;
        v.int("appearance.codebook_iterations", a.codebook_iterations, 0, 10_000)?;
        if a.codebook_seed > i64::MAX as u64 {
            return Err(v.err(format!("appearance.codebook_seed = {} must be at most {}", a.codebook_seed, i64::MAX)));
        }
        let sg = &self.segmentation;
        v.int("segmentation.input_width", sg.input_width, 32, 4096)?;
        v.int("segmentation.input_height", sg.input_height, 32, 4096)?;
        v.real("segmentation.scale", sg.scale, 1e-6, 1e6)?;
        for (c, (&m, &d)) in sg.mean.iter().zip(&sg.std).enumerate() {
            v.real(&format!("segmentation.mean[{c}]"), m, -1e6, 1e6)?;
            v.real(&format!("segmentation.std[{c}]"), d.abs(), 1e-6, 1e6)?;
        }
        v.real("segmentation.brighten_dark", sg.brighten_dark, 0.0, 0.95)?;
        // its names are checked against the class table when a segmenter is loaded
        v.int("segmentation.class_map (entries)", sg.class_map.len(), 1, 4096)?;
        let s = &self.similarity;
        for (name, w) in [
            ("similarity.w_area", s.w_area),
            ("similarity.w_position", s.w_position),
            ("similarity.w_appearance", s.w_appearance),
            ("similarity.w_intrinsic", s.w_intrinsic),
            ("similarity.w_neighbours", s.w_neighbours),
        ] {
            v.real(name, w, 0.0, 1e3)?;
        }
        if s.w_area + s.w_position + s.w_appearance <= 0.0 || s.w_intrinsic + s.w_neighbours <= 0.0 {
            return Err(v.err("similarity weights must not all be zero (w_area + w_position + w_appearance, w_intrinsic + w_neighbours)".into()));
        }
        v.real("similarity.position_sigma", s.position_sigma, 1e-4, 10.0)?;
        v.real("similarity.neutral_appearance", s.neutral_appearance, 0.0, 1.0)?;
        v.int("matching.top_k", self.matching.top_k, 1, 1024)?;
        v.real("matching.w_global", self.matching.w_global, 0.0, 1e3)?;
        v.real("matching.w_embedding", self.matching.w_embedding, 0.0, 1e3)?;
        v.int("embedding.long_side", self.embedding.long_side as usize, 32, 4096)?;
        let k = &self.keypoints;
        v.int("keypoints.stored", k.stored, 0, 8192)?;
        v.int("keypoints.nms_radius", k.nms_radius, 0, 64)?;
        v.real("keypoints.score_threshold", k.score_threshold, 0.0, 1.0)?;
        v.int("keypoints.border", k.border, 0, 4096)?;
        let vf = &self.verification;
        v.real("verification.min_cosine", vf.min_cosine, -1.0, 1.0)?;
        v.real("verification.threshold", vf.threshold, 1e-6, 1.0)?;
        v.int("verification.max_iterations", vf.max_iterations as usize, 1, 1_000_000)?;
        v.real("verification.confidence", vf.confidence, 0.0, 1.0 - 1e-12)?;
        if vf.seed > i64::MAX as u64 {
            return Err(v.err(format!("verification.seed = {} must be at most {}", vf.seed, i64::MAX)));
        }
        v.real("verification.glue_threshold", vf.glue_threshold, 0.0, 1.0)?;
        if vf.matcher == Matcher::Lighterglue && vf.w_glue > 0.0 {
            return Err(v.err(
                "verification.w_glue adds LighterGlue beside the MNN matcher; with matcher = \"lighterglue\" it would do nothing (set w_inliers)"
                    .into(),
            ));
        }
        if (vf.matcher == Matcher::Lighterglue || vf.w_glue > 0.0) && self.appearance.model != AppearanceModelKind::Xfeat {
            // LighterGlue was trained on XFeat's descriptors: another network's keypoints would be matched as if they were
            return Err(v.err(format!(
                "verification.matcher = \"lighterglue\" (or w_glue > 0) matches XFeat keypoints; appearance.model is {:?}",
                self.appearance.model
            )));
        }
        if vf.glue_min_inliers > 0 && vf.w_glue == 0.0 {
            return Err(v.err(
                "verification.glue_min_inliers chooses the pairs LighterGlue verifies beside MNN; without w_glue > 0 it would do nothing".into(),
            ));
        }
        v.int("verification.glue_min_inliers", vf.glue_min_inliers as usize, 0, 100_000)?;
        v.int("verification.min_inliers", vf.min_inliers as usize, 0, 100_000)?;
        v.real("verification.unusual_above", vf.unusual_above, -10.0, 10.0)?;
        v.real("verification.compact_hog_above", vf.compact_hog_above, -10.0, 10.0)?;
        v.real("verification.null_alarms", vf.null_alarms, 1e-12, 1e6)?;
        v.real("verification.max_bonus", vf.max_bonus, 0.0, 1e6)?;
        v.int("verification.null_gap", vf.null_gap as usize, 0, 1_000_000)?;
        v.int("verification.null_sources", vf.null_sources as usize, 1, 1_000_000)?;
        v.real("verification.glue_width_confidence", vf.glue_width_confidence, -1.0, 1.0)?;
        v.real("verification.glue_depth_confidence", vf.glue_depth_confidence, -1.0, 1.0)?;
        for (name, w) in [
            ("verification.w_inliers", vf.w_inliers),
            ("verification.w_coarse", vf.w_coarse),
            ("verification.w_fine", vf.w_fine),
            ("verification.w_glue", vf.w_glue),
            ("verification.w_compact_hog", vf.w_compact_hog),
        ] {
            v.real(name, w, 0.0, 1e3)?;
        }
        v.int("matching.tile", self.matching.tile, 1, 65536)?;
        let sq = &self.sequence;
        v.int("sequence.length", sq.length, 1, 256)?;
        v.real("sequence.velocity_min", sq.velocity_min, -16.0, 16.0)?;
        v.real("sequence.velocity_max", sq.velocity_max, sq.velocity_min, 16.0)?;
        if let Some(k) = sq.velocity_scale {
            v.real("sequence.velocity_scale", k, 1.0 / 64.0, 64.0)?;
        }
        v.int("sequence.velocity_steps", sq.velocity_steps, 1, 64)?;
        v.int("sequence.widen", sq.widen, 0, 16)?;
        v.int("sequence.contrast_window", sq.contrast_window, 1, 1000)?;
        v.int("sequence.refine", sq.refine, 0, 1000)?;
        v.int("sequence.uniqueness_window", sq.uniqueness_window, 0, 100_000)?;
        v.real("sequence.min_uniqueness", sq.min_uniqueness, 0.0, 1e6)?;
        v.int("sequence.min_frames", sq.min_frames, 1, sq.length)?;
        v.real("sequence.velocity_change", sq.velocity_change, 0.0, 1e9)?;
        v.real("sequence.refine_share", sq.refine_share, 0.0, 1.0)?;
        v.real("sequence.stop_velocity", sq.stop_velocity, 0.0, 16.0)?;
        v.real("sequence.stillness", sq.stillness, 0.0, 2.0)?;
        v.real("sequence.support", sq.support, 0.0, 1.0)?;
        let ix = &self.index;
        v.int("index.min_places", ix.min_places, 0, usize::MAX)?;
        v.int("index.probe", ix.probe, 1, 65536)?;
        v.int("index.shortlist", ix.shortlist, 0, 1 << 20)?;
        v.int("index.pool", ix.pool, 0, 1 << 22)?;
        v.int("index.thumbnail", ix.thumbnail, 0, 64)?;
        v.int("index.dims", ix.dims, 1, 4096)?;
        v.int("index.lists", ix.lists, 0, 65536)?;
        v.int("index.sample", ix.sample, 1, 1 << 24)?;
        v.int("index.iterations", ix.iterations, 1, 100)?;
        let st = &self.stream;
        v.int("stream.exclude_frames", st.exclude_frames, 1, 1 << 24)?;
        v.real("stream.exclude_seconds", st.exclude_seconds, 0.0, 1e7)?;
        v.int("stream.commit_frames", st.commit_frames, 1, st.exclude_frames)?;
        v.int("stream.track_radius", st.track_radius, 0, 1 << 20)?;
        v.int("stream.lost_after", st.lost_after, 1, 1 << 20)?;
        v.real("stream.closure_uniqueness", st.closure_uniqueness, 1.0, 1e6)?;
        v.real("stream.closure_min_velocity", st.closure_min_velocity, 0.0, 16.0)?;
        v.real("stream.closure_min_score", st.closure_min_score, 0.0, 1e6)?;
        v.int("eval.recall_at (entries)", self.eval.recall_at.len(), 0, 16)?;
        for (k, &n) in self.eval.recall_at.iter().enumerate() {
            v.int(&format!("eval.recall_at[{k}]"), n, 1, 1000)?;
        }
        Ok(())
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
