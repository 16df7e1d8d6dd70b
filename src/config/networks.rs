//! The sections of the networks: `[appearance]` and `[keypoints]` (XFeat; encoding sections),
//! `[segmentation]` (encoding), `[models]` (where model files are) and `[embedding]`.

use serde::{Deserialize, Serialize};

/// Which keypoint network gives appearance descriptors (`appearance.model`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AppearanceModelKind {
    /// XFeat run natively from the authors' weights (`models.xfeat_weights`).
    Xfeat,
    /// Any ONNX keypoint network with SuperPoint's output layout (`models.keypoint_onnx`).
    Onnx,
    /// No appearance: trees carry class, area, position and neighbours only.
    None,
}

/// Where appearance descriptors are taken.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Sampling {
    /// At the detected keypoints (SuperPoint-style decoding), as the paper does.
    Keypoints,
    /// At every cell of the network's descriptor map (1/8 resolution): every object gets
    /// descriptors in proportion to its area, whatever the texture (DenseVLAD, Torii et al. 2015).
    Dense,
}

/// The `[appearance]` section: the descriptors of each object and their VLAD aggregation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct AppearanceConfig {
    /// Keypoint network: "xfeat" (default), "onnx" or "none".
    pub model: AppearanceModelKind,
    /// Descriptors at "keypoints" or "dense" over the descriptor map. \[R\] dense: sweeps 01-02
    /// (`sweeps/`): on the real sets per-object VLAD of dense cells beat keypoint VLAD
    /// (gardens day/night 0.9 vs 0.7 R@1, Nordland equal); every object gets descriptors.
    pub sampling: Sampling,
    /// Non-maximum suppression radius in pixels. \[X\] SuperPoint demo: 4.
    pub nms_radius: usize,
    /// Keypoints scoring (probability x reliability) at or below this are dropped. \[R\]
    pub score_threshold: f64,
    /// At most this many keypoints per image, best first. \[R\]
    pub max_keypoints: usize,
    /// Keypoints this close to the border are dropped. \[X\] SuperPoint demo: 4.
    pub border: usize,
    /// VLAD codebook size Kv. \[R\] 64 (sweeps 02 and 04: 16 < 32 <= 64 in mean R@1 over the four
    /// development sets; 64 x 64-d XFeat = 4096 values per tree, the size of the paper's 16 x
    /// 256-d SuperPoint-VLAD).
    pub vlad_centres: usize,
    /// L2-normalise each centre's residual sum (intra-normalisation, Arandjelovic & Zisserman 2013). \[R\] on.
    pub intra_norm: bool,
    /// Signed square root of the VLAD vector before the final L2 normalisation. \[R\] off.
    pub power_norm: bool,
    /// Objects with fewer descriptors than this carry no appearance (their VLAD is noise). \[R\] 1.
    pub min_descriptors: usize,
    /// Codebook training: reference images sampled, descriptors kept per image, Lloyd
    /// iterations and seed. \[R\]
    pub codebook_images: usize,
    /// Codebook training: descriptors kept per sampled image. \[R\] 128.
    pub codebook_samples_per_image: usize,
    /// Codebook training: Lloyd iterations. \[R\] 20.
    pub codebook_iterations: usize,
    /// Codebook training: the seed of k-means++. \[R\] 1.
    pub codebook_seed: u64,
    /// Classes (names of the class table) whose descriptors are left out of the whole-image VLAD
    /// (issue 32: dynamic classes and sky say little about the place). \[R\] none (sweep 13). Not
    /// written where empty, so that the manifests (and checksums) of maps built before it stay as
    /// they were.
    #[serde(skip_serializing_if = "Vec::is_empty")]
    pub ignore_classes: Vec<String>,
}

impl Default for AppearanceConfig {
    fn default() -> Self {
        AppearanceConfig {
            model: AppearanceModelKind::Xfeat,
            sampling: Sampling::Dense,
            nms_radius: 4,
            score_threshold: 0.005,
            max_keypoints: 1024,
            border: 4,
            vlad_centres: 64,
            intra_norm: true,
            power_norm: false,
            min_descriptors: 1,
            codebook_images: 48,
            codebook_samples_per_image: 128,
            codebook_iterations: 20,
            codebook_seed: 1,
            ignore_classes: vec![],
        }
    }
}

/// The verification keypoints every image stores (beyond the paper; `verify`): the keypoint
/// network's detections (SuperPoint-style decoding of its heads), best first.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct KeypointsConfig {
    /// Keypoints stored per image; 0 stores none (no geometric verification). \[R\] 384: 69 bytes
    /// each with XFeat (26.5 kB per image). Sweep 05 (`verified`, three dev sets, K = 30): mean
    /// R@1 0.809 / 0.852 / 0.842 at 256 / 384 / 512 (an earlier run without XFeat's detector:
    /// 768 lower still); 512 would not fit a reference in 64 kB.
    pub stored: usize,
    /// Non-maximum suppression radius in pixels. \[X\] XFeat's detector: a 5x5 window (radius 2).
    pub nms_radius: usize,
    /// Keypoints scoring (probability x reliability) at or below this are dropped. \[X\] XFeat: 0.05.
    pub score_threshold: f64,
    /// Keypoints this close to the border are dropped. \[X\] XFeat: none.
    pub border: usize,
}

impl Default for KeypointsConfig {
    fn default() -> Self {
        KeypointsConfig { stored: 384, nms_radius: 2, score_threshold: 0.05, border: 0 }
    }
}

/// How a segmentation network's input is prepared and its output read (used when a frame has
/// no label map and `models.segmenter_onnx` is set). Defaults fit ESPNet's Cityscapes export.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SegmentationConfig {
    /// Network input size (the image is resized to it); multiples of 32 for most networks.
    pub input_width: usize,
    /// Network input height (with `input_width`). 512, ESPNet's training size.
    pub input_height: usize,
    /// input = (pixel * scale - mean) / std per channel, pixel in 0..255.
    pub scale: f64,
    /// Per-channel mean subtracted after scaling (see `scale`). 0.
    pub mean: [f64; 3],
    /// Per-channel divisor applied after the mean (see `scale`). 1.
    pub std: [f64; 3],
    /// Channel order fed to the network.
    pub bgr: bool,
    /// Class of each output channel ("void" for ignore), in the class table's names.
    pub class_map: Vec<String>,
    /// Dark frames (mean grey level below this, in [0, 1]) are brightened by a gamma curve to
    /// this mean before segmentation; 0 turns it off. \[R\] 0.35 (sweep 03: +0.03 to +0.07 R@1 on the
    /// CamVid night change with segmenter labels, no loss elsewhere at Kv = 64).
    pub brighten_dark: f64,
}

impl Default for SegmentationConfig {
    fn default() -> Self {
        let mut class_map: Vec<String> = crate::classes::CITYSCAPES.iter().map(|c| c.0.to_string()).collect();
        class_map.push("void".into());
        SegmentationConfig {
            input_width: 1024,
            input_height: 512,
            scale: 1.0,
            mean: [0.0; 3],
            std: [1.0; 3],
            bgr: false,
            class_map,
            brighten_dark: 0.35,
        }
    }
}

/// Where model files are. Paths not given are looked up in the model folders
/// (`onnx::model_dirs`: $SEMLOOK_MODELS, `.semlook` beside the working directory or the
/// executable, the user's data directory). Not part of a map's encoding (maps record checksums).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ModelPaths {
    /// XFeat's weights for `appearance.model = "xfeat"` (else `xfeat.pt` in the model folders).
    #[serde(serialize_with = "lossy_path")]
    pub xfeat_weights: Option<std::path::PathBuf>,
    /// The ONNX keypoint network for `appearance.model = "onnx"`.
    #[serde(serialize_with = "lossy_path")]
    pub keypoint_onnx: Option<std::path::PathBuf>,
    /// The ONNX segmentation network that labels frames without a label map (`[segmentation]`).
    #[serde(serialize_with = "lossy_path")]
    pub segmenter_onnx: Option<std::path::PathBuf>,
    /// Without `segmenter_onnx`, segment frames that have no label map with the default
    /// segmenter when it is installed (`networks::segmenter::DEFAULT_SEGMENTER`).
    pub default_segmenter: bool,
    /// The ONNX Runtime shared library (else $ORT_DYLIB_PATH, then the model folders).
    #[serde(serialize_with = "lossy_path")]
    pub onnxruntime: Option<std::path::PathBuf>,
}

/// Paths are written as text even when they are not UTF-8 (serde's own impl fails on those).
fn lossy_path<S: serde::Serializer>(p: &Option<std::path::PathBuf>, s: S) -> std::result::Result<S::Ok, S::Error> {
    match p {
        Some(p) => s.serialize_some(&p.to_string_lossy()),
        None => s.serialize_none(),
    }
}

impl Default for ModelPaths {
    fn default() -> Self {
        ModelPaths { xfeat_weights: None, keypoint_onnx: None, segmenter_onnx: None, default_segmenter: true, onnxruntime: None }
    }
}

/// The default image-embedding network (EfficientNet-Lite1 ImageNet, GeM pooling), as looked up in
/// the model folders (`setup.sh` installs it; [`crate::models`] lists it).
pub const EMBEDDING_NETWORK: &str = "efficientnet_lite1_gem.onnx";

/// The `[embedding]` section: the whole-image embedding a new map stores ([`crate::networks::embedding`]).
/// Not an encoding section: a map records the network it was built with (its file name and
/// SHA-256, `map info`) and its queries are embedded with that one, whatever this section says; a
/// map built without one (or before embeddings) has none, and its fused score no embedding term.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EmbeddingConfig {
    /// The network (a file name looked up in the model folders, or an absolute path): an ONNX
    /// graph, or an EfficientNet-Lite checkpoint (`.pth`, `.pt`) run natively; or "none".
    /// \[R\] `efficientnet_lite1_gem.onnx`, EfficientNet-Lite1's ImageNet weights with GeM pooling,
    /// converted by `setup.sh` (sweep 16: Lite0, Lite1 and Lite2 compared). Where the default
    /// network is not installed, maps are built without embeddings and a warning says so; a
    /// network named here that is missing is an error. With appearance off (no RGB image is
    /// loaded) there are no embeddings either.
    pub network: String,
    /// The image's long side in pixels as the network sees it. \[R\] 448 (sweep 16: 320-640).
    pub long_side: u32,
}

impl Default for EmbeddingConfig {
    fn default() -> Self {
        EmbeddingConfig { network: EMBEDDING_NETWORK.into(), long_side: 448 }
    }
}

impl AppearanceConfig {
    /// Checks that every value of `[appearance]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("appearance.nms_radius", self.nms_radius, 0, 64)?;
        v.real("appearance.score_threshold", self.score_threshold, 0.0, 1.0)?;
        v.int("appearance.max_keypoints", self.max_keypoints, 1, 1 << 20)?;
        v.int("appearance.border", self.border, 0, 4096)?;
        v.int("appearance.vlad_centres", self.vlad_centres, 1, 64)?;
        v.int("appearance.min_descriptors", self.min_descriptors, 0, 1_000_000)?;
        v.int("appearance.codebook_images", self.codebook_images, 1, 100_000)?;
        v.int("appearance.codebook_samples_per_image", self.codebook_samples_per_image, 1, 100_000)?;
        v.int("appearance.codebook_iterations", self.codebook_iterations, 0, 10_000)?;
        if self.codebook_seed > i64::MAX as u64 {
            return Err(v.err(format!("appearance.codebook_seed = {} must be at most {}", self.codebook_seed, i64::MAX)));
        }
        Ok(())
    }
}

impl SegmentationConfig {
    /// Checks that every value of `[segmentation]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("segmentation.input_width", self.input_width, 32, 4096)?;
        v.int("segmentation.input_height", self.input_height, 32, 4096)?;
        v.real("segmentation.scale", self.scale, 1e-6, 1e6)?;
        for (c, (&m, &d)) in self.mean.iter().zip(&self.std).enumerate() {
            v.real(&format!("segmentation.mean[{c}]"), m, -1e6, 1e6)?;
            v.real(&format!("segmentation.std[{c}]"), d.abs(), 1e-6, 1e6)?;
        }
        v.real("segmentation.brighten_dark", self.brighten_dark, 0.0, 0.95)?;
        // its names are checked against the class table when a segmenter is loaded
        v.int("segmentation.class_map (entries)", self.class_map.len(), 1, 4096)?;
        Ok(())
    }
}

impl EmbeddingConfig {
    /// Checks that every value of `[embedding]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("embedding.long_side", self.long_side as usize, 32, 4096)?;
        Ok(())
    }
}

impl KeypointsConfig {
    /// Checks that every value of `[keypoints]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("keypoints.stored", self.stored, 0, 8192)?;
        v.int("keypoints.nms_radius", self.nms_radius, 0, 64)?;
        v.real("keypoints.score_threshold", self.score_threshold, 0.0, 1.0)?;
        v.int("keypoints.border", self.border, 0, 4096)?;
        Ok(())
    }
}
