//! What a stream takes and answers: its frames, options and per-frame results.

use super::latency::Latency;
use super::sequence::SequenceMatch;
use crate::descriptors::source::Place;
use crate::input::{FrameSource, LabelMap};
use crate::matching::Setting;
use crate::verify::pose::RelativePose;
use image::RgbImage;
use serde::Serialize;

/// Where a frame's pixels come from.
#[derive(Debug, Clone)]
pub enum Pixels {
    /// Files: an image and/or a label map (as `map build` reads them).
    Files(FrameSource),
    /// An image file's bytes (JPEG or PNG) in memory, optionally with a label map at its size.
    Bytes {
        /// The file's bytes.
        bytes: Vec<u8>,
        /// Label map at the image's size.
        labels: Option<LabelMap>,
    },
    /// Decoded pixels, optionally with a label map at their size.
    Rgb {
        /// The decoded image.
        image: RgbImage,
        /// Label map at the image's size.
        labels: Option<LabelMap>,
    },
    /// A label map alone (maps encoded without appearance).
    Labels(LabelMap),
}

/// One frame of a stream.
#[derive(Debug, Clone)]
pub struct StreamFrame {
    /// The frame's id (its file stem, a ROS stamp...); in loop-closure mode the id it is stored
    /// under, so unique in the map.
    pub id: String,
    /// The frame's pixels.
    pub pixels: Pixels,
    /// Seconds, when the stream has clocks; must not go backwards.
    pub timestamp: Option<f64>,
}

/// How a stream is matched.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamOptions {
    /// Matching setting.
    pub setting: Setting,
    /// Sequence matching over the last frames ([`sequence`](super::sequence); on for streams by default).
    pub sequence: bool,
    /// Loop-closure mode: query the map, then add the frame to it (one traversal for the stream,
    /// committed every `stream.commit_frames`); the newest `stream.exclude_frames` frames (and
    /// `exclude_seconds`) are never matched. Needs `sequence`: closures are accepted sequence
    /// matches.
    pub loop_closure: bool,
    /// The frames come with their label maps: a map that holds labels then needs no segmenter
    /// (without them, opening such a map without a segmenter is refused: `Encoder::labels_rule`).
    pub labelled_frames: bool,
    /// Loop-closure mode, a restarted stream: the map's last traversal is continued rather than
    /// a new one started, and [`Localizer::holds`](super::Localizer::holds) names the frames the map already holds (to be
    /// skipped: every frame stored once, whatever was committed before a kill).
    pub resume: bool,
}

impl Default for StreamOptions {
    fn default() -> Self {
        StreamOptions { setting: Setting::RECOMMENDED, sequence: true, loop_closure: false, labelled_frames: false, resume: false }
    }
}

/// A reference as a stream reports it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct PlaceMatch {
    /// Index in the map's generation the frame was answered from.
    pub index: u32,
    /// The reference's image id.
    pub id: String,
    /// Where the reference lies on the map's routes.
    pub place: Place,
    /// Ranking score (for a loop closure, the sequence match's score).
    pub score: f32,
    /// Keypoint inliers of the verification, where it ran.
    pub inliers: Option<u32>,
}

/// Where a stream's answer comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum AnswerSource {
    /// The accepted sequence match.
    Sequence,
    /// The single-frame best (sequence matching off, no match accepted yet, or none accepted at
    /// this frame).
    Frame,
}

impl AnswerSource {
    /// `sequence` or `frame`, as the CSV and JSON lines write it.
    pub fn name(self) -> &'static str {
        match self {
            AnswerSource::Sequence => "sequence",
            AnswerSource::Frame => "frame",
        }
    }
}

/// The stream's answer for one frame: the accepted sequence match where there is one, else the
/// single-frame best. Its `score` is on one scale whatever the source: the setting's score of the
/// answered place against this frame (the scale of [`FrameResult::top_k`]'s scores; the sequence
/// match's own score stays in [`FrameResult::sequence`]).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Answer {
    /// Index of the place in the map's generation the frame was answered from.
    pub index: u32,
    /// The place's image id.
    pub id: String,
    /// Where the place lies on the map's routes.
    pub place: Place,
    /// The setting's score of the place against this frame (higher is better; the scale of
    /// `top_k`'s scores).
    pub score: f32,
    /// Whether the answer is the accepted sequence match or the single-frame best.
    pub source: AnswerSource,
    /// The answer is an accepted sequence match (`source` is `sequence`); a single-frame answer
    /// is never accepted.
    pub accepted: bool,
}

/// The sequence match of a frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SequenceResult {
    /// Index of the matched place in the map's generation the frame was answered from.
    pub index: u32,
    /// Image id of the matched place.
    pub id: String,
    /// The trajectory search's result.
    #[serde(flatten)]
    pub matched: SequenceMatch,
    /// What the velocity range was multiplied by ([`crate::config::SequenceConfig::velocity_scale`]:
    /// set, or the stream's frame interval over the map's).
    pub velocity_scale: f64,
}

/// A loop closure: the frame matched a place the stream passed before (loop-closure mode).
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LoopClosure {
    /// Id of the frame that closed the loop.
    pub frame: String,
    /// The place matched.
    pub place: PlaceMatch,
    /// The sequence match's uniqueness and velocity.
    pub uniqueness: f32,
    /// Velocity of the sequence match, in positions per frame.
    pub velocity: f32,
    /// The frame's pose relative to the place's, where the stream has the camera's intrinsics
    /// ([`Localizer::with_camera`](super::Localizer::with_camera)) and the verified matches give one.
    pub relative_pose: Option<RelativePose>,
}

/// What a stream answers after each frame.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct FrameResult {
    /// Frames pushed before this one (refused ones included).
    pub frame: u64,
    /// The frame's id.
    pub id: String,
    /// The stream's answer ([`Answer`]): the accepted sequence match, else the single-frame best;
    /// `None` where the frame has no match (a loop-closure map warming up, an empty map).
    pub answer: Option<Answer>,
    /// The frame's timestamp, in seconds, when it has one.
    pub timestamp: Option<f64>,
    /// The map generation the frame was answered from.
    pub generation: u64,
    /// The single-frame ranking, best first (`matching.top_k` long at most).
    pub top_k: Vec<PlaceMatch>,
    /// The sequence match, where sequence matching runs and the ring has evidence.
    pub sequence: Option<SequenceResult>,
    /// Loop-closure mode: the closure this frame found.
    pub closure: Option<LoopClosure>,
    /// The frame's size differs from the previous frame's (it is answered all the same).
    pub size_changed: bool,
    /// Only the references near the tracked place were searched (`stream.track_radius`).
    pub tracking: bool,
    /// The frame was encoded with its whole-image embedding (false: the map has none, or a
    /// tracked frame with `stream.embed_when_tracking` off).
    pub embedded: bool,
    /// The frame's pose relative to the answer's place, for an accepted answer where the stream
    /// has the camera's intrinsics ([`Localizer::with_camera`](super::Localizer::with_camera)): from the pair's verified
    /// keypoint matches ([`crate::verify::pose`]).
    pub relative_pose: Option<RelativePose>,
    /// Why an accepted answer has no relative pose where the stream has the intrinsics (too few
    /// matches, no parallax, a planar scene, a frame of another aspect ratio).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub relative_pose_refused: Option<String>,
    /// Loop-closure mode: no map yet (the first frames train its codebook).
    pub warming_up: bool,
    /// The pose the map stores for the stream's answer ([`FrameResult::place`]), where it stores
    /// one (`map build` from a dataset with poses, or with `--poses`).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub pose: Option<crate::descriptors::PlacePose>,
    /// Milliseconds per stage of this frame.
    pub latency: Latency,
}

impl FrameResult {
    /// The best single-frame match.
    pub fn best(&self) -> Option<&PlaceMatch> {
        self.top_k.first()
    }
    /// The stream's answer ([`FrameResult::answer`]): the sequence match where it is accepted,
    /// else the single-frame best.
    pub fn place(&self) -> Option<&Answer> {
        self.answer.as_ref()
    }
    /// The map index of [`FrameResult::place`].
    pub fn place_index(&self) -> Option<u32> {
        self.answer.as_ref().map(|a| a.index)
    }
}

/// Counters of a stream so far.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize)]
pub struct StreamCounts {
    /// Frames pushed (refused ones included).
    pub frames: u64,
    /// Frames refused (undecodable, a timestamp going backwards, ...): counted, skipped.
    pub refused: u64,
    /// Frames whose sequence match was accepted.
    pub accepted: u64,
    /// Loop closures found.
    pub closures: u64,
    /// Map generations moved to by [`Localizer::refresh`](super::Localizer::refresh).
    pub reloads: u64,
    /// Loop-closure mode: frames kept to create the map with (answered without a match).
    pub warm_up: u64,
    /// Frames whose best trajectory ran at the fastest (or, below 0, the slowest) velocity tried:
    /// the camera may move faster than the range follows (a warning is logged once 8 come in a
    /// row).
    pub velocity_edge: u64,
    /// Frames whose best trajectory the newest frame did not vouch for (`sequence.support`), so
    /// not accepted: a camera faster than the range follows leaves its trajectories behind it.
    /// Such frames and those at the velocity range's edge, 8 in a row, log the warning.
    pub unsupported: u64,
}
