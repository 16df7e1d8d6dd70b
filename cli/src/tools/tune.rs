//! `semlook dev tune`: sweeps configuration values over one or more datasets and tabulates Recall@1
//! and AUC per setting, so that every default can name the sweep it came from.
//!
//! A sweep file (TOML) lists, per dotted config key, the values to try; every combination runs:
//!
//! ```toml
//! [base]                     # optional: a partial config applied first
//! matching.top_k = 20
//! [values]
//! "appearance.vlad_centres" = [16, 32, 64]
//! "similarity.w_appearance" = [0.34, 0.8]
//! ```
//!
//! Instead of `[values]`, several `[[grid]]` tables each give a product of their own, run one
//! after another on one encoding (a key a grid does not list keeps the base value there):
//! families of settings that share no axis, e.g. `verification.inliers = ["count"]` with its
//! weights and `["unusual"]` with its thresholds.
//!
//! The expensive part of encoding (decoding, segmentation, the keypoint network) depends only on
//! the input, class, segmentation, model and keypoint-decoding settings; it is run once per
//! distinct group of those and cached in memory, and every configuration of the group encodes
//! from the cache (objects, forests, codebook, VLAD, global descriptor). Configurations that differ
//! only in matching settings share one encoding.

use rayon::prelude::*;
use semlook::appearance::{keypoints::Keypoints, Features};
use semlook::config::{Config, EncodingConfig};
use semlook::dataset::Dataset;
use semlook::descriptors::DescriptorSet;
use semlook::encode::{Encoder, Loaded};
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::eval::{match_query_set, report_matches, SettingReport};
use semlook::matching::Setting;
use serde::Serialize;
use std::collections::HashMap;

/// A parsed sweep: the base config and its grids, each a list of axes (dotted key, values).
#[derive(Debug, Clone)]
pub struct Sweep {
    base: toml::Table,
    pub grids: Vec<Vec<(String, Vec<toml::Value>)>>,
}

/// Most combinations one sweep may hold (a guard against a typo exploding the product).
pub const MAX_COMBINATIONS: usize = 10_000;

impl Sweep {
    pub fn parse(text: &str, name: &str, base: &Config) -> Result<Sweep> {
        let bad = |reason: String| Error::InvalidConfig { source_name: name.into(), reason };
        let doc: toml::Table = toml::from_str(text).map_err(|e| bad(e.to_string()))?;
        let mut base_table: toml::Table = toml::from_str(&base.to_toml()?).map_err(|e| bad(e.to_string()))?;
        if let Some(b) = doc.get("base") {
            let b = b.as_table().ok_or_else(|| bad("[base] must be a table".into()))?;
            merge(&mut base_table, b);
        }
        let axes_of = |v: &toml::Value, what: &str| -> Result<Vec<(String, Vec<toml::Value>)>> {
            let v = v.as_table().ok_or_else(|| bad(format!("{what} must be a table of dotted keys")))?;
            v.iter()
                .map(|(key, vals)| {
                    let list = vals.as_array().filter(|a| !a.is_empty()).ok_or_else(|| bad(format!("values of {key:?} must be a non-empty list")))?;
                    Ok((key.clone(), list.clone()))
                })
                .collect()
        };
        let mut grids = Vec::new();
        match (doc.get("values"), doc.get("grid")) {
            (Some(_), Some(_)) => return Err(bad("give [values] or [[grid]] tables, not both".into())),
            (Some(v), None) => grids.push(axes_of(v, "[values]")?),
            (None, Some(g)) => {
                let g = g.as_array().ok_or_else(|| bad("grid must be [[grid]] tables".into()))?;
                for t in g {
                    grids.push(axes_of(t, "[[grid]]")?);
                }
            }
            (None, None) => grids.push(vec![]),
        }
        if let Some(k) = doc.keys().find(|k| !["base", "values", "grid"].contains(&k.as_str())) {
            return Err(bad(format!("unknown section [{k}] (expected [base], and [values] or [[grid]])")));
        }
        let sweep = Sweep { base: base_table, grids };
        let n = sweep
            .grids
            .iter()
            .try_fold(0usize, |total, axes| axes.iter().try_fold(1usize, |a, (_, v)| a.checked_mul(v.len())).and_then(|n| total.checked_add(n)))
            .filter(|&n| n <= MAX_COMBINATIONS);
        n.ok_or_else(|| bad(format!("more than {MAX_COMBINATIONS} combinations")))?;
        // every combination must make a valid config
        for values in sweep.combinations() {
            sweep.config(&values, name)?;
        }
        Ok(sweep)
    }

    /// Every combination of each grid's values, grid after grid, the last axis fastest; each
    /// lists every key of every grid (in the order first seen), a key its grid does not vary at
    /// the base config's value.
    pub fn combinations(&self) -> Vec<Vec<(String, toml::Value)>> {
        let mut keys: Vec<&String> = Vec::new();
        for (k, _) in self.grids.iter().flatten() {
            if !keys.contains(&k) {
                keys.push(k);
            }
        }
        let mut all = Vec::new();
        for axes in &self.grids {
            let mut out: Vec<Vec<(String, toml::Value)>> = vec![vec![]];
            for (key, vals) in axes {
                out = out
                    .into_iter()
                    .flat_map(|c| {
                        vals.iter().map(move |v| {
                            let mut c = c.clone();
                            c.push((key.clone(), v.clone()));
                            c
                        })
                    })
                    .collect();
            }
            for c in out {
                let full = keys
                    .iter()
                    .map(|&k| match c.iter().find(|(ck, _)| ck == k) {
                        Some((_, v)) => (k.clone(), v.clone()),
                        None => (k.clone(), get_dotted(&self.base, k).unwrap_or(toml::Value::String("-".into()))),
                    })
                    .collect();
                all.push(full);
            }
        }
        all
    }

    /// The config of one combination.
    pub fn config(&self, values: &[(String, toml::Value)], name: &str) -> Result<Config> {
        let mut t = self.base.clone();
        for (key, v) in values {
            set_dotted(&mut t, key, v.clone()).map_err(|e| e.named(|reason| Error::InvalidConfig { source_name: name.into(), reason }))?;
        }
        Config::from_toml(&toml::to_string(&t).map_err(|e| Error::InvalidConfig { source_name: name.into(), reason: e.to_string() })?, name)
    }
}

fn merge(dst: &mut toml::Table, src: &toml::Table) {
    for (k, v) in src {
        match (dst.get_mut(k), v) {
            (Some(toml::Value::Table(d)), toml::Value::Table(s)) => merge(d, s),
            _ => {
                dst.insert(k.clone(), v.clone());
            }
        }
    }
}

/// The value at dotted `key` of `t`, if any.
fn get_dotted(t: &toml::Table, key: &str) -> Option<toml::Value> {
    let mut parts = key.split('.').peekable();
    let mut cur = t;
    while let Some(p) = parts.next() {
        let v = cur.get(p)?;
        if parts.peek().is_none() {
            return Some(v.clone());
        }
        cur = v.as_table()?;
    }
    None
}

fn set_dotted(t: &mut toml::Table, key: &str, v: toml::Value) -> Result<()> {
    let mut parts: Vec<&str> = key.split('.').collect();
    let last = parts.pop().filter(|l| !l.is_empty()).ok_or_else(|| Error::check(format!("empty key {key:?}")))?;
    let mut cur = t;
    for p in parts {
        cur = cur
            .entry(p.to_string())
            .or_insert_with(|| toml::Value::Table(Default::default()))
            .as_table_mut()
            .ok_or_else(|| Error::check(format!("{key:?}: {p:?} is not a section")))?;
    }
    cur.insert(last.to_string(), v);
    Ok(())
}

/// What the network-dependent cache is keyed by: everything that changes decoding,
/// segmentation or the keypoint network's output.
fn frame_key(cfg: &Config) -> String {
    let mut a = cfg.appearance.clone();
    let d = semlook::config::AppearanceConfig::default();
    (a.vlad_centres, a.intra_norm, a.power_norm, a.min_descriptors) = (d.vlad_centres, d.intra_norm, d.power_norm, d.min_descriptors);
    (a.codebook_images, a.codebook_samples_per_image, a.codebook_iterations, a.codebook_seed) =
        (d.codebook_images, d.codebook_samples_per_image, d.codebook_iterations, d.codebook_seed);
    // detections are cached for the most keypoints any member stores (each takes its best N)
    let k = semlook::config::KeypointsConfig { stored: 0, ..cfg.keypoints.clone() };
    serde_json::json!([cfg.input, cfg.classes, cfg.segmentation, cfg.models, a, k]).to_string()
}

/// One decoded frame and its keypoint network output.
struct Cached {
    id: String,
    loaded: Loaded,
    keypoints: Option<Features>,
}

/// A dataset's frames, decoded once: references, then each query traversal with its ground truth.
struct CachedDataset {
    name: String,
    refs: Vec<Cached>,
    queries: Vec<(String, Vec<Cached>, Vec<Vec<u32>>)>,
}

/// `frames` of `ds` decoded (and segmented) and through the keypoint network.
fn load_frames(frames: &[semlook::dataset::Frame], ds: &Dataset, encoder: &Encoder, tick: &(dyn Fn() + Sync)) -> Result<Vec<Cached>> {
    frames
        .par_iter()
        .map(|f| {
            let loaded = encoder.frames().load(&f.source, ds.label_format)?;
            let keypoints = match (encoder.appearance_model(), &loaded.rgb) {
                (Some(m), Some(rgb)) => Some(m.features(rgb)?),
                _ => None,
            };
            tick();
            Ok(Cached { id: f.source.id.clone(), loaded, keypoints })
        })
        .collect()
}

fn cache_dataset(ds: &Dataset, encoder: &Encoder, tick: &(dyn Fn() + Sync)) -> Result<CachedDataset> {
    let load = |frames: &[semlook::dataset::Frame]| load_frames(frames, ds, encoder, tick);
    let refs = load(&ds.reference.frames)?;
    let mut queries = Vec::new();
    for q in &ds.queries {
        queries.push((q.name.clone(), load(&q.frames)?, ds.ground_truth(q)?));
    }
    Ok(CachedDataset { name: ds.name.clone(), refs, queries })
}

fn encode_cached(encoder: &Encoder, frames: &[Cached]) -> Result<DescriptorSet> {
    let images: Vec<_> = frames
        .par_iter()
        .map_init(Default::default, |scratch, c| encoder.encode_loaded_with(&c.id, &c.loaded, c.keypoints.as_ref(), scratch).map(|r| r.0))
        .collect::<Result<_>>()?;
    let mut set = encoder.descriptor_set();
    for img in &images {
        set.push(img).map_err(|e| e.named(|r| Error::invalid("tune", r)))?;
    }
    Ok(set)
}

/// The results of one configuration.
#[derive(Debug, Clone, Serialize)]
pub struct TuneRow {
    /// The swept keys and their values in this configuration.
    pub values: Vec<(String, String)>,
    /// Per dataset, per column: mean Recall@1 and mean AUC over the dataset's query sets. A
    /// column is a setting's name, and with sequence matching also `<setting>+seq` (the
    /// sequence R@1 and its AUC by uniqueness).
    pub results: Vec<(String, String, f64, f64)>,
}

impl TuneRow {
    /// Mean Recall@1 of column `column` over the datasets.
    pub fn mean_r1(&self, column: &str) -> f64 {
        let v: Vec<f64> = self.results.iter().filter(|r| r.1 == column).map(|r| r.2).collect();
        v.iter().sum::<f64>() / v.len().max(1) as f64
    }
}

/// What a sweep measures beside each setting's R@1 and AUC.
#[derive(Debug, Clone, Default)]
pub struct TuneOptions {
    /// Also stream each query set through sequence matching (`<setting>+seq` columns).
    pub sequence: bool,
    /// Write `verified`'s candidate features here (`--candidates`).
    pub candidates: Option<std::path::PathBuf>,
    /// Keep the segmenter's label maps here, read back for the same pixels
    /// ([`Encoder::with_label_cache`]).
    pub label_cache: Option<std::path::PathBuf>,
    /// The null-evidence check (issue 60): each query's candidates are verified against an
    /// unrelated image (a query of the next dataset in the list, encoded as this one's) instead
    /// of the query; column `verified~null` gives the share of queries whose verified order is
    /// then `fused`'s (as R@1), and the share whose top-1 is (as AUC).
    pub null_evidence: bool,
}

/// The column of the null-evidence check ([`TuneOptions::null_evidence`]).
pub const NULL_COLUMN: &str = "verified~null";

/// Runs every combination of `sweep` on `datasets` in `settings` (each dataset's class settings
/// follow it: [`Dataset::adapt_config`]). `progress` hears about each finished dataset and row.
pub fn run(
    datasets: &[Dataset],
    sweep: &Sweep,
    settings: &[Setting],
    opts: &TuneOptions,
    engine: &mut Engine,
    tick: &(dyn Fn() + Sync),
    progress: &mut dyn FnMut(&str, &TuneRow),
) -> Result<Vec<TuneRow>> {
    let (sequence, candidates) = (opts.sequence, opts.candidates.as_deref());
    let combos = sweep.combinations();
    let base: Vec<Config> = combos.iter().map(|c| sweep.config(c, "sweep")).collect::<Result<_>>()?;
    let wants_hog = settings.contains(&Setting::Hog);
    let mut rows: Vec<TuneRow> =
        combos.iter().map(|c| TuneRow { values: c.iter().map(|(k, v)| (k.clone(), v.to_string())).collect(), results: vec![] }).collect();
    for (d, ds) in datasets.iter().enumerate() {
        let configs: Vec<Config> = base.iter().map(|c| ds.adapt_config(c.clone())).collect();
        // the null-evidence check's unrelated images: the next dataset's queries
        let unrelated = (opts.null_evidence && settings.contains(&Setting::Verified)).then(|| &datasets[(d + 1) % datasets.len()]);
        // groups of configurations that share decoded frames, in first-appearance order
        let mut groups: Vec<(String, Vec<usize>)> = Vec::new();
        for (i, c) in configs.iter().enumerate() {
            let key = frame_key(c);
            match groups.iter_mut().find(|g| g.0 == key) {
                Some(g) => g.1.push(i),
                None => groups.push((key, vec![i])),
            }
        }
        for (_, members) in &groups {
            let mut widest = configs[members[0]].clone();
            widest.keypoints.stored = members.iter().map(|&i| configs[i].keypoints.stored).max().unwrap_or(0);
            let first = Encoder::new(&widest)?.with_hog(wants_hog).with_label_cache(opts.label_cache.clone());
            // small frames: compact HOGs, as `map build` of them would store
            let small = first.small_frames(ds.reference.frames.iter().map(|f| &f.source))?;
            let cd = cache_dataset(ds, &first, tick)?;
            let unrelated_frames = match unrelated {
                Some(u) => Some(load_frames(&u.queries.iter().flat_map(|q| q.frames.clone()).collect::<Vec<_>>(), u, &first, tick)?),
                None => None,
            };
            let mut unrelated_sets: HashMap<String, DescriptorSet> = HashMap::new();
            let mut null_measured: HashMap<(String, String), Vec<semlook::matching::PairTerms>> = HashMap::new();
            let mut encoded: HashMap<String, (DescriptorSet, Vec<(String, DescriptorSet, Vec<Vec<u32>>)>)> = HashMap::new();
            let mut matched: HashMap<(String, String, Setting), (Vec<semlook::matching::QueryMatch>, f64)> = HashMap::new();
            // `verified`: candidates and unweighed pair terms, shared by the configurations that
            // differ only in the verified score's weights (ranked again for each)
            let mut measured: HashMap<(String, String), (semlook::matching::CandidateLists, Vec<semlook::matching::PairTerms>, f64)> = HashMap::new();
            let mut scored: HashMap<(String, String, Setting), Vec<Vec<(semlook::descriptors::source::Place, f32)>>> = HashMap::new();
            for &i in members {
                let cfg = &configs[i];
                let enc_key = serde_json::to_string::<EncodingConfig>(&cfg.encoding()).map_err(|e| Error::invalid("sweep", e.to_string()))?;
                if !encoded.contains_key(&enc_key) {
                    let mut encoder = Encoder::new(cfg)?.with_hog(wants_hog).with_compact_hog(small);
                    if let Some(a) = encoder.appearance_mut() {
                        let picks = a.codebook_picks(cd.refs.len());
                        let kps: Vec<&Keypoints> = picks.iter().filter_map(|&p| cd.refs[p].keypoints.as_ref().map(|f| &f.sampled)).collect();
                        a.train_codebook_from(&kps)?;
                    }
                    let refs = encode_cached(&encoder, &cd.refs)?;
                    let mut qs = Vec::new();
                    for (name, frames, gt) in &cd.queries {
                        qs.push((name.clone(), encode_cached(&encoder, frames)?, gt.clone()));
                    }
                    if let Some(frames) = &unrelated_frames {
                        unrelated_sets.insert(enc_key.clone(), encode_cached(&encoder, frames)?);
                    }
                    encoded.insert(enc_key.clone(), (refs, qs));
                }
                let (refs, qs) = &encoded[&enc_key];
                let (mut reports, mut skipped): (Vec<SettingReport>, Vec<(Setting, String)>) = (vec![], vec![]);
                let mut null_rows: Vec<(String, f64, f64)> = vec![];
                // configurations that differ in their sequence section alone share their matches
                let no_seq = Config { sequence: Default::default(), ..cfg.clone() };
                let match_key = format!("{enc_key}|{}", no_seq.to_toml()?);
                for (name, set, gt) in qs {
                    for &st in settings {
                        if st.is_baseline() && semlook::matching::baseline::unavailable(refs, set, st).is_some() {
                            match_query_set(engine, refs, name, set, gt, &[st], cfg, false, &mut reports, &mut skipped)?;
                            continue;
                        }
                        // a setting that does not verify reads no verification section: configurations that
                        // differ only there share its matches (the baselines and `fused` run once)
                        let key = match st.verifies() {
                            true => (match_key.clone(), name.clone(), st),
                            false => {
                                let plain = Config { verification: Default::default(), ..no_seq.clone() };
                                (format!("{enc_key}|{}", plain.to_toml()?), name.clone(), st)
                            }
                        };
                        if !matched.contains_key(&key) && st == Setting::Verified {
                            let terms_key = (format!("{enc_key}|{}", unweighed(&no_seq).to_toml()?), name.clone());
                            if !measured.contains_key(&terms_key) {
                                let t = std::time::Instant::now();
                                let (lists, _) = engine.candidates(refs, set, st, cfg)?;
                                let terms = engine.pair_terms(refs, set, st, &tested(cfg), &semlook::matching::pairs_of(&lists))?;
                                measured.insert(terms_key.clone(), (lists, terms, semlook::util::ms_since(t)));
                            }
                            let (lists, terms, ms) = &measured[&terms_key];
                            let fine: Vec<semlook::matching::PairScore> = terms.iter().map(|t| t.score(&cfg.verification)).collect();
                            matched.insert(key.clone(), (semlook::matching::rank(st, lists, Some(&fine), cfg)?, *ms));
                        }
                        if !matched.contains_key(&key) {
                            let (m, t) = engine.match_batch(refs, set, st, cfg)?;
                            matched.insert(key.clone(), (m, t.coarse_ms + t.fine_ms));
                        }
                        let (m, ms) = &matched[&key];
                        if let (Some(dir), Setting::Verified) = (candidates, st) {
                            let file = dir.join(format!("{}--{}--row{i}.tsv", file_name(&cd.name), file_name(name)));
                            write_candidates(&file, refs, set, gt, cfg)?;
                        }
                        if let (Some(u), Setting::Verified) = (unrelated_sets.get(&enc_key), st) {
                            // candidates from the query, evidence from an unrelated image
                            let terms_key = (format!("{enc_key}|{}", unweighed(&no_seq).to_toml()?), name.clone());
                            let lists = &measured[&terms_key].0;
                            if !null_measured.contains_key(&terms_key) {
                                let picks: Vec<usize> = (0..set.len()).map(|q| q % u.len().max(1)).collect();
                                let swapped = semlook::descriptors::source::RefSource::gather(u, &picks)?;
                                let pairs = semlook::matching::pairs_of(lists);
                                let terms = engine.pair_terms(refs, &swapped, st, &tested(cfg), &pairs)?;
                                if let Some(dir) = candidates {
                                    // the evidence of each candidate from the unrelated image, for prototypes of the check
                                    let file = dir.join(format!("{}--{}--row{i}.unrelated.tsv", file_name(&cd.name), file_name(name)));
                                    let mut out = String::from("query\trank\treference\tinliers\tcompact_hog\n");
                                    let ranks = lists.iter().flat_map(|l| 0..l.len());
                                    for ((&(q, r), t), rank) in pairs.iter().zip(&terms).zip(ranks) {
                                        let c = t.compact_hog.unwrap_or(f32::NAN);
                                        let inliers = t.verified.map_or("NaN".to_string(), |v| v.inliers.to_string());
                                        out += &format!("{q}\t{rank}\t{r}\t{inliers}\t{c}\n");
                                    }
                                    std::fs::write(&file, out).map_err(|e| Error::io(&file, e))?;
                                }
                                null_measured.insert(terms_key.clone(), terms);
                            }
                            let fine: Vec<semlook::matching::PairScore> =
                                null_measured[&terms_key].iter().map(|t| t.score(&cfg.verification)).collect();
                            let ranked = semlook::matching::rank(st, lists, Some(&fine), cfg)?;
                            let same = |m: &semlook::matching::QueryMatch, l: &Vec<(f32, u32)>, n: usize| {
                                m.ranked.iter().take(n).map(|c| c.reference).eq(l.iter().take(n).map(|c| c.1))
                            };
                            let n = lists.len().max(1) as f64;
                            let order = ranked.iter().zip(lists).filter(|(m, l)| same(m, l, usize::MAX)).count() as f64 / n;
                            let top1 = ranked.iter().zip(lists).filter(|(m, l)| same(m, l, 1)).count() as f64 / n;
                            null_rows.push((cd.name.clone(), order, top1));
                        }
                        let mut r = report_matches(engine, refs, name, set, m, gt, st, cfg, *ms, false)?;
                        if sequence {
                            // the scored rows depend on the matching, `rows` and `widen` alone
                            let row_key = (format!("{}|{:?}|{}", key.0, cfg.sequence.rows, cfg.sequence.widen), name.clone(), st);
                            if !scored.contains_key(&row_key) {
                                let rows = semlook::eval::sequence_rows(engine, refs, set, m, st, cfg)?;
                                scored.insert(row_key.clone(), rows);
                            }
                            r.sequence = Some(semlook::eval::sequence_report_from_rows(refs, set, m, gt, cfg, &scored[&row_key]));
                        }
                        reports.push(r);
                    }
                }
                for &st in settings {
                    let r: Vec<&SettingReport> = reports.iter().filter(|r| r.setting == st).collect();
                    if r.is_empty() {
                        continue;
                    }
                    let n = r.len() as f64;
                    let r1 = r.iter().map(|x| x.recall_at.first().map_or(0.0, |v| v.1)).sum::<f64>() / n;
                    let auc = r.iter().map(|x| x.pr.auc).sum::<f64>() / n;
                    rows[i].results.push((cd.name.clone(), st.name().to_string(), r1, auc));
                    let seq: Vec<&semlook::eval::SequenceReport> = r.iter().filter_map(|x| x.sequence.as_ref()).collect();
                    if !seq.is_empty() {
                        let m = seq.len() as f64;
                        let (r1, auc) = (seq.iter().map(|s| s.recall_at_1).sum::<f64>() / m, seq.iter().map(|s| s.pr.auc).sum::<f64>() / m);
                        rows[i].results.push((cd.name.clone(), format!("{st}+seq"), r1, auc));
                        let traj = seq.iter().map(|s| s.trajectory_recall_at_1).sum::<f64>() / m;
                        rows[i].results.push((cd.name.clone(), format!("{st}+traj"), traj, auc));
                        // the accepted flag: precision (R@1 column) and recall (AUC column) over
                        // the queries, pooled over the query sets
                        let (acc, ok) = seq.iter().fold((0, 0), |a, s| (a.0 + s.accepted, a.1 + s.accepted_correct));
                        let total: usize = seq.iter().map(|s| s.outcomes.len()).sum();
                        let precision = if acc > 0 { ok as f64 / acc as f64 } else { 1.0 };
                        rows[i].results.push((cd.name.clone(), format!("{st}+acc"), precision, ok as f64 / total.max(1) as f64));
                    }
                }
                if !null_rows.is_empty() {
                    let n = null_rows.len() as f64;
                    let (order, top1) = (null_rows.iter().map(|r| r.1).sum::<f64>() / n, null_rows.iter().map(|r| r.2).sum::<f64>() / n);
                    rows[i].results.push((cd.name.clone(), NULL_COLUMN.to_string(), order, top1));
                }
                progress(&cd.name, &rows[i]);
            }
        }
    }
    Ok(rows)
}

/// `cfg` with the weights of the verified score (what [`semlook::matching::PairTerms::score`] and
/// `rank` read, nothing the measurements depend on) at their defaults: configurations equal in
/// the rest share their candidates and pair terms.
fn unweighed(cfg: &Config) -> Config {
    Config { verification: semlook::matching::null::measurement(&cfg.verification), ..cfg.clone() }
}

/// `cfg` measuring the evidence's tail probabilities under the null too: the pair terms every
/// form of the verified score reads (the forms differ in weights only, and share one measurement).
fn tested(cfg: &Config) -> Config {
    let mut c = cfg.clone();
    c.verification.inliers = semlook::config::InlierEvidence::Significant;
    c
}

/// `name` with every character a file name should not hold replaced by `_`.
fn file_name(name: &str) -> String {
    name.chars().map(|c| if c.is_ascii_alphanumeric() || c == '-' || c == '.' { c } else { '_' }).collect()
}

/// The features of every candidate pair `verified` re-ranks, as a table a prototype reads
/// (`semlook dev tune --candidates DIR`, one file per dataset, query set and row): per query its
/// fused coarse top-K, each pair with whether the ground truth holds it, the coarse score and its
/// terms (appearance cosine, embedding cosine, SSIM of the global descriptors), the tree-set
/// similarity, the verification's mutual matches and inliers, both images' stored keypoints and
/// source sizes, and the HOG cosine where both have HOG. Beside it: `.null.tsv`, the map's null
/// pairs (what `verified` tests against); `.near.tsv`, the same sources' pairs 1 position
/// apart along their traversal (`matching::null::near_pairs`: what verification finds at the
/// same place, as far as the map alone shows it); `.dense.tsv`, every pair's coarse terms; and, with `--null-evidence`,
/// `.unrelated.tsv`, each candidate's evidence from the unrelated image instead of the query.
fn write_candidates(file: &std::path::Path, refs: &DescriptorSet, queries: &DescriptorSet, gt: &[Vec<u32>], cfg: &Config) -> Result<()> {
    use semlook::matching::{self, CpuStages, Stages};
    use semlook::values::Values;
    let st = Setting::Verified;
    let (lists, _) = matching::candidates(&mut CpuStages, refs, queries, st, cfg)?;
    let pairs = matching::pairs_of(&lists);
    let params = matching::tree_params(cfg, st, refs.neighbour_slots)?;
    let fine = CpuStages.fine_pairs(&params, refs, queries, &pairs)?;
    let vp = semlook::verify::VerifyParams::for_config(&cfg.verification, &semlook::classes::ClassTable::from_config(&cfg.classes)?)?;
    let verified = CpuStages.verify_pairs(&vp, refs, queries, &pairs)?;
    let p = cfg.global.ssim_params();
    let dot = |a: &[f32], b: &[f32]| if a.is_empty() || b.is_empty() { f32::NAN } else { Values::F32(a).dot(&Values::F32(b)) };
    let mut out = String::from(
        "query\tquery_id\trank\treference\treference_id\tcorrect\tcoarse\tappearance\tembedding\tssim\tfine\tmatches\tinliers\tquery_keypoints\treference_keypoints\tquery_width\tquery_height\treference_width\treference_height\thog\tcompact_hog\n",
    );
    let mut scratch = semlook_kernels::ssim::SsimScratch::default();
    let mut k = 0;
    for (q, list) in lists.iter().enumerate() {
        for (rank, &(coarse, r)) in list.iter().enumerate() {
            let (qi, ri) = (q, r as usize);
            let ssim = semlook_kernels::ssim::ssim_pair(&p, queries.global(qi), queries.stats(qi), refs.global(ri), refs.stats(ri), &mut scratch);
            let (qs, rs) = (queries.sizes[qi], refs.sizes[ri]);
            out += &format!(
                "{q}\t{}\t{rank}\t{r}\t{}\t{}\t{coarse}\t{}\t{}\t{ssim}\t{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}\t{}\n",
                queries.ids[qi],
                refs.ids[ri],
                gt.get(q).is_some_and(|g| g.contains(&r)) as u8,
                dot(queries.image_appearance(qi), refs.image_appearance(ri)),
                dot(queries.image_embedding(qi), refs.image_embedding(ri)),
                fine[k],
                verified[k].matches,
                verified[k].inliers,
                queries.keypoints(qi).len(),
                refs.keypoints(ri).len(),
                qs[0],
                qs[1],
                rs[0],
                rs[1],
                dot(queries.image_hog(qi), refs.image_hog(ri)),
                dot(queries.image_compact_hog(qi), refs.image_compact_hog(ri)),
            );
            k += 1;
        }
    }
    if let Some(d) = file.parent() {
        std::fs::create_dir_all(d).map_err(|e| Error::io(d, e))?;
    }
    std::fs::write(file, out).map_err(|e| Error::io(file, e))?;
    // the map's null pairs (`matching::null`): each source reference's candidates of other places
    let v = &cfg.verification;
    let src = semlook::matching::null::sources(refs.len(), v.null_sources as usize);
    let sources = semlook::descriptors::source::RefSource::gather(refs, &src)?;
    let mut wide = cfg.clone();
    wide.matching.top_k = cfg.matching.top_k + 2 * v.null_gap as usize + 1;
    let (nl, _) = matching::candidates(&mut CpuStages, refs, &sources, st, &wide)?;
    let np = semlook::matching::null::null_pairs(refs, &src, &nl, v.null_gap, cfg.matching.top_k);
    let nv = CpuStages.verify_pairs(&vp, refs, &sources, &np)?;
    let mut out = String::from("source\treference\tmatches\tinliers\tcompact_hog\tsource_keypoints\treference_keypoints\n");
    for (&(s, r), v) in np.iter().zip(&nv) {
        let (si, ri) = (src[s as usize], r as usize);
        out += &format!(
            "{si}\t{ri}\t{}\t{}\t{}\t{}\t{}\n",
            v.matches,
            v.inliers,
            dot(refs.image_compact_hog(si), refs.image_compact_hog(ri)),
            refs.keypoints(si).len(),
            refs.keypoints(ri).len()
        );
    }
    let null_file = file.with_extension("null.tsv");
    std::fs::write(&null_file, out).map_err(|e| Error::io(&null_file, e))?;
    // the same sources' pairs of the same place (their neighbours along their traversal, the
    // compact HOGs' other sample): what verification finds where the answer is right, as the
    // map alone can show it
    let near = semlook::matching::null::near_pairs(refs, &src);
    let nv = CpuStages.verify_pairs(&vp, refs, &sources, &near)?;
    let mut out = String::from("source\treference\tmatches\tinliers\tcompact_hog\n");
    for (&(s, r), v) in near.iter().zip(&nv) {
        let (si, ri) = (src[s as usize], r as usize);
        out += &format!("{si}\t{ri}\t{}\t{}\t{}\n", v.matches, v.inliers, dot(refs.image_compact_hog(si), refs.image_compact_hog(ri)));
    }
    let near_file = file.with_extension("near.tsv");
    std::fs::write(&near_file, out).map_err(|e| Error::io(&near_file, e))?;
    // every pair's coarse terms (a dev set's queries x references: small), for prototypes of the
    // coarse score itself
    let dense = file.with_extension("dense.tsv");
    let mut out = String::from("query\treference\tcorrect\tappearance\tembedding\tssim\n");
    for q in 0..queries.len() {
        let rows: Vec<String> = (0..refs.len())
            .into_par_iter()
            .map_init(semlook_kernels::ssim::SsimScratch::default, |scratch, r| {
                let ssim = semlook_kernels::ssim::ssim_pair(&p, queries.global(q), queries.stats(q), refs.global(r), refs.stats(r), scratch);
                format!(
                    "{q}\t{r}\t{}\t{}\t{}\t{ssim}\n",
                    gt.get(q).is_some_and(|g| g.contains(&(r as u32))) as u8,
                    dot(queries.image_appearance(q), refs.image_appearance(r)),
                    dot(queries.image_embedding(q), refs.image_embedding(r)),
                )
            })
            .collect();
        rows.iter().for_each(|r| out += r);
    }
    std::fs::write(&dense, out).map_err(|e| Error::io(&dense, e))
}

/// Leave-one-set-out cross-validation of a sweep: for every dataset and column (a setting, or
/// `<setting>+seq`), the R@1 on that dataset of the row chosen on the *other* datasets (highest
/// mean R@1 over them; ties to the higher mean AUC over them, then to the earlier row, so a sweep
/// lists the current default first), beside the in-sample best row's. What a default chosen this
/// way is expected to give on a set it was not tuned on.
#[derive(Debug, Clone, Serialize)]
pub struct CrossValidated {
    /// The column (setting) cross-validated.
    pub column: String,
    /// Per held-out dataset: its name, the row chosen without it, and that row's R@1 on it.
    pub held_out: Vec<(String, usize, f64)>,
    /// The row with the highest mean R@1 over every dataset (ties as above), and that mean.
    pub in_sample: (usize, f64),
}

impl CrossValidated {
    /// Mean of the held-out R@1s.
    pub fn mean(&self) -> f64 {
        self.held_out.iter().map(|h| h.2).sum::<f64>() / self.held_out.len().max(1) as f64
    }
}

/// The row of `rows` with the highest mean R@1 of `column` over the datasets `keep` admits (ties
/// to the higher mean AUC, then the earlier row).
fn best_row(rows: &[TuneRow], column: &str, keep: &dyn Fn(&str) -> bool) -> Option<(usize, f64)> {
    let mean = |r: &TuneRow, auc: bool| {
        let v: Vec<f64> = r.results.iter().filter(|x| x.1 == column && keep(&x.0)).map(|x| if auc { x.3 } else { x.2 }).collect();
        (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
    };
    let mut best: Option<(usize, f64, f64)> = None;
    for (i, r) in rows.iter().enumerate() {
        let (Some(r1), Some(auc)) = (mean(r, false), mean(r, true)) else { continue };
        // a difference below 1e-9 is a tie (means of the same fractions summed in another order)
        let better = match best {
            None => true,
            Some((_, b1, bauc)) => r1 > b1 + 1e-9 || ((r1 - b1).abs() <= 1e-9 && auc > bauc + 1e-9),
        };
        if better {
            best = Some((i, r1, auc));
        }
    }
    best.map(|(i, r1, _)| (i, r1))
}

/// Leave-one-set-out cross-validation of every column of `rows` ([`CrossValidated`]).
pub fn cross_validate(rows: &[TuneRow]) -> Vec<CrossValidated> {
    let Some(first) = rows.first() else { return vec![] };
    let mut columns: Vec<&str> = Vec::new();
    let mut sets: Vec<&str> = Vec::new();
    for r in &first.results {
        if !columns.contains(&r.1.as_str()) {
            columns.push(&r.1);
        }
        if !sets.contains(&r.0.as_str()) {
            sets.push(&r.0);
        }
    }
    let r1 = |row: &TuneRow, set: &str, column: &str| row.results.iter().find(|x| x.0 == set && x.1 == column).map_or(f64::NAN, |x| x.2);
    columns
        .iter()
        .filter_map(|&column| {
            let in_sample = best_row(rows, column, &|_| true)?;
            let held_out = sets
                .iter()
                .filter_map(|&set| {
                    let (row, _) = best_row(rows, column, &|d| d != set)?;
                    Some((set.to_string(), row, r1(&rows[row], set, column)))
                })
                .collect();
            Some(CrossValidated { column: column.to_string(), held_out, in_sample })
        })
        .collect()
}

/// The cross-validation as a table: per column, each held-out set's R@1 and the values of the row
/// chosen without it, the mean of the held-out R@1s, and the in-sample best row.
pub fn cross_validation_table(rows: &[TuneRow], cv: &[CrossValidated]) -> String {
    let values = |i: usize| rows[i].values.iter().map(|(k, v)| format!("{k}={v}")).collect::<Vec<_>>().join(" ");
    let mut out = String::from("column\theld-out set\tR@1 held out\tR@1 in sample (row)\tchosen without it\n");
    for c in cv {
        let (best, mean) = c.in_sample;
        for (set, row, r1) in &c.held_out {
            let own = rows[best].results.iter().find(|x| &x.0 == set && x.1 == c.column).map_or(f64::NAN, |x| x.2);
            out += &format!("{}\t{set}\t{r1:.3}\t{own:.3}\trow {row}: {}\n", c.column, values(*row));
        }
        out += &format!("{}\tmean\t{:.3}\t{mean:.3}\tin sample: row {best}: {}\n", c.column, c.mean(), values(best));
    }
    out
}

/// The rows as a table: swept values, R@1 per dataset and setting, and the mean over datasets.
pub fn table(rows: &[TuneRow]) -> String {
    let Some(first) = rows.first() else { return String::new() };
    let mut out = String::new();
    for (k, _) in &first.values {
        out += &format!("{k}\t");
    }
    for (d, st, _, _) in &first.results {
        out += &format!("{d}:{st}:R@1\t{d}:{st}:AUC\t");
    }
    let mut settings: Vec<&str> = Vec::new();
    for r in &first.results {
        if !settings.contains(&r.1.as_str()) {
            settings.push(&r.1);
        }
    }
    for st in &settings {
        out += &format!("mean:{st}:R@1\t");
    }
    out.pop();
    out.push('\n');
    for r in rows {
        for (_, v) in &r.values {
            out += &format!("{v}\t");
        }
        for (_, _, r1, auc) in &r.results {
            out += &format!("{r1:.3}\t{auc:.3}\t");
        }
        for st in &settings {
            out += &format!("{:.3}\t", r.mean_r1(st));
        }
        out.pop();
        out.push('\n');
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn sweeps_expand_and_validate() {
        let text = "[base]\nmatching.top_k = 20\n[values]\n\"appearance.vlad_centres\" = [16, 32]\n\"similarity.w_appearance\" = [0.5, 1.0, 2.0]\n";
        let s = Sweep::parse(text, "s.toml", &Config::default()).unwrap();
        let combos = s.combinations();
        assert_eq!(combos.len(), 6);
        let c = s.config(&combos[5], "s").unwrap();
        assert_eq!((c.matching.top_k, c.appearance.vlad_centres, c.similarity.w_appearance), (20, 32, 2.0));
        let bad = Sweep::parse("[values]\n\"matching.top_k\" = [0]\n", "bad.toml", &Config::default()).unwrap_err().to_string();
        assert!(bad.contains("top_k") && bad.contains("bad.toml"), "{bad}");
        assert!(Sweep::parse("[values]\n\"matching.nonsense\" = [1]\n", "x", &Config::default()).is_err());
        assert!(Sweep::parse("[other]\n", "x", &Config::default()).is_err());
    }

    #[test]
    fn grids_run_one_after_another_with_every_key_listed() {
        let text = "[[grid]]\n\"verification.inliers\" = [\"count\"]\n\"verification.w_inliers\" = [1.0, 2.0]\n\n[[grid]]\n\"verification.inliers\" = [\"unusual\"]\n\"verification.unusual_above\" = [0.5, 1.0, 1.5]\n";
        let s = Sweep::parse(text, "g.toml", &Config::default()).unwrap();
        let combos = s.combinations();
        assert_eq!(combos.len(), 5);
        // every combination lists the three keys; a grid's absent key at the base value
        assert!(combos.iter().all(|c| c.len() == 3));
        let c = s.config(&combos[4], "g").unwrap();
        assert_eq!(
            (c.verification.inliers, c.verification.unusual_above, c.verification.w_inliers),
            (semlook::config::InlierEvidence::Unusual, 1.5, Config::default().verification.w_inliers)
        );
        let c = s.config(&combos[1], "g").unwrap();
        assert_eq!((c.verification.inliers, c.verification.w_inliers), (semlook::config::InlierEvidence::Count, 2.0));
        assert!(Sweep::parse("[values]\n\"matching.top_k\" = [5]\n[[grid]]\n\"matching.top_k\" = [6]\n", "x", &Config::default()).is_err());
    }

    #[test]
    fn cross_validation_picks_each_held_out_sets_row_on_the_others() {
        let row = |r1: [f64; 3]| TuneRow {
            values: vec![],
            results: ["a", "b", "c"].iter().zip(r1).map(|(d, v)| (d.to_string(), "verified".to_string(), v, 0.5)).collect(),
        };
        // row 0 wins on a and b, row 1 on c; held out a: b and c tie on means (0.75 vs 0.75) and
        // the earlier row wins; held out c: row 0 (a and b)
        let rows = vec![row([1.0, 1.0, 0.5]), row([0.5, 0.5, 1.0])];
        let cv = cross_validate(&rows);
        assert_eq!(cv.len(), 1);
        let held: Vec<(String, usize, f64)> = cv[0].held_out.clone();
        assert_eq!(held, vec![("a".into(), 0, 1.0), ("b".into(), 0, 1.0), ("c".into(), 0, 0.5)]);
        assert_eq!(cv[0].in_sample.0, 0);
        assert!((cv[0].mean() - 2.5 / 3.0).abs() < 1e-12);
        // a set's own best never leaks into its held-out choice
        let rows = vec![row([0.0, 0.6, 0.6]), row([1.0, 0.5, 0.5])];
        let cv = cross_validate(&rows);
        assert_eq!(cv[0].held_out[0], ("a".into(), 0, 0.0));
        assert_eq!(cv[0].in_sample.0, 1);
    }
}
