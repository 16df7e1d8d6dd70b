//! The sections of the image side of the descriptors: `[input]`, `[classes]` (defined beside its
//! table in `classes`), `[objects]`, `[global]`, `[local]`. Encoding sections: a map records them.

use serde::{Deserialize, Serialize};

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
    /// stores each image's compact HOG (1,764 f16 values, 3.5 kB), which `verified` adds as
    /// evidence where the map shows it tells its places apart (`verification.w_compact_hog`): at
    /// that size the keypoint network finds little; 0: never. \[R\] 320 (sweep 22: the Nordland
    /// copy at 320x240 0.967 -> 0.983 with them, HOG 1.000, no other set moved; sweep 17 had
    /// 256: Nordland copies at 64x32 and 128x64 fell below `hog` without them).
    pub compact_hog_long_side: usize,
}

impl Default for InputConfig {
    fn default() -> Self {
        InputConfig { working_long_side: 640, compact_hog_long_side: 320 }
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

impl InputConfig {
    /// Checks that every value of `[input]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("input.compact_hog_long_side", self.compact_hog_long_side, 0, 8192)?;
        if self.working_long_side != 0 {
            v.int("input.working_long_side", self.working_long_side, 32, 8192)?;
        }
        Ok(())
    }
}

impl ObjectsConfig {
    /// Checks that every value of `[objects]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.real("objects.min_area_fraction", self.min_area_fraction, 0.0, 0.5)?;
        v.int("objects.max_objects", self.max_objects, 1, 256)?;
        Ok(())
    }
}

impl GlobalConfig {
    /// The SSIM kernels' parameters of this descriptor and window.
    pub fn ssim_params(&self) -> semlook_kernels::abi::SsimParams {
        semlook_kernels::abi::SsimParams::new(self.width, self.height, self.ssim_window, (self.ssim_k1, self.ssim_k2), self.ssim_sample_covariance)
    }

    /// Checks that every value of `[global]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.real("global.truncation", self.truncation, 1e-3, 1.0)?;
        v.int("global.ssim_window", self.ssim_window, 3, 1023)?;
        if self.ssim_window.is_multiple_of(2) {
            return Err(v.err(format!("global.ssim_window = {} must be odd", self.ssim_window)));
        }
        v.int("global.width", self.width, self.ssim_window, 1024)?;
        v.int("global.height", self.height, self.ssim_window, 1024)?;
        v.real("global.ssim_k1", self.ssim_k1, 1e-6, 1.0)?;
        v.real("global.ssim_k2", self.ssim_k2, 1e-6, 1.0)?;
        Ok(())
    }
}

impl LocalConfig {
    /// Checks that every value of `[local]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("local.neighbours", self.neighbours, 0, 8)?;
        v.real("local.tie_tolerance", self.tie_tolerance, 0.0, 1.0)?;
        Ok(())
    }
}
