//! The stream's clock: its timestamps (refused when they go back), its frame interval against the
//! map's (the velocity range of sequence matching follows it), and the warning when trajectories
//! run at the range's edge (a camera faster than the range follows).

use crate::config::SequenceConfig;
use crate::error::{Error, Result};
use crate::map::Map;
use crate::stream::sequence::{SequenceMatch, SequenceMatcher};
use crate::stream::types::StreamCounts;
use std::collections::VecDeque;

/// Frames in a row whose best trajectory runs at the velocity range's edge before the warning
/// (at most `sequence.length`).
pub(super) const EDGE_FRAMES: usize = 8;

/// Frames to measure a stream's frame interval over (the median step of their timestamps).
pub(super) const INTERVAL_FRAMES: usize = 15;

/// The stream's frame rate against the map's, and the trajectories at the velocity range's edge.
#[derive(Debug, Clone, Default)]
pub(super) struct Rate {
    /// The last steps between the stream's timestamps, seconds.
    steps: VecDeque<f64>,
    /// Frames in a row whose best trajectory ran at the range's edge.
    edge_run: usize,
    /// The edge was warned about (once per stream).
    warned: bool,
}

impl Rate {
    /// The stream's frame interval: the median of the last steps.
    pub(super) fn interval(&self) -> Option<f64> {
        let mut v: Vec<f64> = self.steps.iter().copied().collect();
        v.sort_by(f64::total_cmp);
        v.get(v.len() / 2).copied()
    }
}

/// Counts the frames whose best trajectory runs at the velocity range's edge, or is refused for
/// want of the newest frame's support (a trajectory left behind a camera the range does not
/// follow), and warns once [`EDGE_FRAMES`] of them come in a row: the camera is likely faster than
/// the range follows.
pub(super) fn watch_edge(seq: &SequenceMatcher, cfg: &SequenceConfig, rate: &mut Rate, counts: &mut StreamCounts, m: Option<&SequenceMatch>) {
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

/// The median frame interval of the map's timed traversals.
pub(super) fn map_interval(map: &Map) -> Option<f64> {
    let mut v: Vec<f64> = map.manifest.frame_intervals.values().copied().collect();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied()
}

/// Sets `seq`'s velocity range to the stream's frame interval over the map's (or the configured
/// `sequence.velocity_scale`), where it moved by more than 5 %.
pub(super) fn follow_rate(seq: &mut SequenceMatcher, cfg: &SequenceConfig, rate: &Rate, map: &Map) {
    let scale = match (cfg.velocity_scale, rate.interval(), map_interval(map)) {
        (Some(k), _, _) => k,
        (None, Some(stream), Some(map)) => (stream / map).clamp(1.0 / 64.0, 64.0),
        _ => 1.0,
    };
    if (scale / seq.velocity_scale() - 1.0).abs() > 0.05 {
        log::info!("sequence: velocity range x{scale:.3} (the stream's frame interval over the map's)");
        seq.set_velocity_scale(scale);
    }
}

impl Rate {
    /// Takes a located frame's timestamp: the step since `last` joins the interval's measurement
    /// (the last `INTERVAL_FRAMES`), and `last` moves on.
    pub(super) fn note(&mut self, last: &mut Option<f64>, timestamp: Option<f64>) {
        if let Some(t) = timestamp {
            if let Some(step) = last.map(|l| t - l).filter(|&d| d > 0.0) {
                if self.steps.len() == INTERVAL_FRAMES {
                    self.steps.pop_front();
                }
                self.steps.push_back(step);
            }
            *last = Some(t);
        }
    }
}

/// Refuses frame `id`'s timestamp where it is not a number or goes back from `last`.
pub(super) fn check_timestamp(id: &str, timestamp: Option<f64>, last: Option<f64>) -> Result<()> {
    match (timestamp, last) {
        (Some(t), _) if !t.is_finite() => Err(Error::invalid(format!("frame {id:?}"), format!("timestamp {t} is not a finite number"))),
        (Some(t), Some(last)) if t < last => Err(Error::invalid(
            format!("frame {id:?}"),
            format!("timestamp {t} is before the previous frame's ({last}): refused (frames must come in time order)"),
        )),
        _ => Ok(()),
    }
}
