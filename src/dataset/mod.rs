//! Datasets for evaluation: a reference traversal (the map), one or more query traversals, and
//! ground truth. [`Dataset::open`] reads a `semlook-dataset.json` manifest, or recognises a
//! folder: `ref/` + `query/` + `ground_truth.csv` (real-vpr), `ref/` + `query/` +
//! `ground_truth_new.npy` (VPR-Bench), `database/` + `queries/` with UTM file names (gmberton's
//! VPR-datasets), or a SYNTHIA-style tree (see [`pairs`] for the first three). Manifest layouts:
//! - `synthia`: `ROOT/<traversal>/RGB/<camera>/<frame>.png`, labels in
//!   `ROOT/<traversal>/GT/LABELS/<camera>/<frame>.png`, poses in
//!   `ROOT/<traversal>/CameraParams/<camera>/<frame>.txt` (16 numbers, a column-major 4x4
//!   camera-to-world matrix); `semlook synth` writes this layout;
//! - `folders`: an image folder, an optional label folder (same file stems, `.png`), and an
//!   optional pose list file, one line per image (Extended CMU Seasons, RobotCar Seasons);
//! - `explicit`: every frame listed with its files, pose and/or ground-truth list.

mod frames;
mod npy;
pub mod pairs;
mod poses;

use crate::error::{Error, Result};
use crate::input::{FrameSource, LabelFormat};
pub use frames::{frames_from_folders, image_files, pose_of_image, unique_ids, Dataset, Frame, GroundTruthRule, Pose, PoseFormat, Traversal};
use pairs::PairTruth;
pub use poses::{parse_pose_list, parse_synthia_pose, read_pose_list, read_synthia_pose, write_synthia_pose};
use serde::{Deserialize, Serialize};
use std::path::{Path, PathBuf};

/// File name of a dataset manifest, in the dataset directory.
pub const MANIFEST: &str = "semlook-dataset.json";
/// Default SYNTHIA camera folder.
pub const SYNTHIA_CAMERA: &str = "Stereo_Left/Omni_F";

/// A traversal as a manifest describes it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(untagged)]
pub enum TraversalSpec {
    /// A traversal folder of the synthia layout.
    Named(String),
    /// An image folder with optional label folder and pose list (the `folders` layout).
    Folders {
        /// Traversal name; frame ids are `name/stem`.
        name: String,
        /// Image folder, relative to the dataset root.
        images: PathBuf,
        /// Label-map folder (same file stems, `.png`), relative to the dataset root.
        #[serde(default)]
        labels: Option<PathBuf>,
        /// Pose list file, relative to the dataset root.
        #[serde(default)]
        poses: Option<PathBuf>,
        /// Line format of the pose list; `quat_center` when not given.
        #[serde(default)]
        pose_format: Option<PoseFormat>,
    },
    /// Every frame listed with its files (the `explicit` layout).
    Explicit {
        /// Traversal name.
        name: String,
        /// Frames in order.
        frames: Vec<FrameSpec>,
    },
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
/// One frame of an explicit traversal.
pub struct FrameSpec {
    /// Frame id.
    pub id: String,
    /// RGB image file, relative to the dataset root.
    #[serde(default)]
    pub image: Option<PathBuf>,
    /// Label-map file, relative to the dataset root.
    #[serde(default)]
    pub labels: Option<PathBuf>,
    /// Camera pose.
    #[serde(default)]
    pub pose: Option<Pose>,
    /// Valid reference indices (query frames only).
    #[serde(default)]
    pub ground_truth: Option<Vec<u32>>,
}

/// The `semlook-dataset.json` file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DatasetManifest {
    /// Always `semlook-dataset`.
    pub format: String,
    /// Manifest version; 1.
    pub version: u32,
    /// Dataset name; the directory's name when not given.
    #[serde(default)]
    pub name: Option<String>,
    /// Layout: `synthia` (the default), `folders` or `explicit`; only `synthia` reads named traversals.
    #[serde(default = "default_layout")]
    pub layout: String,
    /// SYNTHIA camera folder; [`SYNTHIA_CAMERA`] when not given.
    #[serde(default)]
    pub camera: Option<String>,
    /// How the label-map files encode classes.
    #[serde(default)]
    pub label_format: LabelFormat,
    /// The `classes.label_ids` the label files use, when known.
    #[serde(default)]
    pub label_ids: Option<crate::config::LabelIds>,
    /// Reference traversal (the map).
    pub reference: TraversalSpec,
    /// Query traversals; one equal to the reference is skipped.
    pub queries: Vec<TraversalSpec>,
    /// Rule that makes ground truth from poses.
    #[serde(default)]
    pub ground_truth: Option<GroundTruthRule>,
}

fn default_layout() -> String {
    "synthia".into()
}

/// Overrides from the command line.
#[derive(Debug, Clone, Default)]
pub struct DatasetOptions {
    /// Reference traversal name, replacing the manifest's.
    pub reference: Option<String>,
    /// Query traversal names, replacing the manifest's when not empty.
    pub queries: Vec<String>,
    /// Ground-truth distance (dataset units, usually metres), replacing the manifest's rule.
    pub max_distance: Option<f64>,
    /// Ground-truth angle between optical axes, in degrees.
    pub max_angle_deg: Option<f64>,
}

impl Dataset {
    /// The dataset a caller names: a dataset directory (see [`Dataset::open`]), or a reference and
    /// a query folder with a ground-truth file (else UTM names within `opts.max_distance`, default
    /// [`pairs::UTM_DEFAULT_DISTANCE`] metres; see [`pairs::from_folders`]).
    pub fn open_any(
        dir: Option<&Path>,
        references: Option<&Path>,
        queries: Option<&Path>,
        ground_truth: Option<&Path>,
        opts: &DatasetOptions,
    ) -> Result<Dataset> {
        match (dir, references, queries) {
            (Some(dir), _, _) => Dataset::open(dir, opts),
            (None, Some(refs), Some(queries)) => {
                if let (Ok(a), Ok(b)) = (refs.canonicalize(), queries.canonicalize()) {
                    if a == b {
                        log::warn!(
                            "{}: the query folder is the reference folder: every query finds its own image, so the metrics say nothing (give the queries of another visit)",
                            queries.display()
                        );
                    }
                }
                let truth = match ground_truth {
                    Some(f) => PairTruth::from_file(f)?,
                    None => PairTruth::Utm(opts.max_distance.unwrap_or(pairs::UTM_DEFAULT_DISTANCE)),
                };
                pairs::from_folders(refs, queries, &truth)
            }
            _ => Err(Error::invalid("arguments", "give a dataset directory, or a reference and a query folder (and a ground-truth file)")),
        }
    }

    /// Opens `root`: its manifest if present, else a synthia-layout tree (then `opts.reference`
    /// is required). Command-line options override the manifest's choices.
    pub fn open(root: &Path, opts: &DatasetOptions) -> Result<Dataset> {
        let mpath = root.join(MANIFEST);
        let manifest = if mpath.exists() {
            let text = std::fs::read(&mpath).map_err(|e| Error::io(&mpath, e))?;
            let m: DatasetManifest = serde_json::from_slice(&text).map_err(|e| Error::dataset(&mpath, format!("manifest: {e}")))?;
            if m.format != "semlook-dataset" || m.version != 1 {
                return Err(Error::dataset(&mpath, "not a semlook-dataset version 1 manifest"));
            }
            m
        } else if let Some(ds) = Self::open_folder_pair(root, opts)? {
            return Ok(ds);
        } else {
            let found = synthia_traversals(root);
            let reference = opts.reference.clone().ok_or_else(|| {
                Error::refused(
                    format!("dataset {}", root.display()),
                    format!("no {MANIFEST}: which traversal is the reference? (traversals found: {})", found.join(", ")),
                    crate::error::Remedy::NameReferenceTraversal,
                )
            })?;
            DatasetManifest {
                format: "semlook-dataset".into(),
                version: 1,
                name: None,
                layout: "synthia".into(),
                camera: None,
                label_format: LabelFormat::FirstChannel,
                label_ids: Some(crate::config::LabelIds::Named("synthia".into())),
                reference: TraversalSpec::Named(reference.clone()),
                queries: found.into_iter().filter(|n| *n != reference).map(TraversalSpec::Named).collect(),
                ground_truth: Some(GroundTruthRule { max_distance: 7.0, max_angle_deg: None }),
            }
        };
        let mut manifest = manifest;
        if let Some(r) = &opts.reference {
            manifest.reference = TraversalSpec::Named(r.clone());
        }
        if !opts.queries.is_empty() {
            manifest.queries = opts.queries.iter().cloned().map(TraversalSpec::Named).collect();
        }
        if let Some(d) = opts.max_distance {
            manifest.ground_truth = Some(GroundTruthRule { max_distance: d, max_angle_deg: opts.max_angle_deg });
        } else if let (Some(a), Some(rule)) = (opts.max_angle_deg, manifest.ground_truth.as_mut()) {
            rule.max_angle_deg = Some(a);
        }
        Self::from_manifest(root, &manifest)
    }

    /// A folder laid out as real-vpr, VPR-Bench or gmberton's datasets (see [`pairs`]), if it is one.
    fn open_folder_pair(root: &Path, opts: &DatasetOptions) -> Result<Option<Dataset>> {
        let (refs, queries) = (root.join("ref"), root.join("query"));
        let (csv, npy) = (root.join("ground_truth.csv"), root.join("ground_truth_new.npy"));
        let found = if refs.is_dir() && queries.is_dir() && (csv.is_file() || npy.is_file()) {
            let truth = if csv.is_file() { PairTruth::Csv(csv) } else { PairTruth::Npy(npy) };
            Some((refs, queries, truth))
        } else {
            pairs::gmberton_folders(root).map(|(d, q)| (d, q, PairTruth::Utm(opts.max_distance.unwrap_or(pairs::UTM_DEFAULT_DISTANCE))))
        };
        let Some((refs, queries, truth)) = found else { return Ok(None) };
        if opts.reference.is_some() || !opts.queries.is_empty() || opts.max_angle_deg.is_some() {
            return Err(Error::dataset(
                root,
                "reference and query traversals and a ground-truth angle do not apply to a folder-pair dataset (ref/query or database/queries)",
            ));
        }
        if opts.max_distance.is_some() && !matches!(truth, PairTruth::Utm(_)) {
            return Err(Error::dataset(root, "a ground-truth distance applies only to datasets with positions (UTM file names)"));
        }
        pairs::from_folders(&refs, &queries, &truth).map(Some)
    }

    /// Loads the traversals `m` describes, with paths relative to `root`, and checks every
    /// query's ground truth.
    pub fn from_manifest(root: &Path, m: &DatasetManifest) -> Result<Dataset> {
        let camera = m.camera.clone().unwrap_or_else(|| SYNTHIA_CAMERA.into());
        let load = |spec: &TraversalSpec| load_traversal(root, &m.layout, &camera, spec);
        let reference = load(&m.reference)?;
        if reference.frames.is_empty() {
            return Err(Error::dataset(root, format!("reference traversal {:?} has no frames", reference.name)));
        }
        let mut queries = Vec::new();
        for q in &m.queries {
            let t = load(q)?;
            if t.name == reference.name {
                continue;
            }
            queries.push(t);
        }
        if queries.is_empty() {
            return Err(Error::dataset(root, "no query traversal"));
        }
        let ds = Dataset {
            root: root.into(),
            name: m.name.clone().unwrap_or_else(|| root.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default()),
            label_format: m.label_format,
            label_ids: m.label_ids.clone(),
            reference,
            queries,
            rule: m.ground_truth,
        };
        for q in &ds.queries {
            ds.ground_truth(q)?;
        }
        Ok(ds)
    }

    /// `cfg` with its class settings following this dataset's label files: CamVid ids take the
    /// CamVid table (and a Cityscapes segmenter's channels mapped to it), other named ids set
    /// `classes.label_ids`.
    pub fn adapt_config(&self, mut cfg: crate::config::Config) -> crate::config::Config {
        match &self.label_ids {
            Some(crate::config::LabelIds::Named(n)) if n == "camvid" => {
                let camvid = crate::config::Config::camvid();
                cfg.classes = camvid.classes;
                cfg.segmentation.class_map = camvid.segmentation.class_map;
            }
            Some(ids) => cfg.classes.label_ids = ids.clone(),
            None => {}
        }
        cfg
    }

    /// The same dataset with its label maps dropped: every frame is then segmented from its
    /// image (to measure a segmenter against the real labels' results).
    pub fn without_labels(mut self) -> Dataset {
        for t in std::iter::once(&mut self.reference).chain(self.queries.iter_mut()) {
            for f in &mut t.frames {
                f.source.labels = None;
            }
        }
        self
    }

    /// Valid reference indices for every frame of query traversal `q`: the listed ones, else
    /// those the pose rule accepts.
    pub fn ground_truth(&self, q: &Traversal) -> Result<Vec<Vec<u32>>> {
        if let Some(gt) = &q.ground_truth {
            let n = self.reference.frames.len() as u32;
            if let Some(bad) = gt.iter().flatten().find(|&&i| i >= n) {
                return Err(Error::dataset(&self.root, format!("ground truth of {:?} names reference {bad}, there are {n}", q.name)));
            }
            return Ok(gt.clone());
        }
        let rule = self
            .rule
            .ok_or_else(|| Error::dataset(&self.root, format!("traversal {:?} has no ground-truth lists and no pose rule is set", q.name)))?;
        if !rule.max_distance.is_finite() || rule.max_distance < 0.0 {
            return Err(Error::dataset(&self.root, format!("ground-truth distance {} is not a finite non-negative number", rule.max_distance)));
        }
        if let Some(a) = rule.max_angle_deg.filter(|a| !(0.0..=180.0).contains(a)) {
            return Err(Error::dataset(&self.root, format!("ground-truth angle {a} is not a number of degrees in [0, 180]")));
        }
        let pose =
            |f: &Frame| f.pose.ok_or_else(|| Error::dataset(&self.root, format!("frame {:?} has no pose for pose-based ground truth", f.source.id)));
        let refs: Vec<Pose> = self.reference.frames.iter().map(pose).collect::<Result<_>>()?;
        q.frames.iter().map(|f| Ok(pose_matches(&pose(f)?, &refs, &rule))).collect()
    }
}

/// Indices of the reference poses that `rule` accepts for `q`.
pub fn pose_matches(q: &Pose, refs: &[Pose], rule: &GroundTruthRule) -> Vec<u32> {
    let cos_limit = rule.max_angle_deg.map(|a| a.to_radians().cos());
    refs.iter()
        .enumerate()
        .filter(|(_, r)| {
            let d2: f64 = (0..3).map(|i| (q.position[i] - r.position[i]).powi(2)).sum();
            let angle_ok = cos_limit.is_none_or(|c| (0..3).map(|i| q.forward[i] * r.forward[i]).sum::<f64>() >= c);
            d2.sqrt() <= rule.max_distance && angle_ok
        })
        .map(|(i, _)| i as u32)
        .collect()
}

/// Traversal folders of a synthia-layout root (those with an `RGB` folder), sorted.
pub fn synthia_traversals(root: &Path) -> Vec<String> {
    let mut v: Vec<String> = std::fs::read_dir(root)
        .into_iter()
        .flatten()
        .flatten()
        .filter(|e| e.path().join("RGB").is_dir())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .collect();
    v.sort();
    v
}

fn stem(p: &Path) -> String {
    p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default()
}

fn load_traversal(root: &Path, layout: &str, camera: &str, spec: &TraversalSpec) -> Result<Traversal> {
    match (layout, spec) {
        ("synthia", TraversalSpec::Named(name)) => {
            let base = root.join(name);
            let rgb_dir = base.join("RGB").join(camera);
            let mut frames = Vec::new();
            for img in image_files(&rgb_dir)? {
                let s = stem(&img);
                let labels = base.join("GT/LABELS").join(camera).join(format!("{s}.png"));
                let pose_file = base.join("CameraParams").join(camera).join(format!("{s}.txt"));
                let pose = if pose_file.exists() { Some(read_synthia_pose(&pose_file)?) } else { None };
                frames.push(Frame { source: FrameSource { id: format!("{name}/{s}"), image: Some(img), labels: Some(labels) }, pose });
            }
            Ok(Traversal { name: name.clone(), frames, ground_truth: None })
        }
        (_, TraversalSpec::Folders { name, images, labels, poses, pose_format }) => {
            let dir = root.join(images);
            let pose_map = match poses {
                Some(p) => Some(read_pose_list(&root.join(p), pose_format.unwrap_or(PoseFormat::QuatCenter))?),
                None => None,
            };
            let mut frames = Vec::new();
            for img in image_files(&dir)? {
                let s = stem(&img);
                let pose = match &pose_map {
                    Some(m) => Some(*pose_of_image(m, &img).ok_or_else(|| {
                        let fname = img.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
                        Error::dataset(root, format!("pose list has no line for image {fname:?}"))
                    })?),
                    None => None,
                };
                frames.push(Frame {
                    source: FrameSource {
                        id: format!("{name}/{s}"),
                        labels: labels.as_ref().map(|l| root.join(l).join(format!("{s}.png"))),
                        image: Some(img),
                    },
                    pose,
                });
            }
            Ok(Traversal { name: name.clone(), frames, ground_truth: None })
        }
        (_, TraversalSpec::Explicit { name, frames }) => {
            // ground-truth lists count only when every frame has one
            let gt: Option<Vec<Vec<u32>>> = frames.iter().map(|f| f.ground_truth.clone()).collect::<Option<_>>().filter(|g: &Vec<_>| !g.is_empty());
            let frames = frames
                .iter()
                .map(|f| Frame {
                    source: FrameSource {
                        id: f.id.clone(),
                        image: f.image.as_ref().map(|p| root.join(p)),
                        labels: f.labels.as_ref().map(|p| root.join(p)),
                    },
                    pose: f.pose,
                })
                .collect();
            Ok(Traversal { name: name.clone(), frames, ground_truth: gt })
        }
        (layout, spec) => Err(Error::dataset(root, format!("traversal {spec:?} does not fit layout {layout:?}"))),
    }
}
