//! Encoding: one image's label map (and, with an appearance model, its pixels) to its global
//! descriptor and its forest, timing each stage as the paper's Table 2 splits them.

use crate::classes::ClassTable;
use crate::config::EncodingConfig;
use crate::error::{Error, Result};
use crate::global::{self, ssim::SsimParams, GlobalScratch};
use crate::input::{self, FrameSource, LabelFormat, LabelMap};
use crate::local::{self, Forest};
use crate::objects;
use crate::util::ms_since;
use rayon::prelude::*;
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
    /// Reading and decoding the input files.
    pub load_ms: f64,
    /// "Edge (coarse)": edges, distance transform, pooling, SSIM stats.
    pub global_ms: f64,
    /// "Forest": objects, contours statistics, trees and neighbours.
    pub forest_ms: f64,
    /// Appearance: keypoint network and VLAD (0 without an appearance model).
    pub appearance_ms: f64,
}

impl std::ops::AddAssign for StageTimes {
    fn add_assign(&mut self, o: StageTimes) {
        self.load_ms += o.load_ms;
        self.global_ms += o.global_ms;
        self.forest_ms += o.forest_ms;
        self.appearance_ms += o.appearance_ms;
    }
}

/// Encodes images with one encoding config. Cheap to share between threads.
#[derive(Debug, Clone)]
pub struct Encoder {
    cfg: EncodingConfig,
    table: ClassTable,
    used: [bool; 256],
    ssim: SsimParams,
}

impl Encoder {
    pub fn new(cfg: &EncodingConfig) -> Result<Encoder> {
        let table = ClassTable::from_config(&cfg.classes)?;
        Ok(Encoder { used: table.used_mask(), ssim: SsimParams::new(&cfg.global), table, cfg: cfg.clone() })
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

    /// Encodes a label map already in memory.
    pub fn encode_labels(&self, id: &str, labels: &LabelMap, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let mut global = vec![0.0; self.ssim.len()];
        let mut global_stats = vec![0.0; self.ssim.stats_len()];
        global::encode_global(labels, &self.used, &self.cfg.global, scratch, &mut global, &mut global_stats)?;
        Ok(self.finish(id, labels, global, global_stats, ms_since(t)))
    }

    /// Completes an image whose global descriptor was pooled elsewhere (on the GPU): its SSIM
    /// statistics, objects and forest. `global_ms` is the time already spent on the descriptor.
    pub fn encode_with_global(&self, id: &str, labels: &LabelMap, global: Vec<f32>, global_ms: f64) -> (EncodedImage, StageTimes) {
        let t = Instant::now();
        let mut global_stats = vec![0.0; self.ssim.stats_len()];
        global::ssim::ssim_stats(&self.ssim, &global, &mut global_stats, &mut Default::default());
        self.finish(id, labels, global, global_stats, global_ms + ms_since(t))
    }

    fn finish(&self, id: &str, labels: &LabelMap, global: Vec<f32>, global_stats: Vec<f32>, global_ms: f64) -> (EncodedImage, StageTimes) {
        let t = Instant::now();
        let objects = objects::extract_objects(labels, &self.table, &self.cfg.objects);
        let forest = local::build_forest(&objects, &self.cfg.local);
        let times = StageTimes { global_ms, forest_ms: ms_since(t), ..Default::default() };
        (EncodedImage { id: id.to_string(), width: labels.width(), height: labels.height(), global, global_stats, forest }, times)
    }

    /// The classes that make edges (see `ClassTable::used_mask`).
    pub fn used_mask(&self) -> &[bool; 256] {
        &self.used
    }

    /// Loads a frame's files and encodes it.
    pub fn encode_source(&self, src: &FrameSource, format: LabelFormat, scratch: &mut GlobalScratch) -> Result<(EncodedImage, StageTimes)> {
        let t = Instant::now();
        let labels = input::load_frame_labels(src, &self.table, format)?;
        let load_ms = ms_since(t);
        let (img, mut times) = self.encode_labels(&src.id, &labels, scratch)?;
        times.load_ms = load_ms;
        Ok((img, times))
    }

    /// Encodes many frames in parallel, in order; `tick` is called once per finished frame.
    pub fn encode_all(
        &self,
        sources: &[FrameSource],
        format: LabelFormat,
        tick: &(dyn Fn() + Sync),
    ) -> Vec<Result<(EncodedImage, StageTimes)>> {
        sources
            .par_iter()
            .map_init(GlobalScratch::default, |scratch, src| {
                let r = self.encode_source(src, format, scratch);
                tick();
                r
            })
            .collect()
    }
}

/// Splits encoding results into successes and errors; with `skip_invalid` false, the first error
/// (in input order) is returned instead.
pub fn collect_encoded(
    results: Vec<Result<(EncodedImage, StageTimes)>>,
    skip_invalid: bool,
) -> Result<(Vec<EncodedImage>, StageTimes, Vec<Error>)> {
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
