//! `semlook dev bench-stream`: a real sequence replayed through the streaming localizer against
//! stored maps of growing size, as a camera would feed it, reporting frames per second and the
//! median and 99th-percentile latency of every stage.
//!
//! Each map holds the real reference traversal the stream was recorded against (encoded from its
//! images) and, to reach its size, distractor places: the descriptors of other real images (other
//! routes, other countries) written again under new ids, one traversal of them. The map is
//! written through the store, as `map build` writes one, opened, and the stream is replayed
//! through [`semlook::stream::replay`] (the next frame decoded, and segmented, on a second thread
//! while the current one is matched), exactly as `semlook localize` runs it.

use semlook::batch::{encode_frames, train_codebook};
use semlook::config::{Config, IndexSearch};
use semlook::encode::Encoder;
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::index::IndexParams;
use semlook::input::FrameSource;
use semlook::map::{ColumnDims, MapWriter, StoreOptions, TraversalPlan};
use semlook::matching::Setting;
use semlook::stream::{replay, Latency, Localizer, Pixels, Replayed, StreamFrame, StreamOptions};
use serde::Serialize;
use std::path::{Path, PathBuf};
use std::time::Instant;

pub struct StreamBenchOptions {
    /// The frames of the reference traversal the stream was recorded against.
    pub references: Vec<FrameSource>,
    /// The frames replayed, in order (cycled when `frames` asks for more).
    pub stream: Vec<FrameSource>,
    /// Frames of other places whose descriptors fill the map to its size.
    pub distractors: Vec<FrameSource>,
    pub sizes: Vec<usize>,
    pub frames: usize,
    pub setting: Setting,
    pub sequence: bool,
    /// Where the maps are written (each removed after its row unless `keep`).
    pub dir: PathBuf,
    pub keep: bool,
    pub quiet: bool,
}

/// One map size.
#[derive(Debug, Clone, Serialize)]
pub struct StreamBenchRow {
    pub map_size: usize,
    pub setting: Setting,
    pub sequence: bool,
    /// Whether frames without label maps were segmented (else encoded without labels).
    pub segmented: bool,
    pub frames: u64,
    pub refused: u64,
    /// Frames answered per second of wall clock, end to end (decoding to answer).
    pub frames_per_s: f64,
    pub p50: Latency,
    pub p99: Latency,
    /// Per stage, the mean (frames/s is about 1,000 / `mean.total_ms` when the matcher is the
    /// bottleneck: a few slow frames show here, not in the percentiles).
    pub mean: Latency,
    /// Seconds opening the localizer over the map before the first frame (the map's checks run
    /// then: [`semlook::map::Map::prepare`]); not in frames/s.
    pub open_s: f64,
    /// Share of frames answered from a tracking window rather than the whole map.
    pub tracking: f64,
    /// Share of frames whose sequence match was accepted.
    pub accepted: f64,
    pub map_write_s: f64,
    pub map_bytes: u64,
    /// Seconds building the map's approximate index (none below `index.min_places` or with
    /// `index.search = "exact"`: the map is scanned exactly).
    pub index_build_s: Option<f64>,
}

/// Runs every size; `engine` makes the engine of each row; `tick` hears about each row.
pub fn run(
    cfg: &Config,
    opts: &StreamBenchOptions,
    engine: &dyn Fn() -> Result<Engine>,
    tick: &mut dyn FnMut(&StreamBenchRow),
) -> Result<Vec<StreamBenchRow>> {
    if opts.references.is_empty() || opts.stream.is_empty() {
        return Err(Error::invalid("bench-stream", "needs reference frames and stream frames"));
    }
    if let Some(&n) = opts.sizes.iter().find(|&&n| n < opts.references.len()) {
        return Err(Error::invalid("bench-stream", format!("a map of {n} places cannot hold the {} references", opts.references.len())));
    }
    if opts.distractors.is_empty() && opts.sizes.iter().any(|&n| n > opts.references.len()) {
        return Err(Error::invalid("bench-stream", "maps larger than the references need distractor frames"));
    }
    let mut e = engine()?;
    let mut encoder = Encoder::new(cfg)?;
    let segmented = encoder.frames().can_segment();
    let labels_free = encoder.labels_rule(None, opts.references.iter())?;
    encoder = encoder.without_labels(labels_free);
    train_codebook(&mut encoder, &opts.references, opts.quiet)?;
    let refs = encode_frames(&mut e, &encoder, &opts.references, Default::default(), "references", false, opts.quiet)?.set;
    let fill = encode_frames(&mut e, &encoder, &opts.distractors, Default::default(), "distractors", false, opts.quiet)?.set;
    drop(e);
    let mut rows = Vec::new();
    for &size in &opts.sizes {
        let dir = opts.dir.join(format!("bench-stream-{size}-{}", std::process::id()));
        let t = Instant::now();
        write_map(&dir, cfg, &encoder, &refs, &fill, size, labels_free)?;
        let map_write_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let index_build_s = if size >= cfg.index.min_places && cfg.index.search != IndexSearch::Exact {
            semlook::map::index::build(&dir, &IndexParams::from_config(&cfg.index, size), cfg.index.probe, cfg.index.shortlist)?;
            Some(t.elapsed().as_secs_f64())
        } else {
            None
        };
        let map_bytes = dir_bytes(&dir);
        let sopts = StreamOptions { setting: opts.setting, sequence: opts.sequence, ..Default::default() };
        let t = Instant::now();
        let mut loc = Localizer::open(&dir, Some(cfg.clone()), sopts, engine()?)?;
        let open_s = t.elapsed().as_secs_f64();
        let frames: Vec<StreamFrame> = (0..opts.frames)
            .map(|k| {
                let f = &opts.stream[k % opts.stream.len()];
                StreamFrame { id: format!("{}#{k}", f.id), pixels: Pixels::Files(f.clone()), timestamp: None }
            })
            .collect();
        let (mut tracking, mut accepted) = (0u64, 0u64);
        let t = Instant::now();
        let stats = replay(&mut loc, frames.into_iter().map(Ok), 2, |_, r| {
            if let Replayed::Answered(r) = r {
                tracking += u64::from(r.tracking);
                accepted += u64::from(r.sequence.as_ref().is_some_and(|s| s.matched.accepted));
            }
            Ok(())
        })?;
        let wall = t.elapsed().as_secs_f64();
        let s = stats.summary();
        let c = loc.counts();
        drop(loc);
        let answered = (c.frames - c.refused).max(1) as f64;
        let row = StreamBenchRow {
            map_size: size,
            setting: opts.setting,
            sequence: opts.sequence,
            segmented: segmented && !labels_free,
            frames: c.frames,
            refused: c.refused,
            frames_per_s: c.frames as f64 / wall.max(1e-9),
            p50: s.p50,
            p99: s.p99,
            mean: s.mean,
            open_s,
            tracking: tracking as f64 / answered,
            accepted: accepted as f64 / answered,
            map_write_s,
            map_bytes,
            index_build_s,
        };
        tick(&row);
        rows.push(row);
        if !opts.keep {
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
    }
    Ok(rows)
}

/// A map of `size` places in `dir`: `refs` (traversal 0), then `fill`'s images again and again
/// under new ids (one traversal), up to `size`.
fn write_map(
    dir: &Path,
    cfg: &Config,
    encoder: &Encoder,
    refs: &semlook::descriptors::DescriptorSet,
    fill: &semlook::descriptors::DescriptorSet,
    size: usize,
    without_labels: bool,
) -> Result<()> {
    let dims = ColumnDims { appearance: encoder.appearance_dim(), hog: 0, keypoints: encoder.keypoint_dim(), compact_hog: encoder.compact_hog_dim() };
    let mut w = MapWriter::create(dir, &cfg.encoding(), dims, encoder.appearance_record(), StoreOptions::default(), false)?
        .with_embedding(encoder.embedding_record())?;
    if without_labels {
        w = w.without_labels()?;
    }
    w.push_set(refs)?;
    w.finish()?;
    if size > refs.len() {
        let mut w = MapWriter::append(dir, StoreOptions::default())?.with_traversal(TraversalPlan::Named("distractors".into()))?;
        for k in 0..size - refs.len() {
            let mut one = fill.slice(k % fill.len(), k % fill.len() + 1);
            one.ids[0] = format!("distractor-{k:07}");
            w.push_set(&one)?;
        }
        w.finish()?;
    }
    Ok(())
}

fn dir_bytes(dir: &Path) -> u64 {
    std::fs::read_dir(dir).map(|rd| rd.flatten().filter_map(|e| e.metadata().ok()).map(|m| m.len()).sum()).unwrap_or(0)
}

/// The rows as a table.
pub fn table(rows: &[StreamBenchRow]) -> String {
    let mut s = format!(
        "{:>9} {:>5} {:<10} {:>4} {:>4} {:>7} {:>8} {:>8} {:>6} | {:>6} {:>11} {:>11} {:>11} {:>11} {:>11} {:>11} {:>11} | {:>6} {:>6}\n",
        "places",
        "index",
        "setting",
        "seq",
        "seg",
        "frames",
        "frames/s",
        "MB",
        "open s",
        "mean",
        "total",
        "decode",
        "segment",
        "encode",
        "coarse",
        "fine",
        "sequence",
        "track",
        "accept"
    );
    for r in rows {
        let c = |a: f64, b: f64| format!("{a:.1}/{b:.1}");
        s += &format!(
            "{:>9} {:>5} {:<10} {:>4} {:>4} {:>7} {:>8.2} {:>8.0} {:>6.1} | {:>6.1} {:>11} {:>11} {:>11} {:>11} {:>11} {:>11} {:>11} | {:>6.2} {:>6.2}\n",
            r.map_size,
            if r.index_build_s.is_some() { "ivf" } else { "exact" },
            r.setting.name(),
            if r.sequence { "on" } else { "off" },
            if r.segmented { "yes" } else { "no" },
            r.frames,
            r.frames_per_s,
            r.map_bytes as f64 / 1e6,
            r.open_s,
            r.mean.total_ms,
            c(r.p50.total_ms, r.p99.total_ms),
            c(r.p50.decode_ms, r.p99.decode_ms),
            c(r.p50.segment_ms, r.p99.segment_ms),
            c(r.p50.encode_ms, r.p99.encode_ms),
            c(r.p50.coarse_ms, r.p99.coarse_ms),
            c(r.p50.fine_ms, r.p99.fine_ms),
            c(r.p50.sequence_ms, r.p99.sequence_ms),
            r.tracking,
            r.accepted
        );
    }
    s + "open s: opening the localizer over the map (its checks), before the first frame; mean: the mean total ms per frame; latency columns: p50/p99 ms per frame; total from the localizer taking the decoded frame to its answer (decoding and segmentation run a frame ahead on a second thread: their columns; frames/s is end to end)\n"
}

/// One source of [`pipe_vs_folder`]: the same files as a folder or piped.
#[derive(Debug, Clone, Serialize)]
pub struct PipeBenchRow {
    /// `images` (a folder, as `localize --images`) or `stdin` (the files' bytes one after another
    /// through an OS pipe, as `cat *.jpg | localize --stdin`).
    pub source: &'static str,
    /// Frames answered.
    pub frames: u64,
    /// Frames per second of wall clock, end to end.
    pub frames_per_s: f64,
    /// Latency from the frame's bytes being complete to its answer (p50, p99, ms).
    pub arrival_ms: (f64, f64),
    /// Latency from the localizer taking the decoded frame to its answer (p50, p99, ms).
    pub total_ms: (f64, f64),
    /// Reading and decoding on the second thread (p50, p99, ms).
    pub decode_ms: (f64, f64),
}

/// `semlook dev bench-pipe`: the files of `images` (name order) localized against the map in
/// `map`, once from the folder and once piped through an OS pipe into [`ImageStream`] (as
/// `localize --stdin` reads them), each through [`replay`]. Returns both rows, and the first frame
/// whose answers differ (ranking, sequence, answer), if any.
///
/// [`ImageStream`]: semlook::stream::input::ImageStream
pub fn pipe_vs_folder(
    map: &Path,
    images: &Path,
    cfg: Option<Config>,
    opts: StreamOptions,
    engine: &dyn Fn() -> Result<Engine>,
) -> Result<(Vec<PipeBenchRow>, Option<String>)> {
    use semlook::stream::input::{folder_frames, ImageStream};
    let listed = folder_frames(images, None, None)?;
    let files: Vec<PathBuf> = listed
        .iter()
        .filter_map(|f| match &f.pixels {
            Pixels::Files(s) => s.image.clone(),
            _ => None,
        })
        .collect();
    let mut rows = Vec::new();
    let mut answers: Vec<Vec<serde_json::Value>> = Vec::new();
    for source in ["images", "stdin"] {
        let mut loc = Localizer::open(map, cfg.clone(), opts, engine()?)?;
        let mut got = Vec::new();
        let mut on = |_: &mut Localizer, r: Replayed| -> Result<()> {
            if let Replayed::Answered(r) = r {
                let mut v = serde_json::to_value(&*r).map_err(|e| Error::invalid("bench-pipe", e.to_string()))?;
                if let Some(o) = v.as_object_mut() {
                    // what depends on the source alone: the frame's id and the clock
                    o.remove("id");
                    o.remove("latency");
                }
                got.push(v);
            }
            Ok(())
        };
        let t = Instant::now();
        let stats = match source {
            "images" => replay(&mut loc, listed.clone().into_iter().map(Ok), 2, &mut on)?,
            _ => {
                let (reader, mut writer) = std::io::pipe().map_err(|e| Error::io(Path::new("pipe"), e))?;
                let files = files.clone();
                let feeder = std::thread::spawn(move || -> std::io::Result<()> {
                    use std::io::Write;
                    for f in &files {
                        writer.write_all(&std::fs::read(f)?)?;
                    }
                    Ok(())
                });
                let frames = ImageStream::new(reader, "the pipe").enumerate().map(|(k, bytes)| {
                    bytes.map(|b| StreamFrame { id: format!("frame-{k:06}"), pixels: Pixels::Bytes { bytes: b, labels: None }, timestamp: None })
                });
                let stats = replay(&mut loc, frames, 2, &mut on)?;
                feeder.join().map_err(|_| Error::invalid("bench-pipe", "the feeding thread panicked"))?.map_err(|e| Error::io(images, e))?;
                stats
            }
        };
        let wall = t.elapsed().as_secs_f64();
        let s = stats.summary();
        let c = loc.counts();
        rows.push(PipeBenchRow {
            source,
            frames: c.frames - c.refused,
            frames_per_s: c.frames as f64 / wall.max(1e-9),
            arrival_ms: (s.p50.arrival_ms, s.p99.arrival_ms),
            total_ms: (s.p50.total_ms, s.p99.total_ms),
            decode_ms: (s.p50.decode_ms, s.p99.decode_ms),
        });
        answers.push(got);
    }
    let differ = match answers[0].len() == answers[1].len() {
        false => Some(format!("{} frames answered from the folder, {} from the pipe", answers[0].len(), answers[1].len())),
        true => {
            answers[0].iter().zip(&answers[1]).position(|(a, b)| a != b).map(|k| format!("frame {k}: {} against {}", answers[0][k], answers[1][k]))
        }
    };
    Ok((rows, differ))
}

/// The rows of [`pipe_vs_folder`] as a table.
pub fn pipe_table(rows: &[PipeBenchRow]) -> String {
    let mut s = format!("{:<7} {:>7} {:>9} | {:>15} {:>13} {:>13}\n", "source", "frames", "frames/s", "from bytes", "total", "decode");
    for r in rows {
        let c = |(a, b): (f64, f64)| format!("{a:.1}/{b:.1}");
        s += &format!(
            "{:<7} {:>7} {:>9.2} | {:>15} {:>13} {:>13}\n",
            r.source,
            r.frames,
            r.frames_per_s,
            c(r.arrival_ms),
            c(r.total_ms),
            c(r.decode_ms)
        );
    }
    s + "latency columns: p50/p99 ms per frame; from bytes: from the frame's bytes being complete (piped: read to its end; folder: taken in turn) to its answer\n"
}
