//! `semlook dev index-bench`: the approximate index of the coarse stage against the exact scan on
//! stored maps of 100k to millions of references, as issue 29 asks: build time and bytes per
//! reference of the index, p50/p99 latency of one query and queries/s of a batch of 1,000 through
//! each, recall@30 of the index's fused top-30 against the exact fused top-30 on the same queries,
//! and the peak RSS of each pass.
//!
//! References: the images of a real map (`--from`, labelled, with appearance) written again and
//! again under new ids, each with its global descriptor as it is and its appearance vector made
//! new: `a x v_i + (1 - a) x v_j + noise`, renormalised, with `v_i` the image's own vector, `v_j`
//! another image's, `a` in [0.6, 1] and noise of norm 0.25, all from a seed, so that no two
//! references are the same (copies would make the exact top-30 a tie among copies). Queries: real
//! photos (`--queries`) encoded for the map.

use super::{reset_peak, status_mib};
use semlook::config::{Config, IndexSearch};
use semlook::descriptors::{DescriptorSet, EncodedImage};
use semlook::encode::Encoder;
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::input::FrameSource;
use semlook::local::Forest;
use semlook::map::{ColumnDims, Map, MapWriter, StoreOptions};
use semlook::matching::{candidates, CpuStages, Setting};
use semlook::util::SplitMix64;
use serde::Serialize;
use std::collections::HashSet;
use std::path::PathBuf;
use std::time::Instant;

pub struct IndexBenchOptions {
    /// The real map whose images the references are made from.
    pub from: PathBuf,
    /// Real query photos.
    pub queries: Vec<FrameSource>,
    pub sizes: Vec<usize>,
    /// Queries scanned exactly too, for the recall (the exact scan of a large map takes seconds
    /// a query), evenly spread over the query photos.
    pub exact_queries: usize,
    /// The batch whose queries/s is measured (queries cycled).
    pub batch: usize,
    /// (probe, shortlist, pool: the config's where none) searched on each map (one row each);
    /// empty: the config's.
    pub searches: Vec<(usize, usize, Option<usize>)>,
    /// Exact single queries timed (each scans the whole map alone).
    pub exact_timed: usize,
    pub dir: PathBuf,
    pub keep: bool,
    pub quiet: bool,
}

/// One map size.
#[derive(Debug, Clone, Serialize)]
pub struct IndexBenchRow {
    pub map_size: usize,
    pub map_bytes_per_reference: f64,
    pub map_write_s: f64,
    /// Index build (sample, training, every segment's codes, recall, commit).
    pub index_build_s: f64,
    pub index_bytes_per_reference: f64,
    pub index_dims: usize,
    pub index_lists: usize,
    pub probe: usize,
    pub shortlist: usize,
    /// `index.pool`: the codes' best re-ranked with the thumbnails' SSIM (0 or <= shortlist: none).
    pub pool: usize,
    /// Bytes of a reference's thumbnail in the index (0: none).
    pub thumbnail_bytes: usize,
    /// Recall@30 recorded by the build (shortlists against the exact appearance ranking).
    pub build_recall: f64,
    /// One query at a time through the index (fused coarse stage): p50, p99 ms.
    pub index_p50_ms: f64,
    pub index_p99_ms: f64,
    /// Queries/s of a batch of `batch` through the index.
    pub index_batch_qps: f64,
    /// One query at a time, exact scan: p50, p99 ms (the `exact_queries`).
    pub exact_p50_ms: f64,
    pub exact_p99_ms: f64,
    /// Queries/s of the exact scan over a batch of `exact_queries`.
    pub exact_batch_qps: f64,
    /// Mean over the exact queries of |index top-30 ∩ exact top-30| / 30 (fused scores).
    pub recall_at_30: f64,
    /// The lowest of those.
    pub recall_at_30_min: f64,
    pub queries: usize,
    pub exact_queries: usize,
    pub batch: usize,
    /// Peak RSS (VmHWM) of the index passes and of the exact passes, MiB.
    pub index_peak_rss_mib: f64,
    pub exact_peak_rss_mib: f64,
}

fn percentile(v: &mut [f64], p: f64) -> f64 {
    if v.is_empty() {
        return f64::NAN;
    }
    v.sort_by(f64::total_cmp);
    v[((v.len() - 1) as f64 * p).round() as usize]
}

/// Reference `k` of a generated map: image `k` of `base` cycled, its appearance made new.
fn reference(base: &DescriptorSet, k: usize, rng_seed: u64) -> EncodedImage {
    let n = base.len();
    let i = k.wrapping_mul(7919) % n;
    let mut rng = SplitMix64::new(rng_seed ^ (k as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15));
    let j = (rng.next_u64() % n as u64) as usize;
    let a = rng.range(0.6, 1.0) as f32;
    let d = base.appearance_dim;
    let (vi, vj) = (base.image_appearance(i), base.image_appearance(j));
    let sigma = 0.25 / (d.max(1) as f32).sqrt();
    let mut v: Vec<f32> = (0..d).map(|t| a * vi[t] + (1.0 - a) * vj[t] + sigma * (rng.range(-1.0, 1.0) as f32 * 1.732)).collect();
    let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-12);
    v.iter_mut().for_each(|x| *x /= norm);
    EncodedImage {
        id: format!("r{k:08}"),
        width: base.sizes[i][0],
        height: base.sizes[i][1],
        global: base.global(i).to_vec(),
        global_stats: base.stats(i).to_vec(),
        forest: Forest { neighbour_slots: base.neighbour_slots, ..Default::default() },
        appearance: v,
        hog: vec![],
        embedding: vec![],
        compact_hog: vec![],
        keypoints: Default::default(),
        pose: None,
    }
}

/// Runs every size; `tick` hears about each row.
pub fn run(cfg: &Config, opts: &IndexBenchOptions, engine: &mut Engine, tick: &mut dyn FnMut(&IndexBenchRow)) -> Result<Vec<IndexBenchRow>> {
    let from = Map::open(&opts.from)?;
    if from.manifest.appearance_dim == 0 || from.manifest.without_labels {
        return Err(Error::invalid(format!("map {}", opts.from.display()), "needs a map with appearance and labels (the fused score uses both)"));
    }
    let base = from.to_descriptor_set()?;
    let qcfg = Config { index: cfg.index.clone(), models: cfg.models.clone(), ..from.query_config() };
    let encoder = Encoder::for_map(&qcfg, &from)?;
    let queries = semlook::batch::encode_frames(engine, &encoder, &opts.queries, Default::default(), "queries", false, opts.quiet)?.set;
    if queries.is_empty() {
        return Err(Error::invalid("index-bench", "no query photos"));
    }
    let record = from.codebook().map(|c| (c.clone(), from.manifest.appearance_model.clone().unwrap_or_default()));
    drop(from);
    std::fs::create_dir_all(&opts.dir).map_err(|e| Error::io(&opts.dir, e))?;
    let mut rows = Vec::new();
    for &size in &opts.sizes {
        let dir = opts.dir.join(format!("index-bench-{size}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let t = Instant::now();
        {
            let dims = ColumnDims { appearance: base.appearance_dim, ..Default::default() };
            let rec = record.as_ref().map(|(c, s)| (c, s.as_str()));
            let mut w = MapWriter::create(&dir, &qcfg.encoding(), dims, rec, StoreOptions::default(), false)?;
            let pb = semlook::progress::bar(size, "references", opts.quiet);
            for k in 0..size {
                w.push(&reference(&base, k, 29))?;
                pb.inc(1);
            }
            pb.finish_and_clear();
            w.finish()?;
        }
        let map_write_s = t.elapsed().as_secs_f64();
        let t = Instant::now();
        let ix = semlook::map::index::build(&dir, &semlook::index::IndexParams::from_config(&cfg.index, size), cfg.index.probe, cfg.index.shortlist)?;
        let index_build_s = t.elapsed().as_secs_f64();
        let map = Map::open(&dir)?;
        map.check_all()?;
        let m = &map.manifest;
        let seg_bytes: u64 = m.segments.iter().map(|s| s.bytes).sum();
        let index_bytes: u64 = m.segments.iter().filter_map(|s| s.index.as_ref().map(|f| f.bytes)).sum::<u64>() + ix.entry.model.bytes;
        let exact_cfg = Config { index: semlook::config::IndexConfig { search: IndexSearch::Exact, ..cfg.index.clone() }, ..qcfg.clone() };
        let k = 30;
        let with_k = |c: &Config| Config { matching: semlook::config::MatchingConfig { top_k: k, ..c.matching.clone() }, ..c.clone() };
        let one = |q: usize| queries.slice(q, q + 1);
        // the recall queries, evenly spread over the photos (they come set after set)
        let nx = opts.exact_queries.min(queries.len());
        let recall_of: Vec<usize> = (0..nx).map(|i| i * queries.len() / nx.max(1)).collect();
        let mut exact_set = encoder.descriptor_set();
        for &q in &recall_of {
            exact_set.append_range(&queries, q, q + 1)?;
        }
        // their exact top-30, in one batch
        reset_peak();
        let t = Instant::now();
        let (truth, _) =
            if nx > 0 { candidates(&mut CpuStages, &map, &exact_set, Setting::Fused, &with_k(&exact_cfg))? } else { (vec![], Default::default()) };
        let exact_batch_qps = nx as f64 / t.elapsed().as_secs_f64().max(1e-9);
        let mut exact_ms = Vec::new();
        for q in 0..opts.exact_timed.min(nx) {
            let t = Instant::now();
            let (_, times) = candidates(&mut CpuStages, &map, &one(q), Setting::Fused, &with_k(&exact_cfg))?;
            exact_ms.push(t.elapsed().as_secs_f64() * 1e3);
            if times.approximate {
                return Err(Error::invalid("index-bench", "the exact pass took the index"));
            }
        }
        let exact_peak = status_mib("VmHWM:");
        let searches = if opts.searches.is_empty() { vec![(cfg.index.probe, cfg.index.shortlist, None)] } else { opts.searches.clone() };
        let thumbnail_bytes = map.index().map_or(0, |i| i.thumb.len());
        for &(probe, shortlist, pool) in &searches {
            let pool = pool.unwrap_or(cfg.index.pool);
            let approx_cfg = Config {
                index: semlook::config::IndexConfig { search: IndexSearch::Approximate, probe, shortlist, pool, ..cfg.index.clone() },
                ..qcfg.clone()
            };
            // one query at a time through the index
            reset_peak();
            let mut approx_ms = Vec::new();
            let mut recalls = Vec::new();
            for q in 0..queries.len() {
                let set = one(q);
                let t = Instant::now();
                let (l, times) = candidates(&mut CpuStages, &map, &set, Setting::Fused, &with_k(&approx_cfg))?;
                approx_ms.push(t.elapsed().as_secs_f64() * 1e3);
                if !times.approximate {
                    return Err(Error::invalid("index-bench", "the coarse stage did not take the index"));
                }
                if let Some(tr) = recall_of.iter().position(|&x| x == q).and_then(|i| truth.get(i)) {
                    let want: Vec<u32> = tr.iter().take(k).map(|x| x.1).collect();
                    let got: HashSet<u32> = l[0].iter().take(k).map(|x| x.1).collect();
                    recalls.push(want.iter().filter(|r| got.contains(r)).count() as f64 / want.len().max(1) as f64);
                }
            }
            // a batch through the index
            let mut batch = encoder.descriptor_set();
            for b in 0..opts.batch {
                batch.append_range(&queries, b % queries.len(), b % queries.len() + 1)?;
            }
            let t = Instant::now();
            candidates(&mut CpuStages, &map, &batch, Setting::Fused, &approx_cfg)?;
            let index_batch_qps = opts.batch as f64 / t.elapsed().as_secs_f64();
            let index_peak = status_mib("VmHWM:");
            let row = IndexBenchRow {
                map_size: size,
                map_bytes_per_reference: seg_bytes as f64 / size as f64,
                map_write_s,
                index_build_s,
                index_bytes_per_reference: index_bytes as f64 / size as f64,
                index_dims: ix.entry.dims,
                index_lists: ix.entry.lists,
                probe,
                shortlist,
                pool,
                thumbnail_bytes,
                build_recall: ix.entry.recall(),
                index_p50_ms: percentile(&mut approx_ms.clone(), 0.5),
                index_p99_ms: percentile(&mut approx_ms, 0.99),
                index_batch_qps,
                exact_p50_ms: percentile(&mut exact_ms.clone(), 0.5),
                exact_p99_ms: percentile(&mut exact_ms.clone(), 0.99),
                exact_batch_qps,
                recall_at_30: recalls.iter().sum::<f64>() / recalls.len().max(1) as f64,
                recall_at_30_min: recalls.iter().copied().fold(f64::INFINITY, f64::min),
                queries: queries.len(),
                exact_queries: nx,
                batch: opts.batch,
                index_peak_rss_mib: index_peak,
                exact_peak_rss_mib: exact_peak,
            };
            tick(&row);
            rows.push(row);
        }
        drop(map);
        if !opts.keep {
            std::fs::remove_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        }
    }
    Ok(rows)
}

/// The rows as a table.
pub fn table(rows: &[IndexBenchRow]) -> String {
    let mut s = String::from(
        "references  build s  B/ref  dims lists probe short  pool | index p50/p99 ms  q/s (batch) | exact p50/p99 ms  q/s | recall@30 mean/min (n) | build recall | RSS MiB index/exact\n",
    );
    for r in rows {
        s += &format!(
            "{:>10} {:>8.1} {:>6.0} {:>5} {:>5} {:>5} {:>5} {:>5} | {:>7.2}/{:<7.2} {:>6.0} ({}) | {:>8.1}/{:<8.1} {:>5.2} | {:.3}/{:.3} ({}) | {:.3} | {:.0}/{:.0}\n",
            r.map_size,
            r.index_build_s,
            r.index_bytes_per_reference,
            r.index_dims,
            r.index_lists,
            r.probe,
            r.shortlist,
            r.pool,
            r.index_p50_ms,
            r.index_p99_ms,
            r.index_batch_qps,
            r.batch,
            r.exact_p50_ms,
            r.exact_p99_ms,
            r.exact_batch_qps,
            r.recall_at_30,
            r.recall_at_30_min,
            r.exact_queries,
            r.build_recall,
            r.index_peak_rss_mib,
            r.exact_peak_rss_mib
        );
    }
    s
}
