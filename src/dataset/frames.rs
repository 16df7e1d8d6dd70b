//! What a dataset is made of (frames, traversals, poses, the ground-truth rule) and the image
//! files of a folder: the types the readers of every layout (`super`, `pairs`, `poses`) share.

use crate::error::{Error, Result};
use crate::input::{FrameSource, LabelFormat};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// Camera centre and optical axis (unit vector) in world coordinates, and the whole rotation
/// where the dataset gives it.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    /// Camera centre (dataset units, usually metres).
    pub position: [f64; 3],
    /// Optical axis, a unit vector.
    pub forward: [f64; 3],
    /// The camera-to-world rotation as a unit quaternion `[x, y, z, w]` (ROS order; the camera's
    /// z axis is `forward`), where the dataset gives a rotation (pose lists, SYNTHIA matrices);
    /// none where it gives a position alone (UTM names).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub orientation: Option<[f64; 4]>,
}

impl Pose {
    /// What a map stores of the pose ([`crate::descriptors::PlacePose`]).
    pub fn place_pose(&self) -> crate::descriptors::PlacePose {
        crate::descriptors::PlacePose { position: self.position, orientation: self.orientation }
    }
}

/// The line of a pose list (name -> pose) for an image file: its file name, else its stem.
pub fn pose_of_image<'a>(list: &'a std::collections::HashMap<String, Pose>, image: &Path) -> Option<&'a Pose> {
    let name = image.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let stem = image.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    list.get(&name).or_else(|| list.get(&stem))
}

/// One frame of a traversal: its files and, when the dataset gives one, its pose.
#[derive(Debug, Clone, PartialEq)]
pub struct Frame {
    /// Id and image and label-map files.
    pub source: FrameSource,
    /// Camera pose, when the dataset gives one.
    pub pose: Option<Pose>,
}

/// One visit of the route: a named, ordered list of frames.
#[derive(Debug, Clone, PartialEq)]
pub struct Traversal {
    /// Traversal name (its folder, or the manifest's `name`).
    pub name: String,
    /// Frames in order.
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
    /// Dataset directory; manifest paths are relative to it.
    pub root: PathBuf,
    /// Dataset name (the manifest's, else the directory's name).
    pub name: String,
    /// How the dataset's label-map files encode classes.
    pub label_format: LabelFormat,
    /// The `classes.label_ids` the dataset's label files use, when it says.
    pub label_ids: Option<crate::config::LabelIds>,
    /// Reference traversal (the map).
    pub reference: Traversal,
    /// Query traversals, none of them the reference.
    pub queries: Vec<Traversal>,
    /// Rule that makes ground truth from poses, for queries without ground-truth lists.
    pub rule: Option<GroundTruthRule>,
}

/// Line format of a pose list file (one line per image).
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

/// The frames of a folder of images and/or a folder of label maps, as `map build --images/--labels`
/// and Python's `Map.build` take them: each image `NAME.ext` is frame `NAME` (its file stem), with
/// label map `NAME.png` of the labels folder when one is given; a labels folder alone gives one
/// frame per label map. A folder without images, and two files of one stem (one id for two frames),
/// are refused naming the files, before any work.
pub fn frames_from_folders(images: Option<&Path>, labels: Option<&Path>) -> Result<Vec<FrameSource>> {
    let listing = |dir: &Path| -> Result<Vec<PathBuf>> {
        let files = image_files(dir)?;
        if files.is_empty() {
            return Err(Error::invalid(dir.display().to_string(), "no images (png, jpg) in this folder"));
        }
        Ok(files)
    };
    let stem = |p: &Path| p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let frames: Vec<FrameSource> = match (images, labels) {
        (Some(img), labels) => listing(img)?
            .into_iter()
            .map(|p| {
                // the label file from the OS name itself: a non-UTF-8 name is found, not mangled
                let label_name = |l: &Path| {
                    let mut n = p.file_stem().unwrap_or_default().to_os_string();
                    n.push(".png");
                    l.join(n)
                };
                FrameSource { id: stem(&p), labels: labels.map(label_name), image: Some(p.clone()) }
            })
            .collect(),
        (None, Some(labels)) => listing(labels)?.into_iter().map(|p| FrameSource { id: stem(&p), image: None, labels: Some(p) }).collect(),
        (None, None) => return Err(Error::invalid("frames", "give a folder of images or of label maps")),
    };
    unique_ids(&frames)?;
    Ok(frames)
}

/// Refuses two frames of one id, naming both frames' files (two files of one stem in a folder,
/// or one id given twice).
pub fn unique_ids(frames: &[FrameSource]) -> Result<()> {
    let mut seen: std::collections::HashMap<&str, &FrameSource> = std::collections::HashMap::new();
    for f in frames {
        if let Some(other) = seen.insert(f.id.as_str(), f) {
            let file = |s: &FrameSource| s.image.as_ref().or(s.labels.as_ref()).map_or(String::new(), |p| p.display().to_string());
            return Err(Error::invalid(file(f), format!("has the same name (id {:?}) as {}: rename one of them", f.id, file(other))));
        }
    }
    Ok(())
}
