//! Every tunable of the engine, with the defaults of the design reference (`docs/design/method.md` §3).
//! Choices the paper does not state (\[R\] in method.md) are all here, so that a user can change them
//! in a TOML file. `semlook config` prints this struct's defaults.
//!
//! Sections split in two groups: the *encoding* sections ([`EncodingConfig`]: `input`, `classes`,
//! `objects`, `global`, `local`, `appearance`, `keypoints`, `segmentation`) change what is stored
//! in a map, so a map records them and refuses queries encoded differently; the *matching*
//! sections (`similarity`, `matching`, `verification`, `eval`) may change at query time.

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

/// The `[input]` section: the working resolution.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct InputConfig {
    /// Label maps and images are brought to this long side (keeping the aspect ratio) before
    /// edges, objects and keypoints: descriptors then cost the same for any input resolution, and
    /// the keypoint network sees structures at a scale that survives seasons. 0: native size.
    /// \[R\] 640, the resolution XFeat was trained and evaluated at (640x480). A segmenter runs on
    /// the full image at its own input size.
    pub working_long_side: usize,
    /// A map whose frames have a long side of at most this many pixels (its first frame's) also
    /// stores each image's compact HOG, which `verified` adds as evidence where it stands out
    /// (`verification.w_compact_hog`): at that size the keypoint network finds little; 0: never.
    /// \[R\] 256 (sweep 17: Nordland dev copies at 64x32 and 128x64 fell below `hog` without it,
    /// at 256x128 not).
    pub compact_hog_long_side: usize,
}

impl Default for InputConfig {
    fn default() -> Self {
        InputConfig { working_long_side: 640, compact_hog_long_side: 256 }
    }
}

/// The `[classes]` section; defined beside the table it builds ([`crate::classes`]).
pub use crate::classes::{ClassSpec, ClassesConfig, LabelIds, TableSpec};

/// The `[objects]` section: which regions of a label map become objects (trees).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct ObjectsConfig {
    /// Objects smaller than this fraction of the image area are dropped. \[R\] 0.1 %.
    pub min_area_fraction: f64,
    /// At most this many objects per image, the largest kept (bounds GPU scratch space). \[R\] 64.
    pub max_objects: usize,
    /// Object area: "pixels" (pixel count of the region) or "contour" (shoelace area of the
    /// Suzuki-Abe outer border, as cv2.contourArea). \[R\] pixels.
    pub area: AreaMode,
}

impl Default for ObjectsConfig {
    fn default() -> Self {
        ObjectsConfig { min_area_fraction: 0.001, max_objects: 64, area: AreaMode::Pixels }
    }
}

/// How an object's area is measured (`objects.area`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum AreaMode {
    /// The pixel count of the region.
    Pixels,
    /// The shoelace area of the Suzuki-Abe outer border, as cv2.contourArea.
    Contour,
}

/// The `[global]` section: the semantic-edge global descriptor and its SSIM (method.md §2.7).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GlobalConfig {
    /// Distance-transform truncation τ as a fraction of the image diagonal. \[R\] 0.1.
    pub truncation: f64,
    /// Global descriptor width and height after area resizing. \[R\] 64 x 48.
    pub width: usize,
    /// Global descriptor height (with `width`). \[R\] 48.
    pub height: usize,
    /// SSIM window side (uniform window, odd). \[R\] 7, as skimage.
    pub ssim_window: usize,
    /// SSIM stabilisers C1 = (k1 L)^2, C2 = (k2 L)^2 with data range L = 1. \[X\] Wang et al. 2004.
    pub ssim_k1: f64,
    /// k2 of the stabiliser C2 (with `ssim_k1`). \[X\] 0.03.
    pub ssim_k2: f64,
    /// Use sample (N-1) rather than population variances, as skimage does by default.
    pub ssim_sample_covariance: bool,
}

impl Default for GlobalConfig {
    fn default() -> Self {
        GlobalConfig { truncation: 0.1, width: 64, height: 48, ssim_window: 7, ssim_k1: 0.01, ssim_k2: 0.03, ssim_sample_covariance: true }
    }
}

/// The `[local]` section: the neighbours of each tree.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct LocalConfig {
    /// Neighbours per tree. \[Q\] 3.
    pub neighbours: usize,
    /// Centroid distances (in image diagonals) closer than this count as a tie, broken by the
    /// larger area. \[R\] 0.02.
    pub tie_tolerance: f64,
}

impl Default for LocalConfig {
    fn default() -> Self {
        LocalConfig { neighbours: 3, tie_tolerance: 0.02 }
    }
}

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
    /// segmenter when it is installed (`segmentation::DEFAULT_SEGMENTER`).
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

/// The `[similarity]` section: tree similarity and image similarity (method.md §2.8).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SimilarityConfig {
    /// Weights of area, position and appearance inside S_in (normalised by their sum). \[R\]
    /// 1/3, 1/3, 16 (sweeps 01-02: with segmenter labels, area and position of objects are
    /// noise on real frames; appearance carries the place: 0.3 -> 0.7 R@1 on Nordland).
    pub w_area: f64,
    /// Weight of position inside S_in (see `w_area`). \[R\] 1/3.
    pub w_position: f64,
    /// Weight of appearance inside S_in (see `w_area`). \[R\] 16.
    pub w_appearance: f64,
    /// Weights of the intrinsic part and the neighbour part of the tree similarity, normalised
    /// by their sum. \[R\] 0.5 / 0.2 (sweep 02: 0.2 > 0 and > 0.5 in mean R@1).
    pub w_intrinsic: f64,
    /// Weight of the neighbour part S_N (see `w_intrinsic`). \[R\] 0.2.
    pub w_neighbours: f64,
    /// Position similarity: "linear" max(0, 1 - d) or "gaussian" exp(-d^2 / 2 sigma^2), d in diagonals.
    pub position: PositionSimilarity,
    /// sigma of the "gaussian" position term, in image diagonals. \[R\] 0.1.
    pub position_sigma: f64,
    /// Appearance missing on either side: "neutral" (score `neutral_appearance`) or "drop" (leave
    /// the term out and renormalise the weights). \[R\] neutral 0.5.
    pub missing_appearance: MissingAppearance,
    /// The appearance score of a pair where a tree has no appearance, with
    /// `missing_appearance = "neutral"`. \[R\] 0.5.
    pub neutral_appearance: f64,
    /// Image similarity from tree similarities: "greedy" one-to-one assignment, or "best_match"
    /// (each query tree takes its best reference tree). \[R\] greedy.
    pub assignment: Assignment,
    /// Weight of a tree in the image similarity: "uniform", "area", "sqrt_area", or
    /// "descriptors" (its appearance descriptor count + 1; settings without appearance use the
    /// area instead). A pair counts sqrt(w_t w_u). \[R\] descriptors (sweep 01: the single largest
    /// gain: many small, fragmented objects no longer outvote the large ones).
    pub tree_weight: TreeWeight,
    /// The sum of weighted pair scores is divided by "larger_forest" (the larger total tree
    /// weight, method.md §2.8) or "geometric_mean" (sqrt of the product of the totals). \[R\] larger_forest.
    pub normalise: Normalise,
    /// Which trees may pair (method.md §2.8: only the same class): "class", "category" (the same
    /// category, e.g. road with sidewalk, building with wall: what an off-domain segmenter swaps),
    /// or "category_with_appearance" (categories where appearance takes part, classes in the
    /// label-only Forest settings). \[R\] category_with_appearance (sweep 06, mean R@1 over the
    /// three dev sets: categories raised `local` and `semlook` from 0.641 to 0.678 and `verified`
    /// from 0.848 to 0.852, and lowered `forest` from 0.228 to 0.174, which classes keep).
    pub class_match: ClassMatch,
}

/// Which trees may pair (`similarity.class_match`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ClassMatch {
    /// Only trees of the same class (method.md §2.8).
    Class,
    /// Trees of the same category (road with sidewalk, building with wall, ...).
    Category,
    /// Categories in the settings where appearance takes part, classes in the label-only ones.
    CategoryWithAppearance,
}

impl SimilarityConfig {
    /// The design reference's reconstruction (method.md §2.8) before any sweep: S_in in equal thirds,
    /// S = 0.5 S_in + 0.5 S_N, uniform tree weights.
    pub fn spec() -> Self {
        SimilarityConfig {
            w_appearance: 1.0 / 3.0,
            w_neighbours: 0.5,
            tree_weight: TreeWeight::Uniform,
            class_match: ClassMatch::Class,
            ..Default::default()
        }
    }
}

/// The weight of a tree in the image similarity (`similarity.tree_weight`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TreeWeight {
    /// Every tree weighs 1 (method.md §2.8).
    Uniform,
    /// The tree's object area.
    Area,
    /// The square root of the tree's object area.
    SqrtArea,
    /// The tree's appearance descriptor count + 1 (the area in settings without appearance).
    Descriptors,
}

/// What the sum of weighted pair scores is divided by (`similarity.normalise`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Normalise {
    /// The larger of the two forests' total tree weights (method.md §2.8).
    LargerForest,
    /// The square root of the product of the two totals.
    GeometricMean,
}

impl Default for SimilarityConfig {
    fn default() -> Self {
        SimilarityConfig {
            w_area: 1.0 / 3.0,
            w_position: 1.0 / 3.0,
            w_appearance: 16.0,
            w_intrinsic: 0.5,
            w_neighbours: 0.2,
            position: PositionSimilarity::Linear,
            position_sigma: 0.1,
            missing_appearance: MissingAppearance::Neutral,
            neutral_appearance: 0.5,
            assignment: Assignment::Greedy,
            tree_weight: TreeWeight::Descriptors,
            normalise: Normalise::LargerForest,
            class_match: ClassMatch::CategoryWithAppearance,
        }
    }
}

/// The position similarity of two trees from their centroid distance d, in image diagonals
/// (`similarity.position`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PositionSimilarity {
    /// max(0, 1 - d).
    Linear,
    /// exp(-d^2 / 2 sigma^2), sigma = `position_sigma`.
    Gaussian,
}

/// What a pair scores for appearance when either tree has none (`similarity.missing_appearance`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum MissingAppearance {
    /// The score `neutral_appearance`.
    Neutral,
    /// No score: the term is left out and the weights renormalised.
    Drop,
}

/// How tree similarities make the image similarity (`similarity.assignment`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Assignment {
    /// Greedy one-to-one assignment of tree pairs, best pair first.
    Greedy,
    /// Each query tree takes its best reference tree.
    BestMatch,
}

/// The `[matching]` section: the coarse stage and the final score.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct MatchingConfig {
    /// Candidates the coarse stage passes to the fine stage. \[R\] 30 (sweep 05: with geometric
    /// verification, 30 candidates gave `verified` 0.852 mean R@1 over the three real dev sets,
    /// 20 gave 0.840 and 10 0.825; `semlook` was the same at 20 and 30; sweeps 02-03 had chosen
    /// 20 over 10 and 40 before verification existed).
    pub top_k: usize,
    /// References scored per tile while streaming top-K; bounds the scratch memory.
    pub tile: usize,
    /// Final score: "fine" (image similarity) or "fine_times_global" (times the SSIM). \[R\] fine.
    pub score: ScoreFusion,
    /// The fused coarse stage (`fused`, `verified`) ranks by cos(whole-image appearance) +
    /// w_global x SSIM(global descriptors). \[R\] 0.25 (sweep 08: 0, 0.1, 0.25, 0.5, 1 compared).
    pub w_global: f64,
    /// The coarse stage of the paper's two-stage settings (`global-forest`, `semlook`): "global",
    /// the semantic-edge descriptor alone (the paper's reading), or "fused" with the whole-image
    /// appearance, as `fused` ranks. \[R\] fused (sweep 08: with the edge descriptor alone the right
    /// place survived to the fine stage for 27 % of the landmark queries at K = 20, and
    /// coarse-to-fine lost places that the fine stage alone finds).
    pub coarse: CoarseStage,
    /// The fused coarse stage of `fused` and `verified` adds w_embedding x the cosine of the
    /// whole-image embeddings (`[embedding]`) where the map and the queries both have them, made by
    /// one network; the paper's two-stage settings never (their coarse stage keeps its meaning). \[R\] 2 (sweep 16: 1, 2, 3
    /// and 4 compared on the three real dev sets).
    pub w_embedding: f64,
}

/// Which scores the coarse stage of the paper's two-stage settings ranks by.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CoarseStage {
    /// SSIM of the semantic-edge global descriptors (method.md §2.7).
    Global,
    /// cos(whole-image appearance) + w_global x SSIM.
    Fused,
}

impl Default for MatchingConfig {
    fn default() -> Self {
        MatchingConfig { top_k: 30, tile: 4096, score: ScoreFusion::Fine, w_global: 0.25, coarse: CoarseStage::Fused, w_embedding: 2.0 }
    }
}

/// The final score of a candidate (`matching.score`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ScoreFusion {
    /// The image similarity of the fine stage.
    Fine,
    /// The image similarity times the SSIM of the global descriptors.
    FineTimesGlobal,
}

/// Which RANSAC inliers count towards a verified score.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SemanticCheck {
    /// Every inlier.
    Off,
    /// Only inliers whose keypoints lie on the same semantic class in both images.
    SameClass,
}

/// How the verified score counts a candidate's inliers (`verification.inliers`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum InlierEvidence {
    /// `w_inliers` x ln(1 + inliers), whatever the query's other candidates show (the score before
    /// issue 51).
    Count,
    /// `w_inliers` x how far ln(1 + inliers) stands above the query's other candidates: its
    /// z-score among them beyond `unusual_above` (0 below `min_inliers`).
    Unusual,
}

/// How verification pairs up the keypoints of a query and a candidate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Matcher {
    /// Mutual nearest neighbours of the descriptors above `min_cosine`.
    Mnn,
    /// LighterGlue, XFeat's learned matcher (`verify::lighterglue`; weights
    /// `xfeat-lighterglue.pt` in the model folders).
    Lighterglue,
}

/// Geometric verification of candidates (the `verified` setting; beyond the paper, `verify`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct VerificationConfig {
    /// Keypoints match when each is the other's nearest neighbour and their cosine reaches this.
    /// \[X\] XFeat's matcher: 0.82.
    pub min_cosine: f64,
    /// RANSAC inlier threshold on the homography's transfer error, in fractions of the image's
    /// long side. \[R\] 0.00625 (4 px at the 640 px working size; sweep 07: 0.003125 and 0.0125
    /// lower).
    pub threshold: f64,
    /// RANSAC iterations at most, and the confidence that stops earlier. \[R\] 1000, 0.999.
    pub max_iterations: u32,
    /// RANSAC stops once an all-inlier sample was drawn with this probability, at the best
    /// model's inlier ratio (see `max_iterations`). \[R\] 0.999.
    pub confidence: f64,
    /// Seed of RANSAC's sampling (the same for every pair: results do not depend on the batch).
    pub seed: u64,
    /// Least-squares refits on the inliers of each new best model (LO-RANSAC). \[R\] on.
    pub refine: bool,
    /// Which inliers count. \[R\] off (sweep 07: `same_class` lost 0.044 mean R@1: the segmenter's
    /// labels disagree across conditions where the geometry agrees).
    pub semantic: SemanticCheck,
    /// The verified score: w_coarse coarse + w_fine fine + w_inliers x the inliers' evidence
    /// (`inliers`) + w_compact_hog x the compact HOGs' evidence, with the fused coarse score and
    /// the tree-set similarity of the pair. \[R\] 2 (sweep 17, leave-one-set-out; 1 with
    /// `inliers = "count"` before, sweep 07).
    pub w_inliers: f64,
    /// How the inliers count: "unusual" (how far above the query's other candidates they stand,
    /// so that where every candidate shows as many, geometry says little and the coarse order
    /// stands) or "count" (ln(1 + inliers) whatever the others show). \[R\] unusual (sweep 17:
    /// restricted to either form, leave-one-set-out picks of "unusual" give the higher held-out
    /// mean R@1 over the six dev sets, 0.801 against 0.785, and over the four real ones, 0.838
    /// against 0.821).
    pub inliers: InlierEvidence,
    /// With `inliers = "unusual"`: the z-score of a candidate's ln(1 + inliers) among its query's
    /// K candidates counts beyond this. \[R\] 1 (sweep 17).
    pub unusual_above: f64,
    /// With `inliers = "unusual"`: fewer inliers than this count nothing (what chance gives a
    /// homography on few keypoints). \[R\] 8 (sweep 17).
    pub min_inliers: u32,
    /// Weight of the compact HOGs' evidence (maps of small frames, `input.compact_hog_long_side`):
    /// the z-score of the pair's compact HOG cosine among its query's K candidates beyond
    /// `compact_hog_above`. \[R\] 2 (sweep 17: Nordland 64x32 0.550 -> 1.000).
    pub w_compact_hog: f64,
    /// See `w_compact_hog`. \[R\] 1 (sweep 17).
    pub compact_hog_above: f64,
    /// Weight of the fused coarse score in the verified score (see `w_inliers`). \[R\] 2.
    pub w_coarse: f64,
    /// Weight of the tree-set similarity in the verified score (see `w_inliers`). \[R\] 2.
    pub w_fine: f64,
    /// Classes (names of the class table) whose keypoints take no part in verification: a mutual
    /// match with either end on one of them is dropped before RANSAC (issue 32: dynamic classes
    /// and sky, whose matches do not say where the camera is). \[R\] none (sweep 13).
    pub ignore_classes: Vec<String>,
    /// Which matcher pairs the keypoints up before RANSAC. \[R\] mnn.
    pub matcher: Matcher,
    /// LighterGlue: a mutual best match counts when its assignment probability exceeds this.
    /// \[X\] 0.1 (the authors' `filter_threshold`).
    pub glue_threshold: f64,
    /// LighterGlue's point pruning: after each layer but the last, keypoints whose matchability is
    /// at most 1 - this are dropped; -1 turns it off. \[X\] 0.95 (the authors' `width_confidence`;
    /// `configs/verified-lighterglue.toml` sets 0.8: sweep 14c).
    pub glue_width_confidence: f64,
    /// LighterGlue's early exit: after each layer but the last, stop once more than this share of
    /// the keypoints is confident; -1 turns it off. \[X\] -1 (the authors' `depth_confidence`).
    pub glue_depth_confidence: f64,
    /// With `matcher = "mnn"`: weight of ln(1 + LighterGlue's RANSAC inliers) added to the verified
    /// score, LighterGlue then also verifying every candidate (those `glue_min_inliers` admits); 0 runs
    /// only the chosen matcher.
    /// \[R\] 0 (sweep 14: 0.5 with `glue_threshold` 0.7 and `w_inliers` 2 is the best measured
    /// fusion, dev mean R@1 0.864 against 0.852; with `glue_min_inliers` 5 and
    /// `glue_width_confidence` 0.8 at about 25 times the verification time: sweeps 14b and 14c,
    /// `configs/verified-lighterglue.toml`).
    pub w_glue: f64,
    /// With `w_glue` > 0: LighterGlue verifies only the pairs whose MNN verification found at
    /// least this many inliers (a rule of the pair alone, so a pair scores the same in any batch,
    /// shard or sequence window); the others add nothing. 0: every pair. \[R\] 0 (sweep 14b: 5,
    /// more than a homography's minimal sample, keeps the fusion's dev R@1 with LighterGlue on
    /// 61 % of the pairs).
    pub glue_min_inliers: u32,
}

impl Default for VerificationConfig {
    fn default() -> Self {
        VerificationConfig {
            min_cosine: 0.82,
            threshold: 0.00625,
            max_iterations: 1000,
            confidence: 0.999,
            seed: 1,
            refine: true,
            semantic: SemanticCheck::Off,
            w_inliers: 2.0,
            inliers: InlierEvidence::Unusual,
            unusual_above: 1.0,
            min_inliers: 8,
            w_compact_hog: 2.0,
            compact_hog_above: 1.0,
            w_coarse: 2.0,
            w_fine: 2.0,
            ignore_classes: vec![],
            matcher: Matcher::Mnn,
            glue_threshold: 0.1,
            glue_width_confidence: 0.95,
            glue_depth_confidence: -1.0,
            w_glue: 0.0,
            glue_min_inliers: 0,
        }
    }
}

/// How the contributions of a frame's scores to a trajectory are normalised (the contrast
/// enhancement of SeqSLAM's difference matrix, Milford & Wyeth 2012, on a sparse row).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Contrast {
    /// The score above the frame's lowest candidate score, unscaled.
    None,
    /// z-score over the frame's scored references.
    Frame,
    /// z-score over the references within `contrast_window` positions along the traversal
    /// (references the frame did not score count at its lowest score), as SeqSLAM does.
    Window,
}

/// Which references each frame scores for sequence matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SequenceRows {
    /// The setting's candidates (its top-K) widened by `widen` positions either side.
    Candidates,
    /// Every reference of the map (a dense row: small maps only).
    Full,
}

/// Sequence matching over a stream (beyond the paper; `stream`): each frame's candidate scores
/// go into a ring of the last `length` frames, and trajectories through them whose velocity
/// changes smoothly are scored (SeqSLAM, Milford & Wyeth 2012; SeqMatch, Garg & Milford 2021).
/// Causal: the result at frame t uses frames up to t. A matching section: it may change at query
/// time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SequenceConfig {
    /// Frames a trajectory spans (SeqSLAM's ds). \[R\] 20 (sweep 10f: 12 / 16 / 20 / 24 over the six
    /// ordered dev sets and nine settings with trajectories whose speed changes; 20 is the longest
    /// with no set's stream below its single frames; SeqSLAM used 10 to 20).
    pub length: usize,
    /// Velocities tried, in reference positions per query frame: `velocity_steps` values evenly
    /// from `velocity_min` to `velocity_max`. 0 is a stop; negative values drive backwards.
    /// \[R\] 0 to 2 in 9 steps (sweep 10; SeqSLAM: 0.8 to 1.2, which misses stops).
    pub velocity_min: f64,
    /// The fastest velocity tried (see `velocity_min`). \[R\] 2.
    pub velocity_max: f64,
    /// The number of velocities tried (see `velocity_min`). \[R\] 9.
    pub velocity_steps: usize,
    /// `velocity_min` and `velocity_max` are multiplied by this (issue 48: a map recorded at one
    /// frame rate and a camera at another). Unset (the default): the stream's frame interval over
    /// the map's where both are known (the stream's timestamps, the map's `map build/add
    /// --timestamps`), else 1. \[R\] unset (derived).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub velocity_scale: Option<f64>,
    /// What a trajectory pays, in contribution units, each time its velocity changes by one step
    /// between two frames (a very large value keeps SeqSLAM's straight lines). \[R\] 1 (sweep 10e).
    pub velocity_change: f64,
    /// Which references each frame scores. \[R\] candidates.
    pub rows: SequenceRows,
    /// The candidates of each frame are widened by this many positions either side along their
    /// traversal, each scored by the setting, so trajectories pass through scored neighbours.
    /// \[R\] 1 (sweep 10).
    pub widen: usize,
    /// Contrast normalisation of each frame's scores. \[R\] frame (sweep 10: SeqSLAM's window
    /// normalisation lost 0.08 to 0.58 R@1 on Nordland, where a route's neighbouring places all
    /// score high and an isolated alias stands out of its window; none was 0.01 to 0.02 below
    /// frame on the mean).
    pub contrast: Contrast,
    /// Half-width of the contrast window, in positions. \[X\] SeqSLAM's R_window: 10.
    pub contrast_window: usize,
    /// The match is the newest frame's strongest place within this many positions of the best
    /// trajectory's end, where the frame gives that place at least `refine_share` of its
    /// strongest evidence (a trajectory through frames of a varying speed may end a place off).
    /// \[R\] 2 (sweep 10e).
    pub refine: usize,
    /// See `refine`. \[R\] 0.9 (sweep 10e).
    pub refine_share: f64,
    /// The uniqueness of a match is its score over the best score of a place further than this
    /// many positions along the same traversal (or on another one). \[X\] SeqSLAM's R_window: 10.
    pub uniqueness_window: usize,
    /// A sequence match is accepted when its uniqueness reaches this and its trajectory spans at
    /// least `min_frames` frames. \[R\] 1.05, 5 (sweep 10).
    pub min_uniqueness: f64,
    /// The fewest frames an accepted trajectory spans (see `min_uniqueness`). \[R\] 5.
    pub min_frames: usize,
    /// A trajectory slower than this (positions per frame, either way) is a stop, accepted only
    /// where the frames stand still (`stillness`): a place that scores well against every frame
    /// of a moving camera otherwise wins as a standing trajectory. \[R\] 0.3 (sweep 10e).
    pub stop_velocity: f64,
    /// The cosine of the newest two frames' rows at which the camera counts as standing still
    /// (see `stop_velocity`; above 1: stops are never accepted). \[R\] 0.95 (sweep 10e).
    pub stillness: f64,
}

impl Default for SequenceConfig {
    fn default() -> Self {
        SequenceConfig {
            length: 20,
            velocity_min: 0.0,
            velocity_max: 2.0,
            velocity_steps: 9,
            velocity_scale: None,
            velocity_change: 1.0,
            rows: SequenceRows::Candidates,
            widen: 1,
            contrast: Contrast::Frame,
            contrast_window: 10,
            refine: 2,
            refine_share: 0.9,
            uniqueness_window: 10,
            min_uniqueness: 1.05,
            min_frames: 5,
            stop_velocity: 0.3,
            stillness: 0.95,
        }
    }
}

/// Streams (`stream::Localizer`, `semlook localize`): loop closure and tracking. A matching
/// section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StreamConfig {
    /// Loop-closure mode: frames of the stream are matched only against frames at least this
    /// many frames older, and at least `exclude_seconds` older where frames carry timestamps
    /// (the recent past always looks like the present). \[R\] 50 frames (5 s at 10 Hz), 0 s.
    pub exclude_frames: usize,
    /// Loop-closure mode: the seconds a matched frame is at least older, where frames carry
    /// timestamps (see `exclude_frames`). \[R\] 0.
    pub exclude_seconds: f64,
    /// Loop-closure mode: the frames added are committed to the map (one segment, the store's
    /// crash-safe commit) every this many frames; at most `exclude_frames`, so that every frame
    /// that may be matched is stored. \[R\] 25.
    pub commit_frames: usize,
    /// While the last sequence match was accepted, only the references within this many
    /// positions of where it predicts the frame are searched (0: the whole map every frame);
    /// after `lost_after` frames without an accepted match, the whole map again. Large maps.
    /// \[R\] 0 (off), 5.
    pub track_radius: usize,
    /// Frames without an accepted match after which the whole map is searched again (see
    /// `track_radius`). \[R\] 5.
    pub lost_after: usize,
    /// Whether a frame searched within the tracking window (`track_radius`) gets its whole-image
    /// embedding too; off, only the frames that search the whole map are embedded (the window's
    /// few dozen places are ranked by appearance and SSIM, then verified), which saves the
    /// embedding network's time on tracked frames (issue 48). \[R\] true (off, the real-time
    /// replay at 1,000 places ran 7 % faster but accepted 0.22 of its frames against 0.52).
    pub embed_when_tracking: bool,
    /// Loop-closure mode: an accepted sequence match is a closure when its uniqueness reaches
    /// `closure_uniqueness` (some other place must score: a match with no competitor is not
    /// evidence) and its trajectory moves at least `closure_min_velocity` positions per frame
    /// (a standing trajectory says only that the recent frames all resemble one old place).
    /// \[R\] 1.5 and 0.5, from the CamVid loop (the drive, then its shifted copy; tests/stream.rs):
    /// of the false closures of the first pass 92 % stood or crawled (|v| <= 0.25), the true ones
    /// of the second moved at 0.5 to 1 with uniqueness 1.49 to 4.5.
    pub closure_uniqueness: f64,
    /// Loop-closure mode: the least speed of a closure's trajectory, in positions per frame (see
    /// `closure_uniqueness`). \[R\] 0.5.
    pub closure_min_velocity: f64,
    /// Loop-closure mode: the least score of a closure's sequence match (the mean contrast-
    /// normalised evidence of its trajectory a frame). Uniqueness alone lets a first pass close
    /// on the places just older than the excluded window: they are the only ones it may match,
    /// and the best of a few is unique. \[R\] 2.25 (sweep 12: over the CamVid loop and a
    /// synthetic route driven twice, the lowest floor with no closure in a first pass, 23 of
    /// them at 0; it keeps 93 % and 99 % of the right closures of the second passes).
    pub closure_min_score: f64,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            exclude_frames: 50,
            exclude_seconds: 0.0,
            commit_frames: 25,
            track_radius: 0,
            lost_after: 5,
            embed_when_tracking: true,
            closure_uniqueness: 1.5,
            closure_min_velocity: 0.5,
            closure_min_score: 2.25,
        }
    }
}

/// When the fused coarse stage searches a map through its approximate index ([`crate::index`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IndexSearch {
    /// Where the map has an index and the search covers at least `index.min_places` references.
    Auto,
    /// Never: every reference is scored exactly.
    Exact,
    /// Wherever the map has an index, whatever its size.
    Approximate,
}

/// The `[index]` section: the approximate index of the coarse stage over large maps (beyond the
/// paper; [`crate::index`]): how `map build --index` and `map index` build it (recorded in the
/// map), and when and how matching uses it (a matching section: it may change at query time).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IndexConfig {
    /// When the fused coarse stage (`fused`, `verified`, and the coarse stage of `semlook` and
    /// `global-forest`) uses the map's index. \[R\] auto.
    pub search: IndexSearch,
    /// `auto` uses the index from this many references searched. \[R\] 20,000 (sweep 11: at
    /// 20,000 one query's exact scan took 368 ms and the index's 18 ms on the 2-core machine;
    /// smaller maps keep the exact scan, which costs little there and assumes nothing).
    pub min_places: usize,
    /// Lists scanned per query. \[R\] 112 (sweep 11b: with `shortlist` and `pool`, the best
    /// recall@30 against the exact fused top-30 at 1M references under 20 ms a query: 0.969 at
    /// 16.5 ms; sweep 11 had chosen 96 with a shortlist of 1,000 and no pool).
    pub probe: usize,
    /// References rescored exactly by the fused score (the best of the pool by its approximation);
    /// 0: 150 where the pool is re-ranked with thumbnails, 1,000 where the codes alone choose
    /// (an index without thumbnails). \[R\] 0 (sweep 11b: 150/200/300 with the pool; sweep 11:
    /// 1,000 without it).
    pub shortlist: usize,
    /// The scan's best references by the appearance codes that are re-ranked by the codes plus
    /// `matching.w_global` x the SSIM of the index's thumbnails before the `shortlist` best go to
    /// the exact score (an index without thumbnails, or `pool` <= `shortlist`: the codes alone
    /// choose the shortlist). \[R\] 6,000 (sweep 11b: 4,000/6,000).
    pub pool: usize,
    /// Build: reduced dimensions. \[R\] 256 (faiss's 1M-image example reduces 4,096-d image
    /// descriptors to 256 the same way; 262 bytes a reference with its list and scale).
    pub dims: usize,
    /// Build: lists; 0 chooses 4 x sqrt(images) rounded to a power of two, 16 to 4,096.
    /// \[R\] 0 (faiss's guideline: 4 to 16 x sqrt(N)).
    pub lists: usize,
    /// Build: images sampled to train on. \[R\] 32,768.
    pub sample: usize,
    /// Build: subspace and k-means iterations. \[R\] 8.
    pub iterations: usize,
    /// Build: seed. \[R\] 7.
    pub seed: u64,
    /// Build: the global descriptors' thumbnails kept beside the codes, pooled by this factor
    /// (8-bit, 768 bytes a reference at 2 for a 64 x 48 descriptor); 0: none. \[R\] 2 (on the
    /// real dev sets the SSIM of thumbnails pooled by 2 follows the exact SSIM at r = 0.990, by 4
    /// at 0.951: docs/index.md).
    pub thumbnail: usize,
}

impl Default for IndexConfig {
    fn default() -> Self {
        IndexConfig {
            search: IndexSearch::Auto,
            min_places: 20_000,
            probe: 112,
            shortlist: 0,
            pool: 6000,
            dims: 256,
            lists: 0,
            sample: 32_768,
            iterations: 8,
            seed: 7,
            thumbnail: 2,
        }
    }
}

/// The `[eval]` section: what evaluation reports.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EvalConfig {
    /// N of the Recall@N columns.
    pub recall_at: Vec<usize>,
}

impl Default for EvalConfig {
    fn default() -> Self {
        EvalConfig { recall_at: vec![1, 5, 10] }
    }
}

impl Config {
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

/// The default image-embedding network (EfficientNet-Lite1 ImageNet, GeM pooling), as looked up in
/// the model folders (`setup.sh` installs it; [`crate::models`] lists it).
pub const EMBEDDING_NETWORK: &str = "efficientnet_lite1_gem.onnx";

/// The `[embedding]` section: the whole-image embedding a new map stores ([`crate::embedding`]).
/// Not an encoding section: a map records the network it was built with (its file name and
/// SHA-256, `map info`) and its queries are embedded with that one, whatever this section says; a
/// map built without one (or before embeddings) has none, and its fused score no embedding term.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct EmbeddingConfig {
    /// The ONNX network (a file name looked up in the model folders, or an absolute path), or "none".
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
