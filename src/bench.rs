//! Large-map batch matching benchmark (`semlook bench`): coarse matching of query batches against
//! maps of 1k to 1M references, on every available backend, with throughput and peak memory.
//!
//! Maps up to [`RESIDENT_LIMIT`] references are real in-memory descriptor sets; larger ones are a
//! [`SyntheticMap`] that assembles each tile from a pool of real descriptors as it is streamed, so
//! a million references never need to exist at once (this is how a map larger than memory is read).
//! Each configuration runs as many queries of its batch as fit a time budget (at least one), and
//! reports how many it ran.

use crate::config::Config;
use crate::engine::Engine;
use crate::error::Result;
use crate::global::ssim::SsimParams;
use crate::map::DescriptorSet;
use crate::matching::source::{GlobalSource, TileBuf};
use crate::matching::{CpuStages, Stages};
use serde::Serialize;
use std::time::Instant;

/// Maps up to this size are materialised in memory.
pub const RESIDENT_LIMIT: usize = 10_000;

/// A map of `len` references whose descriptors cycle through a pool (a large prime stride, so
/// neighbouring references differ).
pub struct SyntheticMap<'a> {
    pub len: usize,
    pub pool: &'a DescriptorSet,
}

impl GlobalSource for SyntheticMap<'_> {
    fn len(&self) -> usize {
        self.len
    }
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        use rayon::prelude::*;
        let p = self.pool;
        let (gl, sl) = (p.global_len, p.stats_len);
        buf.globals.resize((end - start) * gl, 0.0);
        buf.stats.resize((end - start) * sl, 0.0);
        let pick = |i: usize| (i.wrapping_mul(7919)) % p.len();
        buf.globals.par_chunks_mut(gl).enumerate().for_each(|(k, dst)| dst.copy_from_slice(p.global(pick(start + k))));
        buf.stats.par_chunks_mut(sl).enumerate().for_each(|(k, dst)| dst.copy_from_slice(p.stats(pick(start + k))));
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
        set.append(&one);
    }
    set
}

#[derive(Debug, Clone, Serialize)]
pub struct BenchRow {
    pub map_size: usize,
    pub batch: usize,
    pub backend: String,
    pub queries_run: usize,
    pub seconds: f64,
    pub queries_per_s: f64,
    pub comparisons_per_s: f64,
    /// Peak resident memory of the process during this configuration (MiB).
    pub peak_mib: f64,
    /// This backend's comparisons per second over the CPU's, for the same configuration.
    pub gpu_cpu_ratio: Option<f64>,
}

/// Resets the kernel's peak-RSS counter of this process (Linux), so each configuration reports
/// its own peak.
fn reset_peak() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}

fn peak_mib() -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("VmHWM:")).and_then(|l| l.split_whitespace().nth(1)).and_then(|v| v.parse::<f64>().ok()))
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Queries `0..n` of `queries`, cycling (ids made unique).
fn batch_of(queries: &DescriptorSet, n: usize) -> DescriptorSet {
    cycle(queries, n, "q", 1)
}

/// Runs every (map size, batch, backend) configuration. `engines` are (label, engine) pairs; the
/// first CPU one is the reference for the GPU/CPU ratio. `tick` reports each finished row.
pub fn run(
    pool: &DescriptorSet,
    queries: &DescriptorSet,
    sizes: &[usize],
    batches: &[usize],
    engines: &mut [Engine],
    budget_s: f64,
    cfg: &Config,
    tick: &mut dyn FnMut(&BenchRow),
) -> Result<Vec<BenchRow>> {
    let p = SsimParams::new(&cfg.global);
    let k = cfg.matching.top_k;
    let mut rows = Vec::new();
    for &n in sizes {
        let resident = (n <= RESIDENT_LIMIT).then(|| resident_map(pool, n));
        let synthetic = SyntheticMap { len: n, pool };
        let source: &dyn GlobalSource = match &resident {
            Some(r) => r,
            None => &synthetic,
        };
        for &b in batches {
            let mut cpu_rate = None;
            for engine in engines.iter_mut() {
                let label = engine.describe();
                let mut stages: Box<dyn FnMut(&DescriptorSet, &dyn GlobalSource) -> Result<Vec<Vec<(f32, u32)>>>> = match engine.gpu_stages() {
                    Some(g) => Box::new(move |q, s| g.coarse(s, q, &p, k, cfg.matching.tile)),
                    None => Box::new(move |q, s| CpuStages.coarse(s, q, &p, k, cfg.matching.tile)),
                };
                // probe: a few queries against at most 20k references, to size the run to the budget
                let probe_refs = n.min(20_000);
                let probe_q = b.min(4);
                let probe_map = SyntheticMap { len: probe_refs, pool };
                let t = Instant::now();
                stages(&batch_of(queries, probe_q), &probe_map)?;
                let per_pair = t.elapsed().as_secs_f64() / (probe_refs * probe_q) as f64;
                let m = ((budget_s / (per_pair * n as f64)) as usize).clamp(1, b);
                let batch = batch_of(queries, m);
                reset_peak();
                let t = Instant::now();
                let lists = stages(&batch, source)?;
                let secs = t.elapsed().as_secs_f64();
                assert_eq!(lists.len(), m);
                let rate = (m * n) as f64 / secs;
                let ratio = if label.starts_with("cpu") {
                    cpu_rate.get_or_insert(rate);
                    None
                } else {
                    cpu_rate.map(|c| rate / c)
                };
                let row = BenchRow {
                    map_size: n,
                    batch: b,
                    backend: label,
                    queries_run: m,
                    seconds: secs,
                    queries_per_s: m as f64 / secs,
                    comparisons_per_s: rate,
                    peak_mib: peak_mib(),
                    gpu_cpu_ratio: ratio,
                };
                tick(&row);
                rows.push(row);
            }
        }
    }
    Ok(rows)
}

/// The rows as a plain-text table.
pub fn table(rows: &[BenchRow]) -> String {
    let mut s = format!(
        "{:>9} {:>6} {:<52} {:>8} {:>10} {:>14} {:>9} {:>8}\n",
        "map size", "batch", "backend", "queries", "queries/s", "comparisons/s", "peak MiB", "GPU/CPU"
    );
    for r in rows {
        s += &format!(
            "{:>9} {:>6} {:<52} {:>8} {:>10.2} {:>14.0} {:>9.0} {:>8}\n",
            r.map_size,
            r.batch,
            r.backend,
            r.queries_run,
            r.queries_per_s,
            r.comparisons_per_s,
            r.peak_mib,
            r.gpu_cpu_ratio.map_or("-".to_string(), |x| format!("{x:.2}"))
        );
    }
    s
}

/// Descriptors of `n` rendered street frames of traversal `traversal` under `cond`, for pools.
pub fn street_descriptors(cfg: &Config, n: usize, cond: crate::synth::condition::Condition, traversal: u64) -> Result<DescriptorSet> {
    use crate::synth::{self, SynthConfig};
    let scfg = SynthConfig { places: n, width: 320, height: 240, ..Default::default() };
    let scene = synth::Scene::new(&scfg);
    let dynamic = synth::dynamic_objects(&scene.world, scfg.seed, traversal, scfg.persistence);
    let enc = crate::encode::Encoder::new(&Config { appearance: crate::config::AppearanceConfig { model: crate::config::AppearanceModelKind::None, ..cfg.appearance.clone() }, ..cfg.clone() })?;
    let table = enc.class_table().clone();
    use rayon::prelude::*;
    let images: Vec<_> = (0..n)
        .into_par_iter()
        .map_init(crate::global::GlobalScratch::default, |scratch, i| {
            let f = synth::render_frame(&scfg, &scene, &dynamic, traversal, i, cond);
            let m = crate::input::LabelMap::new(320, 240, f.labels, &table)?;
            Ok(enc.encode_labels(&format!("{}{i}", cond.name()), &m, scratch)?.0)
        })
        .collect::<Result<_>>()?;
    let mut set = DescriptorSet::new(&enc.ssim_params(), cfg.local.neighbours, 0, 0);
    for img in &images {
        set.push(img).map_err(|r| crate::Error::invalid("bench pool", r))?;
    }
    Ok(set)
}
