//! The sections of streams: `[sequence]` (sequence matching) and `[stream]` (the localizer, loop
//! closure, tracking).

use serde::{Deserialize, Serialize};

/// How the contributions of a frame's scores to a trajectory are normalised (the contrast
/// enhancement of SeqSLAM's difference matrix, Milford & Wyeth 2012, on a sparse row).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Contrast {
    /// The score above the frame's lowest candidate score, unscaled.
    None,
    /// z-score over the frame's scored references.
    Frame,
    /// z-score over the references within `contrast_window` positions along the traversal
    /// (references the frame did not score count at its lowest score), as SeqSLAM does.
    Window,
}

/// Which references each frame scores for sequence matching.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SequenceRows {
    /// The setting's candidates (its top-K) widened by `widen` positions either side.
    Candidates,
    /// Every reference of the map (a dense row: small maps only).
    Full,
}

/// Sequence matching over a stream (beyond the paper; `stream`): each frame's candidate scores
/// go into a ring of the last `length` frames, and trajectories through them whose velocity
/// changes smoothly are scored (SeqSLAM, Milford & Wyeth 2012; SeqMatch, Garg & Milford 2021).
/// Causal: the result at frame t uses frames up to t. A matching section: it may change at query
/// time.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SequenceConfig {
    /// Frames a trajectory spans (SeqSLAM's ds). \[R\] 20 (sweep 10f: 12 / 16 / 20 / 24 over the six
    /// ordered dev sets and nine settings with trajectories whose speed changes; 20 is the longest
    /// with no set's stream below its single frames; SeqSLAM used 10 to 20).
    pub length: usize,
    /// Velocities tried, in reference positions per query frame: `velocity_steps` values evenly
    /// from `velocity_min` to `velocity_max`. 0 is a stop; negative values drive backwards.
    /// \[R\] 0 to 4 in 17 steps of 0.25 (sweep 20: a camera at a quarter of the map's frame rate
    /// is followed without timestamps; sweep 10's 0 to 2 in 9 steps lost every accepted answer at
    /// every 3rd frame. SeqSLAM: 0.8 to 1.2, which misses stops).
    pub velocity_min: f64,
    /// The fastest velocity tried (see `velocity_min`). \[R\] 4 (sweep 20).
    pub velocity_max: f64,
    /// The number of velocities tried (see `velocity_min`). \[R\] 17 (sweep 20).
    pub velocity_steps: usize,
    /// `velocity_min` and `velocity_max` are multiplied by this (issue 48: a map recorded at one
    /// frame rate and a camera at another). Unset (the default): the stream's frame interval over
    /// the map's where both are known (the stream's timestamps, the map's `map build/add
    /// --timestamps`), else 1. \[R\] unset (derived).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub velocity_scale: Option<f64>,
    /// What a trajectory pays, in contribution units, each time its velocity changes by one step
    /// between two frames (a very large value keeps SeqSLAM's straight lines). \[R\] 1 (sweep 10e).
    pub velocity_change: f64,
    /// Which references each frame scores. \[R\] candidates.
    pub rows: SequenceRows,
    /// The candidates of each frame are widened by this many positions either side along their
    /// traversal, each scored by the setting, so trajectories pass through scored neighbours.
    /// \[R\] 1 (sweep 10).
    pub widen: usize,
    /// Contrast normalisation of each frame's scores. \[R\] frame (sweep 10: SeqSLAM's window
    /// normalisation lost 0.08 to 0.58 R@1 on Nordland, where a route's neighbouring places all
    /// score high and an isolated alias stands out of its window; none was 0.01 to 0.02 below
    /// frame on the mean).
    pub contrast: Contrast,
    /// Half-width of the contrast window, in positions. \[X\] SeqSLAM's R_window: 10.
    pub contrast_window: usize,
    /// The match is the newest frame's strongest place within this many positions of the best
    /// trajectory's end, where the frame gives that place at least `refine_share` of its
    /// strongest evidence (a trajectory through frames of a varying speed may end a place off).
    /// \[R\] 2 (sweep 10e).
    pub refine: usize,
    /// See `refine`. \[R\] 0.9 (sweep 10e).
    pub refine_share: f64,
    /// The uniqueness of a match is its score over the best score of a place further than this
    /// many positions along the same traversal (or on another one). \[X\] SeqSLAM's R_window: 10.
    pub uniqueness_window: usize,
    /// A sequence match is accepted when its uniqueness reaches this and its trajectory spans at
    /// least `min_frames` frames. \[R\] 1.05, 5 (sweep 10).
    pub min_uniqueness: f64,
    /// The fewest frames an accepted trajectory spans (see `min_uniqueness`). \[R\] 5.
    pub min_frames: usize,
    /// A trajectory slower than this (positions per frame, either way) is a stop, accepted only
    /// where the frames stand still (`stillness`): a place that scores well against every frame
    /// of a moving camera otherwise wins as a standing trajectory. \[R\] 0.3 (sweep 10e).
    pub stop_velocity: f64,
    /// The cosine of the newest two frames' rows at which the camera counts as standing still
    /// (see `stop_velocity`; above 1: stops are never accepted). \[R\] 0.95 (sweep 10e).
    pub stillness: f64,
    /// A sequence match is accepted only where the newest frame itself vouches for it: it gives a
    /// place within `refine` positions of the trajectory's end some evidence, and at least this
    /// share of its strongest. A camera faster than the velocity range follows leaves trajectories
    /// behind the places it passes, where the newest frame says least (issue 57: Nordland at every
    /// 3rd frame, 16 of 20 answers wrong and accepted). \[R\] 0: any evidence (sweep 20: with
    /// velocities 0 to 2, a camera beyond the range, it took the stream's answer on Nordland at
    /// every 3rd frame from 0.200 to 0.750 and on CamVid from 0.103 to 0.517; beside 0 to 4 it
    /// changes no rate copy's answers; it costs the synthetic aliasing sets 0.009 and 0.006, and
    /// 0.5 cost them 0.030 and 0.017, `global` 0.10).
    pub support: f64,
}

impl Default for SequenceConfig {
    fn default() -> Self {
        SequenceConfig {
            length: 20,
            velocity_min: 0.0,
            velocity_max: 4.0,
            velocity_steps: 17,
            velocity_scale: None,
            velocity_change: 1.0,
            rows: SequenceRows::Candidates,
            widen: 1,
            contrast: Contrast::Frame,
            contrast_window: 10,
            refine: 2,
            refine_share: 0.9,
            uniqueness_window: 10,
            min_uniqueness: 1.05,
            min_frames: 5,
            stop_velocity: 0.3,
            stillness: 0.95,
            support: 0.0,
        }
    }
}

/// Streams (`stream::Localizer`, `semlook localize`): loop closure and tracking. A matching
/// section.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct StreamConfig {
    /// Loop-closure mode: frames of the stream are matched only against frames at least this
    /// many frames older, and at least `exclude_seconds` older where frames carry timestamps
    /// (the recent past always looks like the present). \[R\] 50 frames (5 s at 10 Hz), 0 s.
    pub exclude_frames: usize,
    /// Loop-closure mode: the seconds a matched frame is at least older, where frames carry
    /// timestamps (see `exclude_frames`). \[R\] 0.
    pub exclude_seconds: f64,
    /// Loop-closure mode: the frames added are committed to the map (one segment, the store's
    /// crash-safe commit) every this many frames; at most `exclude_frames`, so that every frame
    /// that may be matched is stored. \[R\] 25.
    pub commit_frames: usize,
    /// While the last sequence match was accepted, only the references within this many
    /// positions of where it predicts the frame are searched (0: the whole map every frame);
    /// after `lost_after` frames without an accepted match, the whole map again. Large maps.
    /// \[R\] 0 (off), 5.
    pub track_radius: usize,
    /// Frames without an accepted match after which the whole map is searched again (see
    /// `track_radius`). \[R\] 5.
    pub lost_after: usize,
    /// Whether a frame searched within the tracking window (`track_radius`) gets its whole-image
    /// embedding too; off, only the frames that search the whole map are embedded (the window's
    /// few dozen places are ranked by appearance and SSIM, then verified), which saves the
    /// embedding network's time on tracked frames (issue 48). \[R\] true (off, the real-time
    /// replay at 1,000 places ran 7 % faster but accepted 0.22 of its frames against 0.52).
    pub embed_when_tracking: bool,
    /// Loop-closure mode: an accepted sequence match is a closure when its uniqueness reaches
    /// `closure_uniqueness` (some other place must score: a match with no competitor is not
    /// evidence) and its trajectory moves at least `closure_min_velocity` positions per frame
    /// (a standing trajectory says only that the recent frames all resemble one old place).
    /// \[R\] 1.5 and 0.5, from the CamVid loop (the drive, then its shifted copy; tests/stream.rs):
    /// of the false closures of the first pass 92 % stood or crawled (|v| <= 0.25), the true ones
    /// of the second moved at 0.5 to 1 with uniqueness 1.49 to 4.5.
    pub closure_uniqueness: f64,
    /// Loop-closure mode: the least speed of a closure's trajectory, in positions per frame (see
    /// `closure_uniqueness`). \[R\] 0.5.
    pub closure_min_velocity: f64,
    /// Loop-closure mode: the least score of a closure's sequence match (the mean contrast-
    /// normalised evidence of its trajectory a frame). Uniqueness alone lets a first pass close
    /// on the places just older than the excluded window: they are the only ones it may match,
    /// and the best of a few is unique. \[R\] 2.25 (sweep 12: over the CamVid loop and a
    /// synthetic route driven twice, the lowest floor with no closure in a first pass, 23 of
    /// them at 0; it keeps 93 % and 99 % of the right closures of the second passes).
    pub closure_min_score: f64,
}

impl Default for StreamConfig {
    fn default() -> Self {
        StreamConfig {
            exclude_frames: 50,
            exclude_seconds: 0.0,
            commit_frames: 25,
            track_radius: 0,
            lost_after: 5,
            embed_when_tracking: true,
            closure_uniqueness: 1.5,
            closure_min_velocity: 0.5,
            closure_min_score: 2.25,
        }
    }
}

impl SequenceConfig {
    /// Checks that every value of `[sequence]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("sequence.length", self.length, 1, 256)?;
        v.real("sequence.velocity_min", self.velocity_min, -16.0, 16.0)?;
        v.real("sequence.velocity_max", self.velocity_max, self.velocity_min, 16.0)?;
        if let Some(k) = self.velocity_scale {
            v.real("sequence.velocity_scale", k, 1.0 / 64.0, 64.0)?;
        }
        v.int("sequence.velocity_steps", self.velocity_steps, 1, 64)?;
        v.int("sequence.widen", self.widen, 0, 16)?;
        v.int("sequence.contrast_window", self.contrast_window, 1, 1000)?;
        v.int("sequence.refine", self.refine, 0, 1000)?;
        v.int("sequence.uniqueness_window", self.uniqueness_window, 0, 100_000)?;
        v.real("sequence.min_uniqueness", self.min_uniqueness, 0.0, 1e6)?;
        v.int("sequence.min_frames", self.min_frames, 1, self.length)?;
        v.real("sequence.velocity_change", self.velocity_change, 0.0, 1e9)?;
        v.real("sequence.refine_share", self.refine_share, 0.0, 1.0)?;
        v.real("sequence.stop_velocity", self.stop_velocity, 0.0, 16.0)?;
        v.real("sequence.stillness", self.stillness, 0.0, 2.0)?;
        v.real("sequence.support", self.support, 0.0, 1.0)?;
        Ok(())
    }
}

impl StreamConfig {
    /// Checks that every value of `[stream]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("stream.exclude_frames", self.exclude_frames, 1, 1 << 24)?;
        v.real("stream.exclude_seconds", self.exclude_seconds, 0.0, 1e7)?;
        v.int("stream.commit_frames", self.commit_frames, 1, self.exclude_frames)?;
        v.int("stream.track_radius", self.track_radius, 0, 1 << 20)?;
        v.int("stream.lost_after", self.lost_after, 1, 1 << 20)?;
        v.real("stream.closure_uniqueness", self.closure_uniqueness, 1.0, 1e6)?;
        v.real("stream.closure_min_velocity", self.closure_min_velocity, 0.0, 16.0)?;
        v.real("stream.closure_min_score", self.closure_min_score, 0.0, 1e6)?;
        Ok(())
    }
}
