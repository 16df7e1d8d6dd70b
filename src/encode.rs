//! Encoding: one frame (label map, and RGB pixels when appearance is on) to its global
//! descriptor and its forest, timing each stage as the paper's Table 2 splits them:
//! "edge (coarse)" = global descriptor, "forest" = objects and trees, "appearance" = keypoint
//! network and per-object VLAD.

use crate::appearance::{
    self,
    keypoints::Keypoints,
    vlad::{Codebook, VladNorm},
    AppearanceModel, Features,
};
use crate::classes::ClassTable;
use crate::config::{Config, EncodingConfig};
use crate::error::{Error, Result};
use crate::global::{self, GlobalScratch};
use crate::input::{self, FrameSource, LabelFormat, LabelMap};
use crate::kernels::{self, abi::SsimParams};
use crate::local;
use crate::objects;
use crate::util::ms_since;
use image::RgbImage;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;

pub use crate::descriptors::EncodedImage;

/// Milliseconds spent per stage on one image.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Reading and decoding the input files, and bringing them to the working size.
    pub decode_ms: f64,
    /// The segmentation network (frames without a label map).
    pub segment_ms: f64,
    /// "Edge (coarse)": edges, distance transform, pooling, SSIM stats.
    pub global_ms: f64,
    /// "Forest": objects, trees and neighbours.
    pub forest_ms: f64,
    /// Appearance: keypoint network, decoding and per-object VLAD.
    pub appearance_ms: f64,
    /// Of `appearance_ms`, the network alone.
    pub network_ms: f64,
    /// The HOG baseline descriptor.
    pub hog_ms: f64,
}

impl StageTimes {
    /// Encoding as the paper counts it: descriptors only (no decoding, segmentation, baselines).
    pub fn encode_ms(&self) -> f64 {
        self.global_ms + self.forest_ms + self.appearance_ms
    }
    /// Everything but the segmentation network.
    pub fn without_segmentation_ms(&self) -> f64 {
        self.decode_ms + self.encode_ms()
    }
    /// Each field of `self` through `f` with the same field of `o`.
    fn zip(self, o: StageTimes, f: impl Fn(f64, f64) -> f64) -> StageTimes {
        StageTimes {
            decode_ms: f(self.decode_ms, o.decode_ms),
            segment_ms: f(self.segment_ms, o.segment_ms),
            global_ms: f(self.global_ms, o.global_ms),
            forest_ms: f(self.forest_ms, o.forest_ms),
            appearance_ms: f(self.appearance_ms, o.appearance_ms),
            network_ms: f(self.network_ms, o.network_ms),
            hog_ms: f(self.hog_ms, o.hog_ms),
        }
    }
    pub fn scaled(self, by: f64) -> StageTimes {
        self.zip(self, |a, _| a * by)
    }
    /// Per-field medians of `times`.
    pub fn median(times: &[StageTimes]) -> StageTimes {
        let pick = |f: fn(&StageTimes) -> f64| -> f64 {
            let mut v: Vec<f64> = times.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            match v.len() {
                0 => 0.0,
                n if n % 2 == 1 => v[n / 2],
                n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
            }
        };
        StageTimes {
            decode_ms: pick(|t| t.decode_ms),
            segment_ms: pick(|t| t.segment_ms),
            global_ms: pick(|t| t.global_ms),
            forest_ms: pick(|t| t.forest_ms),
            appearance_ms: pick(|t| t.appearance_ms),
            network_ms: pick(|t| t.network_ms),
            hog_ms: pick(|t| t.hog_ms),
        }
    }
}

impl std::ops::AddAssign for StageTimes {
    fn add_assign(&mut self, o: StageTimes) {
        *self = self.zip(o, |a, b| a + b);
    }
}

/// A frame's decoded inputs, at the working size.
#[derive(Debug, Clone)]
pub struct Loaded {
    pub labels: LabelMap,
    pub rgb: Option<RgbImage>,
    /// Size of the source image.
    pub source_size: (u32, u32),
    pub hog: Option<Vec<f32>>,
    pub times: StageTimes,
}

/// Appearance descriptors of one frame sorted by object, with each object's run, and last a run
/// of all the frame's descriptors (for the whole-image VLAD): what the VLAD kernels take.
#[derive(Debug, Clone, Default)]
pub struct VladInput {
    pub descriptors: Vec<f32>,
    /// objects + 2 entries: object o owns offsets[o]..offsets[o + 1]; the last run is the image.
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
    segmenter: Option<Arc<LazySegmenter>>,
    /// Also compute the VPR-Bench HOG baseline descriptor.
    hog: bool,
    /// Encode frames that have no label map, when there is no segmenter, with a void one
    /// ([`Encoder::without_labels`]) instead of refusing them.
    void_labels: bool,
}

/// A segmenter loaded on first use: encoding label maps never needs ONNX Runtime.
struct LazySegmenter {
    path: std::path::PathBuf,
    cfg: crate::config::SegmentationConfig,
    table: ClassTable,
    onnxruntime: Option<std::path::PathBuf>,
    loaded: std::sync::OnceLock<std::result::Result<crate::segmentation::Segmenter, String>>,
}

impl std::fmt::Debug for LazySegmenter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Segmenter({})", self.path.display())
    }
}

impl LazySegmenter {
    fn get(&self) -> Result<&crate::segmentation::Segmenter> {
        self.loaded
            .get_or_init(|| {
                crate::segmentation::Segmenter::load(&self.path, &self.cfg, &self.table, self.onnxruntime.as_deref()).map_err(|e| e.to_string())
            })
            .as_ref()
            .map_err(|reason| Error::Model { path: self.path.clone(), reason: reason.clone() })
    }
}

/// The segmenter `cfg` names, else the default one when it is installed; `None`: frames without
/// label maps cannot be segmented.
pub fn segmenter_path(cfg: &Config) -> Result<Option<std::path::PathBuf>> {
    Ok(match &cfg.models.segmenter_onnx {
        Some(p) => Some(crate::onnx::find_model(crate::segmentation::DEFAULT_SEGMENTER, Some(p), "segmenter")?),
        None if cfg.models.default_segmenter => crate::onnx::find_model(crate::segmentation::DEFAULT_SEGMENTER, None, "segmenter").ok(),
        None => None,
    })
}

impl Encoder {
    /// An encoder for `cfg`: loads the keypoint network (and segmenter) the config names.
    pub fn new(cfg: &Config) -> Result<Encoder> {
        let table = ClassTable::from_config(&cfg.classes)?;
        let appearance = AppearanceModel::load(&cfg.appearance, &cfg.models)?.map(|m| Arc::new(m.with_detection(&cfg.keypoints)));
        let segmenter = segmenter_path(cfg)?.map(|path| {
            Arc::new(LazySegmenter {
                path,
                cfg: cfg.segmentation.clone(),
                table: table.clone(),
                onnxruntime: cfg.models.onnxruntime.clone(),
                loaded: Default::default(),
            })
        });
        Ok(Encoder {
            used: table.used_mask(),
            ssim: SsimParams::new(&cfg.global),
            table,
            cfg: cfg.encoding(),
            appearance,
            codebook: None,
            segmenter,
            hog: false,
            void_labels: false,
        })
    }
    /// Whether the encoder also computes the HOG baseline (VPR-Bench's, [`crate::baseline`]).
    pub fn with_hog(mut self, hog: bool) -> Encoder {
        self.hog = hog;
        self
    }
    pub fn computes_hog(&self) -> bool {
        self.hog
    }
    /// With `on`, a frame with neither a label map nor a segmenter to make one is encoded with a
    /// void label map: no edges, no objects, a global descriptor the same for every frame. Only
    /// the settings that need no labels ([`crate::matching::Setting::label_free`]) may then be
    /// matched; the caller skips the others.
    pub fn without_labels(mut self, on: bool) -> Encoder {
        self.void_labels = on;
        self
    }
    /// Whether a segmenter makes the label maps of frames that have none.
    pub fn has_segmenter(&self) -> bool {
        self.segmenter.is_some()
    }
    /// The segmentation network (loaded now if it was not yet); `image` names the frame in
    /// the error when there is none.
    pub fn segmenter_for(&self, image: &std::path::Path) -> Result<&crate::segmentation::Segmenter> {
        match &self.segmenter {
            Some(s) => s.get(),
            None => Err(Error::NoLabels { image: image.to_path_buf() }),
        }
    }

    /// The segmentation network, once a frame without a label map was segmented.
    pub fn segmenter(&self) -> Option<&crate::segmentation::Segmenter> {
        self.segmenter.as_ref().and_then(|s| s.loaded.get()).and_then(|r| r.as_ref().ok())
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
    pub fn descriptor_set(&self) -> crate::descriptors::DescriptorSet {
        let hog = if self.hog { crate::baseline::HOG_DIM } else { 0 };
        let codebook = self.codebook.as_ref().filter(|_| self.appearance_dim() > 0).and_then(|c| c.sha256().ok());
        crate::descriptors::DescriptorSet::new(&self.ssim, self.cfg.local.neighbours, self.appearance_dim(), hog)
            .with_keypoint_dim(self.keypoint_dim())
            .with_codebook(codebook)
    }

    /// Values per stored verification keypoint descriptor: the network's descriptor width when
    /// keypoints are stored, else 0.
    pub fn keypoint_dim(&self) -> usize {
        match (&self.appearance, &self.codebook) {
            (Some(a), Some(c)) if a.detects() => c.dim,
            _ => 0,
        }
    }

    /// Loads a frame at the working size: its label map (from file, or segmented from the
    /// image), and the RGB image when appearance is on; the HOG baseline from the full image.
    ///
    /// HOG gets a full-size decode of its own: the encoding's pixels come from the same (often
    /// scaled JPEG) decode whether or not HOG is computed too, so a setting's results do not
    /// depend on the other settings of an evaluation run.
    pub fn load(&self, src: &FrameSource, format: LabelFormat) -> Result<Loaded> {
        let mut times = StageTimes::default();
        let t = Instant::now();
        let segment = src.labels.is_none() && self.segmenter.is_some();
        let needs_rgb = self.appearance.is_some() || segment;
        let needed = |full: (u32, u32)| self.decoded_size(full, segment);
        let (rgb, hog_rgb, decoded_size) = match (&src.image, needs_rgb || self.hog) {
            (Some(p), true) => {
                let bytes = std::fs::read(p).map_err(|e| Error::io(p, e))?;
                let (hog_bytes, rgb_bytes) = match (self.hog, needs_rgb) {
                    (true, true) => (Some(bytes.clone()), Some(bytes)),
                    (true, false) => (Some(bytes), None),
                    (false, _) => (None, Some(bytes)),
                };
                // VPR-Bench's HOG resizes the full image
                let hog_rgb = hog_bytes.map(|b| input::decode_rgb_at_least(b, p, |full| full)).transpose()?;
                let rgb = rgb_bytes.map(|b| input::decode_rgb_at_least(b, p, needed)).transpose()?;
                let full = rgb.as_ref().or(hog_rgb.as_ref()).map(|r| r.1);
                (rgb.map(|r| r.0), hog_rgb.map(|r| r.0), full)
            }
            (None, true) => {
                return Err(Error::refused(
                    format!("frame {:?}", src.id),
                    "appearance, segmentation and HOG need the RGB image",
                    crate::error::Remedy::GiveImagesOrNoAppearance,
                ))
            }
            _ => (None, None, None),
        };
        times.decode_ms = ms_since(t);
        let full_labels = match (&src.labels, &self.segmenter, &rgb) {
            (None, Some(_), Some(_)) => None,
            (None, None, Some(_)) if self.void_labels => None,
            // the decoded image is compared below; no need to read its header again
            (Some(path), _, Some(_)) => Some(input::load_label_map(path, &self.table, format)?),
            _ => Some(input::load_frame_labels(src, &self.table, format)?),
        };
        self.load_decoded(&src.id, src.image.as_deref(), src.labels.as_deref(), rgb, hog_rgb, decoded_size, full_labels, times)
    }

    /// The smallest size a frame of size `full` is decoded at (JPEGs by a scaled DCT): the
    /// working size, and the segmenter's input when the frame is segmented.
    fn decoded_size(&self, full: (u32, u32), segment: bool) -> (u32, u32) {
        let (w, h) = input::working_size(full.0, full.1, self.cfg.input.working_long_side);
        let seg = &self.cfg.segmentation;
        match segment {
            // the segmenter resizes to its input; 10 % short of it costs nothing visible
            true => (w.max((seg.input_width as f64 * 0.9) as u32), h.max((seg.input_height as f64 * 0.9) as u32)),
            false => (w, h),
        }
    }

    /// The RGB pixels the keypoint network sees for `src`: decoded as [`Encoder::load`] decodes
    /// them (so a codebook is trained on the very pixels frames are encoded from), at the working
    /// size.
    pub fn working_rgb(&self, src: &FrameSource) -> Result<RgbImage> {
        let path = src.image.as_ref().ok_or_else(|| Error::invalid(format!("frame {:?}", src.id), "appearance needs the RGB image"))?;
        let segment = src.labels.is_none() && self.segmenter.is_some();
        let (rgb, full) = input::load_rgb_at_least(path, |full| self.decoded_size(full, segment))?;
        let (w, h) = input::working_size(full.0, full.1, self.cfg.input.working_long_side);
        Ok(input::resize_rgb(&rgb, w, h))
    }

    /// [`Encoder::load`] for frames already in memory: the RGB image (needed by appearance,
    /// segmentation and HOG) and the label map at the image's size (needed unless a segmenter is
    /// configured), both at full size.
    pub fn load_arrays(&self, id: &str, rgb: Option<RgbImage>, labels: Option<LabelMap>) -> Result<Loaded> {
        let needs_rgb = self.appearance.is_some() || (labels.is_none() && self.segmenter.is_some()) || self.hog;
        if needs_rgb && rgb.is_none() {
            return Err(Error::invalid(format!("frame {id:?}"), "appearance, segmentation and HOG need the RGB image, or turn appearance off"));
        }
        if let Some(img) = rgb.as_ref().filter(|i| i.width() == 0 || i.height() == 0) {
            return Err(Error::invalid(format!("frame {id:?}"), format!("empty image {}x{}", img.width(), img.height())));
        }
        let size = rgb.as_ref().map(|i| i.dimensions());
        let rgb = rgb.filter(|_| needs_rgb);
        self.load_decoded(id, None, None, rgb, None, size, labels, StageTimes::default())
    }

    /// The part of loading after decoding: sizes checked, labels at the working size (segmented
    /// when not given), HOG from the full image (`hog_rgb`, else `rgb`), RGB at the working size.
    /// The paths only name the inputs in errors.
    #[allow(clippy::too_many_arguments)]
    fn load_decoded(
        &self,
        id: &str,
        image: Option<&std::path::Path>,
        label_path: Option<&std::path::Path>,
        rgb: Option<RgbImage>,
        hog_rgb: Option<RgbImage>,
        decoded_size: Option<(u32, u32)>,
        full_labels: Option<LabelMap>,
        mut times: StageTimes,
    ) -> Result<Loaded> {
        let source_size = match (decoded_size, &full_labels) {
            (Some(size), _) => size,
            (None, Some(l)) => (l.width(), l.height()),
            (None, None) => return Err(Error::invalid(format!("frame {id:?}"), "neither image nor label map")),
        };
        if let (Some(size), Some(l)) = (decoded_size, &full_labels) {
            if size != (l.width(), l.height()) {
                return Err(Error::SizeMismatch {
                    image: image.map_or_else(|| format!("{id} (image)").into(), Into::into),
                    labels: label_path.map_or_else(|| format!("{id} (labels)").into(), Into::into),
                    image_size: size,
                    label_size: (l.width(), l.height()),
                });
            }
        }
        let (ww, wh) = input::working_size(source_size.0, source_size.1, self.cfg.input.working_long_side);
        if self.appearance.is_some() && (ww < appearance::MIN_NETWORK_SIDE as u32 || wh < appearance::MIN_NETWORK_SIDE as u32) {
            let what = image.map_or_else(|| format!("frame {id:?}"), |p| p.display().to_string());
            let m = appearance::MIN_NETWORK_SIDE;
            return Err(Error::invalid(
                what,
                format!("{}x{} (working size {ww}x{wh}) is below the {m}x{m} a keypoint network needs", source_size.0, source_size.1),
            ));
        }
        let labels = match (full_labels, &self.segmenter, &rgb) {
            (Some(l), _, _) => l.resized_nearest(ww, wh),
            (None, Some(seg), Some(img)) => {
                let t = Instant::now();
                let l = seg.get()?.segment_to(img, image.unwrap_or(std::path::Path::new(id)), (ww, wh))?;
                times.segment_ms = ms_since(t);
                l
            }
            (None, None, Some(_)) if self.void_labels => LabelMap::void(ww, wh),
            _ => return Err(Error::invalid(format!("frame {id:?}"), "no label map")),
        };
        let hog = match (hog_rgb.as_ref().or(rgb.as_ref()), self.hog) {
            (Some(img), true) => {
                let t = Instant::now();
                let h = crate::baseline::vprbench_hog(img);
                times.hog_ms = ms_since(t);
                Some(h)
            }
            _ => None,
        };
        let t = Instant::now();
        let rgb = match rgb {
            Some(img) if self.appearance.is_some() => Some(input::resize_rgb(&img, ww, wh)),
            _ => None,
        };
        times.decode_ms += ms_since(t);
        Ok(Loaded { labels, rgb, source_size, hog, times })
    }

    /// Encodes a label map alone (no appearance: only for encoders with appearance off).
    pub fn encode_labels(&self, id: &str, labels: &LabelMap, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        if self.appearance.is_some() {
            return Err(Error::invalid(format!("frame {id:?}"), "appearance is on, so the RGB image is needed: use encode_loaded"));
        }
        let loaded =
            Loaded { labels: labels.clone(), rgb: None, source_size: (labels.width(), labels.height()), hog: None, times: StageTimes::default() };
        self.encode_loaded(id, &loaded, scratch)
    }

    /// Encodes a loaded frame on the CPU: every stage.
    pub fn encode_loaded(&self, id: &str, loaded: &Loaded, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        self.encode_loaded_with(id, loaded, None, scratch)
    }

    /// [`Encoder::encode_loaded`] with the keypoint network's output given.
    pub fn encode_loaded_with(
        &self,
        id: &str,
        loaded: &Loaded,
        keypoints: Option<&Features>,
        scratch: &mut GlobalScratch,
    ) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let mut global = vec![0.0; self.ssim.len()];
        let mut stats = vec![0.0; self.ssim.stats_len()];
        global::encode_global(&loaded.labels, &self.used, &self.cfg.global, scratch, &mut global, &mut stats)?;
        let pending = self.encode_rest_with(id, loaded, global, Some(stats), ms_since(t), keypoints)?;
        self.finish_on_cpu(pending)
    }

    /// Loads and encodes one frame on the CPU.
    pub fn encode_source(&self, src: &FrameSource, format: LabelFormat, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let loaded = self.load(src, format)?;
        self.encode_loaded(&src.id, &loaded, scratch)
    }

    /// Everything after the global descriptor (pooled here or on the GPU; its stats are computed
    /// if not given): objects, forest, and the appearance network; VLAD is left to the caller.
    pub fn encode_rest(&self, id: &str, loaded: &Loaded, global: Vec<f32>, stats: Option<Vec<f32>>, global_ms: f64) -> Result<Pending> {
        self.encode_rest_with(id, loaded, global, stats, global_ms, None)
    }

    /// [`Encoder::encode_rest`] with the keypoint network's output given (cached by a caller that
    /// encodes the same frames with several configurations, such as `tune`).
    pub fn encode_rest_with(
        &self,
        id: &str,
        loaded: &Loaded,
        global: Vec<f32>,
        stats: Option<Vec<f32>>,
        global_ms: f64,
        keypoints: Option<&Features>,
    ) -> Result<Pending> {
        let t = Instant::now();
        let global_stats = stats.unwrap_or_else(|| {
            let mut s = vec![0.0; self.ssim.stats_len()];
            kernels::ssim::ssim_stats(&self.ssim, &global, &mut s, &mut Default::default());
            s
        });
        let global_ms = global_ms + ms_since(t);
        let t = Instant::now();
        let objects = objects::extract_objects(&loaded.labels, &self.table, &self.cfg.objects);
        let forest = local::build_forest(&objects, &self.cfg.local);
        let forest_ms = ms_since(t);
        let mut times = StageTimes { global_ms, forest_ms, ..loaded.times };
        let mut verification = crate::descriptors::keypoints::ImageKeypoints::default();
        let vlad = match (&self.appearance, &loaded.rgb) {
            (Some(model), Some(rgb)) => {
                let codebook = self.codebook.as_ref().ok_or_else(|| {
                    Error::invalid("encoder", "appearance is on but no VLAD codebook is set (train one, or open a map that has one)")
                })?;
                let t = Instant::now();
                let computed;
                let f = match keypoints {
                    Some(f) => f,
                    None => {
                        computed = model.features(rgb)?;
                        times.network_ms = computed.network_ms;
                        &computed
                    }
                };
                let k = &f.sampled;
                if k.dim != codebook.dim {
                    return Err(Error::Model {
                        path: model.path.clone(),
                        reason: format!("descriptors have {} values, the codebook {}", k.dim, codebook.dim),
                    });
                }
                if let Some(d) = &f.detected {
                    let long = loaded.labels.width().max(loaded.labels.height());
                    verification = crate::appearance::verification_keypoints(d, self.cfg.keypoints.stored, &loaded.labels, long);
                }
                let (mut descriptors, mut offsets) = appearance::group_by_object(k, &objects);
                // the last run: every descriptor of the image
                descriptors.extend_from_slice(&k.descriptors);
                offsets.push(offsets.last().copied().unwrap_or(0) + k.len() as u32);
                times.appearance_ms = ms_since(t);
                Some(VladInput { descriptors, offsets })
            }
            (Some(_), None) => return Err(Error::invalid(format!("frame {id:?}"), "appearance needs the RGB image")),
            _ => None,
        };
        let (width, height) = loaded.source_size;
        let hog = loaded.hog.clone().unwrap_or_default();
        let image =
            EncodedImage { id: id.to_string(), width, height, global, global_stats, forest, appearance: vec![], hog, keypoints: verification };
        Ok(Pending { image, times, vlad })
    }

    /// Completes a pending frame with its VLAD vectors (computed by `vlad_cpu` or on the GPU:
    /// one vector of the encoder's appearance size per run of its [`VladInput`], the image's
    /// last); other counts fail, naming the image.
    pub fn finish(&self, mut p: Pending, vlad: Option<Vec<f32>>, vlad_ms: f64) -> Result<(EncodedImage, StageTimes)> {
        if let (Some(mut vectors), Some(input)) = (vlad, &p.vlad) {
            let dim = self.appearance_dim();
            let bad = |r: String| Error::invalid(format!("VLAD vectors of image {:?}", p.image.id), r);
            if vectors.len() != dim * input.offsets.len().saturating_sub(1) {
                return Err(bad(format!("{} values for {} runs of dimension {dim}", vectors.len(), input.offsets.len().saturating_sub(1))));
            }
            // the values a map stores (int8 blocks, one per centre): a stored image reads back the same
            if let Some(cb) = &self.codebook {
                crate::values::round_to_blocks(&mut vectors, cb.dim);
            }
            let image = vectors.split_off(vectors.len() - dim);
            let mut counts = appearance::object_counts(&input.offsets);
            counts.pop();
            p.image.forest.set_appearance(dim, vectors, counts, self.cfg.appearance.min_descriptors).map_err(bad)?;
            p.image.appearance = image;
            p.times.appearance_ms += vlad_ms;
        }
        Ok((p.image, p.times))
    }

    /// The VLAD normalisations of this encoder's config.
    pub fn vlad_norm(&self) -> VladNorm {
        VladNorm::from_config(&self.cfg.appearance)
    }

    /// VLAD of a pending frame's objects and of the whole image on the CPU (the twins of the GPU
    /// kernels).
    pub fn vlad_cpu(&self, input: &VladInput) -> Result<Vec<f32>> {
        let cb = self.codebook.as_ref().ok_or_else(|| Error::invalid("encoder", "VLAD input without a codebook"))?;
        appearance::check_vlad_input(&input.descriptors, &input.offsets, cb).map_err(|r| Error::invalid("VLAD input", r))?;
        Ok(appearance::object_vlad(&input.descriptors, &input.offsets, cb, self.vlad_norm()))
    }

    fn finish_on_cpu(&self, p: Pending) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let vlad = p.vlad.as_ref().map(|v| self.vlad_cpu(v)).transpose()?;
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

    /// Indices of the reference frames the codebook is trained on: up to
    /// `appearance.codebook_images`, spread evenly over `n` frames.
    pub fn codebook_picks(&self, n: usize) -> Vec<usize> {
        let m = self.cfg.appearance.codebook_images.min(n);
        (0..m).map(|i| i * n / m).collect()
    }

    /// Trains the VLAD codebook on the keypoints of the picked reference frames (see
    /// [`Encoder::codebook_picks`]) and sets it.
    pub fn train_codebook_from(&mut self, keypoints: &[&Keypoints]) -> Result<()> {
        let a = &self.cfg.appearance;
        let dim = keypoints.first().map(|k| k.dim).ok_or_else(|| Error::invalid("codebook", "no reference images to train it on"))?;
        let all: Vec<f32> = keypoints.iter().flat_map(|k| appearance::sample_descriptors(k, a.codebook_samples_per_image)).collect();
        let cb = appearance::vlad::train_codebook(&all, dim, a.vlad_centres, a.codebook_iterations, a.codebook_seed)
            .map_err(|r| Error::invalid("codebook", format!("{r} (too few keypoints in the reference images)")))?;
        self.set_codebook(cb);
        Ok(())
    }

    /// Trains the VLAD codebook on descriptors of up to `appearance.codebook_images` frames
    /// spread evenly over `sources` (the map's references), and sets it.
    pub fn train_codebook(&mut self, sources: &[FrameSource], tick: &(dyn Fn() + Sync)) -> Result<()> {
        self.train_codebook_skipping(sources, false, tick).map(|_| ())
    }

    /// [`Encoder::train_codebook`]; with `skip_invalid`, frames that cannot be read are left out
    /// and returned (index in `sources`, error) instead of ending the training.
    pub fn train_codebook_skipping(&mut self, sources: &[FrameSource], skip_invalid: bool, tick: &(dyn Fn() + Sync)) -> Result<Vec<(usize, Error)>> {
        let Some(model) = self.appearance.clone() else { return Ok(vec![]) };
        let picks = self.codebook_picks(sources.len());
        let results: Vec<Result<Keypoints>> = picks
            .par_iter()
            .map(|&i| {
                let k = self.working_rgb(&sources[i]).and_then(|rgb| model.keypoints(&rgb));
                tick();
                k
            })
            .collect();
        let (mut keypoints, mut skipped) = (Vec::new(), Vec::new());
        for (&i, r) in picks.iter().zip(results) {
            match r {
                Ok(k) => keypoints.push(k),
                Err(e) if skip_invalid => skipped.push((i, e)),
                Err(e) => return Err(e),
            }
        }
        self.train_codebook_from(&keypoints.iter().collect::<Vec<_>>())?;
        Ok(skipped)
    }
}

/// Splits encoding results into successes and errors; with `skip_invalid` false, the first error
/// (in input order) is returned instead.
pub fn collect_encoded(
    results: Vec<Result<(EncodedImage, StageTimes)>>,
    skip_invalid: bool,
) -> Result<(Vec<EncodedImage>, Vec<StageTimes>, Vec<(usize, Error)>)> {
    let mut images = Vec::with_capacity(results.len());
    let mut total = Vec::with_capacity(results.len());
    let mut skipped = Vec::new();
    for (i, r) in results.into_iter().enumerate() {
        match r {
            Ok((img, t)) => {
                images.push(img);
                total.push(t);
            }
            Err(e) if skip_invalid => skipped.push((i, e)),
            Err(e) => return Err(e),
        }
    }
    Ok((images, total, skipped))
}
