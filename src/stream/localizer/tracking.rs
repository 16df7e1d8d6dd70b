//! Tracking: the last accepted sequence match and the frames since it, the window of the map a
//! tracked frame is searched in, the ring's places carried to a new map generation, and the lean
//! encoder of tracked frames.

use crate::config::{Config, StreamConfig};
use crate::descriptors::source::{Place, RefSource};
use crate::encode::Encoder;
use crate::map::Map;
use crate::stream::sequence::{SequenceMatch, SequenceMatcher};
use std::collections::{HashMap, HashSet};

/// Tracking: the last accepted sequence match (place, velocity) and the frames since it.
#[derive(Debug, Clone, Copy, Default)]
pub(super) struct Track {
    /// The place and velocity of the last accepted match.
    pub(super) at: Option<(Place, f32)>,
    /// Frames since it.
    pub(super) misses: usize,
}

impl Track {
    /// Follows an accepted match (`Some`), or counts a frame without one and lets go after
    /// `lost_after` of them.
    pub(super) fn follow(&mut self, accepted: Option<&SequenceMatch>, lost_after: usize) {
        match accepted {
            Some(m) => *self = Track { at: Some((m.place, m.velocity)), misses: 0 },
            None => {
                self.misses += 1;
                if self.misses >= lost_after {
                    self.at = None;
                }
            }
        }
    }
}

/// The map's indices around where the last accepted match, moving on at its velocity, is
/// now (`stream.track_radius` positions either side), where they are one contiguous run;
/// `None`: not tracking.
pub(super) fn tracking_window(track: &Track, st: &StreamConfig, map: &Map) -> Option<std::ops::Range<usize>> {
    match track.at {
        Some((p, v)) if st.track_radius > 0 => {
            // where the last accepted match, moving on at its velocity, is now
            let ahead = (track.misses + 1) as f64;
            let centre = (p.position as f64 + v as f64 * ahead).round().max(0.0) as u32;
            let r = st.track_radius as u32;
            let lo = centre.saturating_sub(r);
            let hi = (centre + r).min(map.traversal_len(p.traversal).saturating_sub(1));
            match (map.at(Place { traversal: p.traversal, position: lo }), map.at(Place { traversal: p.traversal, position: hi })) {
                // one contiguous run of the map's indices
                (Some(a), Some(b)) if b >= a && b - a == (hi - lo) as usize => Some(a..b + 1),
                _ => None,
            }
        }
        _ => None,
    }
}

/// The encoder of tracked frames where `stream.embed_when_tracking` is off and `encoder` embeds.
pub(super) fn lean_encoder(cfg: &Config, encoder: &Encoder) -> Option<Encoder> {
    (!cfg.stream.embed_when_tracking && encoder.embedder().is_some()).then(|| encoder.clone().without_embedding())
}

/// Moves the ring's places from generation `old` to `new`: unchanged where `new` only appended
/// segments (true), else through the images' ids (false).
pub(super) fn follow(seq: &mut SequenceMatcher, old: &Map, new: &Map) -> bool {
    let (a, b) = (&old.manifest.segments, &new.manifest.segments);
    if new.manifest.uid == old.manifest.uid && b.len() >= a.len() && a.iter().zip(b).all(|(x, y)| x == y) {
        return true;
    }
    let wanted: HashSet<&str> = seq.places().filter_map(|p| old.at(p)).map(|i| old.id(i)).collect();
    let found: HashMap<&str, usize> = (0..new.len()).map(|i| (new.id(i), i)).filter(|(id, _)| wanted.contains(*id)).collect();
    seq.remap(|p| old.at(p).and_then(|i| found.get(old.id(i))).map(|&j| new.place(j)));
    false
}
