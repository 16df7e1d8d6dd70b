//! Frames replayed through a [`Localizer`]: decoded (and segmented) on a second thread while the
//! previous one is matched.

use super::latency::LatencyStats;
use super::localizer::Localizer;
use super::types::{FrameResult, StreamFrame};
use crate::encode::Loaded;
use crate::error::{Error, Result};
use crate::util::ms_since;
use std::sync::mpsc::RecvTimeoutError;
use std::time::{Duration, Instant};

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
/// not a frame's own (the map, the device) end it. Returns the latencies of the frames answered
/// (a loop-closure map's warm-up frames, which are buffered and not matched, left out).
pub fn replay(
    loc: &mut Localizer,
    frames: impl Iterator<Item = Result<StreamFrame>> + Send + 'static,
    ahead: usize,
    on: impl FnMut(&mut Localizer, Replayed) -> Result<()>,
) -> Result<LatencyStats> {
    replay_until(loc, frames, ahead, || false, on)
}

/// How often a replay waiting for the next frame looks at its `stopped` condition.
const STOP_POLL: Duration = Duration::from_millis(50);

/// [`replay`] that also ends between frames once `stopped` says so (a signal handler's flag:
/// SIGINT or SIGTERM), looked at after each frame and every 50 ms (`STOP_POLL`) while the next is
/// awaited: every frame answered until then has been reported to `on`, the one being matched
/// is finished first. The source's thread is then left behind (a read of standard input blocked
/// on a silent camera would hold a join): the caller is to end the process. Ended otherwise (the
/// frames, an error), the replay joins it.
pub fn replay_until(
    loc: &mut Localizer,
    frames: impl Iterator<Item = Result<StreamFrame>> + Send + 'static,
    ahead: usize,
    stopped: impl Fn() -> bool,
    mut on: impl FnMut(&mut Localizer, Replayed) -> Result<()>,
) -> Result<LatencyStats> {
    let decoder = loc.loader();
    let (tx, rx) = std::sync::mpsc::sync_channel::<(String, Option<f64>, Result<Loaded>, Instant)>(ahead.max(1));
    // set when the replay ends early: the source's thread takes no further frame
    let leaving = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let left = leaving.clone();
    let source = std::thread::spawn(move || {
        for (k, f) in frames.enumerate() {
            if left.load(std::sync::atomic::Ordering::Relaxed) {
                return;
            }
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
    let mut stats = LatencyStats::default();
    let mut ended = Ok(());
    while !stopped() {
        let (id, ts, loaded, arrived) = match rx.recv_timeout(STOP_POLL) {
            Ok(item) => item,
            Err(RecvTimeoutError::Timeout) => continue,
            Err(RecvTimeoutError::Disconnected) => break,
        };
        let (frame, refused) = (loc.counts().frames, loc.counts().refused);
        let heard = match loc.push_loaded(id.clone(), ts, loaded) {
            Ok(mut r) => {
                r.latency.arrival_ms = ms_since(arrived);
                // a loop-closure map's warm-up frames are buffered, not matched: their near-zero
                // times are not the stream's latency
                if !r.warming_up {
                    stats.push(&r.latency);
                }
                on(&mut *loc, Replayed::Answered(Box::new(r)))
            }
            Err(e) if loc.counts().refused > refused => on(&mut *loc, Replayed::Refused(frame, id, e)),
            Err(e) => Err(e),
        };
        if let Err(e) = heard {
            ended = Err(e);
            break;
        }
    }
    leaving.store(true, std::sync::atomic::Ordering::Relaxed);
    drop(rx);
    // stopped by a signal: the thread is left behind (it may wait on a silent camera's pipe; the
    // caller ends the process). Otherwise it ends at its next frame, and is joined, as a scoped
    // thread was: no decoding outlives the replay.
    if stopped() && ended.is_ok() {
        return Ok(stats);
    }
    let joined = source.join();
    ended?;
    joined.map_err(|_| Error::invalid("stream", "the thread that reads and decodes the frames panicked"))?;
    Ok(stats)
}
