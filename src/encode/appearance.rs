//! What computes appearance: the keypoint network's descriptors of a frame grouped by object, the
//! VLAD codebook they are aggregated with (trained on the references), the per-object and
//! whole-image VLAD vectors, and the verification keypoints a map stores.

use crate::appearance::{self, keypoints::Keypoints, AppearanceModel, Features};
use crate::config::{AppearanceConfig, KeypointsConfig};
use crate::descriptors::keypoints::ImageKeypoints;
use crate::error::{Error, Result};
use crate::global::vlad::{self, Codebook, VladNorm};
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
    /// Per class index: whether its descriptors are left out of the whole-image VLAD.
    ignored: [bool; 256],
}

impl AppearanceEncoder {
    pub(super) fn new(model: AppearanceModel, cfg: &AppearanceConfig, keypoints: &KeypointsConfig) -> AppearanceEncoder {
        AppearanceEncoder {
            model: Arc::new(model.with_detection(keypoints)),
            codebook: None,
            cfg: cfg.clone(),
            keypoints: keypoints.clone(),
            ignored: [false; 256],
        }
    }

    /// Resolves `appearance.ignore_classes` in `classes`; a name the table does not have is an
    /// error naming it.
    pub(super) fn ignoring(mut self, classes: &crate::classes::ClassTable) -> Result<Self> {
        self.ignored = classes.mask("appearance.ignore_classes", &self.cfg.ignore_classes)?;
        Ok(self)
    }

    /// Whether the whole-image VLAD leaves some class out (`appearance.ignore_classes`): it then
    /// reads the frame's labels.
    pub fn reads_labels(&self) -> bool {
        self.ignored.contains(&true)
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
        // the last run: every descriptor of the image not on an ignored class
        let n = image_run(k, labels, &self.ignored, &mut descriptors);
        offsets.push(offsets.last().copied().unwrap_or(0) + n as u32);
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
        let cb = vlad::train_codebook(&all, dim, a.vlad_centres, a.codebook_iterations, a.codebook_seed)
            .map_err(|e| e.named(|r| Error::invalid("codebook", format!("{r} (too few keypoints in the reference images)"))))?;
        self.set_codebook(cb);
        Ok(())
    }
}

/// Appends to `out` the descriptors of `k` whose keypoint is not on a class `ignored` marks (the
/// class under its position in `labels`, whose pixels its positions are in); returns how many.
fn image_run(k: &Keypoints, labels: &LabelMap, ignored: &[bool; 256], out: &mut Vec<f32>) -> usize {
    if !ignored.iter().any(|&i| i) {
        out.extend_from_slice(&k.descriptors);
        return k.len();
    }
    let mut n = 0;
    for (p, d) in k.xy.iter().zip(k.descriptors.chunks_exact(k.dim.max(1))) {
        if !ignored[labels.class_near(p[0], p[1]) as usize] {
            out.extend_from_slice(d);
            n += 1;
        }
    }
    n
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::classes::ClassTable;

    /// The image run leaves out exactly the descriptors whose keypoint lies on an ignored class,
    /// in their order, and keeps all of them when nothing is ignored.
    #[test]
    fn the_image_run_leaves_out_ignored_classes() {
        let table = ClassTable::cityscapes();
        let (road, sky) = (table.index("road").unwrap(), table.index("sky").unwrap());
        // 4 x 2 pixels: the left half road, the right half sky
        let labels = LabelMap::new(4, 2, vec![road, road, sky, sky, road, road, sky, sky], &table).unwrap();
        let k = Keypoints {
            xy: vec![[0.0, 0.0], [3.0, 1.0], [1.2, 1.0], [2.6, 0.0], [-5.0, 9.0]],
            scores: vec![1.0; 5],
            descriptors: vec![1.0, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0, 4.5, 5.0, 5.5],
            dim: 2,
        };
        let mut ignored = [false; 256];
        let mut out = vec![9.0];
        assert_eq!(image_run(&k, &labels, &ignored, &mut out), 5);
        assert_eq!(out[1..], k.descriptors[..]);
        ignored[sky as usize] = true;
        let mut out = vec![];
        // (3, 1) and (2.6 -> 3, 0) are on sky; (-5, 9) is clamped to (0, 1): road
        assert_eq!(image_run(&k, &labels, &ignored, &mut out), 3);
        assert_eq!(out, vec![1.0, 1.5, 3.0, 3.5, 5.0, 5.5]);
        // an image without keypoints
        let none = Keypoints { xy: vec![], scores: vec![], descriptors: vec![], dim: 2 };
        assert_eq!(image_run(&none, &labels, &ignored, &mut out), 0);
    }
}
