//! The [`Localizer`]: one generation of a map held open, the encoder for it, the sequence ring
//! and, in loop-closure mode, the writer; one frame at a time.

use super::latency::Latency;
use super::sequence::{contributions, SequenceMatch, SequenceMatcher};
use super::types::{Answer, AnswerSource, FrameResult, LoopClosure, Pixels, PlaceMatch, SequenceResult, StreamCounts, StreamFrame, StreamOptions};
use crate::config::{Config, SequenceRows};
use crate::descriptors::source::{GlobalSource, Place, RefSource, Window};
use crate::descriptors::EncodedImage;
use crate::encode::{Encoder, Loaded, StageTimes};
use crate::engine::Engine;
use crate::error::{Error, Result};
use crate::input::LabelFormat;
use crate::map::{manifest, ColumnDims, Map, MapWriter, StoreOptions, TraversalPlan};
use crate::matching::{Candidate, QueryMatch, Setting};
use crate::util::ms_since;
use crate::verify::pose::{Camera, PoseParams};
use crate::verify::VerifyParams;
use std::collections::{HashMap, HashSet, VecDeque};
use std::path::{Path, PathBuf};
use std::time::Instant;

/// Loop-closure state: the writer of the stream's traversal and what the exclusion needs.
struct LoopState {
    writer: Option<MapWriter>,
    dir: PathBuf,
    /// Frames of the stream added so far (committed or buffered in the writer).
    added: u64,
    /// (position along the stream's traversal, timestamp) of the frames added within
    /// `stream.exclude_seconds`.
    recent: VecDeque<(u64, f64)>,
    /// Before the map exists: the first frames, decoded, to train its codebook on.
    warm: Vec<(String, Loaded, Option<f64>)>,
    /// A resumed stream: the traversal it continues (known before the writer's first commit).
    resumed: Option<u32>,
    /// A resumed stream: the ids the map held when it was opened.
    held: HashSet<String>,
}

impl LoopState {
    fn new(dir: &Path, writer: Option<MapWriter>) -> LoopState {
        LoopState { writer, dir: dir.to_path_buf(), added: 0, recent: VecDeque::new(), warm: vec![], resumed: None, held: HashSet::new() }
    }
}

/// Tracking: the last accepted sequence match (place, velocity) and the frames since it.
#[derive(Debug, Clone, Copy, Default)]
struct Track {
    at: Option<(Place, f32)>,
    misses: usize,
}

/// Localizes a stream of frames against a map, one frame at a time.
pub struct Localizer {
    engine: Engine,
    encoder: Encoder,
    cfg: Config,
    opts: StreamOptions,
    map: Option<Map>,
    dir: PathBuf,
    seq: SequenceMatcher,
    track: Track,
    lc: Option<LoopState>,
    counts: StreamCounts,
    last_timestamp: Option<f64>,
    last_size: Option<(u32, u32)>,
    format: LabelFormat,
    /// The velocity range's scale and what it follows.
    rate: Rate,
    /// `stream.embed_when_tracking = false` on a map with embeddings: the encoder of the frames
    /// searched within the tracking window (no embedding).
    tracked: Option<Encoder>,
    /// The camera's intrinsics and the matching of a pair, for the relative poses.
    camera: Option<(Camera, VerifyParams)>,
    /// The size of the frame being located, as it came (the intrinsics' scale).
    frame_size: (u32, u32),
    /// The newest generation, refused by [`Localizer::refresh`] for a damaged file: a next try
    /// at the same generation takes its checks over.
    refused: Option<Map>,
}

/// Frames in a row whose best trajectory runs at the velocity range's edge before the warning
/// (at most `sequence.length`).
const EDGE_FRAMES: usize = 8;

/// Frames to measure a stream's frame interval over (the median step of their timestamps).
const INTERVAL_FRAMES: usize = 15;

/// The stream's frame rate against the map's, and the trajectories at the velocity range's edge.
#[derive(Debug, Clone, Default)]
struct Rate {
    /// The last steps between the stream's timestamps, seconds.
    steps: VecDeque<f64>,
    /// Frames in a row whose best trajectory ran at the range's edge.
    edge_run: usize,
    /// The edge was warned about (once per stream).
    warned: bool,
}

impl Rate {
    /// The stream's frame interval: the median of the last steps.
    fn interval(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.steps.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    }
}

/// Counts the frames whose best trajectory runs at the velocity range's edge, or is refused for
/// want of the newest frame's support (a trajectory left behind a camera the range does not
/// follow), and warns once [`EDGE_FRAMES`] of them come in a row: the camera is likely faster than
/// the range follows.
fn watch_edge(seq: &SequenceMatcher, cfg: &crate::config::SequenceConfig, rate: &mut Rate, counts: &mut StreamCounts, m: Option<&SequenceMatch>) {
    let (lo, hi) = seq.velocity_range();
    let at_edge = m.is_some_and(|m| {
        let v = m.velocity as f64;
        m.frames > 1 && ((v - hi).abs() < 1e-3 * hi.abs().max(1.0) || (lo < 0.0 && (v - lo).abs() < 1e-3 * lo.abs().max(1.0)))
    });
    let unsupported = m.is_some_and(|m| m.frames >= cfg.min_frames && !m.supported);
    counts.velocity_edge += u64::from(at_edge);
    counts.unsupported += u64::from(unsupported);
    match at_edge || unsupported {
        true => rate.edge_run += 1,
        false => rate.edge_run = 0,
    }
    if rate.edge_run >= EDGE_FRAMES.min(cfg.length).max(2) && !rate.warned {
        rate.warned = true;
        log::warn!(
            "sequence: the best trajectory has run at the edge of the velocity range ({lo:.2} to {hi:.2} positions per frame), or without \
             the newest frame's support, for {} frames: \
             the camera may move faster than the range follows (a map and a stream at other frame rates?); give the map's \
             images and the stream's frames timestamps, or set sequence.velocity_scale (docs/streams.md, \"Rates\")",
            rate.edge_run
        );
    }
}

/// The encoder of tracked frames where `stream.embed_when_tracking` is off and `encoder` embeds.
fn lean_encoder(cfg: &Config, encoder: &Encoder) -> Option<Encoder> {
    (!cfg.stream.embed_when_tracking && encoder.embedder().is_some()).then(|| encoder.clone().without_embedding())
}

/// The median frame interval of the map's timed traversals.
fn map_interval(map: &Map) -> Option<f64> {
    let mut v: Vec<f64> = map.manifest.frame_intervals.values().copied().collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

impl Localizer {
    /// A localizer over `map`, which the caller opened (and may have read its configuration
    /// from), with `cfg` (its encoding must be the map's; `None`: the map's own), running on
    /// `engine`. With `opts.loop_closure`, the stream's frames are added to this map as a new
    /// traversal (with `opts.resume`, its last traversal is continued: a restarted stream).
    /// Settings the map cannot serve are refused here.
    fn new(map: Map, cfg: Option<Config>, opts: StreamOptions, engine: Engine) -> Result<Localizer> {
        let cfg = cfg.unwrap_or_else(|| map.query_config());
        if !opts.loop_closure {
            return Localizer::with_map(map, cfg, opts, engine, None);
        }
        let opts = StreamOptions { loop_closure: true, sequence: true, ..opts };
        let plan = if opts.resume { TraversalPlan::Last } else { TraversalPlan::New };
        let writer = MapWriter::append(&map.path, StoreOptions::default())?.with_traversal(plan)?;
        let mut state = LoopState::new(&map.path, Some(writer));
        if opts.resume {
            // the last traversal goes on where the stream stopped: its frames are the ones
            // the restarted stream does not add again
            let last = manifest::traversal_names(&map.manifest).len().saturating_sub(1) as u32;
            state.resumed = Some(last);
            state.added = map.traversal_len(last) as u64;
            state.held = (0..map.len()).map(|i| map.id(i).to_string()).collect();
        }
        Localizer::with_map(map, cfg, opts, engine, Some(state))
    }

    /// The map a stream over `dir` runs on, opened once (a caller may read its configuration
    /// before [`Localizer::over`]): `None` only in loop-closure mode for a folder without a map
    /// (a new one, or a first build not committed).
    pub fn open_map(dir: &Path, loop_closure: bool) -> Result<Option<Map>> {
        match loop_closure {
            true => Map::open_if_exists(dir),
            false => Map::open(dir).map(Some),
        }
    }

    /// A localizer over what [`Localizer::open_map`] gave for `dir`: over the map (with `cfg`, its
    /// encoding the map's; `None`: the map's own configuration; settings the map cannot serve are
    /// refused here; with `opts.loop_closure` the stream's frames are added to it as a new
    /// traversal, or with `opts.resume` its last one continued), or, in loop-closure mode without one, a map started from the stream (its codebook
    /// trained on the first min(`appearance.codebook_images`, `stream.exclude_frames`) frames,
    /// answered without a match: nothing older exists to match them against).
    pub fn over(map: Option<Map>, dir: &Path, cfg: Option<Config>, opts: StreamOptions, engine: Engine) -> Result<Localizer> {
        match map {
            Some(map) => Localizer::new(map, cfg, opts, engine),
            None if opts.loop_closure => Localizer::create(dir, cfg, opts, engine),
            None => Localizer::new(Map::open(dir)?, cfg, opts, engine),
        }
    }

    /// A localizer over the map in `dir` ([`Localizer::open_map`], then [`Localizer::over`]).
    pub fn open(dir: &Path, cfg: Option<Config>, opts: StreamOptions, engine: Engine) -> Result<Localizer> {
        Localizer::over(Localizer::open_map(dir, opts.loop_closure)?, dir, cfg, opts, engine)
    }

    /// Loop-closure mode in `dir`, which holds no map yet.
    fn create(dir: &Path, cfg: Option<Config>, opts: StreamOptions, engine: Engine) -> Result<Localizer> {
        let opts = StreamOptions { loop_closure: true, sequence: true, ..opts };
        // a stream killed before its map's first commit left no map: it starts anew (files of the
        // unfinished build taken over with `resume`)
        MapWriter::check_new_dir(dir, opts.resume)?;
        let cfg = cfg.unwrap_or_default();
        cfg.validate("configuration")?;
        let encoder = Encoder::new(&cfg)?.with_hog(opts.setting == Setting::Hog);
        // photos without label maps and no segmenter: encoded without labels (the map says so)
        let can_segment = encoder.frames().can_segment();
        let encoder = encoder.without_labels(!can_segment);
        Ok(Localizer {
            seq: SequenceMatcher::new(&cfg.sequence),
            engine,
            encoder,
            cfg,
            opts,
            map: None,
            dir: dir.to_path_buf(),
            track: Track::default(),
            lc: Some(LoopState::new(dir, None)),
            counts: StreamCounts::default(),
            last_timestamp: None,
            last_size: None,
            format: LabelFormat::default(),
            rate: Rate::default(),
            tracked: None,
            camera: None,
            frame_size: (0, 0),
            refused: None,
        })
    }

    fn with_map(map: Map, cfg: Config, opts: StreamOptions, engine: Engine, lc: Option<LoopState>) -> Result<Localizer> {
        cfg.validate("configuration")?;
        crate::matching::check_labels(&map, opts.setting)?;
        if opts.setting.is_baseline() && opts.setting == Setting::Hog && map.manifest.hog_dim == 0 {
            return Err(Error::invalid(format!("setting {}", opts.setting), "the map stores no HOG descriptors"));
        }
        let encoder = Encoder::for_map(&cfg, &map)?.with_hog(opts.setting == Setting::Hog);
        // photos without label maps: segmented, label-free where nothing reads labels, else
        // refused now rather than frame by frame
        let encoder = match opts.labelled_frames {
            true => encoder,
            false => {
                let free = encoder.photos_rule(Some(opts.setting), &format!("the stream's frames (map {})", map.path.display()))?;
                encoder.without_labels(free || map.manifest.without_labels)
            }
        };
        let tracked = lean_encoder(&cfg, &encoder);
        // the map's checks now, not in the first frame's search (a damaged map is refused here)
        prepare(&map, &cfg)?;
        Ok(Localizer {
            tracked,
            seq: SequenceMatcher::new(&cfg.sequence),
            engine,
            encoder,
            cfg,
            opts,
            dir: map.path.clone(),
            map: Some(map),
            track: Track::default(),
            lc,
            counts: StreamCounts::default(),
            last_timestamp: None,
            last_size: None,
            format: LabelFormat::default(),
            rate: Rate::default(),
            camera: None,
            frame_size: (0, 0),
            refused: None,
        })
    }

    /// The camera's intrinsics (checked: [`Camera::check`]): an accepted answer (and a loop
    /// closure) then carries the frame's pose relative to the place's ([`FrameResult::relative_pose`]),
    /// estimated from the pair's keypoint matches as verification makes them. The map's
    /// references are taken to be of the same camera (a loop closure's are: the stream's own
    /// frames); a frame of another aspect ratio gets no pose. A map without verification
    /// keypoints is refused (a loop-closure map the stream starts: an encoder whose network
    /// detects none); the first closures of a new map get poses.
    pub fn with_camera(mut self, camera: Camera) -> Result<Localizer> {
        self.set_camera(camera)?;
        Ok(self)
    }

    /// [`with_camera`](Self::with_camera) on a localizer already running (a ROS 2 node's camera
    /// intrinsics come on a topic, after the localizer has started): the same checks, then the
    /// frames pushed from now on get relative poses with these intrinsics (replacing any the
    /// localizer had). Refused (the intrinsics or the map), the localizer keeps the camera it had.
    pub fn set_camera(&mut self, camera: Camera) -> Result<()> {
        camera.check().map_err(|r| Error::invalid("camera intrinsics", r))?;
        // a map this stream starts has its keypoints once its first frames trained the codebook:
        // what counts until then is whether the encoder's network detects them
        let keypoints = match &self.map {
            Some(_) => self.encoder.keypoint_dim() > 0,
            None => self.encoder.appearance().is_some_and(|a| a.model().detects()),
        };
        if !keypoints {
            return Err(Error::invalid(
                "camera intrinsics",
                "the map stores no verification keypoints (built without appearance), so no relative pose can be estimated",
            ));
        }
        let classes = crate::classes::ClassTable::from_config(&self.cfg.classes)?;
        let vp = VerifyParams::for_config(&self.cfg.verification, &classes)?;
        self.camera = Some((camera, vp));
        Ok(())
    }

    /// How label files of [`Pixels::Files`] frames encode classes (default: ids).
    pub fn with_label_format(mut self, format: LabelFormat) -> Localizer {
        self.format = format;
        self
    }

    /// The camera intrinsics of the relative poses ([`Localizer::set_camera`]), if any.
    pub fn camera(&self) -> Option<Camera> {
        self.camera.as_ref().map(|(c, _)| *c)
    }

    /// The map generation frames are answered from (`None` while a loop-closure map warms up).
    pub fn map(&self) -> Option<&Map> {
        self.map.as_ref()
    }
    /// The configuration frames are encoded and matched with.
    pub fn config(&self) -> &Config {
        &self.cfg
    }
    /// The encoder frames are encoded with (the map's).
    pub fn encoder(&self) -> &Encoder {
        &self.encoder
    }
    /// How the stream is matched.
    pub fn options(&self) -> StreamOptions {
        self.opts
    }
    /// Counters of the stream so far.
    pub fn counts(&self) -> StreamCounts {
        self.counts
    }
    /// The engine frames run on.
    pub fn engine(&self) -> &Engine {
        &self.engine
    }
    /// A resumed loop-closure stream ([`StreamOptions::resume`]): whether the map held a frame of
    /// this id when it was opened (the frame was stored before a restart: skip it).
    pub fn holds(&self, id: &str) -> bool {
        self.lc.as_ref().is_some_and(|l| l.held.contains(id))
    }

    /// What the stream keeps: frames in the ring and their entries.
    pub fn state_size(&self) -> (usize, usize) {
        (self.seq.frames(), self.seq.entries())
    }

    /// Forgets the stream's past (ring and tracking): the next frame starts a new sequence.
    pub fn reset(&mut self) {
        self.seq.clear();
        self.track = Track::default();
        self.last_timestamp = None;
        self.last_size = None;
        self.rate = Rate::default();
    }

    /// Moves to the map's newest generation when another writer committed one (an add, a removal,
    /// a compaction, a rebuild): the frames answered so far keep theirs, the next ones get the
    /// new one, and the ring follows the places that are still there. Returns whether it moved.
    /// On an error (a map being replaced, another encoding) the old generation stays in use.
    pub fn refresh(&mut self) -> Result<bool> {
        let Some(old) = &self.map else { return Ok(false) };
        let m = manifest::read_existing(&self.dir)?;
        if m.generation == old.manifest.generation && m.uid == old.manifest.uid {
            return Ok(false);
        }
        let new = old.reopen()?;
        // the generation refused last time fails at once; a later one is checked again
        if let Some(r) = self.refused.as_ref().filter(|r| r.manifest.generation == new.manifest.generation) {
            new.inherit_checks(r);
        }
        let encoder = match new.manifest.uid == old.manifest.uid {
            true => None,
            false => Some(Encoder::for_map(&self.cfg, &new)?.with_hog(self.opts.setting == Setting::Hog)),
        };
        crate::matching::check_labels(&new, self.opts.setting)?;
        // the new files' checks, on this thread between frames; a generation refused for damage
        // is kept so that the next try takes its checks over and fails at once
        if let Err(e) = prepare(&new, &self.cfg) {
            self.refused = Some(new);
            return Err(e);
        }
        self.refused = None;
        if !follow(&mut self.seq, old, &new) {
            self.track = Track::default();
        }
        if let Some(e) = encoder {
            self.tracked = lean_encoder(&self.cfg, &e);
            self.encoder = e;
        }
        self.map = Some(new);
        self.counts.reloads += 1;
        Ok(true)
    }

    /// What decodes frames to the working size (the labels read or made as `map build` does):
    /// cheap to clone, so another thread can decode the next frame while this one is matched
    /// (`load_frame`, then [`Localizer::push_loaded`]).
    pub fn loader(&self) -> FrameDecoder {
        FrameDecoder { encoder: self.encoder.clone(), format: self.format }
    }

    /// Localizes the next frame. A frame that cannot be used (undecodable, of a timestamp before
    /// the previous one's) is refused with its error, counted, and leaves the stream as it was.
    pub fn push(&mut self, frame: StreamFrame) -> Result<FrameResult> {
        let t0 = Instant::now();
        let StreamFrame { id, pixels, timestamp } = frame;
        let meta = FrameMeta { id, timestamp };
        let loaded = match self.check_timestamp(&meta) {
            Ok(()) => load_frame(&self.encoder, &meta.id, pixels, self.format),
            Err(e) => Err(e),
        };
        self.push_loaded_at(meta, loaded, t0)
    }

    /// [`Localizer::push`] of a frame decoded by [`Localizer::loader`] (perhaps on another thread).
    pub fn push_loaded(&mut self, id: String, timestamp: Option<f64>, loaded: Result<Loaded>) -> Result<FrameResult> {
        self.push_loaded_at(FrameMeta { id, timestamp }, loaded, Instant::now())
    }

    /// Errors of the frame itself (it cannot be read, decoded or encoded, or its time goes back)
    /// are counted in [`StreamCounts::refused`]; other errors (the map, the device) are not.
    fn push_loaded_at(&mut self, meta: FrameMeta, loaded: Result<Loaded>, t0: Instant) -> Result<FrameResult> {
        let index = self.counts.frames;
        self.counts.frames += 1;
        match self.check_timestamp(&meta).and(loaded) {
            Ok(l) => self.locate_loaded(index, &meta, l, t0),
            Err(e) => {
                self.counts.refused += 1;
                Err(e)
            }
        }
    }

    fn check_timestamp(&self, frame: &FrameMeta) -> Result<()> {
        match (frame.timestamp, self.last_timestamp) {
            (Some(t), _) if !t.is_finite() => Err(Error::invalid(format!("frame {:?}", frame.id), format!("timestamp {t} is not a finite number"))),
            (Some(t), Some(last)) if t < last => Err(Error::invalid(
                format!("frame {:?}", frame.id),
                format!("timestamp {t} is before the previous frame's ({last}): refused (frames must come in time order)"),
            )),
            _ => Ok(()),
        }
    }

    fn locate_loaded(&mut self, index: u64, frame: &FrameMeta, loaded: Loaded, t0: Instant) -> Result<FrameResult> {
        let size = loaded.source_size;
        let mut latency = Latency { decode_ms: loaded.times.decode_ms, segment_ms: loaded.times.segment_ms, ..Latency::default() };
        if self.map.is_none() {
            return self.warm_up(index, frame, loaded, latency, t0);
        }
        // a frame searched within the tracking window goes without its embedding where asked
        let lean = self.tracked.is_some() && self.map.as_ref().is_some_and(|m| self.search_range(m, frame.timestamp).1);
        let (img, times) = match self.encode_one(&frame.id, loaded, lean) {
            Ok(v) => v,
            Err(e) => {
                if !matches!(e, Error::Gpu(_)) {
                    self.counts.refused += 1;
                }
                return Err(e);
            }
        };
        add_times(&mut latency, &times);
        let size_changed = self.last_size.is_some_and(|s| s != size);
        self.last_size = Some(size);
        self.frame_size = size;
        if let Some(t) = frame.timestamp {
            if let Some(step) = self.last_timestamp.map(|last| t - last).filter(|&d| d > 0.0) {
                if self.rate.steps.len() == INTERVAL_FRAMES {
                    self.rate.steps.pop_front();
                }
                self.rate.steps.push_back(step);
            }
            self.last_timestamp = Some(t);
        }
        let mut r = self.locate(index, frame, &img, latency, t0, lean)?;
        r.size_changed = size_changed;
        if self.lc.is_some() {
            let t = Instant::now();
            self.store(&img, frame.timestamp)?;
            r.latency.store_ms = ms_since(t);
        }
        r.latency.total_ms = ms_since(t0);
        r.latency.arrival_ms = r.latency.total_ms;
        Ok(r)
    }

    fn encode_one(&mut self, id: &str, loaded: Loaded, lean: bool) -> Result<(EncodedImage, StageTimes)> {
        let encoder = match (lean, &self.tracked) {
            (true, Some(e)) => e,
            _ => &self.encoder,
        };
        let mut out = self.engine.encode_loaded(encoder, vec![(id.to_string(), Ok(loaded))])?;
        out.pop().unwrap_or_else(|| Err(Error::invalid(format!("frame {id:?}"), "not encoded")))
    }

    /// The part of the map this frame may be matched against (index range), and whether it is a
    /// tracking window.
    fn search_range(&self, map: &Map, timestamp: Option<f64>) -> (std::ops::Range<usize>, bool) {
        let all = 0..map.len();
        if let Some(lc) = &self.lc {
            let Some(t) = lc.writer.as_ref().and_then(MapWriter::traversal).or(lc.resumed) else { return (all, false) };
            let st = &self.cfg.stream;
            let mut excluded = (st.exclude_frames as u64).min(lc.added);
            if let (Some(now), true) = (timestamp, st.exclude_seconds > 0.0) {
                let within = lc.recent.iter().filter(|(_, ts)| now - ts < st.exclude_seconds).count() as u64;
                excluded = excluded.max(within);
            }
            let cutoff = (lc.added - excluded) as u32;
            return match map.at(Place { traversal: t, position: cutoff }) {
                Some(i) => (0..i, false),
                None => (all, false),
            };
        }
        let st = &self.cfg.stream;
        match self.track.at {
            Some((p, v)) if st.track_radius > 0 => {
                // where the last accepted match, moving on at its velocity, is now
                let ahead = (self.track.misses + 1) as f64;
                let centre = (p.position as f64 + v as f64 * ahead).round().max(0.0) as u32;
                let r = st.track_radius as u32;
                let lo = centre.saturating_sub(r);
                let hi = (centre + r).min(map.traversal_len(p.traversal).saturating_sub(1));
                match (map.at(Place { traversal: p.traversal, position: lo }), map.at(Place { traversal: p.traversal, position: hi })) {
                    // one contiguous run of the map's indices
                    (Some(a), Some(b)) if b >= a && b - a == (hi - lo) as usize => (a..b + 1, true),
                    _ => (all, false),
                }
            }
            _ => (all, false),
        }
    }

    fn locate(&mut self, index: u64, frame: &FrameMeta, img: &EncodedImage, mut latency: Latency, t0: Instant, lean: bool) -> Result<FrameResult> {
        let map = self.map.as_ref().ok_or_else(|| Error::invalid("stream", "no map"))?;
        let (range, tracking) = self.search_range(map, frame.timestamp);
        let src = Window::new(map, range);
        let mut queries = match (lean, &self.tracked) {
            (true, Some(e)) => e.descriptor_set(),
            _ => self.encoder.descriptor_set(),
        };
        queries.push(img).map_err(|e| e.named(|r| Error::invalid(format!("frame {:?}", frame.id), r)))?;
        let setting = self.opts.setting;
        let full_rows = self.opts.sequence && self.cfg.sequence.rows == SequenceRows::Full;
        let cfg_rows;
        let cfg = match full_rows {
            true => {
                cfg_rows = Config {
                    matching: crate::config::MatchingConfig { top_k: GlobalSource::len(&src).max(1), ..self.cfg.matching.clone() },
                    ..self.cfg.clone()
                };
                &cfg_rows
            }
            false => &self.cfg,
        };
        let (mut matches, times) = self.engine.match_batch(&src, &queries, setting, cfg)?;
        latency.coarse_ms = times.coarse_ms;
        latency.fine_ms = times.fine_ms;
        let matched = matches.pop().unwrap_or(QueryMatch { ranked: vec![], evidence: None });
        let ranked = &matched.ranked;
        let report = |c: &Candidate| PlaceMatch {
            index: src.inner_index(c.reference as usize) as u32,
            id: src.id(c.reference as usize).to_string(),
            place: src.place(c.reference as usize),
            score: c.score,
            inliers: c.inliers,
        };
        let top_k: Vec<PlaceMatch> = ranked.iter().take(self.cfg.matching.top_k).map(report).collect();
        let mut sequence = None;
        let mut answer = top_k.first().map(|b| Answer {
            index: b.index,
            id: b.id.clone(),
            place: b.place,
            score: b.score,
            source: AnswerSource::Frame,
            accepted: false,
        });
        if self.opts.sequence {
            let t = Instant::now();
            let widen = if full_rows { 0 } else { self.cfg.sequence.widen };
            let scored =
                scored_rows(&mut self.engine, &src, &queries, std::slice::from_ref(&matched), setting, &self.cfg, widen)?.pop().unwrap_or_default();
            let lens = |t: u32| map.traversal_len(t);
            let row = contributions(&self.cfg.sequence, &scored, &lens);
            // the velocity range follows the stream's frame rate against the map's
            let scale = match (self.cfg.sequence.velocity_scale, self.rate.interval(), map_interval(map)) {
                (Some(k), _, _) => k,
                (None, Some(stream), Some(map)) => (stream / map).clamp(1.0 / 64.0, 64.0),
                _ => 1.0,
            };
            if (scale / self.seq.velocity_scale() - 1.0).abs() > 0.05 {
                log::info!("sequence: velocity range x{scale:.3} (the stream's frame interval over the map's)");
                self.seq.set_velocity_scale(scale);
            }
            let m = self.seq.push(row, &lens);
            let velocity_scale = self.seq.velocity_scale();
            sequence =
                m.and_then(|m| map.at(m.place).map(|i| SequenceResult { index: i as u32, id: map.id(i).to_string(), matched: m, velocity_scale }));
            watch_edge(&self.seq, &self.cfg.sequence, &mut self.rate, &mut self.counts, sequence.as_ref().map(|s| &s.matched));
            if let Some(s) = sequence.as_ref().filter(|s| s.matched.accepted) {
                // the answer's score on the frame's scale: the place's score in this frame's row,
                // or (a place the row did not reach) scored now, as its neighbours were
                let score = match scored.iter().find(|(p, _)| *p == s.matched.place) {
                    Some(&(_, v)) => v,
                    None => {
                        let evidence = [matched.evidence];
                        let c = self.engine.score_pairs(map, &queries, setting, &self.cfg, &[(0, s.index)], Some(&evidence))?;
                        c.first().map_or(f32::NEG_INFINITY, |c| c.score)
                    }
                };
                answer =
                    Some(Answer { index: s.index, id: s.id.clone(), place: s.matched.place, score, source: AnswerSource::Sequence, accepted: true });
            }
            latency.sequence_ms = ms_since(t);
        }
        // tracking follows accepted matches, and lets go after `lost_after` frames without one
        match &sequence {
            Some(s) if s.matched.accepted => {
                self.track = Track { at: Some((s.matched.place, s.matched.velocity)), misses: 0 };
                self.counts.accepted += 1;
            }
            _ => {
                self.track.misses += 1;
                if self.track.misses >= self.cfg.stream.lost_after {
                    self.track.at = None;
                }
            }
        }
        // the relative pose of an accepted answer, with the camera's intrinsics
        let (mut relative_pose, mut relative_pose_refused) = (None, None);
        if let (Some((camera, vp)), Some(a)) = (&self.camera, answer.as_ref().filter(|a| a.accepted)) {
            let t = Instant::now();
            let (w, h) = self.frame_size;
            let found = match camera.fits(w, h) {
                false => Err(format!(
                    "the frame is {w} x {h}, the camera's intrinsics are for {} x {} (another aspect ratio)",
                    camera.width, camera.height
                )),
                true => {
                    let (q, r) = (queries.keypoints(0), map.keypoints(a.index as usize));
                    let m = crate::verify::pair_matches(vp, q, r)?;
                    crate::verify::pose::pair_pose(camera, q, r, &m, &PoseParams::for_camera(camera, vp.ransac.seed)).map_err(|e| e.to_string())
                }
            };
            match found {
                Ok(p) => relative_pose = Some(p),
                Err(e) => relative_pose_refused = Some(e),
            }
            latency.pose_ms = ms_since(t);
        }
        let st = &self.cfg.stream;
        let closes = |m: &SequenceMatch| {
            m.accepted
                && m.uniqueness < super::sequence::UNIQUENESS_CAP
                && m.uniqueness as f64 >= st.closure_uniqueness
                && (m.velocity.abs() as f64) >= st.closure_min_velocity
                && m.score as f64 >= st.closure_min_score
        };
        let closure = match (&self.lc, &sequence) {
            (Some(_), Some(s)) if closes(&s.matched) => {
                self.counts.closures += 1;
                let inliers = ranked.iter().find(|c| src.inner_index(c.reference as usize) == s.index as usize).and_then(|c| c.inliers);
                Some(LoopClosure {
                    frame: frame.id.clone(),
                    place: PlaceMatch { index: s.index, id: s.id.clone(), place: s.matched.place, score: s.matched.score, inliers },
                    uniqueness: s.matched.uniqueness,
                    velocity: s.matched.velocity,
                    relative_pose,
                })
            }
            _ => None,
        };
        latency.total_ms = ms_since(t0);
        let mut r = FrameResult {
            frame: index,
            id: frame.id.clone(),
            answer,
            timestamp: frame.timestamp,
            generation: map.manifest.generation,
            top_k,
            sequence,
            closure,
            size_changed: false,
            tracking,
            embedded: !img.embedding.is_empty(),
            relative_pose,
            relative_pose_refused,
            warming_up: false,
            pose: None,
            latency,
        };
        r.pose = r.place_index().and_then(|i| map.pose(i as usize));
        Ok(r)
    }

    /// Loop-closure mode: adds the frame to the stream's traversal; commits every
    /// `stream.commit_frames` and moves to the generation of the commit.
    fn store(&mut self, img: &EncodedImage, timestamp: Option<f64>) -> Result<()> {
        let (commit, exclude_s) = (self.cfg.stream.commit_frames, self.cfg.stream.exclude_seconds);
        let Some(lc) = &mut self.lc else { return Ok(()) };
        let Some(w) = &mut lc.writer else { return Ok(()) };
        w.push(img)?;
        if let Some(t) = timestamp {
            lc.recent.push_back((lc.added, t));
            while lc.recent.front().is_some_and(|(_, ts)| t - ts >= exclude_s) {
                lc.recent.pop_front();
            }
        }
        lc.added += 1;
        if lc.added % commit as u64 == 0 {
            // the stream's traversal records its frame interval (what a later stream's range follows)
            if let Some(dt) = self.rate.interval() {
                w.set_frame_interval(dt)?;
            }
            w.flush()?;
            self.refresh()?;
        }
        Ok(())
    }

    /// Loop-closure mode before the map exists: keeps the frame; once enough frames are kept,
    /// trains the codebook on them, creates the map with them and opens it.
    fn warm_up(&mut self, index: u64, frame: &FrameMeta, loaded: Loaded, latency: Latency, t0: Instant) -> Result<FrameResult> {
        let size_changed = self.last_size.is_some_and(|s| s != loaded.source_size);
        self.last_size = Some(loaded.source_size);
        if let Some(t) = frame.timestamp {
            self.last_timestamp = Some(t);
        }
        let need = self.cfg.appearance.codebook_images.min(self.cfg.stream.exclude_frames).max(1);
        let lc = self.lc.as_mut().ok_or_else(|| Error::invalid("stream", "no map"))?;
        lc.warm.push((frame.id.clone(), loaded, frame.timestamp));
        self.counts.warm_up += 1;
        if lc.warm.len() >= need || self.encoder.appearance().is_none() {
            self.create_map()?;
        }
        Ok(FrameResult {
            frame: index,
            id: frame.id.clone(),
            answer: None,
            timestamp: frame.timestamp,
            generation: self.map.as_ref().map_or(0, |m| m.manifest.generation),
            top_k: vec![],
            sequence: None,
            closure: None,
            size_changed,
            tracking: false,
            embedded: false,
            relative_pose: None,
            relative_pose_refused: None,
            warming_up: true,
            pose: None,
            latency: Latency { total_ms: ms_since(t0), arrival_ms: ms_since(t0), ..latency },
        })
    }

    fn create_map(&mut self) -> Result<()> {
        // the stream's velocity scale (`--velocity-scale`) is this camera's, not the map's
        fn profile_of(cfg: &Config) -> Config {
            let mut c = cfg.clone();
            c.sequence.velocity_scale = Config::default().sequence.velocity_scale;
            c
        }
        let Some(lc) = &mut self.lc else { return Ok(()) };
        let warm = std::mem::take(&mut lc.warm);
        if let Some(a) = self.encoder.appearance_mut() {
            let model = a.model();
            let kps: Vec<crate::appearance::keypoints::Keypoints> =
                warm.iter().filter_map(|(_, l, _)| l.rgb.as_ref()).map(|rgb| model.keypoints(rgb)).collect::<Result<_>>()?;
            a.train_codebook_from(&kps.iter().collect::<Vec<_>>())?;
        }
        // frames without labels and no segmenter to make them: a map without labels
        let void = warm.iter().all(|(_, l, _)| l.labels.classes().iter().all(|&c| c == crate::classes::VOID));
        let dims = ColumnDims {
            appearance: self.encoder.appearance_dim(),
            hog: 0,
            keypoints: self.encoder.keypoint_dim(),
            compact_hog: self.encoder.compact_hog_dim(),
        };
        let mut w =
            MapWriter::create(&lc.dir, &self.cfg.encoding(), dims, self.encoder.appearance_record(), StoreOptions::default(), self.opts.resume)?
                .with_embedding(self.encoder.embedding_record())?
                .with_profile(&profile_of(&self.cfg))?;
        if void && !self.encoder.frames().can_segment() {
            w = w.without_labels()?;
        }
        let mut w = w.with_traversal(TraversalPlan::New)?;
        let ids: Vec<(String, Option<f64>)> = warm.iter().map(|(id, _, t)| (id.clone(), *t)).collect();
        let encoded = self.engine.encode_loaded(&self.encoder, warm.into_iter().map(|(id, l, _)| (id, Ok(l))).collect())?;
        let mut added = 0u64;
        for (r, (_, t)) in encoded.into_iter().zip(&ids) {
            w.push(&r?.0)?;
            if let Some(t) = t {
                lc.recent.push_back((added, *t));
            }
            added += 1;
        }
        w.flush()?;
        lc.added = added;
        lc.writer = Some(w);
        let map = Map::open(&lc.dir)?;
        crate::matching::check_labels(&map, self.opts.setting)?;
        prepare(&map, &self.cfg)?;
        self.map = Some(map);
        Ok(())
    }

    /// Commits what loop-closure mode buffered (also done when the localizer is dropped,
    /// errors then only logged).
    pub fn finish(&mut self) -> Result<()> {
        if self.map.is_none() && self.lc.as_ref().is_some_and(|l| !l.warm.is_empty()) {
            self.create_map()?;
        }
        if let Some(w) = self.lc.as_mut().and_then(|l| l.writer.as_mut()) {
            w.flush()?;
        }
        Ok(())
    }
}

impl Drop for Localizer {
    fn drop(&mut self) {
        if let Err(e) = self.finish() {
            log::error!("stream: the last frames were not committed: {e}");
        }
    }
}

/// Each query's scored places for sequence matching: its ranked candidates (`matches[q]`, in
/// `refs`' indices) with their scores, and the references within `widen` positions of them along
/// their traversals, scored by `setting` as if they had been candidates (all of a batch in one
/// call; `verified` weighs their evidence against the query's candidates').
pub fn scored_rows(
    engine: &mut Engine,
    refs: &dyn RefSource,
    queries: &crate::descriptors::DescriptorSet,
    matches: &[QueryMatch],
    setting: Setting,
    cfg: &Config,
    widen: usize,
) -> Result<Vec<Vec<(Place, f32)>>> {
    let mut rows: Vec<Vec<(Place, f32)>> =
        matches.iter().map(|m| m.ranked.iter().map(|c| (refs.place(c.reference as usize), c.score)).collect()).collect();
    let mut pairs: Vec<(u32, u32)> = Vec::new();
    for (q, list) in matches.iter().map(|m| &m.ranked).enumerate() {
        let have: HashSet<u32> = list.iter().map(|c| c.reference).collect();
        let mut extra: Vec<u32> = Vec::new();
        for c in list {
            let p = refs.place(c.reference as usize);
            for d in 1..=widen as u32 {
                for pos in [p.position.checked_sub(d), p.position.checked_add(d)].into_iter().flatten() {
                    if let Some(j) = refs.at(Place { traversal: p.traversal, position: pos }).map(|j| j as u32) {
                        if !have.contains(&j) && !extra.contains(&j) {
                            extra.push(j);
                        }
                    }
                }
            }
        }
        pairs.extend(extra.into_iter().map(|j| (q as u32, j)));
    }
    if !pairs.is_empty() {
        let evidence: Vec<Option<crate::matching::Evidence>> = matches.iter().map(|m| m.evidence).collect();
        let scores = engine.score_pairs(refs, queries, setting, cfg, &pairs, Some(&evidence))?;
        for (&(q, _), c) in pairs.iter().zip(&scores) {
            rows[q as usize].push((refs.place(c.reference as usize), c.score));
        }
    }
    Ok(rows)
}

/// Moves the ring's places from generation `old` to `new`: unchanged where `new` only appended
/// segments (true), else through the images' ids (false).
fn follow(seq: &mut SequenceMatcher, old: &Map, new: &Map) -> bool {
    let (a, b) = (&old.manifest.segments, &new.manifest.segments);
    if new.manifest.uid == old.manifest.uid && b.len() >= a.len() && a.iter().zip(b).all(|(x, y)| x == y) {
        return true;
    }
    let wanted: HashSet<&str> = seq.places().filter_map(|p| old.at(p)).map(|i| old.id(i)).collect();
    let found: HashMap<&str, usize> = (0..new.len()).map(|i| (new.id(i), i)).filter(|(id, _)| wanted.contains(*id)).collect();
    seq.remap(|p| old.at(p).and_then(|i| found.get(old.id(i))).map(|&j| new.place(j)));
    false
}

/// The checks of `map` a stream under `cfg` will need (its segments, and the index's codes where
/// its searches go through the index), run before a frame does.
fn prepare(map: &Map, cfg: &Config) -> Result<()> {
    map.prepare(crate::matching::searches_index(cfg, map.len()))
}

fn add_times(l: &mut Latency, t: &StageTimes) {
    l.decode_ms = t.decode_ms.max(l.decode_ms);
    l.segment_ms = t.segment_ms.max(l.segment_ms);
    l.encode_ms = t.encode_ms();
    l.network_ms = t.network_ms;
    l.embedding_ms = t.embedding_ms;
}

/// A frame's id and time, what matching needs of it besides its pixels.
struct FrameMeta {
    id: String,
    timestamp: Option<f64>,
}

/// Decodes frames for a [`Localizer`] (see [`Localizer::loader`]).
#[derive(Clone)]
pub struct FrameDecoder {
    encoder: Encoder,
    format: LabelFormat,
}

impl FrameDecoder {
    /// The frame's pixels at the working size, its labels read or made.
    pub fn load(&self, id: &str, pixels: Pixels) -> Result<Loaded> {
        load_frame(&self.encoder, id, pixels, self.format)
    }
}

fn load_frame(encoder: &Encoder, id: &str, pixels: Pixels, format: LabelFormat) -> Result<Loaded> {
    let loader = encoder.frames();
    match pixels {
        Pixels::Files(src) => loader.load(&src, format),
        Pixels::Bytes { bytes, labels } => loader.load_bytes(id, Path::new(id), bytes, labels),
        Pixels::Rgb { image, labels } => loader.load_arrays(id, Some(image), labels),
        Pixels::Labels(labels) => loader.load_arrays(id, None, Some(labels)),
    }
}
