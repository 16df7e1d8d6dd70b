//! What loads a frame: its files read and decoded (JPEGs by a scaled DCT, no larger than the
//! working size needs), the label map read or made by the segmenter, everything brought to the
//! working size, and the HOG baseline from the full image. Errors name the file.

use super::times::StageTimes;
use crate::classes::ClassTable;
use crate::config::{Config, SegmentationConfig};
use crate::error::{Error, Remedy, Result};
use crate::input::{self, FrameSource, LabelFormat, LabelMap};
use crate::networks::segmenter::Segmenter;
use crate::util::ms_since;
use image::RgbImage;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::Instant;

/// A frame's decoded inputs, at the working size.
#[derive(Debug, Clone)]
pub struct Loaded {
    /// The label map (given, or made by the segmenter) at the working size.
    pub labels: LabelMap,
    /// The RGB image at the working size; only with appearance on and an image given.
    pub rgb: Option<RgbImage>,
    /// Size of the source image.
    pub source_size: (u32, u32),
    /// The HOG baseline descriptor of the full image; only when the encoder stores HOG and an
    /// image is given.
    pub hog: Option<Vec<f32>>,
    /// Times of the loading stages (decode, segmentation, HOG); the others are 0.
    pub times: StageTimes,
}

/// A segmenter loaded on first use: encoding label maps never needs ONNX Runtime.
struct LazySegmenter {
    path: PathBuf,
    cfg: SegmentationConfig,
    table: ClassTable,
    onnxruntime: Option<PathBuf>,
    loaded: std::sync::OnceLock<std::result::Result<Segmenter, String>>,
}

impl std::fmt::Debug for LazySegmenter {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Segmenter({})", self.path.display())
    }
}

/// Segmenter files whose warning (not the tested build: [`crate::models::segmenter_warning`])
/// this process has given: once per file, however many encoders load it.
static WARNED: std::sync::Mutex<Vec<PathBuf>> = std::sync::Mutex::new(Vec::new());

impl LazySegmenter {
    fn get(&self) -> Result<&Segmenter> {
        self.loaded
            .get_or_init(|| {
                // kept as the reason of the model error every later frame gets: a model error's
                // own reason, not its message (which names the model already)
                let s = Segmenter::load(&self.path, &self.cfg, &self.table, self.onnxruntime.as_deref()).map_err(|e| match e {
                    Error::Model { path, reason } if path == self.path => reason,
                    other => other.to_string(),
                })?;
                if let Some(w) = crate::models::segmenter_warning(s.path(), s.sha256()) {
                    let mut warned = WARNED.lock().unwrap_or_else(|e| e.into_inner());
                    if !warned.iter().any(|p| p == s.path()) {
                        warned.push(s.path().to_path_buf());
                        log::warn!("{w}");
                    }
                }
                Ok(s)
            })
            .as_ref()
            .map_err(|reason| Error::Model { path: self.path.clone(), reason: reason.clone() })
    }
}

/// The segmenter `cfg` names, else the default one when it is installed; `None`: frames without
/// label maps cannot be segmented.
pub fn segmenter_path(cfg: &Config) -> Result<Option<PathBuf>> {
    Ok(match &cfg.models.segmenter_onnx {
        Some(p) => Some(crate::nn::onnx::find_model(crate::networks::segmenter::DEFAULT_SEGMENTER, Some(p), "segmenter")?),
        None if cfg.models.default_segmenter => crate::nn::onnx::find_model(crate::networks::segmenter::DEFAULT_SEGMENTER, None, "segmenter").ok(),
        None => None,
    })
}

/// A frame decoded but not yet brought to the working size: what [`FrameLoader::load`] and
/// [`FrameLoader::load_arrays`] hand to the common rest of loading.
struct Decoded<'a> {
    id: &'a str,
    /// The files, only to name them in errors.
    image: Option<&'a Path>,
    labels_path: Option<&'a Path>,
    rgb: Option<RgbImage>,
    /// A full-size decode for HOG, where the encoding's decode is scaled down.
    hog_rgb: Option<RgbImage>,
    /// The source image's size (the decoded one for images given as pixels).
    size: Option<(u32, u32)>,
    /// The label map at the source size, unless the segmenter makes it.
    labels: Option<LabelMap>,
}

/// Loads frames for one configuration. Cheap to share between threads.
#[derive(Debug, Clone)]
pub struct FrameLoader {
    table: ClassTable,
    working_long_side: usize,
    segmentation: SegmentationConfig,
    segmenter: Option<Arc<LazySegmenter>>,
    /// The keypoint network runs, so frames need their pixels at the working size.
    appearance: bool,
    /// Also compute the VPR-Bench HOG baseline descriptor.
    pub(super) hog: bool,
    /// Give frames that have no label map, when there is no segmenter, a void one instead of
    /// refusing them (see `Encoder::without_labels`).
    pub(super) void_labels: bool,
    /// `semlook dev tune --label-cache DIR`: the segmenter's label maps kept in DIR, one PNG per
    /// distinct input, keyed by the SHA-256 of the segmenter file's digest, the segmentation
    /// config, the working size and the input's pixels (so nothing but the same network on the
    /// same pixels reads a file back).
    pub(super) label_cache: Option<PathBuf>,
}

impl FrameLoader {
    pub(super) fn new(cfg: &Config, table: &ClassTable, appearance: bool) -> Result<FrameLoader> {
        let segmenter = segmenter_path(cfg)?.map(|path| {
            Arc::new(LazySegmenter {
                path,
                cfg: cfg.segmentation.clone(),
                table: table.clone(),
                onnxruntime: cfg.models.onnxruntime.clone(),
                loaded: Default::default(),
            })
        });
        Ok(FrameLoader {
            table: table.clone(),
            working_long_side: cfg.input.working_long_side,
            segmentation: cfg.segmentation.clone(),
            segmenter,
            appearance,
            hog: false,
            void_labels: false,
            label_cache: None,
        })
    }

    /// No segmenter: frames without label maps stay without (a map built without labels).
    pub(super) fn drop_segmenter(&mut self) {
        self.segmenter = None;
    }

    /// Whether a segmenter makes the label maps of frames that have none.
    pub fn can_segment(&self) -> bool {
        self.segmenter.is_some()
    }

    /// The segmentation network (loaded now if it was not yet); `image` names the frame in
    /// the error when there is none.
    pub fn segmenter_for(&self, image: &Path) -> Result<&Segmenter> {
        match &self.segmenter {
            Some(s) => s.get(),
            None => Err(Error::NoLabels { image: image.to_path_buf() }),
        }
    }

    /// The segmentation network, once a frame without a label map was segmented.
    pub fn segmenter(&self) -> Option<&Segmenter> {
        self.segmenter.as_ref().and_then(|s| s.loaded.get()).and_then(|r| r.as_ref().ok())
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
        let needs_rgb = self.appearance || segment;
        let needed = |full: (u32, u32)| self.decoded_size(full, segment);
        let (rgb, hog_rgb, size) = match (&src.image, needs_rgb || self.hog) {
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
                    Remedy::GiveImagesOrNoAppearance,
                ))
            }
            _ => (None, None, None),
        };
        times.decode_ms = ms_since(t);
        let labels = match (&src.labels, &self.segmenter, &rgb) {
            (None, Some(_), Some(_)) => None,
            // no segmenter, and void labels asked for: whether or not the image was decoded (HOG
            // alone decodes it into `hog_rgb`)
            (None, None, _) if self.void_labels => None,
            // the decoded image is compared below; no need to read its header again
            (Some(path), _, Some(_)) => Some(input::load_label_map(path, &self.table, format)?),
            _ => Some(input::load_frame_labels(src, &self.table, format)?),
        };
        let frame = Decoded { id: &src.id, image: src.image.as_deref(), labels_path: src.labels.as_deref(), rgb, hog_rgb, size, labels };
        self.to_working_size(frame, times)
    }

    /// The smallest size a frame of size `full` is decoded at (JPEGs by a scaled DCT): the
    /// working size, and the segmenter's input when the frame is segmented.
    fn decoded_size(&self, full: (u32, u32), segment: bool) -> (u32, u32) {
        let (w, h) = input::working_size(full.0, full.1, self.working_long_side);
        let seg = &self.segmentation;
        match segment {
            // the segmenter resizes to its input; 10 % short of it costs nothing visible
            true => (w.max((seg.input_width as f64 * 0.9) as u32), h.max((seg.input_height as f64 * 0.9) as u32)),
            false => (w, h),
        }
    }

    /// The RGB pixels the keypoint network sees for `src`: decoded as [`FrameLoader::load`]
    /// decodes them (so a codebook is trained on the very pixels frames are encoded from), at
    /// the working size.
    pub fn working_rgb(&self, src: &FrameSource) -> Result<RgbImage> {
        let path = src.image.as_ref().ok_or_else(|| Error::invalid(format!("frame {:?}", src.id), "appearance needs the RGB image"))?;
        let segment = src.labels.is_none() && self.segmenter.is_some();
        let (rgb, full) = input::load_rgb_at_least(path, |full| self.decoded_size(full, segment))?;
        let (w, h) = input::working_size(full.0, full.1, self.working_long_side);
        Ok(input::resize_rgb(&rgb, w, h))
    }

    /// [`FrameLoader::load`] for frames already in memory: the RGB image (needed by appearance,
    /// segmentation and HOG) and the label map at the image's size (needed unless a segmenter is
    /// configured), both at full size.
    pub fn load_arrays(&self, id: &str, rgb: Option<RgbImage>, labels: Option<LabelMap>) -> Result<Loaded> {
        let needs_rgb = self.appearance || (labels.is_none() && self.segmenter.is_some()) || self.hog;
        if needs_rgb && rgb.is_none() {
            return Err(Error::refused(
                format!("frame {id:?}"),
                "appearance, segmentation and HOG need the RGB image",
                Remedy::GiveImagesOrNoAppearance,
            ));
        }
        if let Some(img) = rgb.as_ref().filter(|i| i.width() == 0 || i.height() == 0) {
            return Err(Error::invalid(format!("frame {id:?}"), format!("empty image {}x{}", img.width(), img.height())));
        }
        let size = rgb.as_ref().map(|i| i.dimensions());
        let rgb = rgb.filter(|_| needs_rgb);
        self.to_working_size(Decoded { id, image: None, labels_path: None, rgb, hog_rgb: None, size, labels }, StageTimes::default())
    }

    /// [`FrameLoader::load`] for an image file's bytes held in memory (a frame of a stream, a ROS
    /// `CompressedImage`): decoded no larger than the working size needs (JPEGs by a scaled DCT),
    /// `name` naming it in errors; `labels`, when given, at the image's full size.
    pub fn load_bytes(&self, id: &str, name: &Path, bytes: Vec<u8>, labels: Option<LabelMap>) -> Result<Loaded> {
        let mut times = StageTimes::default();
        let t = Instant::now();
        let segment = labels.is_none() && self.segmenter.is_some();
        // VPR-Bench's HOG resizes the full image
        let (rgb, full) = match self.hog {
            true => input::decode_rgb_at_least(bytes, name, |full| full)?,
            false => input::decode_rgb_at_least(bytes, name, |full| self.decoded_size(full, segment))?,
        };
        times.decode_ms = ms_since(t);
        let frame = Decoded { id, image: Some(name), labels_path: None, rgb: Some(rgb), hog_rgb: None, size: Some(full), labels };
        self.to_working_size(frame, times)
    }

    /// The part of loading after decoding: sizes checked, labels at the working size (segmented
    /// when not given), HOG from the full image (`hog_rgb`, else `rgb`), RGB at the working size.
    fn to_working_size(&self, f: Decoded, mut times: StageTimes) -> Result<Loaded> {
        let id = f.id;
        let source_size = match (f.size, &f.labels) {
            (Some(size), _) => size,
            (None, Some(l)) => (l.width(), l.height()),
            (None, None) => return Err(Error::invalid(format!("frame {id:?}"), "neither image nor label map")),
        };
        if let (Some(size), Some(l)) = (f.size, &f.labels) {
            if size != (l.width(), l.height()) {
                return Err(Error::SizeMismatch {
                    image: f.image.map_or_else(|| format!("{id} (image)").into(), Into::into),
                    labels: f.labels_path.map_or_else(|| format!("{id} (labels)").into(), Into::into),
                    image_size: size,
                    label_size: (l.width(), l.height()),
                });
            }
        }
        let (ww, wh) = input::working_size(source_size.0, source_size.1, self.working_long_side);
        if self.appearance && (ww < crate::networks::MIN_NETWORK_SIDE as u32 || wh < crate::networks::MIN_NETWORK_SIDE as u32) {
            let what = f.image.map_or_else(|| format!("frame {id:?}"), |p| p.display().to_string());
            let m = crate::networks::MIN_NETWORK_SIDE;
            return Err(Error::invalid(
                what,
                format!("{}x{} (working size {ww}x{wh}) is below the {m}x{m} a keypoint network needs", source_size.0, source_size.1),
            ));
        }
        let labels = match (f.labels, &self.segmenter, &f.rgb) {
            (Some(l), _, _) => l.resized_nearest(ww, wh),
            (None, Some(seg), Some(img)) => {
                let t = Instant::now();
                let name = f.image.unwrap_or(Path::new(id));
                let l = match &self.label_cache {
                    Some(dir) => cached_labels(dir, seg.get()?, &self.segmentation, img, name, (ww, wh))?,
                    None => seg.get()?.segment_to(img, name, (ww, wh))?,
                };
                times.segment_ms = ms_since(t);
                l
            }
            (None, None, _) if self.void_labels => LabelMap::void(ww, wh),
            (None, None, _) => return Err(Error::NoLabels { image: f.image.map_or_else(|| format!("frame {id:?}").into(), Into::into) }),
            _ => return Err(Error::invalid(format!("frame {id:?}"), "no label map")),
        };
        let hog = match (f.hog_rgb.as_ref().or(f.rgb.as_ref()), self.hog) {
            (Some(img), true) => {
                let t = Instant::now();
                let h = crate::global::hog::vprbench_hog(img);
                times.hog_ms = ms_since(t);
                Some(h)
            }
            _ => None,
        };
        let t = Instant::now();
        let rgb = match f.rgb {
            Some(img) if self.appearance => Some(input::resize_rgb(&img, ww, wh)),
            _ => None,
        };
        times.decode_ms += ms_since(t);
        Ok(Loaded { labels, rgb, source_size, hog, times })
    }
}

/// The label map `seg` makes of `img` at `size`, read from the cache folder `dir` where it was
/// made before (same segmenter file, segmentation config, size and pixels), else made and written
/// there (a temporary file renamed into place: a killed run leaves no partial entry).
fn cached_labels(dir: &Path, seg: &Segmenter, cfg: &SegmentationConfig, img: &RgbImage, name: &Path, size: (u32, u32)) -> Result<LabelMap> {
    use sha2::Digest;
    let mut h = sha2::Sha256::new();
    h.update(seg.sha256().as_bytes());
    h.update(serde_json::to_string(cfg).unwrap_or_default().as_bytes());
    h.update(format!("{}x{} {}x{}", size.0, size.1, img.width(), img.height()).as_bytes());
    h.update(img.as_raw());
    let key: String = h.finalize().iter().map(|b| format!("{b:02x}")).collect();
    let file = dir.join(format!("{key}.png"));
    if let Ok(cached) = image::open(&file) {
        let grey = cached.into_luma8();
        if grey.dimensions() == size {
            return Ok(LabelMap::from_classes_unchecked(size.0, size.1, grey.into_raw()));
        }
    }
    let l = seg.segment_to(img, name, size)?;
    std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
    let part = dir.join(format!("{key}.{}.part.png", std::process::id()));
    image::GrayImage::from_raw(size.0, size.1, l.classes().to_vec())
        .ok_or_else(|| Error::invalid("label cache", "label map size"))?
        .save(&part)
        .map_err(|e| Error::invalid(part.display().to_string(), e.to_string()))?;
    std::fs::rename(&part, &file).map_err(|e| Error::io(&file, e))?;
    Ok(l)
}
