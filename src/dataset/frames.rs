//! What a dataset is made of (frames, traversals, poses, the ground-truth rule) and the image
//! files of a folder: the types the readers of every layout (`super`, `pairs`, `poses`) share.

use crate::error::{Error, Result};
use crate::input::{FrameSource, LabelFormat};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Camera centre and optical axis (unit vector) in world coordinates.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: [f64; 3],
    pub forward: [f64; 3],
}

#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    pub source: FrameSource,
    pub pose: Option<Pose>,
}

#[derive(Debug, Clone, PartialEq)]
pub struct Traversal {
    pub name: String,
    pub frames: Vec<Frame>,
    /// Per frame, the valid reference indices, when the dataset lists them.
    pub ground_truth: Option<Vec<Vec<u32>>>,
}

/// Rule that makes ground truth from poses.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct GroundTruthRule {
    /// Camera centres closer than this (dataset units, usually metres) match.
    pub max_distance: f64,
    /// And optical axes closer than this angle, when given.
    #[serde(default)]
    pub max_angle_deg: Option<f64>,
}

/// A loaded dataset.
#[derive(Debug, Clone)]
pub struct Dataset {
    pub root: PathBuf,
    pub name: String,
    pub label_format: LabelFormat,
    /// The `classes.label_ids` the dataset's label files use, when it says.
    pub label_ids: Option<crate::config::LabelIds>,
    pub reference: Traversal,
    pub queries: Vec<Traversal>,
    pub rule: Option<GroundTruthRule>,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum PoseFormat {
    /// `name qw qx qy qz cx cy cz`: world-to-camera rotation, camera centre.
    QuatCenter,
    /// `name qw qx qy qz tx ty tz`: world-to-camera rotation and translation.
    QuatTranslation,
    /// `name` and 16 numbers: row-major 4x4 camera-to-world matrix.
    MatrixCamToWorld,
    /// `name` and 16 numbers: row-major 4x4 world-to-camera matrix.
    MatrixWorldToCam,
}

/// The png and jpeg files of a folder, sorted by name. Hidden files (macOS's `._name.jpg`
/// resource forks among them) are left out, and what else is left out (sub-folders, files of
/// other kinds) is said in one warning naming the folder.
pub fn image_files(dir: &Path) -> Result<Vec<PathBuf>> {
    if dir.is_file() {
        return Err(Error::invalid(dir.display().to_string(), "is a file, not a folder of images"));
    }
    let rd = std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?;
    let (mut files, mut folders, mut hidden, mut other) = (Vec::new(), 0usize, 0usize, Vec::new());
    for e in rd.flatten() {
        let p = e.path();
        let name = e.file_name().to_string_lossy().into_owned();
        if name.starts_with('.') {
            hidden += 1;
        } else if p.is_dir() {
            folders += 1;
        } else if matches!(p.extension().and_then(|e| e.to_str()).map(|e| e.to_ascii_lowercase()).as_deref(), Some("png" | "jpg" | "jpeg")) {
            files.push(p);
        } else {
            other.push(name);
        }
    }
    if folders + hidden + other.len() > 0 {
        other.sort();
        let mut said = Vec::new();
        if !other.is_empty() {
            let shown: Vec<&str> = other.iter().take(3).map(String::as_str).collect();
            said.push(format!("{} files not png or jpg ({}{})", other.len(), shown.join(", "), if other.len() > 3 { ", ..." } else { "" }));
        }
        if folders > 0 {
            said.push(format!("{folders} sub-folders (not searched)"));
        }
        if hidden > 0 {
            said.push(format!("{hidden} hidden files (macOS ._ resource forks among them)"));
        }
        log::warn!("{}: skipped {}", dir.display(), said.join(", "));
    }
    files.sort();
    Ok(files)
}
