//! What computes appearance: the keypoint network's descriptors of a frame grouped by object, the
//! VLAD codebook they are aggregated with (trained on the references), the per-object and
//! whole-image VLAD vectors, and the verification keypoints a map stores.

use crate::appearance::{self, keypoints::Keypoints, vlad::Codebook, vlad::VladNorm, AppearanceModel, Features};
use crate::config::{AppearanceConfig, KeypointsConfig};
use crate::descriptors::keypoints::ImageKeypoints;
use crate::error::{Error, Result};
use crate::input::LabelMap;
use crate::objects::ObjectMap;
use std::sync::Arc;

/// Appearance descriptors of one frame sorted by object, with each object's run, and last a run
/// of all the frame's descriptors (for the whole-image VLAD): what the VLAD kernels take.
#[derive(Debug, Clone, Default)]
pub struct VladInput {
    /// The descriptors, D values each, object by object, then the image's run.
    pub descriptors: Vec<f32>,
    /// objects + 2 entries: object o owns `offsets[o]..offsets[o + 1]`; the last run is the image.
    pub offsets: Vec<u32>,
}

/// The appearance half of an encoder: the keypoint network and, once trained or taken from a
/// map, the VLAD codebook. Cheap to share between threads.
#[derive(Debug, Clone)]
pub struct AppearanceEncoder {
    model: Arc<AppearanceModel>,
    codebook: Option<Arc<Codebook>>,
    cfg: AppearanceConfig,
    keypoints: KeypointsConfig,
}

impl AppearanceEncoder {
    pub(super) fn new(model: AppearanceModel, cfg: &AppearanceConfig, keypoints: &KeypointsConfig) -> AppearanceEncoder {
        AppearanceEncoder { model: Arc::new(model.with_detection(keypoints)), codebook: None, cfg: cfg.clone(), keypoints: keypoints.clone() }
    }

    /// The keypoint network.
    pub fn model(&self) -> &AppearanceModel {
        &self.model
    }
    /// The VLAD codebook, once trained or set.
    pub fn codebook(&self) -> Option<&Codebook> {
        self.codebook.as_deref()
    }
    /// Sets the VLAD codebook (replacing any).
    pub fn set_codebook(&mut self, codebook: Codebook) {
        self.codebook = Some(Arc::new(codebook));
    }
    /// Length of the trees' (and the image's) appearance vectors: Kv x D once there is a
    /// codebook, else 0.
    pub fn dim(&self) -> usize {
        self.codebook.as_ref().map_or(0, |c| c.k * c.dim)
    }
    /// Values per stored verification keypoint descriptor: the network's descriptor width when
    /// keypoints are stored, else 0.
    pub fn keypoint_dim(&self) -> usize {
        match &self.codebook {
            Some(c) if self.model.detects() => c.dim,
            _ => 0,
        }
    }
    /// The VLAD normalisations of the configuration.
    pub fn vlad_norm(&self) -> VladNorm {
        VladNorm::from_config(&self.cfg)
    }

    /// VLAD of a frame's objects and of the whole image on the CPU (the twins of the GPU kernels).
    pub fn vlad(&self, input: &VladInput) -> Result<Vec<f32>> {
        let cb = self.codebook.as_ref().ok_or_else(|| Error::invalid("encoder", "VLAD input without a codebook"))?;
        appearance::check_vlad_input(&input.descriptors, &input.offsets, cb).map_err(|e| e.named(|r| Error::invalid("VLAD input", r)))?;
        Ok(appearance::object_vlad(&input.descriptors, &input.offsets, cb, self.vlad_norm()))
    }

    /// The network's output for `rgb` (`given`, when a caller already ran it) grouped by the
    /// objects of `objects` into VLAD input, and the verification keypoints of the frame.
    /// Returns (VLAD input, keypoints, network milliseconds when it ran here).
    pub(super) fn describe(
        &self,
        rgb: &image::RgbImage,
        labels: &LabelMap,
        objects: &ObjectMap,
        given: Option<&Features>,
    ) -> Result<(VladInput, ImageKeypoints, Option<f64>)> {
        let codebook = self
            .codebook
            .as_ref()
            .ok_or_else(|| Error::invalid("encoder", "appearance is on but no VLAD codebook is set (train one, or open a map that has one)"))?;
        let computed;
        let (f, network_ms) = match given {
            Some(f) => (f, None),
            None => {
                computed = self.model.features(rgb)?;
                (&computed, Some(computed.network_ms))
            }
        };
        let k = &f.sampled;
        if k.dim != codebook.dim {
            return Err(Error::Model {
                path: self.model.path.clone(),
                reason: format!("descriptors have {} values, the codebook {}", k.dim, codebook.dim),
            });
        }
        let verification = match &f.detected {
            Some(d) => appearance::verification_keypoints(d, self.keypoints.stored, labels, labels.width().max(labels.height())),
            None => ImageKeypoints::default(),
        };
        let (mut descriptors, mut offsets) = appearance::group_by_object(k, objects);
        // the last run: every descriptor of the image
        descriptors.extend_from_slice(&k.descriptors);
        offsets.push(offsets.last().copied().unwrap_or(0) + k.len() as u32);
        Ok((VladInput { descriptors, offsets }, verification, network_ms))
    }

    /// Indices of the reference frames the codebook is trained on: up to
    /// `appearance.codebook_images`, spread evenly over `n` frames.
    pub fn codebook_picks(&self, n: usize) -> Vec<usize> {
        let m = self.cfg.codebook_images.min(n);
        (0..m).map(|i| i * n / m).collect()
    }

    /// Trains the VLAD codebook on the keypoints of the picked reference frames (see
    /// [`AppearanceEncoder::codebook_picks`]) and sets it.
    pub fn train_codebook_from(&mut self, keypoints: &[&Keypoints]) -> Result<()> {
        let a = &self.cfg;
        let dim = keypoints.first().map(|k| k.dim).ok_or_else(|| Error::invalid("codebook", "no reference images to train it on"))?;
        let all: Vec<f32> = keypoints.iter().flat_map(|k| appearance::sample_descriptors(k, a.codebook_samples_per_image)).collect();
        let cb = appearance::vlad::train_codebook(&all, dim, a.vlad_centres, a.codebook_iterations, a.codebook_seed)
            .map_err(|e| e.named(|r| Error::invalid("codebook", format!("{r} (too few keypoints in the reference images)"))))?;
        self.set_codebook(cb);
        Ok(())
    }
}
