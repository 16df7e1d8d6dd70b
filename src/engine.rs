//! The execution engine: runs encoding and matching on the CPU reference path or on the GPU.
//!
//! `Backend::Auto` takes a hardware GPU adapter when there is one and otherwise falls back to the
//! CPU with a warning (a software adapter such as lavapipe is slower than the CPU path, so `auto`
//! never picks it; `gpu` accepts it, which is what the equivalence tests run on).

use crate::config::Config;
use crate::descriptors::source::{GlobalSource, RefSource};
use crate::descriptors::DescriptorSet;
use crate::descriptors::EncodedImage;
use crate::encode::phases::Pending;
use crate::encode::NetworkRuns;
use crate::encode::{Encoder, Loaded, StageTimes};
use crate::error::{Error, Result};
use crate::gpu::{GpuContext, GpuOptions, GpuStages};
use crate::input::{FrameSource, LabelFormat, LabelMap};
use crate::matching::{candidates, fine_scores, match_with, CandidateLists, CpuStages, MatchTimes, QueryMatch, Setting, Stages};
use crate::util::ms_since;
use rayon::prelude::*;
use std::sync::Arc;
use std::time::Instant;

/// Frames the GPU path decodes at once: a few device batches' worth (the batches take up to 32
/// frames of one size), so both cores decode while memory stays bounded whatever the number of
/// frames (tested: `tests/gpu/stream.rs`).
pub const STREAM_FRAMES: usize = 64;

/// Where the heavy work runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum Backend {
    /// The CPU reference path (all cores, through rayon).
    Cpu,
    /// The WGSL kernels on a GPU adapter (a software one too); fails if there is none.
    Gpu,
    /// A hardware GPU if there is one, else the CPU (with a warning).
    Auto,
}

impl Backend {
    /// Every backend.
    pub const ALL: [Backend; 3] = [Backend::Cpu, Backend::Gpu, Backend::Auto];
    /// The backend of every front end (command line, Python) when none is named.
    pub const DEFAULT: Backend = Backend::Auto;
    /// The backend's name, as the front ends spell it: "cpu", "gpu" or "auto".
    pub fn name(self) -> &'static str {
        match self {
            Backend::Cpu => "cpu",
            Backend::Gpu => "gpu",
            Backend::Auto => "auto",
        }
    }
}

impl Default for Backend {
    fn default() -> Backend {
        Backend::DEFAULT
    }
}

/// Runs the pipeline on the chosen backend.
pub struct Engine {
    gpu: Option<GpuStages>,
    /// `auto`: a GPU failure during work switches to the CPU (with a warning) instead of failing.
    fall_back: bool,
    /// Calls (match, candidates, fine scores, encode) completed with work on the GPU stages.
    gpu_calls: u64,
    /// Why `auto` switched to the CPU during work, once it has.
    fell_back: Option<String>,
}

impl Engine {
    /// An engine on the CPU reference path.
    pub fn cpu() -> Engine {
        Engine { gpu: None, fall_back: false, gpu_calls: 0, fell_back: None }
    }

    /// An engine for `backend`. For `Auto`, the second value is the reason it fell back to the CPU.
    pub fn new(backend: Backend, opts: &GpuOptions) -> Result<(Engine, Option<String>)> {
        match backend {
            Backend::Cpu => Ok((Engine::cpu(), None)),
            Backend::Gpu => Ok((Engine::with_context(Arc::new(GpuContext::new(opts)?)), None)),
            Backend::Auto => match GpuContext::new(&GpuOptions { allow_software: false, ..opts.clone() }) {
                Ok(ctx) => Ok((Engine { fall_back: true, ..Engine::with_context(Arc::new(ctx)) }, None)),
                Err(e) => Ok((Engine::cpu(), Some(format!("no hardware GPU ({e}); using the CPU path")))),
            },
        }
    }

    /// An engine inside a host application's GPU context (see [`GpuContext::from_device`]).
    ///
    /// ```no_run
    /// # fn main() -> semlook::Result<()> {
    /// use semlook::{config::Config, encode::Encoder, engine::Engine, gpu::{GpuContext, GpuOptions}, map::Map, matching::Setting};
    /// use std::sync::Arc;
    /// // the host application's own wgpu setup
    /// let instance = wgpu::Instance::new(wgpu::InstanceDescriptor::new_without_display_handle());
    /// let adapter = pollster::block_on(instance.request_adapter(&Default::default())).expect("adapter");
    /// let (device, queue) = pollster::block_on(adapter.request_device(&Default::default())).expect("device");
    /// // semlook runs inside it: pipelines are added to that device, errors come back typed
    /// let ctx = GpuContext::from_device(device, queue, adapter.get_info(), &GpuOptions::default())?;
    /// let mut engine = Engine::with_context(Arc::new(ctx));
    /// let map = Map::open("my-map".as_ref())?;
    /// let cfg = Config::default().with_encoding(&map.manifest.config);
    /// let encoder = Encoder::for_map(&cfg, &map)?;
    /// let sources = vec![semlook::input::FrameSource { id: "q".into(), image: Some("q.png".into()), labels: Some("q_labels.png".into()) }];
    /// let encoded = engine.encode_all(&encoder, &sources, Default::default(), &|| {})?;
    /// let mut queries = encoder.descriptor_set();
    /// queries.push(&encoded.into_iter().next().unwrap()?.0);
    /// // uploads the map once (later batches find it resident) and the queries, reads back
    /// // only the top-K lists
    /// let (matches, _) = engine.match_batch(&map, &queries, Setting::Semlook, &cfg)?;
    /// println!("{:?}", matches[0].best());
    /// # Ok(()) }
    /// ```
    pub fn with_context(ctx: Arc<GpuContext>) -> Engine {
        Engine { gpu: Some(GpuStages::new(ctx)), fall_back: false, gpu_calls: 0, fell_back: None }
    }

    /// Whether a GPU failure during work switches to the CPU path (what `auto` does) instead of
    /// failing.
    pub fn fall_back_to_cpu(mut self, yes: bool) -> Engine {
        self.fall_back = yes;
        self
    }

    /// With `auto`, turns a GPU failure into a switch to the CPU path (and says so); otherwise
    /// passes the error on.
    fn recover<T>(&mut self, r: Result<T>) -> Result<std::result::Result<T, ()>> {
        match r {
            Err(crate::error::Error::Gpu(e)) if self.fall_back => {
                let why = format!("GPU failed ({e}); continuing on the CPU path");
                log::warn!("{why}");
                self.fell_back = Some(why);
                self.gpu = None;
                Ok(Err(()))
            }
            Err(e) => Err(e),
            Ok(v) => Ok(Ok(v)),
        }
    }

    /// Whether the engine runs on the GPU (false on the CPU path, also after `auto` fell back).
    pub fn is_gpu(&self) -> bool {
        self.gpu.is_some()
    }

    /// Calls (match, candidates, fine scores, encode) completed so far in which the GPU stages
    /// did work: not the baselines (`hog`, `appearance`, always on the CPU), not a call the
    /// `auto` fallback finished on the CPU.
    pub fn gpu_calls(&self) -> u64 {
        self.gpu_calls
    }

    /// Why `auto` switched to the CPU during work (after a GPU failure), once it has.
    pub fn fell_back(&self) -> Option<&str> {
        self.fell_back.as_deref()
    }

    /// The GPU executors, when this engine runs on a GPU.
    pub fn gpu_stages(&mut self) -> Option<&mut GpuStages> {
        self.gpu.as_mut()
    }

    /// "cpu (N threads)" or "gpu: adapter (backend, device type)".
    pub fn describe(&self) -> String {
        match &self.gpu {
            Some(g) => format!("gpu: {}", g.ctx.describe()),
            None => format!("cpu ({} threads)", rayon::current_num_threads()),
        }
    }

    /// Runs `work` on the GPU stages when there are any, counting it in `gpu_calls` if the GPU
    /// did work. `None`: no GPU, or `auto` recovered from a GPU failure (the caller then runs the
    /// CPU path).
    fn on_gpu<T>(&mut self, work: impl FnOnce(&mut GpuStages) -> Result<T>) -> Result<Option<T>> {
        let Some(g) = &mut self.gpu else { return Ok(None) };
        let before = g.work;
        let r = work(g);
        let did = g.work > before;
        let v = self.recover(r)?.ok();
        self.gpu_calls += u64::from(did && v.is_some());
        Ok(v)
    }

    /// Runs `work` on the GPU stages when there are any (with `auto`, again on the CPU if the
    /// GPU fails), else on the CPU stages.
    fn on_stages<T>(&mut self, mut work: impl FnMut(&mut dyn Stages) -> Result<T>) -> Result<T> {
        match self.on_gpu(|g| work(g))? {
            Some(v) => Ok(v),
            None => work(&mut CpuStages),
        }
    }

    /// Matches a batch of queries (see [`crate::matching::match_with`]).
    pub fn match_batch(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        setting: Setting,
        cfg: &Config,
    ) -> Result<(Vec<QueryMatch>, MatchTimes)> {
        self.on_stages(|st| match_with(st, refs, queries, setting, cfg))
    }

    /// The candidate lists of a batch alone (see [`crate::matching::candidates`]): what one shard
    /// of a map runs.
    pub fn candidates(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        setting: Setting,
        cfg: &Config,
    ) -> Result<(CandidateLists, MatchTimes)> {
        self.on_stages(|st| candidates(st, refs, queries, setting, cfg))
    }

    /// Fine scores of (query, reference) pairs (see [`crate::matching::fine_scores`]).
    pub fn fine_scores(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        setting: Setting,
        cfg: &Config,
        pairs: &[(u32, u32)],
    ) -> Result<Vec<crate::matching::PairScore>> {
        self.on_stages(|st| fine_scores(st, refs, queries, setting, cfg, pairs))
    }

    /// What the fine stage measures of (query, reference) pairs, unweighed (see
    /// [`crate::matching::pair_terms`]).
    pub fn pair_terms(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        setting: Setting,
        cfg: &Config,
        pairs: &[(u32, u32)],
    ) -> Result<Vec<crate::matching::PairTerms>> {
        self.on_stages(|st| crate::matching::pair_terms(st, refs, queries, setting, cfg, pairs))
    }

    /// What `setting` scores each (query, reference) pair, the evidence of `verified` weighed
    /// against `evidence[q]` (see [`crate::matching::score_pairs`]).
    #[allow(clippy::too_many_arguments)]
    pub fn score_pairs(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        setting: Setting,
        cfg: &Config,
        pairs: &[(u32, u32)],
        evidence: Option<&[Option<crate::matching::Evidence>]>,
    ) -> Result<Vec<crate::matching::Candidate>> {
        self.on_stages(|st| crate::matching::score_pairs(st, refs, queries, setting, cfg, pairs, evidence))
    }

    /// Measures the null of `verified`'s evidence over `refs` under `cfg` (see
    /// [`crate::matching::measure_null`]).
    pub fn measure_null(&mut self, refs: &dyn RefSource, cfg: &Config) -> Result<crate::matching::null::NullEvidence> {
        self.on_stages(|st| crate::matching::measure_null(st, refs, cfg))
    }

    /// Measures the null of `verified`'s evidence over the stored map `map` under `cfg` and
    /// stores it in the map's manifest, so every process and every shard of the map tests
    /// candidates against the same one (`map build`, `map add`; [`crate::matching::null`]). Does
    /// nothing where `cfg` does not test evidence against a null, the map stores no verification
    /// keypoints, or it keeps one measured under `cfg` already. Returns the map as it is then,
    /// with the null stored and the milliseconds its measurement took (None: nothing stored; also
    /// where another writer committed meanwhile).
    pub fn store_null(
        &mut self,
        map: crate::map::Map,
        cfg: &Config,
    ) -> Result<(crate::map::Map, Option<(Arc<crate::matching::null::NullEvidence>, f64)>)> {
        use crate::matching::null;
        let wanted = cfg.verification.inliers == crate::config::InlierEvidence::Significant && map.keypoint_dim() > 0 && !map.is_empty();
        if !wanted || map.stored_null().is_some_and(|n| n.key == null::key(cfg)) {
            return Ok((map, None));
        }
        let t = Instant::now();
        let n = self.measure_null(&map, cfg)?;
        let ms = ms_since(t);
        if !crate::map::edit::store_null(&map.path, map.manifest.generation, n)? {
            return Ok((map, None));
        }
        let map = crate::map::Map::open(&map.path)?;
        let stored = map.stored_null().map(|n| (n, ms));
        Ok((map, stored))
    }

    /// Encodes frames, in input order; `tick` is called per frame. Per-frame input errors are
    /// returned per frame; a GPU failure fails the whole call. On the GPU, frames are decoded in
    /// parallel on the CPU, [`STREAM_FRAMES`] at a time (memory does not grow with the number of
    /// frames); for each batch of one size the global descriptors and their SSIM statistics are
    /// computed on the device, then the keypoint network (on the device when it is the native
    /// XFeat, else on the CPU), objects and forests on the CPU, and the per-object VLAD of the
    /// whole batch on the device.
    pub fn encode_all(
        &mut self,
        encoder: &Encoder,
        sources: &[FrameSource],
        format: LabelFormat,
        tick: &(dyn Fn() + Sync),
    ) -> Result<Vec<Result<(EncodedImage, StageTimes)>>> {
        match self.on_gpu(|g| Self::encode_all_gpu(g, encoder, sources, format, tick))? {
            Some(v) => Ok(v),
            None => Ok(encoder.encode_all(sources, format, tick)),
        }
    }

    /// Encodes frames already decoded (by [`crate::encode::FrameLoader::load_arrays`] or
    /// [`crate::encode::FrameLoader::load`]), each with its id, in order: on the device when the
    /// engine has one (with `auto`, again on the CPU if it fails), else on the CPU.
    pub fn encode_loaded(&mut self, encoder: &Encoder, frames: Vec<(String, Result<Loaded>)>) -> Result<Vec<Result<(EncodedImage, StageTimes)>>> {
        // frames that failed to load keep their error; the others are encoded
        let mut out: Vec<Option<Result<(EncodedImage, StageTimes)>>> = Vec::with_capacity(frames.len());
        let (mut sources, mut loaded) = (Vec::new(), Vec::new());
        for (id, l) in frames {
            match l {
                Ok(l) => {
                    out.push(None);
                    sources.push(FrameSource { id, image: None, labels: None });
                    loaded.push(l);
                }
                Err(e) => out.push(Some(Err(e))),
            }
        }
        let mut done = None;
        if self.gpu.is_some() {
            // a copy for the CPU path, should the device fail under `auto`
            let copy: Vec<Result<Loaded>> = loaded.iter().cloned().map(Ok).collect();
            done = self.on_gpu(|g| Self::encode_loaded_gpu(g, encoder, &sources, copy, &|| {}))?;
        }
        let mut encoded = match done {
            Some(v) => v.into_iter(),
            None => {
                let mut scratch = crate::global::GlobalScratch::default();
                loaded.iter().zip(&sources).map(|(l, s)| encoder.encode_loaded(&s.id, l, &mut scratch)).collect::<Vec<_>>().into_iter()
            }
        };
        Ok(out
            .into_iter()
            .map(|o| o.unwrap_or_else(|| encoded.next().unwrap_or_else(|| Err(Error::invalid("encoding", "a frame went missing")))))
            .collect())
    }

    fn encode_all_gpu(
        g: &mut GpuStages,
        encoder: &Encoder,
        sources: &[FrameSource],
        format: LabelFormat,
        tick: &(dyn Fn() + Sync),
    ) -> Result<Vec<Result<(EncodedImage, StageTimes)>>> {
        let mut out = Vec::with_capacity(sources.len());
        for chunk in sources.chunks(STREAM_FRAMES) {
            let loaded: Vec<Result<Loaded>> = chunk.par_iter().map(|s| encoder.frames().load(s, format)).collect();
            g.decoded_peak = g.decoded_peak.max(loaded.len());
            out.extend(Self::encode_loaded_gpu(g, encoder, chunk, loaded, tick)?);
        }
        Ok(out)
    }

    /// Encodes decoded frames (`loaded[i]` of `sources[i]`) on the device, in batches of frames
    /// of one size.
    fn encode_loaded_gpu(
        g: &mut GpuStages,
        encoder: &Encoder,
        sources: &[FrameSource],
        loaded: Vec<Result<Loaded>>,
        tick: &(dyn Fn() + Sync),
    ) -> Result<Vec<Result<(EncodedImage, StageTimes)>>> {
        let mut out: Vec<Option<Result<(EncodedImage, StageTimes)>>> = (0..sources.len()).map(|_| None).collect();
        let mut frames: Vec<Option<Loaded>> = Vec::with_capacity(loaded.len());
        for (i, r) in loaded.into_iter().enumerate() {
            match r {
                Ok(l) => frames.push(Some(l)),
                Err(e) => {
                    out[i] = Some(Err(e));
                    frames.push(None);
                    tick();
                }
            }
        }
        let mut i = 0;
        while i < frames.len() {
            let Some(first) = &frames[i] else {
                i += 1;
                continue;
            };
            let size = (first.labels.width(), first.labels.height());
            let cap = g.encoder.max_batch(size.0, size.1).clamp(1, 32);
            let mut j = i;
            while j < frames.len() && j - i < cap && frames[j].as_ref().is_some_and(|l| (l.labels.width(), l.labels.height()) == size) {
                j += 1;
            }
            // every entry of i..j is loaded (the loop above stopped at the first that is not)
            let batch: Vec<&Loaded> = frames[i..j].iter().flatten().collect();
            let maps: Vec<&LabelMap> = batch.iter().map(|l| &l.labels).collect();
            let t = Instant::now();
            g.work += 1;
            let globals = g.encoder.encode(&maps, encoder.global().used_mask(), encoder.global().config())?;
            let per = ms_since(t) / batch.len() as f64;
            // the keypoint network on the device (native XFeat; None: the CPU path runs it)
            let rgbs: Vec<Option<&image::RgbImage>> = batch.iter().map(|l| l.rgb.as_ref()).collect();
            let features = g.network.features(&g.ctx, encoder.appearance_model(), &rgbs)?;
            // the embedding on the device (the network run natively; None: the CPU path embeds)
            let embedded = g.embedding.embeddings(&g.ctx, encoder.embedder(), &rgbs)?;
            let pending: Vec<Result<Pending>> = globals
                .into_par_iter()
                .zip(batch.par_iter())
                .zip(embedded.into_par_iter())
                .enumerate()
                .map(|(k, (((glob, stats), l), e))| {
                    encoder.encode_rest(&sources[i + k].id, l, glob, Some(stats), per, NetworkRuns { keypoints: features[k].as_ref(), embedding: e })
                })
                .collect();
            // VLAD of every frame of the batch in one GPU pass
            let inputs: Vec<(&[f32], &[u32])> = pending
                .iter()
                .filter_map(|p| p.as_ref().ok())
                .filter_map(|p| p.vlad.as_ref())
                .map(|v| (v.descriptors.as_slice(), v.offsets.as_slice()))
                .collect();
            let t = Instant::now();
            let mut vlads = match (encoder.appearance(), inputs.is_empty()) {
                (Some(a), false) => match a.codebook() {
                    Some(cb) => g.vlad.run(cb, a.vlad_norm(), &inputs)?.into_iter(),
                    None => Vec::new().into_iter(),
                },
                _ => Vec::new().into_iter(),
            };
            let vlad_ms = ms_since(t) / batch.len() as f64;
            for (k, p) in pending.into_iter().enumerate() {
                out[i + k] = Some(p.and_then(|p| {
                    let v = if p.vlad.is_some() { vlads.next() } else { None };
                    encoder.finish(p, v, vlad_ms)
                }));
                tick();
            }
            i = j;
        }
        Ok(out.into_iter().map(|o| o.expect("every frame handled")).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::Backend;

    /// The names the Python bindings parse (`Backend::name`) are the command line's and the JSON's.
    #[test]
    fn backend_names_are_the_command_lines() {
        for b in Backend::ALL {
            assert_eq!(serde_json::to_string(&b).ok(), Some(format!("\"{}\"", b.name())));
        }
        assert_eq!(Backend::default(), Backend::DEFAULT);
    }
}
