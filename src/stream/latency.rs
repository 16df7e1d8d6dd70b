//! A frame's milliseconds per stage, and their percentiles over a bounded window.

use serde::Serialize;
use std::collections::VecDeque;

/// Milliseconds per stage of one frame.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct Latency {
    /// Reading and decoding the frame, to the working size.
    pub decode_ms: f64,
    /// The segmentation network.
    pub segment_ms: f64,
    /// The descriptors (edges, forest, appearance: the network and VLAD).
    pub encode_ms: f64,
    /// Of `encode_ms`, the keypoint network.
    pub network_ms: f64,
    /// Of `encode_ms`, the whole-image embedding (0 where a tracked frame goes without).
    pub embedding_ms: f64,
    /// The coarse stage over the map (or the searched part of it).
    pub coarse_ms: f64,
    /// Re-ranking of the candidates (tree similarity, verification).
    pub fine_ms: f64,
    /// Scoring the candidates' neighbours and the trajectory search.
    pub sequence_ms: f64,
    /// Loop-closure mode: adding the frame to the map (a commit, when one is due).
    pub store_ms: f64,
    /// The relative pose of an accepted match (matching the pair's keypoints again, the
    /// essential matrix's RANSAC), with the camera's intrinsics.
    pub pose_ms: f64,
    /// From the call to the answer.
    pub total_ms: f64,
    /// From the moment the frame's bytes were complete (a piped image read to its end, a
    /// folder's frame taken in turn; [`replay`](super::replay())) to the answer: `total_ms` plus reading,
    /// decoding and the wait for the matcher. [`Localizer::push`](super::Localizer::push) alone: `total_ms`.
    pub arrival_ms: f64,
}

impl Latency {
    /// Each stage's value through `f`, with the same stage of `o`.
    fn zip(self, o: Latency, f: impl Fn(f64, f64) -> f64) -> Latency {
        Latency {
            decode_ms: f(self.decode_ms, o.decode_ms),
            segment_ms: f(self.segment_ms, o.segment_ms),
            encode_ms: f(self.encode_ms, o.encode_ms),
            network_ms: f(self.network_ms, o.network_ms),
            embedding_ms: f(self.embedding_ms, o.embedding_ms),
            coarse_ms: f(self.coarse_ms, o.coarse_ms),
            fine_ms: f(self.fine_ms, o.fine_ms),
            sequence_ms: f(self.sequence_ms, o.sequence_ms),
            store_ms: f(self.store_ms, o.store_ms),
            pose_ms: f(self.pose_ms, o.pose_ms),
            total_ms: f(self.total_ms, o.total_ms),
            arrival_ms: f(self.arrival_ms, o.arrival_ms),
        }
    }
}

/// Percentiles of the latencies of the last frames of a stream (at most [`LATENCY_WINDOW`]
/// kept, so a stream of any length holds the same).
#[derive(Debug, Clone, Default)]
pub struct LatencyStats {
    last: VecDeque<Latency>,
    frames: u64,
}

/// Frames whose latencies [`LatencyStats`] keeps.
pub const LATENCY_WINDOW: usize = 10_000;

/// Per stage, the median and 99th percentile over the frames kept.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize)]
pub struct LatencySummary {
    /// Frames measured in all, and of them kept for the percentiles.
    pub frames: u64,
    /// Frames kept for the percentiles (at most [`LATENCY_WINDOW`]).
    pub kept: usize,
    /// Per stage, the median.
    pub p50: Latency,
    /// Per stage, the 99th percentile.
    pub p99: Latency,
    /// Per stage, the mean.
    pub mean: Latency,
}

impl LatencyStats {
    /// Adds one frame's latencies, dropping the oldest beyond [`LATENCY_WINDOW`].
    pub fn push(&mut self, l: &Latency) {
        if self.last.len() == LATENCY_WINDOW {
            self.last.pop_front();
        }
        self.last.push_back(*l);
        self.frames += 1;
    }
    /// The percentiles and means over the frames kept.
    pub fn summary(&self) -> LatencySummary {
        let n = self.last.len();
        if n == 0 {
            return LatencySummary { frames: self.frames, ..LatencySummary::default() };
        }
        // each stage's own percentile (a stage's p99 frame need not be the total's)
        let pick = |q: f64| {
            let field = |f: fn(&Latency) -> f64| {
                let mut v: Vec<f64> = self.last.iter().map(f).collect();
                v.sort_by(f64::total_cmp);
                v[((q * (n - 1) as f64).round() as usize).min(n - 1)]
            };
            Latency {
                decode_ms: field(|l| l.decode_ms),
                segment_ms: field(|l| l.segment_ms),
                encode_ms: field(|l| l.encode_ms),
                network_ms: field(|l| l.network_ms),
                embedding_ms: field(|l| l.embedding_ms),
                coarse_ms: field(|l| l.coarse_ms),
                fine_ms: field(|l| l.fine_ms),
                sequence_ms: field(|l| l.sequence_ms),
                store_ms: field(|l| l.store_ms),
                pose_ms: field(|l| l.pose_ms),
                total_ms: field(|l| l.total_ms),
                arrival_ms: field(|l| l.arrival_ms),
            }
        };
        let sum = self.last.iter().fold(Latency::default(), |a, b| a.zip(*b, |x, y| x + y));
        LatencySummary { frames: self.frames, kept: n, p50: pick(0.5), p99: pick(0.99), mean: sum.zip(sum, |x, _| x / n as f64) }
    }
}
