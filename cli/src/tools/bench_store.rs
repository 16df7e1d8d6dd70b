//! Map-store benchmark (`semlook dev map-bench`): for each size, writes a map of that many references
//! through the real store ([`MapWriter`], segment by segment, as `map build` does; descriptors
//! cycle through a pool of rendered street frames, without appearance, ids unique), opens it,
//! checks every segment once (the first-use check), and runs the coarse stage for a query batch
//! streamed from the mapped map. Reports build peak RSS, open time, the query pass's peak
//! anonymous RSS (what the process allocated; mapped file pages, which the kernel can drop, left
//! out) next to its peak total RSS, and bytes per reference.

use super::{reset_peak, status_mib};
use crate::tools::synth::{self, condition::Condition, SynthConfig};
use semlook::config::{AppearanceConfig, AppearanceModelKind, Config};
use semlook::descriptors::source::{GlobalSource, TileBuf};
use semlook::descriptors::{DescriptorSet, EncodedImage};
use semlook::encode::Encoder;
use semlook::error::{Error, Result};
use semlook::map::{Map, MapWriter, StoreOptions};
use semlook::matching::{CpuStages, Stages};
use semlook::values::ValueType;
use semlook_kernels::ssim::{ssim_pair, ssim_stats, SsimScratch};
use serde::Serialize;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

/// Rendered frames the references cycle through (a prime stride spreads them), and the query
/// frames (another condition). Enough variety for the SSIM to do real work; rendering them takes
/// a few seconds.
const POOL: usize = 64;
const QUERY_POOL: usize = 32;
/// How often the memory sampler reads /proc/self/status: fine enough to catch a tile's buffers.
const SAMPLE_EVERY: Duration = Duration::from_millis(5);

/// One coarse pass: a batch of queries against the first `refs` references (`None`: all).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Pass {
    pub queries: usize,
    pub refs: Option<usize>,
}

impl std::str::FromStr for Pass {
    type Err = Error;
    /// `QUERIES` or `QUERIES:REFS` (`REFS` a number or `all`); a bad one is an [`Error::Check`]
    /// (the command line names the option).
    fn from_str(s: &str) -> Result<Pass> {
        let (q, r) = s.split_once(':').unwrap_or((s, "all"));
        let num =
            |v: &str| v.trim().parse::<usize>().map_err(|_| Error::check(format!("{v:?} is not a whole number (expected QUERIES or QUERIES:REFS)")));
        let queries = num(q)?;
        let refs = if r.trim() == "all" { None } else { Some(num(r)?) };
        if queries == 0 || refs == Some(0) {
            return Err(Error::check("a pass needs at least one query and one reference"));
        }
        Ok(Pass { queries, refs })
    }
}

pub struct StoreBenchOptions {
    pub sizes: Vec<usize>,
    /// Coarse passes run on each map, in order.
    pub passes: Vec<Pass>,
    pub values: ValueType,
    pub dir: PathBuf,
    pub keep: bool,
    /// Query batch sizes for which a coarse pass over stored statistics (the map materialised in
    /// memory with its statistics) is timed against the same pass over the map, which recomputes
    /// them per tile; maps above [`STATS_COMPARE_LIMIT`] references skip it.
    pub stats_comparison: Vec<usize>,
}

/// Largest map materialised for the statistics comparison (31.5 kB per reference with statistics).
pub const STATS_COMPARE_LIMIT: usize = 50_000;

/// A coarse pass with stored statistics against the same pass recomputing them.
#[derive(Debug, Clone, Serialize)]
pub struct StatsRow {
    pub map_size: usize,
    pub queries: usize,
    pub stored_stats_s: f64,
    pub recomputed_stats_s: f64,
    /// recomputed / stored - 1.
    pub overhead: f64,
}

/// Everything the benchmark measured.
#[derive(Debug, Clone, Serialize)]
pub struct StoreBenchReport {
    pub passes: Vec<StoreBenchRow>,
    pub stats_comparison: Vec<StatsRow>,
}

#[derive(Debug, Clone, Serialize)]
pub struct StoreBenchRow {
    pub map_size: usize,
    pub values: ValueType,
    pub segments: usize,
    pub bytes_on_disk: u64,
    pub bytes_per_reference: f64,
    pub build_s: f64,
    /// Peak RSS of the process while building (VmHWM), including the file pages the final open
    /// of the map maps (segment headers).
    pub build_peak_rss_mib: f64,
    /// Peak anonymous RSS while building (sampled): what the build allocated.
    pub build_peak_rss_anon_mib: f64,
    pub open_ms: f64,
    /// Anonymous and file-backed RSS right after opening: the file pages are the segment headers
    /// the kernel mapped (a whole page-cache folio, up to 2 MiB, per header on recent kernels).
    pub open_rss_anon_mib: f64,
    pub open_rss_file_mib: f64,
    /// The first-use check of every segment (SHA-256 and values), in parallel.
    pub first_use_check_s: f64,
    pub queries: usize,
    pub refs_scored: usize,
    pub query_s: f64,
    pub comparisons_per_s: f64,
    /// Peak anonymous RSS during the query pass (sampled every few ms): excludes mapped file pages.
    pub query_peak_rss_anon_mib: f64,
    /// Peak total RSS during the query pass (VmHWM), mapped file pages included.
    pub query_peak_rss_mib: f64,
    /// One reference's SSIM statistics recomputed, and one SSIM pair, single thread (µs): a tile
    /// pays the first once per reference and the second once per (query, reference).
    pub stats_us_per_ref: f64,
    pub ssim_pair_us: f64,
}

/// Samples RssAnon in a thread until dropped; `peak()` is the largest value seen.
struct AnonSampler {
    stop: Arc<AtomicBool>,
    peak_kib: Arc<AtomicU64>,
    thread: Option<std::thread::JoinHandle<()>>,
}

impl AnonSampler {
    fn start() -> AnonSampler {
        let (stop, peak_kib) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
        let (s, p) = (stop.clone(), peak_kib.clone());
        let thread = std::thread::spawn(move || {
            while !s.load(Ordering::Relaxed) {
                p.fetch_max((status_mib("RssAnon:") * 1024.0) as u64, Ordering::Relaxed);
                std::thread::sleep(SAMPLE_EVERY);
            }
        });
        AnonSampler { stop, peak_kib, thread: Some(thread) }
    }
    fn peak_mib(mut self) -> f64 {
        self.stop.store(true, Ordering::Relaxed);
        if let Some(t) = self.thread.take() {
            let _ = t.join();
        }
        self.peak_kib.load(Ordering::Relaxed).max((status_mib("RssAnon:") * 1024.0) as u64) as f64 / 1024.0
    }
}

/// A source that serves the first `len` references of another.
struct Prefix<'a> {
    inner: &'a dyn GlobalSource,
    len: usize,
}

impl GlobalSource for Prefix<'_> {
    fn len(&self) -> usize {
        self.len
    }
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        self.inner.tile(start, end, buf)
    }
    fn check(&self) -> Result<()> {
        self.inner.check()
    }
}

/// `n` rendered street frames under `cond`, encoded without appearance.
fn frames(cfg: &Config, n: usize, cond: Condition, traversal: u64) -> Result<Vec<EncodedImage>> {
    use rayon::prelude::*;
    let scfg = SynthConfig { places: n, width: 320, height: 240, ..Default::default() };
    let scene = synth::Scene::new(&scfg);
    let dynamic = synth::dynamic_objects(&scene.world, scfg.seed, traversal, scfg.persistence);
    let enc = Encoder::new(&Config { appearance: AppearanceConfig { model: AppearanceModelKind::None, ..cfg.appearance.clone() }, ..cfg.clone() })?;
    (0..n)
        .into_par_iter()
        .map_init(semlook::global::GlobalScratch::default, |scratch, i| {
            let f = synth::render_frame(&scfg, &scene, &dynamic, traversal, i, cond);
            let m = semlook::input::LabelMap::new(320, 240, f.labels, enc.class_table())?;
            Ok(enc.encode_labels(&format!("{}{i}", cond.name()), &m, scratch)?.0)
        })
        .collect()
}

/// Microseconds per call of `f`, over `reps` calls.
fn per_call_us(reps: usize, mut f: impl FnMut(usize)) -> f64 {
    let t = Instant::now();
    for i in 0..reps {
        f(i);
    }
    t.elapsed().as_secs_f64() * 1e6 / reps as f64
}

/// Bytes a stored reference takes beyond its global descriptor (trees, ids, headers): the
/// benchmark's label-only maps measure about 900 (`map info`); this bounds it from above.
const STORED_EXTRA_BYTES_PER_REF: u64 = 4096;
/// Bytes of memory a map reference costs the writer while it builds (its id in the known set).
const BUILD_BYTES_PER_REF: u64 = 64;
/// Share of the available memory (and of the free disk space) a benchmark may plan to use.
const RESOURCE_SHARE: f64 = 0.5;

/// Checks every size against what this machine can give, before anything is rendered, written or
/// allocated: each map on the free space of `opts.dir`, each query batch (descriptors and their
/// SSIM statistics) and each build in half the available memory.
pub fn check_sizes(opts: &StoreBenchOptions, global_len: usize, stats_len: usize) -> Result<()> {
    let value_bytes = if opts.values == ValueType::F16 { 2 } else { 4 };
    let per_ref = global_len as u64 * value_bytes + STORED_EXTRA_BYTES_PER_REF;
    let per_query = (global_len + stats_len) as u64 * 4 + STORED_EXTRA_BYTES_PER_REF;
    let memory = (semlook::util::available_memory_bytes() as f64 * RESOURCE_SHARE) as u64;
    let probe = opts.dir.ancestors().find(|d| d.exists()).unwrap_or(&opts.dir);
    let disk = (fs4::available_space(probe).map_err(|e| Error::io(probe, e))? as f64 * RESOURCE_SHARE) as u64;
    let gib = |b: u64| b as f64 / (1u64 << 30) as f64;
    for &n in &opts.sizes {
        let need = (n as u64).saturating_mul(per_ref);
        if n == 0 || need > disk {
            return Err(Error::invalid(
                "dev map-bench sizes",
                format!(
                    "a map of {n} references takes about {:.1} GiB; half the free space of {} is {:.1} GiB: at most {} references",
                    gib(need),
                    probe.display(),
                    gib(disk),
                    disk / per_ref
                ),
            ));
        }
        if (n as u64).saturating_mul(BUILD_BYTES_PER_REF) > memory {
            return Err(Error::invalid(
                "dev map-bench sizes",
                format!("building a map of {n} references needs more than half this machine's available memory ({:.1} GiB)", gib(memory)),
            ));
        }
    }
    for q in opts.passes.iter().map(|p| p.queries).chain(opts.stats_comparison.iter().copied()) {
        let need = (q as u64).saturating_mul(per_query);
        if q == 0 || need > memory {
            return Err(Error::invalid("dev map-bench passes", format!("a batch of {q} queries takes about {:.1} GiB; this machine can give it {:.1} GiB (half of its available memory): at most {} queries", gib(need), gib(memory), memory / per_query)));
        }
    }
    Ok(())
}

/// Runs the benchmark for every size; `tick` gets each row as it is done.
pub fn run(cfg: &Config, opts: &StoreBenchOptions, tick: &mut dyn FnMut(&StoreBenchRow)) -> Result<StoreBenchReport> {
    let p = cfg.global.ssim_params();
    check_sizes(opts, p.len(), p.stats_len())?;
    let pool = frames(cfg, POOL, Condition::Day, 0)?;
    let qpool = frames(cfg, QUERY_POOL, Condition::Night, 5)?;
    let enc = Encoder::new(&Config { appearance: AppearanceConfig { model: AppearanceModelKind::None, ..cfg.appearance.clone() }, ..cfg.clone() })?;
    let batch = |n: usize| -> Result<DescriptorSet> {
        let mut queries = enc.descriptor_set();
        for i in 0..n {
            let mut q = qpool[i % QUERY_POOL].clone();
            q.id = format!("q{i}");
            queries.push(&q).map_err(|e| e.named(|r| Error::invalid("bench queries", r)))?;
        }
        Ok(queries)
    };
    // the two costs behind the decision not to store SSIM statistics
    let mut sc = SsimScratch::default();
    let mut out = vec![0.0; p.stats_len()];
    let stats_us = per_call_us(2000, |i| ssim_stats(&p, &pool[i % POOL].global, &mut out, &mut sc));
    let pair_us = per_call_us(2000, |i| {
        let (a, b) = (&pool[i % POOL], &qpool[i % QUERY_POOL]);
        std::hint::black_box(ssim_pair(&p, &a.global, &a.global_stats, &b.global, &b.global_stats, &mut sc));
    });
    std::fs::create_dir_all(&opts.dir).map_err(|e| Error::io(&opts.dir, e))?;
    let mut rows = Vec::new();
    let mut stats_rows = Vec::new();
    for &n in &opts.sizes {
        let dir = opts.dir.join(format!("store-bench-{n}-{}-{}", opts.values.name(), std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        // build through the store, as `map build` does
        reset_peak();
        let sampler = AnonSampler::start();
        let t = Instant::now();
        let mut w =
            MapWriter::create(&dir, &cfg.encoding(), Default::default(), None, StoreOptions { values: opts.values, ..Default::default() }, false)?;
        for i in 0..n {
            let mut img = pool[i.wrapping_mul(7919) % POOL].clone();
            img.id = format!("r{i:07}");
            w.push(&img)?;
        }
        drop(w.finish()?);
        let build_s = t.elapsed().as_secs_f64();
        let build_anon = sampler.peak_mib();
        let build_peak = status_mib("VmHWM:");
        // open, first-use check, coarse pass
        let t = Instant::now();
        let map = Map::open(&dir)?;
        let open_ms = t.elapsed().as_secs_f64() * 1e3;
        let (open_anon, open_file) = (status_mib("RssAnon:"), status_mib("RssFile:"));
        let t = Instant::now();
        map.check_all()?;
        let check_s = t.elapsed().as_secs_f64();
        let bytes: u64 = map.manifest.segments.iter().map(|s| s.bytes).sum();
        for pass in &opts.passes {
            let queries = batch(pass.queries)?;
            let refs = pass.refs.unwrap_or(n).min(n);
            let source = Prefix { inner: &map, len: refs };
            reset_peak();
            let sampler = AnonSampler::start();
            let t = Instant::now();
            let lists = CpuStages.coarse(&source, &queries, &p, cfg.matching.top_k, cfg.matching.tile)?;
            let query_s = t.elapsed().as_secs_f64();
            let anon = sampler.peak_mib();
            let total = status_mib("VmHWM:");
            source.check()?;
            if lists.len() != queries.len() || lists.iter().any(|l| l.is_empty() || l.iter().any(|&(_, r)| r as usize >= refs)) {
                return Err(Error::invalid("store bench", "the coarse pass returned an incomplete or out-of-range list"));
            }
            let row = StoreBenchRow {
                map_size: n,
                values: opts.values,
                segments: map.manifest.segments.len(),
                bytes_on_disk: bytes,
                bytes_per_reference: bytes as f64 / n.max(1) as f64,
                build_s,
                build_peak_rss_mib: build_peak,
                build_peak_rss_anon_mib: build_anon,
                open_ms,
                open_rss_anon_mib: open_anon,
                open_rss_file_mib: open_file,
                first_use_check_s: check_s,
                queries: queries.len(),
                refs_scored: refs,
                query_s,
                comparisons_per_s: (queries.len() * refs) as f64 / query_s,
                query_peak_rss_anon_mib: anon,
                query_peak_rss_mib: total,
                stats_us_per_ref: stats_us,
                ssim_pair_us: pair_us,
            };
            tick(&row);
            rows.push(row);
        }
        if n <= STATS_COMPARE_LIMIT && !opts.stats_comparison.is_empty() {
            let set = map.to_descriptor_set()?;
            for &q in &opts.stats_comparison {
                let queries = batch(q)?;
                let time = |src: &dyn GlobalSource| -> Result<f64> {
                    let t = Instant::now();
                    CpuStages.coarse(src, &queries, &p, cfg.matching.top_k, cfg.matching.tile)?;
                    Ok(t.elapsed().as_secs_f64())
                };
                let (stored, recomputed) = (time(&set)?, time(&map)?);
                stats_rows.push(StatsRow {
                    map_size: n,
                    queries: q,
                    stored_stats_s: stored,
                    recomputed_stats_s: recomputed,
                    overhead: recomputed / stored - 1.0,
                });
            }
        }
        drop(map);
        if !opts.keep {
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
    }
    Ok(StoreBenchReport { passes: rows, stats_comparison: stats_rows })
}

/// The statistics comparison as a plain-text table.
pub fn stats_table(rows: &[StatsRow]) -> String {
    let mut s = format!("{:>9} {:>8} {:>14} {:>16} {:>9}\n", "refs", "queries", "stored stats s", "recomputed s", "overhead");
    for r in rows {
        s += &format!("{:>9} {:>8} {:>14.2} {:>16.2} {:>8.1}%\n", r.map_size, r.queries, r.stored_stats_s, r.recomputed_stats_s, 100.0 * r.overhead);
    }
    s
}

/// The rows as a plain-text table.
pub fn table(rows: &[StoreBenchRow]) -> String {
    let mut s = format!(
        "{:>9} {:>4} {:>8} {:>8} {:>10} {:>10} {:>8} {:>8} {:>8} {:>9} {:>9} {:>9} {:>10} {:>10}\n",
        "refs",
        "type",
        "B/ref",
        "build s",
        "build MiB",
        "build anon",
        "open ms",
        "check s",
        "queries",
        "scored",
        "query s",
        "comp/s",
        "pass anon",
        "pass total"
    );
    for r in rows {
        s += &format!(
            "{:>9} {:>4} {:>8.0} {:>8.1} {:>10.0} {:>10.0} {:>8.1} {:>8.1} {:>8} {:>9} {:>9.1} {:>9.0} {:>10.0} {:>10.0}\n",
            r.map_size,
            r.values.name(),
            r.bytes_per_reference,
            r.build_s,
            r.build_peak_rss_mib,
            r.build_peak_rss_anon_mib,
            r.open_ms,
            r.first_use_check_s,
            r.queries,
            r.refs_scored,
            r.query_s,
            r.comparisons_per_s,
            r.query_peak_rss_anon_mib,
            r.query_peak_rss_mib
        );
    }
    s
}
