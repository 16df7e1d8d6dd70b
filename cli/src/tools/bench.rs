//! Large-map batch matching benchmark (`semlook dev bench`): the coarse stage (SSIM top-K) of query
//! batches against maps of 1k to 1M references, on every available backend.
//!
//! What a row measures: one call of `Stages::coarse` (query preparation, the scores of every
//! tile, the streaming top-K) for a batch of exactly `batch` queries against `map_size`
//! references, wall clock. Nothing else is in the timed region:
//! - maps up to `resident_limit` references are real in-memory descriptor sets;
//! - larger maps are a [`SyntheticMap`]: one block of references (real descriptors from the
//!   pool) is assembled before timing and every tile is served from it without copying
//!   (reference i is block entry i mod block). A block far larger than the caches is read from
//!   memory exactly as a real map of that size would be. A tile that does not line up with the
//!   block is copied in the timed region and the row counts it (`tiles_copied`);
//! - batches are assembled before timing;
//! - on a GPU, the map is uploaded once per map size before its first row, untimed (its time is
//!   reported as `upload_seconds`), and stays resident across the rows, as it stays across a
//!   deployment's batches; each GPU row reports the bytes written to the device inside its timed
//!   region (`device_bytes_written`: the batch's queries, lists and pass parameters only). A map
//!   beyond the device's resident budget is streamed inside every timed batch instead, and the
//!   row says so (`map_resident: false`).
//!
//! Rows never run part of their batch. An untimed probe (a few queries against one tile)
//! predicts each row's time; a row predicted to exceed `max_row_seconds` is not run, and the
//! table and JSON say so (`status: "skipped"`, with the prediction).
//!
//! Reported: comparisons/s; bytes/s (the map's descriptor and stats bytes, counted once per
//! batch); effective GFLOP/s at [`flops_per_comparison`]; the fraction of the device's peak where
//! it is known ([`peak`]); peak RSS; the process's CPU time over the row and the 1-minute load
//! average before it (other processes on the machine take cores from the run: the cores column
//! says how many the row had). Software GPU adapters (lavapipe, llvmpipe) are
//! correctness-only backends: their rows say so and carry no peak.

pub mod peak;

use super::{reset_peak, status_mib};
use semlook::config::Config;
use semlook::descriptors::source::{GlobalSource, TileBuf};
use semlook::descriptors::DescriptorSet;
use semlook::engine::Engine;
use semlook::error::Result;
use semlook::matching::{CpuStages, Stages};
use semlook_kernels::abi::SsimParams;
use serde::Serialize;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

/// Maps up to this size are materialised in memory by the CLI.
pub const RESIDENT_LIMIT: usize = 10_000;

/// What to run.
#[derive(Debug, Clone)]
pub struct BenchOptions {
    pub sizes: Vec<usize>,
    pub batches: Vec<usize>,
    /// Rows predicted to take longer are not run (and reported as skipped).
    pub max_row_seconds: f64,
    /// Maps up to this size are materialised in memory; larger ones are synthetic.
    pub resident_limit: usize,
    /// The GPU's peak (GFLOP/s), where the built-in table does not know the adapter.
    pub gpu_peak_gflops: Option<f64>,
}

impl BenchOptions {
    /// Checks every option's range; the error names the option.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: &str, why: String| Err(semlook::error::Error::invalid(what, why));
        if self.sizes.is_empty() || self.sizes.iter().any(|&n| !(1..=100_000_000).contains(&n)) {
            return bad("bench sizes", format!("{:?}: map sizes must be in 1..=100000000", self.sizes));
        }
        if self.batches.is_empty() || self.batches.iter().any(|&b| !(1..=100_000).contains(&b)) {
            return bad("bench batches", format!("{:?}: batch sizes must be in 1..=100000", self.batches));
        }
        if !(self.max_row_seconds.is_finite() && self.max_row_seconds >= 0.0) {
            return bad("bench row limit", format!("{} must be a number of seconds, 0 or more", self.max_row_seconds));
        }
        if let Some(p) = self.gpu_peak_gflops.filter(|p| !(p.is_finite() && *p > 0.0)) {
            return bad("bench peak", format!("{p} must be a positive number"));
        }
        Ok(())
    }
}

/// Operations of one SSIM comparison by the direct algorithm (the twin `ssim_pair` without its
/// precomputed statistics): gw*gh products; (win - 1) additions per window sum, horizontally
/// (gh rows x nw) and vertically (nh x nw); and per window 19 operations of the SSIM formula
/// (mean of xy 1, covariance 3, numerator 6, denominator 7, division 1, accumulation 1).
/// A division counts as one. Precomputed per-descriptor terms do not lower the count: it is the
/// work a comparison represents, not the work an implementation happens to do.
pub fn flops_per_comparison(p: &SsimParams) -> f64 {
    let (gw, gh, win, nw, nh) = (p.gw as f64, p.gh as f64, p.win as f64, p.nw as f64, p.nh as f64);
    gw * gh + (gh * nw + nh * nw) * (win - 1.0) + nw * nh * 19.0
}

/// Bytes of one reference the coarse stage reads: its descriptor and its stats record.
pub fn bytes_per_reference(p: &SsimParams) -> usize {
    (p.len() + p.stats_len()) * 4
}

/// A map of `len` references served from one pre-assembled block (see the module doc).
pub struct SyntheticMap {
    len: usize,
    block: DescriptorSet,
    copied: AtomicUsize,
}

impl SyntheticMap {
    /// A map of `len` references whose block holds `block` references cycling through `pool`.
    pub fn new(pool: &DescriptorSet, len: usize, block: usize) -> Self {
        SyntheticMap { len, block: resident_map(pool, block.clamp(1, len.max(1))), copied: AtomicUsize::new(0) }
    }
    /// Tiles copied since the last call (those that did not line up with the block).
    pub fn take_copied(&self) -> usize {
        self.copied.swap(0, Ordering::Relaxed)
    }
}

impl GlobalSource for SyntheticMap {
    fn len(&self) -> usize {
        self.len
    }
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        let (b, n) = (self.block.len(), end - start);
        let s = start % b;
        if s + n <= b {
            return self.block.tile(s, s + n, buf);
        }
        self.copied.fetch_add(1, Ordering::Relaxed);
        let (gl, sl) = (self.block.global_len, self.block.stats_len);
        buf.globals.clear();
        buf.stats.clear();
        for i in start..end {
            buf.globals.extend_from_slice(self.block.global(i % b));
            buf.stats.extend_from_slice(self.block.stats(i % b));
        }
        debug_assert_eq!(buf.globals.len(), n * gl);
        debug_assert_eq!(buf.stats.len(), n * sl);
        (&buf.globals, &buf.stats)
    }
}

/// A set of `n` references cycling through `pool` (ids made unique).
pub fn resident_map(pool: &DescriptorSet, n: usize) -> DescriptorSet {
    cycle(pool, n, "r", 7919)
}

/// `n` entries of `pool`, entry i taken from position i * stride (mod the pool), ids `prefix{i}`.
fn cycle(pool: &DescriptorSet, n: usize, prefix: &str, stride: usize) -> DescriptorSet {
    let mut set = pool.slice(0, 0);
    for i in 0..n {
        let j = i.wrapping_mul(stride) % pool.len();
        let mut one = pool.slice(j, j + 1);
        one.ids[0] = format!("{prefix}{i}");
        set.append_range(&one, 0, 1).expect("slices of one set share its layout");
    }
    set
}

/// One (map size, batch, backend) configuration.
#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    pub map_size: usize,
    pub batch: usize,
    /// "cpu" or "gpu".
    pub backend: String,
    /// The processor or GPU adapter (and, for the CPU, threads and SIMD instruction set).
    pub adapter: String,
    /// "ran" (the whole batch) or "skipped" (nothing ran; see `note`).
    pub status: String,
    /// Queries scored: the batch, or 0 when skipped.
    pub queries_run: usize,
    pub seconds: Option<f64>,
    pub queries_per_s: Option<f64>,
    pub comparisons_per_s: Option<f64>,
    /// Map bytes (descriptors and stats) per second, the map counted once per batch.
    pub bytes_per_s: Option<f64>,
    /// Effective GFLOP/s at `flops_per_comparison`.
    pub gflops: Option<f64>,
    pub flops_per_comparison: f64,
    pub peak_gflops: Option<f64>,
    pub peak_source: Option<String>,
    pub fraction_of_peak: Option<f64>,
    /// Peak resident memory of the process during this row (MiB).
    pub peak_rss_mib: f64,
    /// Tiles copied inside the timed region (synthetic maps whose tiles miss the block).
    pub tiles_copied: usize,
    /// GPU rows: whether the map stayed resident on the device (false: beyond the resident
    /// budget, streamed through two slots inside every timed batch).
    pub map_resident: Option<bool>,
    /// GPU rows: seconds the untimed upload of this map to the device took (once per map size,
    /// before its first row; 0 upload bytes in later rows show it was not repeated).
    pub upload_seconds: Option<f64>,
    /// GPU rows: bytes written to the device inside the timed region (queries, empty lists, pass
    /// parameters; plus the whole map when it is streamed).
    pub device_bytes_written: Option<u64>,
    /// GPU rows: kernel time from timestamp queries, where the adapter has them.
    pub kernel_seconds: Option<f64>,
    /// 1-minute load average just before the row.
    pub loadavg_1m: f64,
    /// CPU time of the whole process during the row (user + system, all threads); over
    /// `seconds`, the cores the row had (less than the worker threads: other processes competed).
    pub cpu_seconds: Option<f64>,
    /// This backend's comparisons per second over the CPU's, for the same configuration.
    pub gpu_cpu_ratio: Option<f64>,
    /// "correctness only" for software adapters; the prediction for skipped rows.
    pub note: String,
}

/// User + system CPU time of this process so far (Linux /proc, USER_HZ = 100 ticks per second).
fn process_cpu_s() -> f64 {
    std::fs::read_to_string("/proc/self/stat")
        .ok()
        .and_then(|s| {
            // fields after the parenthesised command name: state is field 3, utime 14, stime 15
            let rest = s.rsplit_once(')')?.1;
            let f: Vec<&str> = rest.split_whitespace().collect();
            Some((f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?) / 100.0)
        })
        .unwrap_or(f64::NAN)
}

fn loadavg() -> f64 {
    std::fs::read_to_string("/proc/loadavg").ok().and_then(|s| s.split_whitespace().next().and_then(|v| v.parse().ok())).unwrap_or(f64::NAN)
}

/// Runs every (map size, batch, engine) configuration; the first CPU engine is the reference of
/// the GPU/CPU ratio. `tick` reports each finished row.
pub fn run(
    pool: &DescriptorSet,
    queries: &DescriptorSet,
    opts: &BenchOptions,
    engines: &mut [Engine],
    cfg: &Config,
    tick: &mut dyn FnMut(&BenchRow),
) -> Result<Vec<BenchRow>> {
    opts.validate()?;
    let p = cfg.global.ssim_params();
    let (k, tile) = (cfg.matching.top_k, cfg.matching.tile);
    let flops = flops_per_comparison(&p);
    let devices: Vec<peak::Device> = engines.iter_mut().map(|e| peak::Device::of(e, &p, opts.gpu_peak_gflops)).collect();
    let mut rows = Vec::new();
    for &n in &opts.sizes {
        let (resident, synthetic) =
            if n <= opts.resident_limit { (Some(resident_map(pool, n)), None) } else { (None, Some(SyntheticMap::new(pool, n, tile))) };
        let source: &dyn GlobalSource = match (&resident, &synthetic) {
            (Some(r), _) => r,
            (None, Some(s)) => s,
            (None, None) => return Ok(rows),
        };
        // untimed probe per engine: a few queries against one tile of this map (also a warm-up)
        let probe_q = batch_of(queries, 4);
        let probe_map = SyntheticMap::new(pool, n.min(tile), tile);
        let mut per_pair = Vec::new();
        for engine in engines.iter_mut() {
            let t = Instant::now();
            coarse(engine, &probe_q, &probe_map, &p, k, tile)?;
            per_pair.push(t.elapsed().as_secs_f64() / (probe_q.len() * probe_map.len()) as f64);
        }
        // untimed: each GPU engine uploads this map once (kept resident within its budget)
        let mut uploads = Vec::new();
        for engine in engines.iter_mut() {
            uploads.push(match engine.gpu_stages() {
                Some(g) => {
                    let t = Instant::now();
                    let resident = g.upload_coarse_map(source, &p)?;
                    g.take_kernel_seconds()?;
                    Some((resident, t.elapsed().as_secs_f64()))
                }
                None => None,
            });
        }
        for &b in &opts.batches {
            let batch = batch_of(queries, b);
            let mut cpu_rate = None;
            for (e, engine) in engines.iter_mut().enumerate() {
                let dev = &devices[e];
                let predicted = per_pair[e] * (n * b) as f64;
                let mut row = BenchRow {
                    map_size: n,
                    batch: b,
                    backend: dev.backend.clone(),
                    adapter: dev.adapter.clone(),
                    status: "skipped".into(),
                    queries_run: 0,
                    seconds: None,
                    queries_per_s: None,
                    comparisons_per_s: None,
                    bytes_per_s: None,
                    gflops: None,
                    flops_per_comparison: flops,
                    peak_gflops: dev.peak_gflops,
                    peak_source: dev.peak_source.clone(),
                    fraction_of_peak: None,
                    peak_rss_mib: f64::NAN,
                    tiles_copied: 0,
                    map_resident: uploads[e].map(|u| u.0),
                    upload_seconds: uploads[e].map(|u| u.1),
                    device_bytes_written: None,
                    kernel_seconds: None,
                    loadavg_1m: loadavg(),
                    cpu_seconds: None,
                    gpu_cpu_ratio: None,
                    note: dev.note.clone(),
                };
                if let Some((resident, secs)) = uploads[e] {
                    let how = if resident {
                        format!("map resident (uploaded untimed, {secs:.2} s)")
                    } else {
                        "map streamed in every batch (beyond the resident budget)".into()
                    };
                    row.note = if row.note.is_empty() { how } else { format!("{}; {how}", row.note) };
                }
                if predicted > opts.max_row_seconds {
                    row.note = format!("not run: predicted {predicted:.0} s > the row limit of {:.0} s; {}", opts.max_row_seconds, row.note);
                } else {
                    if let Some(s) = &synthetic {
                        s.take_copied();
                    }
                    reset_peak();
                    let written = engine.gpu_stages().map(|g| g.ctx.bytes_uploaded());
                    let (t, cpu0) = (Instant::now(), process_cpu_s());
                    let lists = coarse(engine, &batch, source, &p, k, tile)?;
                    let secs = t.elapsed().as_secs_f64();
                    row.cpu_seconds = Some(process_cpu_s() - cpu0);
                    if let Some(g) = engine.gpu_stages() {
                        row.device_bytes_written = written.map(|w| g.ctx.bytes_uploaded() - w);
                        row.kernel_seconds = g.take_kernel_seconds()?;
                        row.map_resident = Some(g.coarse_map_is_resident());
                    }
                    if lists.len() != b {
                        return Err(semlook::error::Error::invalid("bench", format!("{} K-lists for {b} queries", lists.len())));
                    }
                    let rate = (n * b) as f64 / secs;
                    row.status = "ran".into();
                    row.queries_run = b;
                    row.seconds = Some(secs);
                    row.queries_per_s = Some(b as f64 / secs);
                    row.comparisons_per_s = Some(rate);
                    row.bytes_per_s = Some((n * bytes_per_reference(&p)) as f64 / secs);
                    row.gflops = Some(rate * flops / 1e9);
                    row.fraction_of_peak = dev.peak_gflops.map(|pk| rate * flops / 1e9 / pk);
                    row.peak_rss_mib = status_mib("VmHWM:");
                    row.tiles_copied = synthetic.as_ref().map_or(0, |s| s.take_copied());
                    if dev.backend == "cpu" {
                        cpu_rate.get_or_insert(rate);
                    } else {
                        row.gpu_cpu_ratio = cpu_rate.map(|c| rate / c);
                    }
                }
                tick(&row);
                rows.push(row);
            }
        }
    }
    Ok(rows)
}

fn coarse(engine: &mut Engine, q: &DescriptorSet, refs: &dyn GlobalSource, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
    match engine.gpu_stages() {
        Some(g) => g.coarse(refs, q, p, k, tile),
        None => CpuStages.coarse(refs, q, p, k, tile),
    }
}

/// Queries `0..n` of `queries`, cycling (ids made unique).
fn batch_of(queries: &DescriptorSet, n: usize) -> DescriptorSet {
    cycle(queries, n, "q", 1)
}

fn opt(v: Option<f64>, scale: f64, digits: usize) -> String {
    v.map_or("-".into(), |x| format!("{:.*}", digits, x * scale))
}

/// The rows as a plain-text table, with the adapters, the flop count and the peaks below it.
pub fn table(rows: &[BenchRow]) -> String {
    let mut s = format!(
        "{:>9} {:>6} {:>4} {:>8} {:>9} {:>6} {:>14} {:>7} {:>8} {:>7} {:>9} {:>5} {:>8}  {}\n",
        "map size", "batch", "on", "queries", "seconds", "cores", "comparisons/s", "GB/s", "GFLOP/s", "% peak", "peak MiB", "load", "GPU/CPU", "note"
    );
    for r in rows {
        s += &format!(
            "{:>9} {:>6} {:>4} {:>8} {:>9} {:>6} {:>14} {:>7} {:>8} {:>7} {:>9.0} {:>5.2} {:>8}  {}\n",
            r.map_size,
            r.batch,
            r.backend,
            r.queries_run,
            opt(r.seconds, 1.0, 2),
            opt(r.cpu_seconds.zip(r.seconds).map(|(c, s)| c / s), 1.0, 2),
            opt(r.comparisons_per_s, 1.0, 0),
            opt(r.bytes_per_s, 1e-9, 2),
            opt(r.gflops, 1.0, 1),
            opt(r.fraction_of_peak, 100.0, 1),
            r.peak_rss_mib,
            r.loadavg_1m,
            opt(r.gpu_cpu_ratio, 1.0, 2),
            r.note
        );
    }
    s
}

/// What the table's columns mean, and each adapter with its peak.
pub fn legend(rows: &[BenchRow]) -> String {
    let mut s = String::new();
    if let Some(r) = rows.first() {
        s += &format!(
            "flops per comparison: {:.0} (the direct algorithm: products, window sums, 19 per window formula; see bench::flops_per_comparison)\n",
            r.flops_per_comparison
        );
    }
    s += "GB/s: map descriptors and stats read per second, the map counted once per batch; cores: process CPU time / wall time\n";
    s += "(below the worker threads when other processes competed); load: 1-minute load average before the row\n";
    if rows.iter().any(|r| r.backend == "gpu") {
        s += "gpu rows: the map is uploaded once per map size before its first row, untimed (the note gives the time); the JSON\n";
        s += "gives the bytes written to the device inside each timed region (device_bytes_written) and timestamp kernel time\n";
    }
    let mut seen = Vec::new();
    for r in rows {
        if !seen.contains(&&r.adapter) {
            seen.push(&r.adapter);
            let peak = match (&r.peak_source, r.note.contains("correctness only")) {
                (Some(p), _) => p.clone(),
                (None, true) => "none: a software adapter, correctness only".into(),
                (None, false) => "unknown (give the peak GFLOP/s)".into(),
            };
            s += &format!("{}: {}; peak {}\n", r.backend, r.adapter, peak);
        }
    }
    s
}

/// Descriptors of `n` rendered street frames of traversal `traversal` under `cond`, for pools.
pub fn street_descriptors(cfg: &Config, n: usize, cond: crate::tools::synth::condition::Condition, traversal: u64) -> Result<DescriptorSet> {
    use crate::tools::synth::{self, SynthConfig};
    let scfg = SynthConfig { places: n, width: 320, height: 240, ..Default::default() };
    let scene = synth::Scene::new(&scfg);
    let dynamic = synth::dynamic_objects(&scene.world, scfg.seed, traversal, scfg.persistence);
    let enc = semlook::encode::Encoder::new(&Config {
        appearance: semlook::config::AppearanceConfig { model: semlook::config::AppearanceModelKind::None, ..cfg.appearance.clone() },
        ..cfg.clone()
    })?;
    let table = enc.class_table().clone();
    use rayon::prelude::*;
    let images: Vec<_> = (0..n)
        .into_par_iter()
        .map_init(semlook::global::GlobalScratch::default, |scratch, i| {
            let f = synth::render_frame(&scfg, &scene, &dynamic, traversal, i, cond);
            let m = semlook::input::LabelMap::new(320, 240, f.labels, &table)?;
            Ok(enc.encode_labels(&format!("{}{i}", cond.name()), &m, scratch)?.0)
        })
        .collect::<Result<_>>()?;
    let mut set = DescriptorSet::new(&enc.global().ssim_params(), cfg.local.neighbours, 0, 0);
    for img in &images {
        set.push(img).map_err(|e| e.named(|r| semlook::Error::invalid("bench pool", r)))?;
    }
    Ok(set)
}

#[cfg(test)]
#[path = "bench_tests.rs"]
mod tests;
