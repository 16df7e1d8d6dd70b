//! Encoding many frames: into one descriptor set with a progress bar (queries, evaluation), or
//! streamed into a map chunk by chunk (`map build`, `map add`), so that building a map runs
//! cli -> batch -> engine/encode -> map and never passes through evaluation. Also the VLAD codebook
//! training with a progress bar, which a new map needs before its first segment.

use crate::descriptors::DescriptorSet;
use crate::encode::{collect_encoded, Encoder, StageTimes};
use crate::engine::Engine;
use crate::error::{Error, Result};
use crate::input::{FrameSource, LabelFormat};
use crate::map::MapWriter;
use crate::progress;
use serde::Serialize;
use std::collections::HashSet;

/// Frames encoded per call while streaming into a map: enough to keep every core (and a GPU
/// batch of 32) busy, few enough that the chunk's encoded images (about 40 kB each without
/// appearance, a few hundred kB with HOG) stay far below a segment's buffer.
pub const ENCODE_CHUNK: usize = 256;

/// Per-frame encoding times of a set of frames: mean and median per stage, and the wall-clock
/// time per frame of the whole (parallel) encoding.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct EncodingSummary {
    /// Frames encoded.
    pub frames: usize,
    /// Mean time per frame of each stage.
    pub mean: StageTimes,
    /// Median time per frame of each stage.
    pub median: StageTimes,
    /// Wall-clock milliseconds per frame over the batch (frames run in parallel).
    pub wall_ms_per_frame: f64,
}

impl EncodingSummary {
    /// The summary of per-frame `times` and the batch's wall-clock milliseconds `wall_ms`.
    pub fn new(times: &[StageTimes], wall_ms: f64) -> Self {
        let mut total = StageTimes::default();
        for t in times {
            total += *t;
        }
        let n = times.len().max(1) as f64;
        EncodingSummary { frames: times.len(), mean: total.scaled(1.0 / n), median: StageTimes::median(times), wall_ms_per_frame: wall_ms / n }
    }
}

/// Trains the encoder's VLAD codebook on reference frames (when appearance is on), with a bar.
pub fn train_codebook(encoder: &mut Encoder, refs: &[FrameSource], quiet: bool) -> Result<()> {
    train_codebook_skipping(encoder, refs, false, quiet)
}

/// [`train_codebook`]; with `skip_invalid`, frames that cannot be read are left out of the
/// training with a warning naming each.
pub fn train_codebook_skipping(encoder: &mut Encoder, refs: &[FrameSource], skip_invalid: bool, quiet: bool) -> Result<()> {
    if encoder.appearance_model().is_none() {
        return Ok(());
    }
    // frames the store will refuse do not shape the codebook ([`encode_into`] reports them)
    let mut usable = Vec::with_capacity(refs.len());
    for f in refs {
        match id_refusal(f) {
            None => usable.push(f.clone()),
            Some(e) if !skip_invalid => return Err(e),
            Some(_) => {}
        }
    }
    let refs = &usable[..];
    let n = encoder.config().appearance.codebook_images.min(refs.len());
    let pb = progress::bar(n, "codebook", quiet);
    let skipped = encoder.train_codebook_skipping(refs, skip_invalid, &|| pb.inc(1))?;
    pb.finish_and_clear();
    for (i, e) in &skipped {
        log::warn!("codebook training skips {}: {e}", refs[*i].id);
    }
    Ok(())
}

/// The store's refusal of a frame's id (empty, too long, control characters), if it has one.
fn id_refusal(f: &FrameSource) -> Option<Error> {
    crate::descriptors::validate::id(&f.id).err().map(|e| e.named(|reason| Error::InvalidImage { id: f.id.clone(), reason }))
}

/// A set of frames encoded into a descriptor set.
pub struct EncodedFrames {
    /// The encoded frames, in input order (skipped frames left out).
    pub set: DescriptorSet,
    /// Per encoded frame, in set order.
    pub times: Vec<StageTimes>,
    /// Wall-clock milliseconds of the whole batch.
    pub wall_ms: f64,
    /// Frames that failed (index in the input, error), when skipping invalid input.
    pub skipped: Vec<(usize, Error)>,
}

impl EncodedFrames {
    /// The per-frame times summarised.
    pub fn summary(&self) -> EncodingSummary {
        EncodingSummary::new(&self.times, self.wall_ms)
    }
}

/// Encodes a list of frames into a descriptor set, with a progress bar.
pub fn encode_frames(
    engine: &mut Engine,
    encoder: &Encoder,
    frames: &[FrameSource],
    format: LabelFormat,
    what: &str,
    skip_invalid: bool,
    quiet: bool,
) -> Result<EncodedFrames> {
    let pb = progress::bar(frames.len(), what, quiet);
    let t = std::time::Instant::now();
    let results = engine.encode_all(encoder, frames, format, &|| pb.inc(1))?;
    let wall = crate::util::ms_since(t);
    pb.finish_and_clear();
    let (images, times, skipped) = collect_encoded(results, skip_invalid)?;
    let mut set = encoder.descriptor_set();
    for img in &images {
        set.push(img).map_err(|e| e.named(|r| Error::invalid(what, r)))?;
    }
    Ok(EncodedFrames { set, times, wall_ms: wall, skipped })
}

/// Poses to store with the images they name (frame id -> pose): a dataset's own, or a pose list's.
pub type PlacePoses = std::collections::HashMap<String, crate::descriptors::PlacePose>;

/// How [`encode_into`] treats frames.
#[derive(Debug, Clone, Copy, Default)]
pub struct IntoOptions<'a> {
    /// Skip (and report) frames that fail to load or encode, instead of stopping.
    pub skip_invalid: bool,
    /// Skip frames whose id the map already holds (`--resume`); otherwise such a frame is an
    /// error before anything is encoded.
    pub skip_stored: bool,
    /// No progress bar.
    pub quiet: bool,
    /// Poses stored with the frames they name (the map's `place_pose` column); frames they do
    /// not name are stored without one.
    pub poses: Option<&'a PlacePoses>,
}

/// What [`encode_into`] did.
#[derive(Debug, Default)]
pub struct IntoReport {
    /// Images written (committed) by this run.
    pub added: usize,
    /// Frames skipped because the map held them already.
    pub already_stored: usize,
    /// Frames skipped as invalid: (id, error).
    pub invalid: Vec<(String, Error)>,
    /// Encoding times of the frames this run encoded and wrote.
    pub summary: EncodingSummary,
}

/// Encodes `frames` chunk by chunk ([`ENCODE_CHUNK`]) into `writer`, which commits a segment
/// whenever its buffer is full; memory is one chunk plus one segment, whatever the number of
/// frames. On an error the images already encoded are committed first, so `--resume` continues
/// after them. The caller finishes the writer.
pub fn encode_into(
    engine: &mut Engine,
    encoder: &Encoder,
    frames: &[FrameSource],
    format: LabelFormat,
    writer: &mut MapWriter,
    opts: IntoOptions<'_>,
) -> Result<IntoReport> {
    let mut ids = HashSet::new();
    if let Some(dup) = frames.iter().find(|f| !ids.insert(f.id.as_str())) {
        return Err(Error::invalid(format!("frame {:?}", dup.id), "two input frames have this id"));
    }
    let stored = writer.stored_among(frames.iter().map(|f| f.id.as_str()));
    if let (false, Some(id)) = (opts.skip_stored, frames.iter().find(|f| stored.contains(&f.id))) {
        return Err(Error::DuplicateImageId { map: writer.dir().to_path_buf(), id: id.id.clone() });
    }
    let mut report = IntoReport::default();
    let mut todo: Vec<&FrameSource> = Vec::with_capacity(frames.len());
    for f in frames {
        if stored.contains(&f.id) {
            report.already_stored += 1;
            continue;
        }
        // an id the store refuses is refused (or skipped) before any frame is encoded
        match id_refusal(f) {
            None => todo.push(f),
            Some(e) => {
                if !opts.skip_invalid {
                    return Err(e);
                }
                log::warn!("skipped {:?}: {e}", f.id);
                report.invalid.push((f.id.clone(), e));
            }
        }
    }
    let pb = progress::bar(todo.len(), "images", opts.quiet);
    let (mut times, t0) = (Vec::new(), std::time::Instant::now());
    let before = writer.committed();
    let outcome = (|| -> Result<()> {
        for chunk in todo.chunks(ENCODE_CHUNK) {
            let chunk: Vec<FrameSource> = chunk.iter().map(|f| (*f).clone()).collect();
            for (src, r) in chunk.iter().zip(engine.encode_all(encoder, &chunk, format, &|| pb.inc(1))?) {
                match r {
                    Ok((mut img, t)) => {
                        img.pose = opts.poses.and_then(|p| p.get(&img.id)).copied();
                        writer.push(&img)?;
                        times.push(t);
                    }
                    Err(e) if opts.skip_invalid => {
                        log::warn!("skipped {}: {e}", src.id);
                        report.invalid.push((src.id.clone(), e));
                    }
                    Err(e) => return Err(e),
                }
            }
        }
        Ok(())
    })();
    pb.finish_and_clear();
    if let Err(e) = outcome {
        if let Err(fe) = writer.flush() {
            log::error!("{fe}");
        }
        let done = writer.committed() - before;
        log::error!("stopped after committing {done} images; fix the input and resume to add the rest");
        return Err(e);
    }
    writer.flush()?;
    report.added = writer.committed() - before;
    report.summary = EncodingSummary::new(&times, crate::util::ms_since(t0));
    Ok(report)
}

/// How [`new_map`] lays out a new map.
#[derive(Debug, Clone, Default)]
pub struct NewMapOptions {
    /// Also store each image's HOG baseline descriptor.
    pub hog: bool,
    /// How the map stores its values, and how large its segments grow.
    pub store: crate::map::StoreOptions,
    /// The traversal's name (default "0").
    pub traversal: Option<String>,
    /// Leave out (and report) frames that cannot be read while training the codebook.
    pub skip_invalid: bool,
    /// With `resume`, `dir` may hold what an interrupted build left (no manifest).
    pub resume: bool,
    /// No progress bar.
    pub quiet: bool,
}

/// The encoder and writer of a new map in `dir` for `frames`, as `map build` makes them: photos
/// with neither label maps nor a segmenter make a map marked without labels (for the settings
/// that need none) rather than no map; the VLAD codebook is trained on `frames` first (it is
/// stored with the first segment). Encode into the writer with [`encode_into`], then finish it.
pub fn new_map(cfg: &crate::config::Config, frames: &[FrameSource], dir: &std::path::Path, opts: &NewMapOptions) -> Result<(Encoder, MapWriter)> {
    MapWriter::check_new_dir(dir, opts.resume)?;
    let encoder = Encoder::new(cfg)?.with_hog(opts.hog);
    let without_labels = encoder.labels_rule(None, frames)?;
    // small frames: the map stores each image's compact HOG too
    let small = encoder.small_frames(frames)?;
    let mut encoder = encoder.without_labels(without_labels).with_compact_hog(small);
    if small {
        log::info!("small frames (long side at most input.compact_hog_long_side): the map stores each image's compact HOG");
    }
    if without_labels {
        let served: Vec<&str> = crate::matching::Setting::served_without_labels(opts.hog).map(|s| s.name()).collect();
        log::warn!(
            "no label maps and no segmenter: the map holds no semantic labels; only {} can be matched against it (`semlook models` says what is installed)",
            served.join(", ")
        );
    }
    train_codebook_skipping(&mut encoder, frames, opts.skip_invalid, opts.quiet)?;
    let hog_dim = if opts.hog { crate::global::hog::HOG_DIM } else { 0 };
    let dims = crate::map::ColumnDims {
        appearance: encoder.appearance_dim(),
        hog: hog_dim,
        keypoints: encoder.keypoint_dim(),
        compact_hog: encoder.compact_hog_dim(),
    };
    let writer = MapWriter::create(dir, &cfg.encoding(), dims, encoder.appearance_record(), opts.store, opts.resume)?
        .with_embedding(encoder.embedding_record())?
        .with_profile(cfg)?;
    let writer = if without_labels { writer.without_labels()? } else { writer };
    let writer = match &opts.traversal {
        Some(name) => writer.with_traversal(crate::map::TraversalPlan::Named(name.clone()))?,
        None => writer,
    };
    Ok((encoder, writer))
}

/// Whether a map build makes the approximate index (`map build --index`, Python's
/// `Map.build(index=)`): one policy, so that the front ends build the same map from the same
/// folder and config.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum IndexPolicy {
    /// When the map holds at least `index.min_places` images (and appearance).
    #[default]
    Auto,
    /// Always (the map must hold appearance vectors).
    Ivf,
    /// Never.
    None,
}

impl crate::Choice for IndexPolicy {
    const CHOICES: &'static [Self] = &[IndexPolicy::Auto, IndexPolicy::Ivf, IndexPolicy::None];
    fn name(self) -> &'static str {
        match self {
            IndexPolicy::Auto => "auto",
            IndexPolicy::Ivf => "ivf",
            IndexPolicy::None => "none",
        }
    }
    fn help(self) -> &'static str {
        match self {
            IndexPolicy::Auto => "When the map holds at least `index.min_places` images (and appearance)",
            IndexPolicy::Ivf => "Always (the map must hold appearance vectors)",
            IndexPolicy::None => "Never",
        }
    }
}

/// How [`build_map`] builds a map: the layout of a new one, its index, its frame interval.
#[derive(Debug, Clone, Default)]
pub struct BuildOptions {
    /// The new map's layout, and whether an interrupted build is continued (`new.resume`).
    pub new: NewMapOptions,
    /// Whether the approximate index is built.
    pub index: IndexPolicy,
    /// The interval between the frames, in seconds, where they are timed (the stream's rate).
    pub frame_interval: Option<f64>,
}

/// What [`build_map`] is about to do, or has just done, as it goes (a front end says it in its
/// words before the long work that follows).
#[derive(Debug)]
pub enum BuildStep<'a> {
    /// An interrupted build is continued: the images its map holds, and its generation.
    Resuming {
        /// Images the map holds.
        images: usize,
        /// The map's generation.
        generation: u64,
    },
    /// The frames are encoded and committed.
    Encoded(&'a IntoReport),
    /// The approximate index of this many images is being built.
    BuildingIndex {
        /// Images the index covers.
        images: usize,
    },
    /// The approximate index is built (before the null of `verified`'s evidence is measured).
    Indexed(&'a crate::map::index::IndexReport),
    /// The null of `verified`'s evidence is measured and stored, in this many milliseconds.
    NullStored(&'a crate::matching::null::NullEvidence, f64),
}

/// The map build every front end runs (`semlook map build`, Python's `Map.build`): a new map in
/// `dir` of `frames` (or, with `opts.new.resume` and a manifest there, the interrupted build
/// continued, which must be given the layout it had), every frame encoded and committed, the
/// index where `opts.index` asks for it (a continued build that has one keeps it current), then
/// the null of `verified`'s evidence (after the index, whose candidates queries see). `step`
/// hears each [`BuildStep`] as it comes: what the build did is said there, once.
#[allow(clippy::too_many_arguments)]
pub fn build_map(
    engine: &mut Engine,
    cfg: &crate::config::Config,
    frames: &[FrameSource],
    fmt: LabelFormat,
    poses: Option<&PlacePoses>,
    dir: &std::path::Path,
    opts: &BuildOptions,
    step: &dyn Fn(BuildStep<'_>),
) -> Result<crate::map::Map> {
    use crate::map::{Map, TraversalPlan};
    use crate::values::ValueType;
    let new = &opts.new;
    let resuming = new.resume && dir.join(crate::map::manifest::MANIFEST).exists();
    let (encoder, mut writer) = if resuming {
        let map = Map::open(dir)?;
        map.check_compatible(&cfg.encoding())?;
        // every layout option of the interrupted build must be given again as it was
        let layout = [
            ("HOG descriptors", map.manifest.hog_dim > 0, new.hog),
            ("f16 values", map.manifest.values == ValueType::F16, new.store.values == ValueType::F16),
        ];
        if let Some((what, _, given)) = layout.into_iter().find(|(_, stored, given)| stored != given) {
            let (asked, had) = if given { ("asked for", "stored none") } else { ("not asked for", "stored them") };
            return Err(Error::refused(
                format!("map {}", dir.display()),
                format!("{what} are {asked}, but the interrupted build {had}: resume with the same layout options"),
                crate::error::Remedy::ResumeWithSameLayout,
            ));
        }
        let encoder = Encoder::for_map(cfg, &map)?.with_hog(new.hog);
        step(BuildStep::Resuming { images: map.len(), generation: map.manifest.generation });
        let plan = new.traversal.clone().map_or(TraversalPlan::Last, TraversalPlan::Named);
        (encoder, MapWriter::append(dir, new.store)?.with_traversal(plan)?)
    } else {
        new_map(cfg, frames, dir, new)?
    };
    if let Some(dt) = opts.frame_interval {
        writer = writer.with_frame_interval(dt)?;
    }
    let into = IntoOptions { skip_invalid: new.skip_invalid, skip_stored: new.resume, quiet: new.quiet, poses };
    let encoding = encode_into(engine, &encoder, frames, fmt, &mut writer, into)?;
    step(BuildStep::Encoded(&encoding));
    let map = writer.finish()?;
    let map = with_index(map, cfg, opts.index, step)?;
    let (map, null) = engine.store_null(map, cfg)?;
    if let Some((n, ms)) = &null {
        step(BuildStep::NullStored(n, *ms));
    }
    Ok(map)
}

/// The index `policy` asks for, built where the map has none yet.
fn with_index(map: crate::map::Map, cfg: &crate::config::Config, policy: IndexPolicy, step: &dyn Fn(BuildStep<'_>)) -> Result<crate::map::Map> {
    let wanted = match policy {
        IndexPolicy::None => false,
        IndexPolicy::Ivf => true,
        IndexPolicy::Auto => map.len() >= cfg.index.min_places && map.manifest.appearance_dim > 0,
    };
    if !wanted || map.manifest.index.is_some() {
        return Ok(map);
    }
    let dir = map.path.clone();
    if map.manifest.appearance_dim == 0 {
        return Err(Error::refused(
            format!("map {}", dir.display()),
            "an approximate index needs appearance vectors (a map built without the keypoint network has none)",
            crate::error::Remedy::NoIndexWithoutAppearance,
        ));
    }
    let n = map.len();
    drop(map);
    step(BuildStep::BuildingIndex { images: n });
    let r = crate::map::index::build(&dir, &crate::index::IndexParams::from_config(&cfg.index, n), cfg.index.probe, cfg.index.shortlist)?;
    step(BuildStep::Indexed(&r));
    crate::map::Map::open(&dir)
}
