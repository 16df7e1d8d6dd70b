//! Encoding: one frame (label map, and RGB pixels when appearance is on) to its global
//! descriptor and its forest, timing each stage as the paper's Table 2 splits them:
//! "edge (coarse)" = global descriptor, "forest" = objects and trees, "appearance" = keypoint
//! network and per-object VLAD.
//!
//! An [`Encoder`] is three parts: what loads a frame ([`FrameLoader`]), what computes the global
//! descriptor (the encoder's own [`GlobalStage`]) and what computes appearance
//! ([`AppearanceEncoder`]). [`Encoder::encode_source`] runs them all on the CPU; the engine's GPU
//! path runs the same steps split into phases (`phases`, crate-private).

mod appearance;
mod load;
pub(crate) mod phases;
mod times;

pub use appearance::{AppearanceEncoder, VladInput};
pub use load::{segmenter_path, FrameLoader, Loaded};
pub use times::StageTimes;

use crate::appearance::{keypoints::Keypoints, AppearanceModel, Features};
use crate::classes::ClassTable;
use crate::config::{Config, EncodingConfig, GlobalConfig};
use crate::error::{Error, Result};
use crate::global::vlad::Codebook;
use crate::global::{self, GlobalScratch};
use crate::input::{FrameSource, LabelFormat, LabelMap};
use crate::util::ms_since;
use rayon::prelude::*;
use semlook_kernels::abi::SsimParams;
use std::time::Instant;

use crate::descriptors::EncodedImage;

/// What computes the global descriptor: semantic edges of the used classes, their distance
/// transform, the pooled descriptor and its SSIM window statistics.
#[derive(Debug, Clone)]
pub struct GlobalStage {
    cfg: GlobalConfig,
    used: [bool; 256],
    ssim: SsimParams,
}

impl GlobalStage {
    /// The `[global]` section it encodes with.
    pub fn config(&self) -> &GlobalConfig {
        &self.cfg
    }
    /// The classes that make edges (see `ClassTable::used_mask`).
    pub fn used_mask(&self) -> &[bool; 256] {
        &self.used
    }
    /// The SSIM parameters of its descriptors (size, window, constants), as the matchers take them.
    pub fn ssim_params(&self) -> SsimParams {
        self.ssim
    }
    /// The descriptor of `labels` and its SSIM statistics.
    pub fn encode(&self, labels: &LabelMap, scratch: &mut GlobalScratch) -> Result<(Vec<f32>, Vec<f32>)> {
        let mut global = vec![0.0; self.ssim.len()];
        let mut stats = vec![0.0; self.ssim.stats_len()];
        global::encode_global(labels, &self.used, &self.cfg, scratch, &mut global, &mut stats)?;
        Ok((global, stats))
    }
}

/// What a caller ran of a frame's networks itself (on the device), for
/// `Encoder::encode_rest` to take instead of running them: the keypoint network's features,
/// the embedding with its milliseconds.
#[derive(Default)]
pub(crate) struct NetworkRuns<'a> {
    pub keypoints: Option<&'a Features>,
    pub embedding: Option<(Vec<f32>, f64)>,
}

/// Encodes frames with one configuration. Cheap to share between threads.
#[derive(Debug, Clone)]
pub struct Encoder {
    cfg: EncodingConfig,
    table: ClassTable,
    frames: FrameLoader,
    global: GlobalStage,
    appearance: Option<AppearanceEncoder>,
    /// The whole-image embedding network (none: `embedding.network = "none"`, not installed, or
    /// appearance off, which loads no RGB image).
    embedder: Option<std::sync::Arc<crate::networks::embedding::Embedder>>,
    /// For an encoder of a map's queries ([`Encoder::for_map`]): whether the map holds semantic
    /// labels, which its queries then need too ([`Encoder::labels_rule`]).
    map_labelled: Option<bool>,
    /// Whether each image also gets a compact HOG ([`crate::global::hog::compact_hog`]): maps of small
    /// frames store one ([`Encoder::small_frames`]), and their queries then need one.
    compact_hog: bool,
    /// Whether a frame encoded alone (outside a thread pool) runs the embedding beside the
    /// appearance stage ([`Encoder::embedding_beside`]).
    beside: bool,
}

impl Encoder {
    /// An encoder for `cfg`: loads the keypoint network (and finds the segmenter) the config names.
    pub fn new(cfg: &Config) -> Result<Encoder> {
        Encoder::build(cfg, true)
    }
    /// [`Encoder::new`]; with `embed` false, without the embedding network `[embedding]` names.
    fn build(cfg: &Config, embed: bool) -> Result<Encoder> {
        let table = ClassTable::from_config(&cfg.classes)?;
        let appearance = AppearanceModel::load(&cfg.appearance, &cfg.models)?
            .map(|m| AppearanceEncoder::new(m, &cfg.appearance, &cfg.keypoints).ignoring(&table))
            .transpose()?;
        let global = GlobalStage { cfg: cfg.global.clone(), used: table.used_mask(), ssim: cfg.global.ssim_params() };
        let embedder = match appearance.is_some() && embed {
            true => crate::networks::embedding::from_config(&cfg.embedding, &cfg.models)?.map(std::sync::Arc::new),
            false => None,
        };
        Ok(Encoder {
            frames: FrameLoader::new(cfg, &table, appearance.is_some())?,
            global,
            table,
            cfg: cfg.encoding(),
            appearance,
            embedder,
            map_labelled: None,
            compact_hog: false,
            beside: true,
        })
    }
    /// Whether a frame encoded alone, outside a thread pool (a stream's), runs the whole-image
    /// embedding on a thread beside the appearance stage (the keypoint network and its
    /// decoding; VLAD follows) rather than after it: on by default. The descriptors are the same
    /// either way (each network keeps its session); the time differs (benches/encode.rs,
    /// `encode_streamed_frame_640x480_realtime_profile`). Frames encoded inside a pool, one per
    /// worker, always run them one after the other.
    pub fn embedding_beside(mut self, on: bool) -> Encoder {
        self.beside = on;
        self
    }
    /// Whether each image also gets a compact HOG (needs appearance on: it is computed from the
    /// RGB image the keypoint network sees; without appearance, none).
    pub fn with_compact_hog(mut self, on: bool) -> Encoder {
        self.compact_hog = on && self.appearance.is_some();
        self
    }
    /// Values per compact HOG (0 when the encoder makes none).
    pub fn compact_hog_dim(&self) -> usize {
        if self.compact_hog {
            crate::global::hog::COMPACT_HOG_DIM
        } else {
            0
        }
    }
    /// Whether `frames` are small frames, whose map stores compact HOGs: the first frame that
    /// has an image (its header read) has a long side of at most `input.compact_hog_long_side`
    /// pixels (0: never). Frames at that size give the keypoint network too little to find
    /// (sweep 17: on Nordland dev copies at 64x32 and 128x64 `verified` fell below `hog`, at
    /// 256x128 it matched it).
    pub fn small_frames<'a>(&self, frames: impl IntoIterator<Item = &'a FrameSource>) -> Result<bool> {
        let limit = self.cfg.input.compact_hog_long_side;
        if limit == 0 || self.appearance.is_none() {
            return Ok(false);
        }
        match frames.into_iter().find_map(|f| f.image.as_ref()) {
            Some(p) => {
                let (w, h) = crate::input::image_size(p)?;
                Ok(w.max(h) as usize <= limit)
            }
            None => Ok(false),
        }
    }
    /// Whether the encoder also computes the HOG baseline (VPR-Bench's, [`crate::global::hog`]).
    pub fn with_hog(mut self, hog: bool) -> Encoder {
        self.frames.hog = hog;
        self
    }
    /// Label maps the segmenter makes are kept in `dir` and read back for the same pixels
    /// (`semlook dev tune --label-cache`: a sweep's second run skips segmentation).
    pub fn with_label_cache(mut self, dir: Option<std::path::PathBuf>) -> Encoder {
        self.frames.label_cache = dir;
        self
    }
    /// The encoder for queries matched in `setting`: it computes the HOG baseline's descriptor
    /// only for that setting (maps store HOG only when built with it).
    pub fn for_setting(self, setting: crate::matching::Setting) -> Encoder {
        self.with_hog(setting == crate::matching::Setting::Hog)
    }
    /// With `on`, a frame with neither a label map nor a segmenter to make one is encoded with a
    /// void label map: no edges, no objects, a global descriptor the same for every frame. Only
    /// the settings that need no labels ([`crate::matching::Setting::label_free`]) may then be
    /// matched; the caller skips the others.
    /// The encoder of a map built without labels keeps its frames without labels whatever `on`.
    pub fn without_labels(mut self, on: bool) -> Encoder {
        self.frames.void_labels = on || self.map_labelled == Some(false);
        self
    }
    /// The one rule for frames that come as photos without label maps, at every entry point (the
    /// command line's `query`, `eval`, `localize` and `map build`/`add`, Python's `Map.query` and
    /// `Encoder`, the ROS node): `Ok(false)` where they are labelled (each has its label map, or a
    /// segmenter makes them); `Ok(true)` where they are encoded without labels: no segmenter, and
    /// either no map's references to match (a new map is then marked so) or a map that holds none,
    /// or `setting` reads no labels (`hog`; `appearance` unless `appearance.ignore_classes` leaves
    /// some class out); an error (refused, naming `first`, the remedy label maps or a segmenter)
    /// where the references hold labels and `setting` (`None`: any) reads them: label-free frames
    /// scored against labelled references would be silently wrong.
    pub fn labels_rule<'a>(&self, setting: Option<crate::matching::Setting>, frames: impl IntoIterator<Item = &'a FrameSource>) -> Result<bool> {
        let mut first = None;
        let all = frames.into_iter().all(|f| {
            first.get_or_insert_with(|| f.image.as_ref().map_or_else(|| f.id.clone(), |p| p.display().to_string()));
            f.labels.is_none() && f.image.is_some()
        });
        match first {
            Some(name) if all => self.photos_rule(setting, &name),
            _ => Ok(false),
        }
    }
    /// [`Encoder::labels_rule`] for photos without label maps, the first named `name` (frames
    /// given as pixels, a stream's).
    pub fn photos_rule(&self, setting: Option<crate::matching::Setting>, name: &str) -> Result<bool> {
        if self.frames.can_segment() {
            return Ok(false);
        }
        use crate::matching::Setting;
        // what reads the frame's labels: every setting but the two baselines (`appearance` only
        // where `appearance.ignore_classes` leaves classes out of its VLAD)
        let reads_labels = match setting {
            Some(Setting::Hog) => false,
            Some(Setting::Appearance) => self.appearance.as_ref().is_some_and(|a| a.reads_labels()),
            _ => true,
        };
        match self.map_labelled {
            Some(true) if reads_labels => Err(Error::refused(
                name.to_string(),
                "the map holds semantic labels, and photos without label maps need a segmenter to make them, but none is configured or installed (label-free scores against labelled references would be wrong)",
                crate::error::Remedy::GiveLabels,
            )),
            _ => Ok(true),
        }
    }
    /// Whether this encoder serves the queries of a map that holds semantic labels.
    pub fn map_labelled(&self) -> Option<bool> {
        self.map_labelled
    }
    /// An encoder for queries of `map`: `cfg`'s encoding must equal the map's, its keypoint
    /// network must be the one the map was built with, and the map's codebook is used.
    pub fn for_map(cfg: &Config, map: &crate::map::Map) -> Result<Encoder> {
        map.check_compatible(&cfg.encoding())?;
        // the map's embedding network below, whatever `[embedding]` says
        let mut enc = Encoder::build(cfg, false)?;
        map.check_model(enc.appearance_model().map(|a| a.sha256.as_str()))?;
        if let Some(cb) = map.codebook() {
            enc.set_codebook(cb.clone());
        }
        // the network that made the map's embeddings
        enc.embedder = match &map.manifest.embedding {
            None => None,
            Some(_) if enc.appearance.is_none() => {
                return Err(Error::invalid(format!("map {}", map.path.display()), "the map's embeddings need appearance on"))
            }
            Some(rec) => Some(std::sync::Arc::new(crate::networks::embedding::for_record(rec, &cfg.models)?)),
        };
        enc.map_labelled = Some(!map.manifest.without_labels);
        // a map of small frames: its queries get the compact HOG it stores
        enc.compact_hog = map.manifest.compact_hog_dim > 0 && enc.appearance.is_some();
        // a map built without labels takes its frames without labels too, unsegmented
        if map.manifest.without_labels {
            enc.frames.drop_segmenter();
        }
        Ok(enc.without_labels(map.manifest.without_labels))
    }

    /// What loads frames.
    pub fn frames(&self) -> &FrameLoader {
        &self.frames
    }
    /// What computes the global descriptor.
    pub fn global(&self) -> &GlobalStage {
        &self.global
    }
    /// What computes appearance (none with appearance off).
    pub fn appearance(&self) -> Option<&AppearanceEncoder> {
        self.appearance.as_ref()
    }
    /// What computes appearance, to set or train its codebook.
    pub fn appearance_mut(&mut self) -> Option<&mut AppearanceEncoder> {
        self.appearance.as_mut()
    }
    /// The keypoint network (none with appearance off).
    pub fn appearance_model(&self) -> Option<&AppearanceModel> {
        self.appearance.as_ref().map(|a| a.model())
    }
    /// The VLAD codebook (none with appearance off, or before it is trained or set).
    pub fn codebook(&self) -> Option<&Codebook> {
        self.appearance.as_ref().and_then(|a| a.codebook())
    }
    /// Sets the VLAD codebook (ignored with appearance off).
    pub fn set_codebook(&mut self, codebook: Codebook) {
        if let Some(a) = &mut self.appearance {
            a.set_codebook(codebook);
        }
    }
    /// The SHA-256 of the keypoint network and the codebook, for a new map.
    pub fn appearance_record(&self) -> Option<(&Codebook, &str)> {
        let a = self.appearance.as_ref()?;
        Some((a.codebook()?, a.model().sha256.as_str()))
    }
    /// The encoding sections it encodes with.
    pub fn config(&self) -> &EncodingConfig {
        &self.cfg
    }
    /// The class table built from its `[classes]` section.
    pub fn class_table(&self) -> &ClassTable {
        &self.table
    }
    /// Length of the trees' appearance vectors: Kv x D with appearance, else 0.
    pub fn appearance_dim(&self) -> usize {
        self.appearance.as_ref().map_or(0, |a| a.dim())
    }
    /// This encoder without its whole-image embedding network: its images carry no embedding, so
    /// the coarse stage ranks them without the embedding term (a stream's tracked frames,
    /// `stream.embed_when_tracking = false`).
    pub fn without_embedding(mut self) -> Encoder {
        self.embedder = None;
        self
    }
    /// The whole-image embedding network (none when the encoder makes no embeddings).
    pub fn embedder(&self) -> Option<&crate::networks::embedding::Embedder> {
        self.embedder.as_deref()
    }
    /// What a new map records of the embedding network (none without one).
    pub fn embedding_record(&self) -> Option<crate::descriptors::EmbeddingRecord> {
        self.embedder.as_ref().map(|e| e.record())
    }
    /// Values per whole-image embedding (0 without an embedding network).
    pub fn embedding_dim(&self) -> usize {
        self.embedder.as_ref().map_or(0, |e| e.dim())
    }
    /// Values per stored verification keypoint descriptor (0 when none are stored).
    pub fn keypoint_dim(&self) -> usize {
        self.appearance.as_ref().map_or(0, |a| a.keypoint_dim())
    }
    /// An empty descriptor set laid out for this encoder's images.
    pub fn descriptor_set(&self) -> crate::descriptors::DescriptorSet {
        let hog = if self.frames.hog { crate::global::hog::HOG_DIM } else { 0 };
        let codebook = self.codebook().filter(|_| self.appearance_dim() > 0).and_then(|c| c.sha256().ok());
        crate::descriptors::DescriptorSet::new(&self.global.ssim, self.cfg.local.neighbours, self.appearance_dim(), hog)
            .with_keypoint_dim(self.keypoint_dim())
            .with_embedding(self.embedding_record())
            .with_compact_hog_dim(self.compact_hog_dim())
            .with_codebook(codebook)
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

    /// [`Encoder::encode_loaded`] with the keypoint network's output given (cached by a caller
    /// that encodes the same frames with several configurations, such as `tune`).
    pub fn encode_loaded_with(
        &self,
        id: &str,
        loaded: &Loaded,
        keypoints: Option<&Features>,
        scratch: &mut GlobalScratch,
    ) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let (global, stats) = self.global.encode(&loaded.labels, scratch)?;
        let pending = self.encode_rest(id, loaded, global, Some(stats), ms_since(t), NetworkRuns { keypoints, embedding: None })?;
        let t = Instant::now();
        let vlad = match (&self.appearance, &pending.vlad) {
            (Some(a), Some(v)) => Some(a.vlad(v)?),
            _ => None,
        };
        self.finish(pending, vlad, ms_since(t))
    }

    /// Loads and encodes one frame on the CPU.
    pub fn encode_source(&self, src: &FrameSource, format: LabelFormat, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let loaded = self.frames.load(src, format)?;
        self.encode_loaded(&src.id, &loaded, scratch)
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
        self.train_codebook_skipping(sources, false, tick).map(|_| ())
    }

    /// [`Encoder::train_codebook`]; with `skip_invalid`, frames that cannot be read are left out
    /// and returned (index in `sources`, error) instead of ending the training.
    pub fn train_codebook_skipping(&mut self, sources: &[FrameSource], skip_invalid: bool, tick: &(dyn Fn() + Sync)) -> Result<Vec<(usize, Error)>> {
        let Some(appearance) = &self.appearance else { return Ok(vec![]) };
        let picks = appearance.codebook_picks(sources.len());
        let (frames, model) = (&self.frames, appearance.model());
        let results: Vec<Result<Keypoints>> = picks
            .par_iter()
            .map(|&i| {
                let k = frames.working_rgb(&sources[i]).and_then(|rgb| model.keypoints(&rgb));
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
        if let Some(a) = &mut self.appearance {
            a.train_codebook_from(&keypoints.iter().collect::<Vec<_>>())?;
        }
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
