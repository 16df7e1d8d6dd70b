//! The sections of query time: `[similarity]` (tree and image similarity), `[matching]` (the
//! coarse stage and the final score), `[verification]` (the `verified` setting) and `[eval]`.

use semlook_kernels::abi::{pack_key, TreeSimParams};
use serde::{Deserialize, Serialize};

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
    /// A test against two explicit nulls (issue 60): the inliers count only from `min_inliers` on
    /// (above what unrelated images give each other) and where they are significant under what
    /// look-alike references of other places give each other (the map's null,
    /// [`crate::matching::null`]), the query's K candidates in the multiple-testing count;
    /// `w_inliers` x the decades of significance beyond `null_alarms`. The compact HOGs (maps of
    /// small frames) count by their likelihood ratio, the map's same-place pairs against its
    /// look-alikes (`w_compact_hog`). The whole bonus at most `max_bonus`.
    Significant,
}

/// How verification pairs up the keypoints of a query and a candidate.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Matcher {
    /// Mutual nearest neighbours of the descriptors above `min_cosine`.
    Mnn,
    /// LighterGlue, XFeat's learned matcher (`networks::lighterglue`; weights
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
    /// the tree-set similarity of the pair. \[R\] 4 (sweep 21: per decade of significance beyond
    /// `null_alarms`; 2 with `inliers = "unusual"`, sweep 17; 1 with `"count"`, sweep 07).
    pub w_inliers: f64,
    /// How the inliers count: "significant" (against the map's null: what look-alike references
    /// of other places give each other), "unusual" (how far above the query's other candidates
    /// they stand) or "count" (ln(1 + inliers) whatever the others show). \[R\] significant
    /// (sweeps 19 and 21: over the four dev sets at full size, 320x240, 160x120 and 64x32, held
    /// out, at least `fused` on every set, and silent on unrelated images on every set, where
    /// "unusual" changed the order of every query's candidates and lost 37 queries to `fused` on
    /// landmarks at 160x120).
    pub inliers: InlierEvidence,
    /// With `inliers = "unusual"`: the z-score of a candidate's ln(1 + inliers) among its query's
    /// K candidates counts beyond this. \[R\] 1 (sweep 17).
    pub unusual_above: f64,
    /// With `inliers = "unusual"` or `"significant"`: fewer inliers than this count nothing (what
    /// chance gives a homography between unrelated images: 0 to 8 inliers on every dev set,
    /// sweep 21). \[R\] 15 (sweep 21, leave-one-set-out over 6 to 30: without it the
    /// significance test needed K in its count to stay silent on unrelated images, and then never
    /// spoke on ie-tower, whose look-alikes show as many inliers as a right answer; 8 with
    /// "unusual", sweep 17, whose profiles set it).
    pub min_inliers: u32,
    /// With `inliers = "significant"`: a candidate's inliers count when the expected number of
    /// candidates of a query that would show as much by chance (K x its tail probability under
    /// the map's null) is below this, adding w x log10(null_alarms / NFA). \[R\] 1000 (sweep 21:
    /// with the floor `min_inliers` in place, the best of 0.01 to 10^6 held out; at K = 30 it
    /// never binds, so every candidate above the floor gains w x (1.5 + its decades of surprise
    /// against the map's look-alikes); 0.01 without a floor, sweep 19).
    pub null_alarms: f64,
    /// With `inliers = "significant"`: the most the evidence terms add to a candidate's score.
    /// \[R\] 32 (sweep 21; 8 in sweep 19).
    pub max_bonus: f64,
    /// The map's null (`inliers = "significant"`): references within this many positions of
    /// each other along a traversal count as one place and never as a null pair. \[R\] 10 (the
    /// dev sets' places span at most 9 references).
    pub null_gap: u32,
    /// The map's null: references (evenly spaced along the map) whose look-alike candidates of
    /// other places are verified to measure it (and, where the map holds compact HOGs, whose
    /// neighbours along their traversal give the same-place sample). \[R\] 200.
    pub null_sources: u32,
    /// Weight of the compact HOGs' evidence (maps of small frames, `input.compact_hog_long_side`).
    /// With `inliers = "significant"`: w x max(0, log10(ratio) - `compact_hog_above`), the
    /// ratio P(a same-place pair of the map is as alike) / P(a look-alike of another place is)
    /// ([`crate::matching::null`]), so that the term speaks only on maps whose own places HOG
    /// tells apart. With "unusual": w x max(0, z - `compact_hog_above`), z the pair's cosine as a
    /// z-score among its query's K candidates. \[R\] 2 (sweep 22, leave-one-set-out over the 16
    /// sets: Nordland 320x240 0.967 -> 0.983 (with `input.compact_hog_long_side` 320), 160x120
    /// 0.900 -> 1.000, 64x32 0.600 -> 0.983, no other set moved, silent on unrelated images; sweep 21 had 0 with the test against the look-alikes alone, which
    /// spoke on landmarks and ie-tower at 160x120 and 64x32 and lost queries there; 2 with
    /// "unusual", sweep 17).
    pub w_compact_hog: f64,
    /// See `w_compact_hog`: decades of the likelihood ratio (with "unusual": the z-score) below
    /// which the compact HOGs say nothing. \[R\] 1, a ratio of 10 (sweep 22, over 0.5 to 1.5:
    /// below 1 the term spoke on unrelated images on Nordland 64x32; at 1.25 with weight 2 and at
    /// 1.5 it lost Nordland queries; sweep 17 for "unusual").
    pub compact_hog_above: f64,
    /// Weight of the fused coarse score in the verified score (see `w_inliers`). \[R\] 2.
    pub w_coarse: f64,
    /// Weight of the tree-set similarity in the verified score (see `w_inliers`; with `inliers =
    /// "significant"` it counts only for a candidate whose evidence is significant). \[R\] 0
    /// (sweep 19, the same R@1 as 2 on every set but one, Nordland, +1 query; 2 with the other forms,
    /// sweeps 07 and 17: the profiles of `configs/` that use them set it).
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
            w_inliers: 4.0,
            inliers: InlierEvidence::Significant,
            unusual_above: 1.0,
            min_inliers: 15,
            null_alarms: 1000.0,
            max_bonus: 32.0,
            null_gap: 10,
            null_sources: 200,
            w_compact_hog: 2.0,
            compact_hog_above: 1.0,
            w_coarse: 2.0,
            w_fine: 0.0,
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

impl SimilarityConfig {
    /// The tree-similarity kernels' parameters; the intrinsic and neighbour weights are normalised
    /// to sum to 1, so identical forests score 1 whatever the weights. Two trees pair when their
    /// classes are equal (see [`SimilarityConfig::tree_params_over`] for the categories).
    pub fn tree_params(&self, use_appearance: bool, neighbour_slots: usize) -> TreeSimParams {
        let wsum = (self.w_intrinsic + self.w_neighbours).max(f64::MIN_POSITIVE);
        TreeSimParams {
            w_area: self.w_area as f32,
            w_position: self.w_position as f32,
            w_appearance: self.w_appearance as f32,
            w_intrinsic: (self.w_intrinsic / wsum) as f32,
            w_neighbours: (self.w_neighbours / wsum) as f32,
            position_sigma: self.position_sigma as f32,
            neutral: self.neutral_appearance as f32,
            gaussian_position: (self.position == PositionSimilarity::Gaussian) as u32,
            drop_missing: (self.missing_appearance == MissingAppearance::Drop) as u32,
            use_appearance: use_appearance as u32,
            greedy: (self.assignment == Assignment::Greedy) as u32,
            neighbour_slots: neighbour_slots as u32,
            // settings without appearance never see descriptor counts: they weigh by area instead
            tree_weight: match self.tree_weight {
                TreeWeight::Uniform => 0,
                TreeWeight::Area => 1,
                TreeWeight::SqrtArea => 2,
                TreeWeight::Descriptors if use_appearance => 3,
                TreeWeight::Descriptors => 1,
            },
            geometric_norm: (self.normalise == Normalise::GeometricMean) as u32,
            _pad: [0; 2],
            class_key: pack_key(&std::array::from_fn(|i| i as u8)),
        }
    }

    /// [`SimilarityConfig::tree_params`] with the pairing rule of `class_match`: by class, or by
    /// the category each class has in `categories` (a class table's `category_key`).
    pub fn tree_params_over(&self, use_appearance: bool, neighbour_slots: usize, categories: &[u8; 256]) -> TreeSimParams {
        let mut p = self.tree_params(use_appearance, neighbour_slots);
        let by_category = match self.class_match {
            ClassMatch::Class => false,
            ClassMatch::Category => true,
            ClassMatch::CategoryWithAppearance => use_appearance,
        };
        if by_category {
            p.class_key = pack_key(categories);
        }
        p
    }

    /// Checks that every value of `[similarity]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        for (name, w) in [
            ("similarity.w_area", self.w_area),
            ("similarity.w_position", self.w_position),
            ("similarity.w_appearance", self.w_appearance),
            ("similarity.w_intrinsic", self.w_intrinsic),
            ("similarity.w_neighbours", self.w_neighbours),
        ] {
            v.real(name, w, 0.0, 1e3)?;
        }
        if self.w_area + self.w_position + self.w_appearance <= 0.0 || self.w_intrinsic + self.w_neighbours <= 0.0 {
            return Err(v.err("similarity weights must not all be zero (w_area + w_position + w_appearance, w_intrinsic + w_neighbours)".into()));
        }
        v.real("similarity.position_sigma", self.position_sigma, 1e-4, 10.0)?;
        v.real("similarity.neutral_appearance", self.neutral_appearance, 0.0, 1.0)?;
        Ok(())
    }
}

impl MatchingConfig {
    /// Checks that every value of `[matching]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("matching.top_k", self.top_k, 1, 1024)?;
        v.real("matching.w_global", self.w_global, 0.0, 1e3)?;
        v.real("matching.w_embedding", self.w_embedding, 0.0, 1e3)?;
        v.int("matching.tile", self.tile, 1, 65536)?;
        Ok(())
    }
}

impl VerificationConfig {
    /// Checks that every value of `[verification]` is in its range (numbers finite), and that
    /// LighterGlue gets the keypoints it was trained on (`appearance`, `appearance.model`); the
    /// error names the field.
    pub(super) fn validate(&self, v: &super::Check, appearance: super::AppearanceModelKind) -> crate::error::Result<()> {
        v.real("verification.min_cosine", self.min_cosine, -1.0, 1.0)?;
        v.real("verification.threshold", self.threshold, 1e-6, 1.0)?;
        v.int("verification.max_iterations", self.max_iterations as usize, 1, 1_000_000)?;
        v.real("verification.confidence", self.confidence, 0.0, 1.0 - 1e-12)?;
        if self.seed > i64::MAX as u64 {
            return Err(v.err(format!("verification.seed = {} must be at most {}", self.seed, i64::MAX)));
        }
        v.real("verification.glue_threshold", self.glue_threshold, 0.0, 1.0)?;
        if self.matcher == Matcher::Lighterglue && self.w_glue > 0.0 {
            return Err(v.err(
                "verification.w_glue adds LighterGlue beside the MNN matcher; with matcher = \"lighterglue\" it would do nothing (set w_inliers)"
                    .into(),
            ));
        }
        if (self.matcher == Matcher::Lighterglue || self.w_glue > 0.0) && appearance != super::AppearanceModelKind::Xfeat {
            // LighterGlue was trained on XFeat's descriptors: another network's keypoints would be matched as if they were
            return Err(
                v.err(format!("verification.matcher = \"lighterglue\" (or w_glue > 0) matches XFeat keypoints; appearance.model is {appearance:?}"))
            );
        }
        if self.glue_min_inliers > 0 && self.w_glue == 0.0 {
            return Err(v.err(
                "verification.glue_min_inliers chooses the pairs LighterGlue verifies beside MNN; without w_glue > 0 it would do nothing".into(),
            ));
        }
        v.int("verification.glue_min_inliers", self.glue_min_inliers as usize, 0, 100_000)?;
        v.int("verification.min_inliers", self.min_inliers as usize, 0, 100_000)?;
        v.real("verification.unusual_above", self.unusual_above, -10.0, 10.0)?;
        v.real("verification.compact_hog_above", self.compact_hog_above, -10.0, 10.0)?;
        v.real("verification.null_alarms", self.null_alarms, 1e-12, 1e6)?;
        v.real("verification.max_bonus", self.max_bonus, 0.0, 1e6)?;
        v.int("verification.null_gap", self.null_gap as usize, 0, 1_000_000)?;
        v.int("verification.null_sources", self.null_sources as usize, 1, 1_000_000)?;
        v.real("verification.glue_width_confidence", self.glue_width_confidence, -1.0, 1.0)?;
        v.real("verification.glue_depth_confidence", self.glue_depth_confidence, -1.0, 1.0)?;
        for (name, w) in [
            ("verification.w_inliers", self.w_inliers),
            ("verification.w_coarse", self.w_coarse),
            ("verification.w_fine", self.w_fine),
            ("verification.w_glue", self.w_glue),
            ("verification.w_compact_hog", self.w_compact_hog),
        ] {
            v.real(name, w, 0.0, 1e3)?;
        }
        Ok(())
    }
}

impl EvalConfig {
    /// Checks that every value of `[eval]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("eval.recall_at (entries)", self.recall_at.len(), 0, 16)?;
        for (k, &n) in self.recall_at.iter().enumerate() {
            v.int(&format!("eval.recall_at[{k}]"), n, 1, 1000)?;
        }
        Ok(())
    }
}
