//! The [`Localizer`]: one generation of a map held open, the encoder for it, the sequence ring
//! and, in loop-closure mode, the writer; one frame at a time.

use super::latency::Latency;
use super::sequence::{contributions, SequenceMatcher};
use super::types::{Answer, AnswerSource, FrameResult, LoopClosure, Pixels, PlaceMatch, SequenceResult, StreamCounts, StreamFrame, StreamOptions};
use crate::config::{Config, SequenceRows};
use crate::descriptors::source::{GlobalSource, Place, RefSource, Window};
use crate::descriptors::EncodedImage;
use crate::encode::{Encoder, Loaded, StageTimes};
use crate::engine::Engine;
use crate::error::{Error, Result};
use crate::input::LabelFormat;
use crate::map::{manifest, Map, MapWriter, StoreOptions, TraversalPlan};
use crate::matching::{Candidate, QueryMatch, Setting};
use crate::util::ms_since;
use crate::verify::pose::{Camera, PoseParams};
use crate::verify::VerifyParams;
mod clock;
mod closure;
mod tracking;

use clock::{check_timestamp, follow_rate, watch_edge, Rate};
use closure::{closes, LoopState};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::time::Instant;
use tracking::{follow, lean_encoder, tracking_window, Track};

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
        let loaded = match check_timestamp(&meta.id, meta.timestamp, self.last_timestamp) {
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
        match check_timestamp(&meta.id, meta.timestamp, self.last_timestamp).and(loaded) {
            Ok(l) => self.locate_loaded(index, &meta, l, t0),
            Err(e) => {
                self.counts.refused += 1;
                Err(e)
            }
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
        self.rate.note(&mut self.last_timestamp, frame.timestamp);
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
    /// tracking window: in loop-closure mode the map before the stream's recent frames, else the
    /// tracking window where the stream is tracked, else the whole map.
    fn search_range(&self, map: &Map, timestamp: Option<f64>) -> (std::ops::Range<usize>, bool) {
        if let Some(lc) = &self.lc {
            return (lc.search_range(map, &self.cfg.stream, timestamp), false);
        }
        match tracking_window(&self.track, &self.cfg.stream, map) {
            Some(r) => (r, true),
            None => (0..map.len(), false),
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
            follow_rate(&mut self.seq, &self.cfg.sequence, &self.rate, map);
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
        let accepted = sequence.as_ref().filter(|s| s.matched.accepted).map(|s| &s.matched);
        self.track.follow(accepted, self.cfg.stream.lost_after);
        self.counts.accepted += u64::from(accepted.is_some());
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
        let closure = match (&self.lc, &sequence) {
            (Some(_), Some(s)) if closes(&self.cfg.stream, &s.matched) => {
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
        let interval = self.rate.interval();
        let Some(lc) = &mut self.lc else { return Ok(()) };
        if lc.push(img, timestamp, &self.cfg.stream, interval)? {
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

    /// Loop-closure mode before the map exists: the map made of the kept frames, checked and opened.
    fn create_map(&mut self) -> Result<()> {
        let Some(lc) = &mut self.lc else { return Ok(()) };
        let map = lc.create_map(&mut self.engine, &mut self.encoder, &self.cfg, self.opts.resume)?;
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
        match &mut self.lc {
            Some(lc) => lc.flush(),
            None => Ok(()),
        }
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
