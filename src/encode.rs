//! Encoding: one frame (label map, and RGB pixels when appearance is on) to its global
//! descriptor and its forest, timing each stage as the paper's Table 2 splits them:
//! "edge (coarse)" = global descriptor, "forest" = objects and trees, "appearance" = keypoint
//! network and per-object VLAD.

use crate::appearance::{self, vlad::Codebook, AppearanceModel};
use crate::classes::ClassTable;
use crate::config::{Config, EncodingConfig};
use crate::error::{Error, Result};
use crate::global::{self, ssim::SsimParams, GlobalScratch};
use crate::input::{self, FrameSource, LabelFormat, LabelMap};
use crate::local::{self, Forest};
use crate::objects;
use crate::util::ms_since;
use image::RgbImage;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;

/// Everything stored for one image.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedImage {
    pub id: String,
    pub width: u32,
    pub height: u32,
    /// Global descriptor, `global.height` x `global.width`, values in [0, 1].
    pub global: Vec<f32>,
    /// SSIM window means then variances of `global`.
    pub global_stats: Vec<f32>,
    pub forest: Forest,
}

/// Milliseconds spent per stage on one image.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Reading and decoding the input files (and segmenting, without label maps).
    pub load_ms: f64,
    /// "Edge (coarse)": edges, distance transform, pooling, SSIM stats.
    pub global_ms: f64,
    /// "Forest": objects, trees and neighbours.
    pub forest_ms: f64,
    /// Appearance: keypoint network, decoding and per-object VLAD.
    pub appearance_ms: f64,
    /// Of `appearance_ms`, the network alone.
    pub network_ms: f64,
}

impl std::ops::AddAssign for StageTimes {
    fn add_assign(&mut self, o: StageTimes) {
        self.load_ms += o.load_ms;
        self.global_ms += o.global_ms;
        self.forest_ms += o.forest_ms;
        self.appearance_ms += o.appearance_ms;
        self.network_ms += o.network_ms;
    }
}

/// A frame's decoded inputs.
#[derive(Debug, Clone)]
pub struct Loaded {
    pub labels: LabelMap,
    pub rgb: Option<RgbImage>,
    pub load_ms: f64,
}

/// Keypoint descriptors of one frame sorted by object, and each object's run: what VLAD needs.
#[derive(Debug, Clone, Default)]
pub struct VladInput {
    pub descriptors: Vec<f32>,
    pub offsets: Vec<u32>,
}

/// A frame encoded up to (not including) its VLAD vectors.
#[derive(Debug, Clone)]
pub struct Pending {
    pub image: EncodedImage,
    pub times: StageTimes,
    pub vlad: Option<VladInput>,
}

/// Encodes frames with one configuration. Cheap to share between threads.
#[derive(Debug, Clone)]
pub struct Encoder {
    cfg: EncodingConfig,
    table: ClassTable,
    used: [bool; 256],
    ssim: SsimParams,
    appearance: Option<Arc<AppearanceModel>>,
    codebook: Option<Arc<Codebook>>,
    segmenter: Option<Arc<crate::segmentation::Segmenter>>,
}

impl Encoder {
    /// An encoder for `cfg`: loads the keypoint network (and segmenter) the config names.
    pub fn new(cfg: &Config) -> Result<Encoder> {
        let table = ClassTable::from_config(&cfg.classes)?;
        let appearance = AppearanceModel::load(&cfg.appearance, &cfg.models)?.map(Arc::new);
        let segmenter = match &cfg.models.segmenter_onnx {
            Some(path) => Some(Arc::new(crate::segmentation::Segmenter::load(path, &cfg.segmentation, &table, cfg.models.onnxruntime.as_deref())?)),
            None => None,
        };
        Ok(Encoder { used: table.used_mask(), ssim: SsimParams::new(&cfg.global), table, cfg: cfg.encoding(), appearance, codebook: None, segmenter })
    }
    /// An encoder for queries of `map`: `cfg`'s encoding must equal the map's, its keypoint
    /// network must be the one the map was built with, and the map's codebook is used.
    pub fn for_map(cfg: &Config, map: &crate::map::Map) -> Result<Encoder> {
        map.check_compatible(&cfg.encoding())?;
        let mut enc = Encoder::new(cfg)?;
        map.check_model(enc.appearance_model().map(|a| a.sha256.as_str()))?;
        if let Some(cb) = map.codebook() {
            enc.set_codebook(cb.clone());
        }
        Ok(enc)
    }

    /// The SHA-256 of the keypoint network and the codebook, for a new map.
    pub fn appearance_record(&self) -> Option<(&Codebook, &str)> {
        match (&self.appearance, &self.codebook) {
            (Some(a), Some(c)) => Some((c, a.sha256.as_str())),
            _ => None,
        }
    }

    pub fn config(&self) -> &EncodingConfig {
        &self.cfg
    }
    pub fn class_table(&self) -> &ClassTable {
        &self.table
    }
    pub fn ssim_params(&self) -> SsimParams {
        self.ssim
    }
    /// The classes that make edges (see `ClassTable::used_mask`).
    pub fn used_mask(&self) -> &[bool; 256] {
        &self.used
    }
    pub fn appearance_model(&self) -> Option<&AppearanceModel> {
        self.appearance.as_deref()
    }
    pub fn codebook(&self) -> Option<&Codebook> {
        self.codebook.as_deref()
    }
    pub fn set_codebook(&mut self, codebook: Codebook) {
        self.codebook = Some(Arc::new(codebook));
    }
    /// Length of the trees' appearance vectors: Kv x D with appearance, else 0.
    pub fn appearance_dim(&self) -> usize {
        match (&self.appearance, &self.codebook) {
            (Some(_), Some(c)) => c.k * c.dim,
            _ => 0,
        }
    }
    /// An empty descriptor set laid out for this encoder's images.
    pub fn descriptor_set(&self) -> crate::map::DescriptorSet {
        crate::map::DescriptorSet::new(&self.ssim, self.cfg.local.neighbours, self.appearance_dim())
    }

    /// Loads a frame: its label map (from file, or segmented from the image) and, when
    /// appearance is on, its RGB image.
    pub fn load(&self, src: &FrameSource, format: LabelFormat) -> Result<Loaded> {
        let t = Instant::now();
        let needs_rgb = self.appearance.is_some() || (src.labels.is_none() && self.segmenter.is_some());
        let rgb = match (&src.image, needs_rgb) {
            (Some(p), true) => Some(input::load_rgb(p)?),
            (None, true) if self.appearance.is_some() => {
                return Err(Error::invalid(
                    format!("frame {:?}", src.id),
                    "appearance needs the RGB image (pass --images), or turn appearance off (--no-appearance)",
                ))
            }
            _ => None,
        };
        let labels = match (&src.labels, &self.segmenter, &rgb) {
            (None, Some(seg), Some(img)) => seg.segment(img, src.image.as_deref().unwrap_or(std::path::Path::new(&src.id)))?,
            // the decoded image is compared below; no need to read its header again
            (Some(path), _, Some(_)) => input::load_label_map(path, &self.table, format)?,
            _ => input::load_frame_labels(src, &self.table, format)?,
        };
        if let Some(img) = &rgb {
            if (img.width(), img.height()) != (labels.width(), labels.height()) {
                return Err(Error::SizeMismatch {
                    image: src.image.clone().unwrap_or_default(),
                    labels: src.labels.clone().unwrap_or_default(),
                    image_size: (img.width(), img.height()),
                    label_size: (labels.width(), labels.height()),
                });
            }
        }
        Ok(Loaded { labels, rgb, load_ms: ms_since(t) })
    }

    /// Encodes a label map alone (no appearance: only for encoders with appearance off).
    pub fn encode_labels(&self, id: &str, labels: &LabelMap, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        if self.appearance.is_some() {
            return Err(Error::invalid(format!("frame {id:?}"), "appearance is on, so the RGB image is needed: use encode_loaded"));
        }
        let loaded = Loaded { labels: labels.clone(), rgb: None, load_ms: 0.0 };
        self.encode_loaded(id, &loaded, scratch)
    }

    /// Encodes a loaded frame on the CPU: every stage.
    pub fn encode_loaded(&self, id: &str, loaded: &Loaded, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let mut global = vec![0.0; self.ssim.len()];
        let mut stats = vec![0.0; self.ssim.stats_len()];
        global::encode_global(&loaded.labels, &self.used, &self.cfg.global, scratch, &mut global, &mut stats)?;
        let pending = self.encode_rest(id, loaded, global, Some(stats), ms_since(t))?;
        Ok(self.finish_on_cpu(pending))
    }

    /// Loads and encodes one frame on the CPU.
    pub fn encode_source(&self, src: &FrameSource, format: LabelFormat, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let loaded = self.load(src, format)?;
        self.encode_loaded(&src.id, &loaded, scratch)
    }

    /// Everything after the global descriptor (pooled here or on the GPU; its stats are computed
    /// if not given): objects, forest, and the appearance network; VLAD is left to the caller.
    pub fn encode_rest(&self, id: &str, loaded: &Loaded, global: Vec<f32>, stats: Option<Vec<f32>>, global_ms: f64) -> Result<Pending> {
        let t = Instant::now();
        let global_stats = stats.unwrap_or_else(|| {
            let mut s = vec![0.0; self.ssim.stats_len()];
            global::ssim::ssim_stats(&self.ssim, &global, &mut s, &mut Default::default());
            s
        });
        let global_ms = global_ms + ms_since(t);
        let t = Instant::now();
        let objects = objects::extract_objects(&loaded.labels, &self.table, &self.cfg.objects);
        let forest = local::build_forest(&objects, &self.cfg.local);
        let forest_ms = ms_since(t);
        let mut times = StageTimes { load_ms: loaded.load_ms, global_ms, forest_ms, ..Default::default() };
        let vlad = match (&self.appearance, &loaded.rgb) {
            (Some(model), Some(rgb)) => {
                let codebook = self.codebook.as_ref().ok_or_else(|| Error::invalid("encoder", "appearance is on but no VLAD codebook is set (train one, or open a map that has one)"))?;
                let t = Instant::now();
                let (k, network_ms) = model.keypoints_timed(rgb)?;
                times.network_ms = network_ms;
                if k.dim != codebook.dim {
                    return Err(Error::Model { path: model.path.clone(), reason: format!("descriptors have {} values, the codebook {}", k.dim, codebook.dim) });
                }
                let (descriptors, offsets) = appearance::group_by_object(&k, &objects);
                times.appearance_ms = ms_since(t);
                Some(VladInput { descriptors, offsets })
            }
            (Some(_), None) => return Err(Error::invalid(format!("frame {id:?}"), "appearance needs the RGB image")),
            _ => None,
        };
        let image = EncodedImage { id: id.to_string(), width: loaded.labels.width(), height: loaded.labels.height(), global, global_stats, forest };
        Ok(Pending { image, times, vlad })
    }

    /// Completes a pending frame with its VLAD vectors (computed by `vlad_cpu` or on the GPU).
    pub fn finish(&self, mut p: Pending, vlad: Option<(Vec<f32>, Vec<u8>)>, vlad_ms: f64) -> (EncodedImage, StageTimes) {
        if let Some((vectors, present)) = vlad {
            p.image.forest.set_appearance(self.appearance_dim(), vectors, present);
            p.times.appearance_ms += vlad_ms;
        }
        (p.image, p.times)
    }

    /// VLAD of a pending frame's objects on the CPU (the twins of the GPU kernels).
    pub fn vlad_cpu(&self, input: &VladInput) -> (Vec<f32>, Vec<u8>) {
        let cb = self.codebook.as_ref().expect("codebook set when there is VLAD input");
        appearance::object_vlad(&input.descriptors, &input.offsets, cb, self.cfg.appearance.power_norm)
    }

    fn finish_on_cpu(&self, p: Pending) -> (EncodedImage, StageTimes) {
        let t = Instant::now();
        let vlad = p.vlad.as_ref().map(|v| self.vlad_cpu(v));
        let ms = ms_since(t);
        self.finish(p, vlad, ms)
    }

    /// Encodes many frames in parallel, in order; `tick` is called once per finished frame.
    pub fn encode_all(&self, sources: &[FrameSource], format: LabelFormat, tick: &(dyn Fn() + Sync)) -> Vec<Result<(EncodedImage, StageTimes)>> {
        sources
            .par_iter()
            .map_init(GlobalScratch::default, |scratch, src| {
                let r = self.encode_source(src, format, scratch);
                tick();
                r
            })
            .collect()
    }

    /// Trains the VLAD codebook on descriptors of up to `appearance.codebook_images` frames
    /// spread evenly over `sources` (the map's references), and sets it.
    pub fn train_codebook(&mut self, sources: &[FrameSource], tick: &(dyn Fn() + Sync)) -> Result<()> {
        let Some(model) = self.appearance.clone() else { return Ok(()) };
        let a = &self.cfg.appearance;
        let n = a.codebook_images.min(sources.len());
        if n == 0 {
            return Err(Error::invalid("codebook", "no reference images to train it on"));
        }
        let picks: Vec<&FrameSource> = (0..n).map(|i| &sources[i * sources.len() / n]).collect();
        let per_image = a.codebook_samples_per_image;
        let samples: Vec<(usize, Vec<f32>)> = picks
            .par_iter()
            .map(|src| {
                let path = src.image.as_ref().ok_or_else(|| Error::invalid(format!("frame {:?}", src.id), "appearance needs the RGB image"))?;
                let k = model.keypoints(&input::load_rgb(path)?)?;
                tick();
                Ok((k.dim, appearance::sample_descriptors(&k, per_image)))
            })
            .collect::<Result<_>>()?;
        let dim = samples[0].0;
        let all: Vec<f32> = samples.into_iter().flat_map(|s| s.1).collect();
        let cb = appearance::vlad::train_codebook(&all, dim, a.vlad_centres, a.codebook_iterations, a.codebook_seed)
            .map_err(|r| Error::invalid("codebook", format!("{r} (too few keypoints in the reference images)")))?;
        self.set_codebook(cb);
        Ok(())
    }
}

/// Splits encoding results into successes and errors; with `skip_invalid` false, the first error
/// (in input order) is returned instead.
pub fn collect_encoded(results: Vec<Result<(EncodedImage, StageTimes)>>, skip_invalid: bool) -> Result<(Vec<EncodedImage>, StageTimes, Vec<Error>)> {
    let mut images = Vec::with_capacity(results.len());
    let mut total = StageTimes::default();
    let mut skipped = Vec::new();
    for r in results {
        match r {
            Ok((img, t)) => {
                images.push(img);
                total += t;
            }
            Err(e) if skip_invalid => skipped.push(e),
            Err(e) => return Err(e),
        }
    }
    Ok((images, total, skipped))
}
