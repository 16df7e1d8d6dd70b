//! `semlook localize`: a stream of frames (a folder in name or time order, or images piped to
//! standard input) localized as the frames come, one line per frame, then a summary. The next
//! frame is decoded (and segmented) on a second thread while the current one is matched.

use super::shared::{apply_models, info, load_config, map_config};
use crate::cli::args::LocalizeArgs;
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::stream::input::{folder_frames, ImageStream};
use semlook::stream::{replay_until, FrameResult, Localizer, Pixels, Replayed, StreamFrame, StreamOptions};
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Instant;

/// Frames decoded ahead of the one being matched.
const AHEAD: usize = 2;
/// The `accepted` column of a refused frame's CSV row (its match columns are empty; the reason
/// goes to standard error): what a reader tells a refused frame by, beside `true` and `false`.
const REFUSED: &str = "refused";
/// The CSV header: the stream's answer first (id, place as `traversal:position`, score on the
/// setting's single-frame scale, source `sequence` or `frame`, accepted), then the single-frame
/// best, the sequence match, the closure and the frame's milliseconds; with `--camera`, the
/// relative pose of an accepted answer: its rotation's angle in degrees and its inliers.
pub const HEADER: &str =
    "frame,id,answer,place,score,source,accepted,best,best_score,sequence,sequence_score,uniqueness,closure,ms,rotation_deg,pose_inliers";

pub fn run(engine: Engine, a: &LocalizeArgs, quiet: bool) -> Result<()> {
    // options that cannot apply are refused, not ignored
    if let (true, Some(t)) = (a.stdin, &a.timestamps) {
        return Err(Error::invalid(
            t.display().to_string(),
            "--timestamps gives the times of --images frames by file name; frames on standard input have no names to give times to",
        ));
    }
    // the frames a folder holds and their times are checked before any work
    let listed = match &a.images {
        Some(dir) => Some(folder_frames(dir, a.labels.as_deref(), a.timestamps.as_deref())?),
        None => None,
    };
    // the map is opened once: its configuration, then the localizer over it
    let map = Localizer::open_map(&a.map, a.loop_closure)?;
    let mut cfg = match &map {
        Some(m) => map_config(m, a.config.as_deref(), &a.models)?,
        None => apply_models(load_config(a.config.as_deref())?, &a.models),
    };
    if let Some(k) = a.velocity_scale {
        cfg.sequence.velocity_scale = Some(k);
    }
    // the camera file is read and checked before any work
    let camera = a.camera.as_deref().map(semlook::verify::pose::Camera::load).transpose()?;
    let opts = StreamOptions {
        setting: a.setting,
        sequence: !a.no_sequence,
        loop_closure: a.loop_closure,
        labelled_frames: a.labels.is_some(),
        resume: a.resume,
    };
    let mut loc = Localizer::over(map, &a.map, Some(cfg), opts, engine)?.with_label_format(a.label_format.unwrap_or_default());
    if let Some(c) = camera {
        loc = loc.with_camera(c)?;
    }
    info(quiet, format!("backend: {}", loc.engine().describe()));
    match loc.map() {
        Some(m) => info(quiet, format!("map {}: {} places, generation {}", a.map.display(), m.len(), m.manifest.generation)),
        None => info(quiet, format!("map {}: created from the stream (its first frames train the codebook)", a.map.display())),
    }
    if !a.json {
        outln!("{HEADER}");
    }
    // a resumed loop closure skips the frames the map already holds (stored before a restart)
    let held: std::collections::HashSet<String> = match a.resume {
        true => loc
            .map()
            .map(|m| (0..m.len()).map(|i| semlook::descriptors::source::RefSource::id(m, i).to_string()).filter(|id| loc.holds(id)).collect())
            .unwrap_or_default(),
        false => Default::default(),
    };
    let skipped = Arc::new(std::sync::atomic::AtomicU64::new(0));
    let skip = {
        let skipped = skipped.clone();
        move |f: &Result<StreamFrame>| {
            let hold = f.as_ref().is_ok_and(|f| held.contains(&f.id));
            if hold {
                skipped.fetch_add(1, Ordering::Relaxed);
            }
            !hold
        }
    };
    let frames: Box<dyn Iterator<Item = Result<StreamFrame>> + Send> = match listed {
        Some(frames) => Box::new(frames.into_iter().map(Ok).filter(skip)),
        None => Box::new(
            ImageStream::new(std::io::stdin(), "standard input")
                .enumerate()
                .map(|(k, bytes)| {
                    bytes.map(|b| StreamFrame { id: format!("frame-{k:06}"), pixels: Pixels::Bytes { bytes: b, labels: None }, timestamp: None })
                })
                .filter(skip),
        ),
    };
    // SIGINT (Ctrl-C) and SIGTERM end the stream between frames: what was answered is committed
    // and summarised, then the process exits 128 + the signal; a second signal ends it at once
    let (signal, seen) = (Arc::new(AtomicUsize::new(0)), Arc::new(AtomicBool::new(false)));
    for sig in [signal_hook::consts::SIGINT, signal_hook::consts::SIGTERM] {
        // in this order: the exit looks at `seen` before the first signal sets it
        signal_hook::flag::register_conditional_shutdown(sig, 128 + sig, seen.clone())
            .and_then(|_| signal_hook::flag::register(sig, seen.clone()))
            .and_then(|_| signal_hook::flag::register_usize(sig, signal.clone(), sig as usize))
            .map_err(|e| Error::io(std::path::Path::new("signal handler"), e))?;
    }
    let interrupted = || signal.load(Ordering::Relaxed);
    let start = Instant::now();
    let mut first_refusal: Option<String> = None;
    let stats = replay_until(
        &mut loc,
        frames,
        AHEAD,
        || interrupted() != 0,
        |loc, r| {
            if a.follow_map {
                // between frames: the next one is answered from the newest generation
                if let Err(e) = loc.refresh() {
                    log::warn!("map {}: kept generation {}: {e}", a.map.display(), loc.map().map_or(0, |m| m.manifest.generation));
                }
            }
            match r {
                Replayed::Answered(r) => print_frame(&r, a.json),
                Replayed::Refused(frame, id, e) => {
                    log::warn!("frame {frame} ({id}) skipped: {e}");
                    first_refusal.get_or_insert_with(|| format!("frame {frame} ({id}): {e}"));
                    match a.json {
                        // the reason, and its kind for a program to tell refusals apart (`ErrorKind::name`)
                        true => outln!("{}", serde_json::json!({ "frame": frame, "id": id, "refused": e.to_string(), "kind": e.kind().name() })),
                        // the frame's row with no match and `refused` in the accepted column
                        false => outln!("{}", refused_row(frame, &id)),
                    }
                    Ok(())
                }
            }
        },
    )?;
    loc.finish()?;
    let wall = start.elapsed().as_secs_f64();
    let counts = loc.counts();
    let signal = interrupted();
    // a stream that never came (`ffmpeg -i missing.mp4 ... | semlook localize --stdin`) is a failure,
    // as an empty --images folder is
    if signal == 0 && a.stdin && counts.frames == 0 && skipped.load(Ordering::Relaxed) == 0 {
        return Err(Error::invalid("standard input", "no frames: the stream was empty"));
    }
    let summary = stats.summary();
    // the rate of answers: refused frames (a bad file is refused in microseconds) are not
    // frames localized (a loop-closure map's warm-up frames count: they are answered, unmatched)
    let answered = counts.frames.saturating_sub(counts.refused);
    let rate = answered as f64 / wall.max(1e-9);
    let skipped = skipped.load(Ordering::Relaxed);
    if a.resume {
        info(quiet, format!("resumed: skipped {skipped} frames the map already held"));
    }
    let signal_name = match signal {
        0 => None,
        s if s == signal_hook::consts::SIGINT as usize => Some("SIGINT"),
        _ => Some("SIGTERM"),
    };
    if let Some(name) = signal_name {
        info(
            quiet,
            format!(
                "{name}: stopped after {} frames; every frame answered is in the output (and, with --loop-closure, committed to the map)",
                counts.frames
            ),
        );
    }
    if a.json {
        outln!(
            "{}",
            serde_json::json!({ "summary": { "counts": counts, "skipped": skipped, "wall_s": wall, "frames_per_s": rate, "latency": summary, "interrupted": signal_name } })
        );
    } else {
        if let Some(name) = signal_name {
            outln!("# interrupted by {name}");
        }
        if a.resume {
            outln!("# resumed: {skipped} frames skipped (the map already held them)");
        }
        outln!(
            "# {} frames ({} refused), {} accepted sequence matches, {} loop closures; {:.2} frames/s answered over {:.1} s",
            counts.frames,
            counts.refused,
            counts.accepted,
            counts.closures,
            rate,
            wall
        );
        if counts.warm_up > 0 {
            outln!("# {} frames started the map (buffered, not matched): not in the latencies", counts.warm_up);
        }
        let (p50, p99) = (summary.p50, summary.p99);
        outln!(
            "# latency ms p50/p99: from the frame's bytes {:.1}/{:.1} | total {:.1}/{:.1} | decode {:.1}/{:.1} segment {:.1}/{:.1} encode {:.1}/{:.1} coarse {:.1}/{:.1} fine {:.1}/{:.1} sequence {:.1}/{:.1} store {:.1}/{:.1}",
            p50.arrival_ms,
            p99.arrival_ms,
            p50.total_ms,
            p99.total_ms,
            p50.decode_ms,
            p99.decode_ms,
            p50.segment_ms,
            p99.segment_ms,
            p50.encode_ms,
            p99.encode_ms,
            p50.coarse_ms,
            p99.coarse_ms,
            p50.fine_ms,
            p99.fine_ms,
            p50.sequence_ms,
            p99.sequence_ms,
            p50.store_ms,
            p99.store_ms
        );
    }
    // interrupted: the summary is out and the map committed (`loc.finish` above); the exit
    // status says which signal ended the run, as the default action's would. `_exit`, not
    // `exit`: the frame reader may still be inside a network (left behind by the replay), and
    // the loaded runtimes' exit handlers must not run under it
    if signal != 0 {
        drop(loc);
        use std::io::Write;
        let _ = std::io::stdout().flush();
        let _ = std::io::stderr().flush();
        signal_hook::low_level::exit(128 + signal as i32);
    }
    // a stream none of whose frames could be used is a failed run, not an empty success
    match first_refusal {
        Some(first) if counts.frames > 0 && counts.refused == counts.frames => {
            Err(Error::invalid("localize", format!("every frame ({}) was refused; the first: {first}", counts.frames)))
        }
        _ => Ok(()),
    }
}

fn print_frame(r: &FrameResult, json: bool) -> Result<()> {
    if json {
        outln!("{}", serde_json::to_string(r).map_err(|e| Error::invalid("JSON output", e.to_string()))?);
        return Ok(());
    }
    outln!("{}", csv_row(r));
    Ok(())
}

/// A frame's CSV row (see [`HEADER`]).
pub fn csv_row(r: &FrameResult) -> String {
    let csv = csv_field;
    let best = r.best();
    let seq = r.sequence.as_ref();
    let a = r.place();
    format!(
        "{},{},{},{},{},{},{},{},{},{},{},{},{},{:.1},{},{}",
        r.frame,
        csv(&r.id),
        a.map_or(String::new(), |a| csv(&a.id)),
        a.map_or(String::new(), |a| format!("{}:{}", a.place.traversal, a.place.position)),
        a.map_or(String::new(), |a| format!("{:.4}", a.score)),
        a.map_or("", |a| a.source.name()),
        a.is_some_and(|a| a.accepted),
        best.map_or(String::new(), |b| csv(&b.id)),
        best.map_or(String::new(), |b| format!("{:.4}", b.score)),
        seq.map_or(String::new(), |s| csv(&s.id)),
        seq.map_or(String::new(), |s| format!("{:.4}", s.matched.score)),
        seq.map_or(String::new(), |s| format!("{:.3}", s.matched.uniqueness)),
        r.closure.as_ref().map_or(String::new(), |c| csv(&c.place.id)),
        r.latency.total_ms,
        r.relative_pose.as_ref().map_or(String::new(), |p| format!("{:.3}", p.rotation_deg)),
        r.relative_pose.as_ref().map_or(String::new(), |p| p.inliers.to_string()),
    )
}

/// A refused frame's CSV row: its number and id, `refused` in the `accepted` column, every
/// other column empty.
pub fn refused_row(frame: u64, id: &str) -> String {
    let columns = HEADER.split(',').count();
    let accepted = HEADER.split(',').position(|c| c == "accepted").unwrap_or(6);
    let mut row: Vec<String> = vec![String::new(); columns];
    row[0] = frame.to_string();
    row[1] = csv_field(id);
    row[accepted] = REFUSED.into();
    row.join(",")
}

/// A CSV field: quoted (quotes doubled) where it holds a separator, a quote or a line break.
fn csv_field(s: &str) -> String {
    match s.contains([',', '"', '\n']) {
        true => format!("\"{}\"", s.replace('"', "\"\"")),
        false => s.to_string(),
    }
}
