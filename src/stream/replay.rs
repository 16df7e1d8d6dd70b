//! Frames replayed through a [`Localizer`]: decoded (and segmented) on a second thread while the
//! previous one is matched.

use super::latency::LatencyStats;
use super::localizer::Localizer;
use super::types::{FrameResult, StreamFrame};
use crate::encode::Loaded;
use crate::error::{Error, Result};
use crate::util::ms_since;
use std::time::Instant;

/// What [`replay`] reports of each frame.
pub enum Replayed {
    /// The frame was localized.
    Answered(Box<FrameResult>),
    /// The frame was refused (its own fault: counted, the stream goes on): its number, id, why.
    Refused(u64, String, Error),
}

/// Localizes `frames` (each a frame, or an error from the source for one) in order, decoding the
/// next `ahead` frames on a second thread while the current one is matched; `on` hears about
/// every frame as it is answered and may stop the replay by returning an error. Errors that are
/// not a frame's own (the map, the device) end it. Returns the latencies of the frames answered.
pub fn replay(
    loc: &mut Localizer,
    frames: impl Iterator<Item = Result<StreamFrame>> + Send,
    ahead: usize,
    mut on: impl FnMut(&mut Localizer, Replayed) -> Result<()>,
) -> Result<LatencyStats> {
    let decoder = loc.loader();
    let (tx, rx) = std::sync::mpsc::sync_channel::<(String, Option<f64>, Result<Loaded>, Instant)>(ahead.max(1));
    let mut stats = LatencyStats::default();
    std::thread::scope(|s| -> Result<()> {
        s.spawn(move || {
            for (k, f) in frames.enumerate() {
                // the source has handed the frame over: its bytes are complete
                let arrived = Instant::now();
                let item = match f {
                    Ok(StreamFrame { id, pixels, timestamp }) => {
                        let l = decoder.load(&id, pixels);
                        (id, timestamp, l, arrived)
                    }
                    Err(e) => (format!("frame-{k:06}"), None, Err(e), arrived),
                };
                if tx.send(item).is_err() {
                    return;
                }
            }
        });
        for (id, ts, loaded, arrived) in rx {
            let (frame, refused) = (loc.counts().frames, loc.counts().refused);
            match loc.push_loaded(id.clone(), ts, loaded) {
                Ok(mut r) => {
                    r.latency.arrival_ms = ms_since(arrived);
                    stats.push(&r.latency);
                    on(&mut *loc, Replayed::Answered(Box::new(r)))?;
                }
                Err(e) if loc.counts().refused > refused => on(&mut *loc, Replayed::Refused(frame, id, e))?,
                Err(e) => return Err(e),
            }
        }
        Ok(())
    })?;
    Ok(stats)
}
