//! Stage 5: evaluation. Encodes a dataset's references (or takes a built map) and queries,
//! matches every query set in every requested setting, and reports the VPR-Bench metrics plus
//! per-stage timings in the paper's Table 2 units (ms per frame for encoding, ms per reference
//! frame for matching).


pub mod metrics;

use crate::config::Config;
use crate::encode::{collect_encoded, Encoder, StageTimes};
use crate::engine::Engine;
use crate::error::{Error, Result};
use crate::map::{DescriptorSet, Map};
use crate::matching::source::RefSource;
use crate::matching::Setting;
use crate::progress;
use crate::dataset::Dataset;
use metrics::{pr_metrics, recall_at_n, PrMetrics};
use serde::Serialize;
use std::collections::HashMap;

/// Mean per-frame encoding times of a set of frames.
#[derive(Debug, Clone, Copy, Default, Serialize)]
pub struct EncodingSummary {
    pub frames: usize,
    pub load_ms: f64,
    pub global_ms: f64,
    pub forest_ms: f64,
    pub appearance_ms: f64,
    /// Of `appearance_ms`, the keypoint network alone.
    pub network_ms: f64,
}

impl EncodingSummary {
    pub fn from_total(frames: usize, t: StageTimes) -> Self {
        let n = frames.max(1) as f64;
        EncodingSummary {
            frames,
            load_ms: t.load_ms / n,
            global_ms: t.global_ms / n,
            forest_ms: t.forest_ms / n,
            appearance_ms: t.appearance_ms / n,
            network_ms: t.network_ms / n,
        }
    }
    /// Encoding time as the paper counts it: descriptors only, without file decoding.
    pub fn encode_ms(&self) -> f64 {
        self.global_ms + self.forest_ms + self.appearance_ms
    }
}

#[derive(Debug, Clone, Serialize)]
pub struct QueryOutcome {
    pub query: String,
    pub top1: Option<String>,
    pub score: Option<f32>,
    pub correct: bool,
    pub valid_references: usize,
}

#[derive(Debug, Clone, Serialize)]
pub struct SettingReport {
    pub query_set: String,
    pub setting: Setting,
    pub queries: usize,
    /// Queries without any valid reference are left out of the metrics.
    pub queries_without_ground_truth: usize,
    #[serde(flatten)]
    pub pr: PrMetrics,
    /// (N, Recall@N).
    pub recall_at: Vec<(usize, f64)>,
    /// Matching time per query per reference frame, as VPR-Bench reports it.
    pub matching_ms_per_ref: f64,
    pub outcomes: Vec<QueryOutcome>,
}

#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    pub dataset: String,
    /// Where it ran: "cpu (N threads)" or "gpu: adapter (backend, type)".
    pub backend: String,
    pub references: usize,
    pub reference_encoding: EncodingSummary,
    pub query_encoding: EncodingSummary,
    pub results: Vec<SettingReport>,
}

/// Options of one evaluation run.
pub struct EvalOptions<'a> {
    pub settings: Vec<Setting>,
    /// A map built from the dataset's references, used instead of encoding them again.
    pub map: Option<&'a Map>,
    pub skip_invalid: bool,
    pub quiet: bool,
}

/// Trains the encoder's VLAD codebook on reference frames (when appearance is on), with a bar.
pub fn train_codebook(encoder: &mut Encoder, refs: &[crate::input::FrameSource], quiet: bool) -> Result<()> {
    if encoder.appearance_model().is_none() {
        return Ok(());
    }
    let n = encoder.config().appearance.codebook_images.min(refs.len());
    let pb = progress::bar(n, "codebook", quiet);
    encoder.train_codebook(refs, &|| pb.inc(1))?;
    pb.finish_and_clear();
    Ok(())
}

/// Encodes a list of frames into a descriptor set, with a progress bar.
pub fn encode_frames(
    engine: &mut Engine,
    encoder: &Encoder,
    frames: &[crate::input::FrameSource],
    format: crate::input::LabelFormat,
    what: &str,
    skip_invalid: bool,
    quiet: bool,
) -> Result<(DescriptorSet, EncodingSummary, Vec<Error>)> {
    let pb = progress::bar(frames.len(), what, quiet);
    let results = engine.encode_all(encoder, frames, format, &|| pb.inc(1))?;
    pb.finish_and_clear();
    let (images, total, skipped) = collect_encoded(results, skip_invalid)?;
    let mut set = encoder.descriptor_set();
    for img in &images {
        set.push(img);
    }
    Ok((set, EncodingSummary::from_total(images.len(), total), skipped))
}

pub fn evaluate(ds: &Dataset, cfg: &Config, opts: &EvalOptions, engine: &mut Engine) -> Result<EvalReport> {
    let ref_sources: Vec<_> = ds.reference.frames.iter().map(|f| f.source.clone()).collect();
    let owned;
    let mut encoder;
    let (refs, ref_enc): (&dyn RefSource, EncodingSummary) = match opts.map {
        Some(m) => {
            encoder = Encoder::for_map(cfg, m)?;
            (m, EncodingSummary::default())
        }
        None => {
            encoder = Encoder::new(cfg)?;
            train_codebook(&mut encoder, &ref_sources, opts.quiet)?;
            let (set, summary, _) = encode_frames(engine, &encoder, &ref_sources, ds.label_format, "references", false, opts.quiet)?;
            owned = set;
            (&owned, summary)
        }
    };
    // dataset reference index -> map index
    let index: HashMap<&str, u32> = (0..refs.len()).map(|i| (refs.id(i), i as u32)).collect();
    let ref_to_map: Vec<u32> = ref_sources
        .iter()
        .map(|s| {
            index.get(s.id.as_str()).copied().ok_or_else(|| {
                Error::dataset(&ds.root, format!("reference {:?} is not in the map", s.id))
            })
        })
        .collect::<Result<_>>()?;
    let mut results = Vec::new();
    let mut q_total = StageTimes::default();
    let mut q_frames = 0;
    for qt in &ds.queries {
        let gt_ds = ds.ground_truth(qt)?;
        let sources: Vec<_> = qt.frames.iter().map(|f| f.source.clone()).collect();
        let pb = progress::bar(sources.len(), &format!("queries {}", qt.name), opts.quiet);
        let encoded = engine.encode_all(&encoder, &sources, ds.label_format, &|| pb.inc(1))?;
        pb.finish_and_clear();
        let mut qset = encoder.descriptor_set();
        let mut gt = Vec::new();
        for (r, g) in encoded.into_iter().zip(&gt_ds) {
            match r {
                Ok((img, t)) => {
                    qset.push(&img);
                    q_total += t;
                    q_frames += 1;
                    gt.push(g.iter().map(|&i| ref_to_map[i as usize]).collect::<Vec<u32>>());
                }
                Err(e) if opts.skip_invalid => eprintln!("warning: skipped query: {e}"),
                Err(e) => return Err(e),
            }
        }
        for &setting in &opts.settings {
            let (matches, times) = engine.match_batch(refs, &qset, setting, cfg)?;
            results.push(report(&qt.name, setting, refs, &qset, &matches, &gt, times.coarse_ms + times.fine_ms, cfg));
        }
    }
    Ok(EvalReport {
        dataset: ds.name.clone(),
        backend: engine.describe(),
        references: refs.len(),
        reference_encoding: ref_enc,
        query_encoding: EncodingSummary::from_total(q_frames, q_total),
        results,
    })
}

#[allow(clippy::too_many_arguments)]
fn report(
    query_set: &str,
    setting: Setting,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    matches: &[crate::matching::QueryMatch],
    gt: &[Vec<u32>],
    matching_ms: f64,
    cfg: &Config,
) -> SettingReport {
    let mut outcomes = Vec::new();
    let (mut scores, mut correct, mut ranked, mut gts) = (vec![], vec![], vec![], vec![]);
    for (q, (m, g)) in matches.iter().zip(gt).enumerate() {
        let best = m.best();
        let ok = best.is_some_and(|b| g.contains(&b.reference));
        outcomes.push(QueryOutcome {
            query: queries.ids[q].clone(),
            top1: best.map(|b| refs.id(b.reference as usize).to_string()),
            score: best.map(|b| b.score),
            correct: ok,
            valid_references: g.len(),
        });
        if g.is_empty() {
            continue;
        }
        scores.push(best.map_or(f64::NEG_INFINITY, |b| b.score as f64));
        correct.push(ok);
        ranked.push(m.ranked.iter().map(|c| c.reference).collect::<Vec<u32>>());
        gts.push(g.clone());
    }
    let pairs = (queries.len() * refs.len()).max(1) as f64;
    SettingReport {
        query_set: query_set.to_string(),
        setting,
        queries: queries.len(),
        queries_without_ground_truth: queries.len() - scores.len(),
        pr: pr_metrics(&scores, &correct),
        recall_at: cfg.eval.recall_at.iter().map(|&n| (n, recall_at_n(&ranked, &gts, n))).collect(),
        matching_ms_per_ref: matching_ms / pairs,
        outcomes,
    }
}

impl EvalReport {
    /// The metrics table and the timing table, as plain text.
    pub fn to_table(&self) -> String {
        let mut s = String::new();
        let recall_cols: Vec<usize> = self.results.first().map(|r| r.recall_at.iter().map(|x| x.0).collect()).unwrap_or_default();
        s += &format!("dataset {}: {} references; backend {}\n\n", self.dataset, self.references, self.backend);
        s += &format!("{:<12} {:<14} {:>6} {:>7} {:>7}", "query set", "setting", "AUC", "R@100P", "P@100R");
        for n in &recall_cols {
            s += &format!(" {:>6}", format!("R@{n}"));
        }
        s += &format!(" {:>10}\n", "ms/ref");
        for r in &self.results {
            s += &format!(
                "{:<12} {:<14} {:>6.3} {:>7.3} {:>7.3}",
                r.query_set, r.setting.name(), r.pr.auc, r.pr.recall_at_100_precision, r.pr.precision_at_100_recall
            );
            for (_, v) in &r.recall_at {
                s += &format!(" {:>6.3}", v);
            }
            s += &format!(" {:>10.4}\n", r.matching_ms_per_ref);
        }
        let e = &self.query_encoding;
        s += &format!(
            "\nencoding, ms per frame (mean of {} query frames; file decoding {:.2} ms not included):\n  edge (coarse) {:.2} | forest {:.2} | appearance {:.2} (network {:.2}, decoding and VLAD {:.2}) | total {:.2}\n",
            e.frames,
            e.load_ms,
            e.global_ms,
            e.forest_ms,
            e.appearance_ms,
            e.network_ms,
            e.appearance_ms - e.network_ms,
            e.encode_ms()
        );
        let mut per_setting: Vec<(Setting, f64, usize)> = Vec::new();
        for r in &self.results {
            match per_setting.iter_mut().find(|x| x.0 == r.setting) {
                Some(x) => {
                    x.1 += r.matching_ms_per_ref;
                    x.2 += 1;
                }
                None => per_setting.push((r.setting, r.matching_ms_per_ref, 1)),
            }
        }
        s += "matching, ms per reference frame (mean over query sets):\n ";
        for (st, ms, n) in per_setting {
            s += &format!(" {} {:.4} |", st.name(), ms / n as f64);
        }
        s.pop();
        s.push('\n');
        s
    }
}

impl EvalReport {
    /// Mean of each metric over the query sets, per setting (the ablation at a glance).
    pub fn summary_table(&self) -> String {
        let mut order: Vec<Setting> = Vec::new();
        for r in &self.results {
            if !order.contains(&r.setting) {
                order.push(r.setting);
            }
        }
        let mut s = format!("\nmean over query sets\n{:<14} {:<36} {:>6} {:>7} {:>7} {:>6}\n", "setting", "what", "AUC", "R@100P", "P@100R", "R@1");
        for st in order {
            let rows: Vec<&SettingReport> = self.results.iter().filter(|r| r.setting == st).collect();
            let n = rows.len() as f64;
            let mean = |f: &dyn Fn(&SettingReport) -> f64| rows.iter().map(|r| f(r)).sum::<f64>() / n;
            s += &format!(
                "{:<14} {:<36} {:>6.3} {:>7.3} {:>7.3} {:>6.3}\n",
                st.name(),
                st.describe(),
                mean(&|r| r.pr.auc),
                mean(&|r| r.pr.recall_at_100_precision),
                mean(&|r| r.pr.precision_at_100_recall),
                mean(&|r| r.recall_at.first().map_or(0.0, |x| x.1)),
            );
        }
        s
    }
}
