//! Loop-closure mode: the stream's frames added to the map as a traversal of its own (a map started
//! from the stream's first frames where there is none), committed every `stream.commit_frames`;
//! the part of the map a frame may close a loop with; and when an accepted match closes one.

use crate::config::{Config, StreamConfig};
use crate::descriptors::source::{Place, RefSource};
use crate::descriptors::EncodedImage;
use crate::encode::{Encoder, Loaded};
use crate::engine::Engine;
use crate::error::Result;
use crate::map::{ColumnDims, Map, MapWriter, StoreOptions, TraversalPlan};
use crate::stream::sequence::{SequenceMatch, UNIQUENESS_CAP};
use std::collections::{HashSet, VecDeque};
use std::path::{Path, PathBuf};

/// Loop-closure state: the writer of the stream's traversal and what the exclusion needs.
pub(super) struct LoopState {
    pub(super) writer: Option<MapWriter>,
    pub(super) dir: PathBuf,
    /// Frames of the stream added so far (committed or buffered in the writer).
    pub(super) added: u64,
    /// (position along the stream's traversal, timestamp) of the frames added within
    /// `stream.exclude_seconds`.
    pub(super) recent: VecDeque<(u64, f64)>,
    /// Before the map exists: the first frames, decoded, to train its codebook on.
    pub(super) warm: Vec<(String, Loaded, Option<f64>)>,
    /// A resumed stream: the traversal it continues (known before the writer's first commit).
    pub(super) resumed: Option<u32>,
    /// A resumed stream: the ids the map held when it was opened.
    pub(super) held: HashSet<String>,
}

impl LoopState {
    pub(super) fn new(dir: &Path, writer: Option<MapWriter>) -> LoopState {
        LoopState { writer, dir: dir.to_path_buf(), added: 0, recent: VecDeque::new(), warm: vec![], resumed: None, held: HashSet::new() }
    }

    /// The map before the stream's recent frames (the last `stream.exclude_frames`, and those of
    /// the last `stream.exclude_seconds`): what a frame may close a loop with; the whole map
    /// before the stream's traversal has a frame.
    pub(super) fn search_range(&self, map: &Map, st: &StreamConfig, timestamp: Option<f64>) -> std::ops::Range<usize> {
        let all = 0..map.len();
        let Some(t) = self.writer.as_ref().and_then(MapWriter::traversal).or(self.resumed) else { return all };
        let mut excluded = (st.exclude_frames as u64).min(self.added);
        if let (Some(now), true) = (timestamp, st.exclude_seconds > 0.0) {
            let within = self.recent.iter().filter(|(_, ts)| now - ts < st.exclude_seconds).count() as u64;
            excluded = excluded.max(within);
        }
        let cutoff = (self.added - excluded) as u32;
        match map.at(Place { traversal: t, position: cutoff }) {
            Some(i) => 0..i,
            None => all,
        }
    }
}

/// Whether an accepted sequence match closes a loop: unique enough (and not at the cap, a match
/// with no rival), moving, and scoring (`stream.closure_*`).
pub(super) fn closes(st: &StreamConfig, m: &SequenceMatch) -> bool {
    m.accepted
        && m.uniqueness < UNIQUENESS_CAP
        && m.uniqueness as f64 >= st.closure_uniqueness
        && (m.velocity.abs() as f64) >= st.closure_min_velocity
        && m.score as f64 >= st.closure_min_score
}

impl LoopState {
    /// Adds the frame to the stream's traversal, and commits every `stream.commit_frames` (the
    /// traversal then records the stream's frame `interval`, what a later stream's range follows).
    /// Returns whether it committed (a new generation of the map).
    pub(super) fn push(&mut self, img: &EncodedImage, timestamp: Option<f64>, st: &StreamConfig, interval: Option<f64>) -> Result<bool> {
        let Some(w) = &mut self.writer else { return Ok(false) };
        w.push(img)?;
        if let Some(t) = timestamp {
            self.recent.push_back((self.added, t));
            while self.recent.front().is_some_and(|(_, ts)| t - ts >= st.exclude_seconds) {
                self.recent.pop_front();
            }
        }
        self.added += 1;
        if !self.added.is_multiple_of(st.commit_frames as u64) {
            return Ok(false);
        }
        if let Some(dt) = interval {
            w.set_frame_interval(dt)?;
        }
        w.flush()?;
        Ok(true)
    }

    /// Before the map exists: trains `encoder`'s codebook on the kept frames, creates the map
    /// with them (a traversal of its own, committed) and opens it.
    pub(super) fn create_map(&mut self, engine: &mut Engine, encoder: &mut Encoder, cfg: &Config, resume: bool) -> Result<Map> {
        // the stream's velocity scale (`--velocity-scale`) is this camera's, not the map's
        fn profile_of(cfg: &Config) -> Config {
            let mut c = cfg.clone();
            c.sequence.velocity_scale = Config::default().sequence.velocity_scale;
            c
        }
        let warm = std::mem::take(&mut self.warm);
        if let Some(a) = encoder.appearance_mut() {
            let model = a.model();
            let kps: Vec<crate::appearance::keypoints::Keypoints> =
                warm.iter().filter_map(|(_, l, _)| l.rgb.as_ref()).map(|rgb| model.keypoints(rgb)).collect::<Result<_>>()?;
            a.train_codebook_from(&kps.iter().collect::<Vec<_>>())?;
        }
        // frames without labels and no segmenter to make them: a map without labels
        let void = warm.iter().all(|(_, l, _)| l.labels.classes().iter().all(|&c| c == crate::classes::VOID));
        let dims =
            ColumnDims { appearance: encoder.appearance_dim(), hog: 0, keypoints: encoder.keypoint_dim(), compact_hog: encoder.compact_hog_dim() };
        let mut w = MapWriter::create(&self.dir, &cfg.encoding(), dims, encoder.appearance_record(), StoreOptions::default(), resume)?
            .with_embedding(encoder.embedding_record())?
            .with_profile(&profile_of(cfg))?;
        if void && !encoder.frames().can_segment() {
            w = w.without_labels()?;
        }
        let mut w = w.with_traversal(TraversalPlan::New)?;
        let ids: Vec<(String, Option<f64>)> = warm.iter().map(|(id, _, t)| (id.clone(), *t)).collect();
        let encoded = engine.encode_loaded(encoder, warm.into_iter().map(|(id, l, _)| (id, Ok(l))).collect())?;
        let mut added = 0u64;
        for (r, (_, t)) in encoded.into_iter().zip(&ids) {
            w.push(&r?.0)?;
            if let Some(t) = t {
                self.recent.push_back((added, *t));
            }
            added += 1;
        }
        w.flush()?;
        self.added = added;
        self.writer = Some(w);
        Map::open(&self.dir)
    }

    /// Commits what the writer buffered.
    pub(super) fn flush(&mut self) -> Result<()> {
        match &mut self.writer {
            Some(w) => w.flush(),
            None => Ok(()),
        }
    }
}
