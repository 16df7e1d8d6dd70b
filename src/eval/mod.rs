//! Stage 5: evaluation. Encodes a dataset's references (or takes a built map) and queries,
//! matches every query set in every requested setting, and reports the VPR-Bench metrics plus
//! per-stage timings in the paper's Table 2 units (ms per frame for encoding, ms per reference
//! frame for matching).

pub mod metrics;
pub mod segmenter;

use crate::batch::{encode_frames, train_codebook, EncodingSummary};
use crate::config::Config;
use crate::dataset::Dataset;
use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::encode::Encoder;
use crate::engine::Engine;
use crate::error::{Error, Result};
use crate::map::Map;
use crate::matching::Setting;
use metrics::{pr_metrics, recall_at_n, PrMetrics};
use serde::Serialize;
use std::collections::HashMap;

/// What matching made of one query in one setting.
#[derive(Debug, Clone, Serialize)]
pub struct QueryOutcome {
    /// Query frame id.
    pub query: String,
    /// Id of the top-1 reference (none when the query got no candidate).
    pub top1: Option<String>,
    /// Score of the top-1 reference.
    pub score: Option<f32>,
    /// Whether the top-1 reference is a valid one.
    pub correct: bool,
    /// Number of valid references of the query (0: no ground truth).
    pub valid_references: usize,
    /// The best-ranked valid reference in the query's list, and its rank (0 = top-1), when one
    /// made the list.
    pub best_valid: Option<(String, usize)>,
    /// Some valid reference (the first by index), for pictures of what should have matched.
    pub a_valid_reference: Option<String>,
}

/// The results of one query set in one setting.
#[derive(Debug, Clone, Serialize)]
pub struct SettingReport {
    /// Query traversal name.
    pub query_set: String,
    /// Matching setting.
    pub setting: Setting,
    /// Queries matched.
    pub queries: usize,
    /// Queries without any valid reference are left out of the metrics.
    pub queries_without_ground_truth: usize,
    /// AUC, R@100P and P@100R over the queries with ground truth.
    #[serde(flatten)]
    pub pr: PrMetrics,
    /// (N, Recall@N).
    pub recall_at: Vec<(usize, f64)>,
    /// For settings with a coarse stage: its K and the share of queries (with ground truth) whose
    /// list of K candidates holds a valid reference, i.e. what survives to the fine stage.
    pub coarse_recall: Option<(usize, f64)>,
    /// Where the coarse stage searched the map's approximate index (`index.search`): recall@K of
    /// its fused top-K against the exact scan's on the same queries, for K = 10, 30, 100 (the
    /// share of the exact top-K the index's top-K holds, averaged over the queries).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub index_recall: Option<Vec<(usize, f64)>>,
    /// For settings with a coarse stage: (K, recall@K of the coarse stage's own ranking) for
    /// K = 10, 30, 100 ([`COARSE_RECALL_KS`]): the share of queries with ground truth whose coarse
    /// top-K holds a valid reference, whatever `matching.top_k` is (what a larger or smaller
    /// shortlist would keep).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub coarse_recall_at: Option<Vec<(usize, f64)>>,
    /// Matching time per query per reference frame, as VPR-Bench reports it.
    pub matching_ms_per_ref: f64,
    /// Every query's top-1 and score, for the precision-recall curve and --explain.
    pub outcomes: Vec<QueryOutcome>,
    /// Sequence matching over the query set in its order (`eval --sequence`), beside the
    /// single-frame metrics above.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub sequence: Option<SequenceReport>,
}

/// Sequence matching over an ordered query set: the queries streamed in order through one ring
/// (`stream::sequence`), each answered from the frames up to it.
#[derive(Debug, Clone, Serialize)]
pub struct SequenceReport {
    /// Share of the queries (with ground truth) whose answer is a valid reference: the
    /// stream's answer is the sequence match where it is accepted, else the single-frame best
    /// (what `stream::FrameResult::place` gives).
    pub recall_at_1: f64,
    /// Share whose sequence match alone (the best trajectory, accepted or not) is valid.
    pub trajectory_recall_at_1: f64,
    /// The precision-recall curve of the sequence matches ranked by their uniqueness.
    #[serde(flatten)]
    pub pr: PrMetrics,
    /// Queries (with ground truth) whose sequence match was accepted, and of those, correct.
    pub accepted: usize,
    /// Accepted queries whose sequence match is correct.
    pub accepted_correct: usize,
    /// Precision and recall of the accepted flag: correct accepted over accepted, and over the
    /// queries with ground truth.
    pub accepted_precision: f64,
    /// Correct accepted queries over the queries with ground truth.
    pub accepted_recall: f64,
    /// Per query: the sequence match (none where the ring had no evidence), its uniqueness,
    /// whether it was accepted and whether it is correct.
    pub outcomes: Vec<SequenceOutcome>,
}

/// What sequence matching made of one query.
#[derive(Debug, Clone, Serialize)]
pub struct SequenceOutcome {
    /// Query frame id.
    pub query: String,
    /// The stream's answer (see [`SequenceReport::recall_at_1`]) and whether it is valid.
    pub answer: Option<String>,
    /// Whether `answer` is a valid reference.
    pub answer_correct: bool,
    /// The best trajectory's place.
    pub top1: Option<String>,
    /// Uniqueness of the best trajectory.
    pub uniqueness: Option<f32>,
    /// Whether the sequence match was accepted.
    pub accepted: bool,
    /// Whether `top1` is a valid reference.
    pub correct: bool,
}

/// A model file that ran: where, and its SHA-256.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct ModelRecord {
    /// Path of the model file.
    pub path: String,
    /// SHA-256 of the model file.
    pub sha256: String,
}

/// What ran: the models, the configuration and the backend.
#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct RunRecord {
    /// The keypoint network (none without appearance).
    pub keypoints: Option<ModelRecord>,
    /// The segmentation network (none when every frame had a label map).
    pub segmenter: Option<ModelRecord>,
    /// SHA-256 of the whole configuration (its TOML).
    pub config_sha256: String,
    /// "cpu (N threads)" or "gpu: adapter (backend, type)".
    pub backend: String,
}

impl RunRecord {
    /// The models of `encoder`, the hash of `cfg` and the backend of `engine`.
    pub fn new(encoder: &Encoder, cfg: &Config, engine: &Engine) -> Result<Self> {
        Ok(RunRecord {
            keypoints: encoder.appearance_model().map(|m| ModelRecord { path: m.path.display().to_string(), sha256: m.sha256.clone() }),
            segmenter: encoder.frames().segmenter().map(|s| ModelRecord { path: s.path().display().to_string(), sha256: s.sha256().to_string() }),
            config_sha256: cfg.sha256()?,
            backend: engine.describe(),
        })
    }
    /// One line per item, for text reports.
    pub fn describe(&self) -> String {
        let model = |m: &Option<ModelRecord>| m.as_ref().map_or("none".to_string(), |m| format!("{} (sha256 {})", m.path, m.sha256));
        format!(
            "keypoints: {}
segmenter: {}
config sha256: {}
backend: {}
",
            model(&self.keypoints),
            model(&self.segmenter),
            self.config_sha256,
            self.backend
        )
    }
}

/// The results of one evaluation run.
#[derive(Debug, Clone, Serialize)]
pub struct EvalReport {
    /// Dataset name.
    pub dataset: String,
    /// What ran.
    pub run: RunRecord,
    /// Reference images matched against.
    pub references: usize,
    /// Encoding times of the references (empty when a built map was used).
    pub reference_encoding: EncodingSummary,
    /// Encoding times of all query sets together.
    pub query_encoding: EncodingSummary,
    /// One report per query set and setting that ran.
    pub results: Vec<SettingReport>,
    /// Settings asked for that could not run, with the reason (e.g. a map without HOG).
    pub skipped: Vec<(Setting, String)>,
    /// The frames were encoded without semantic labels (photos with neither label maps nor a
    /// segmenter, or a map built so): what draws them later must load them so too.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub without_labels: bool,
}

/// The settings an evaluation runs when none are named (every front end): all nine.
pub const DEFAULT_SETTINGS: [Setting; 9] = Setting::ALL;

/// Options of one evaluation run.
pub struct EvalOptions<'a> {
    /// Settings to run, in order.
    pub settings: Vec<Setting>,
    /// A map built from the dataset's references, used instead of encoding them again.
    pub map: Option<&'a Map>,
    /// Skip (and report) query frames that fail to load or encode, instead of stopping.
    pub skip_invalid: bool,
    /// No progress bars.
    pub quiet: bool,
    /// Also sequence matching over each query set in its order ([`SequenceReport`]).
    pub sequence: bool,
    /// Keep the segmenter's label maps here and read them back for the same pixels, segmenter
    /// and segmentation config ([`Encoder::with_label_cache`]): a second run skips segmentation.
    pub label_cache: Option<std::path::PathBuf>,
}

/// Evaluates `ds`: encodes its references (or takes `opts.map`) and its queries, and matches
/// every query set in every setting; settings that need labels are skipped, with the reason,
/// when the frames have none.
pub fn evaluate(ds: &Dataset, cfg: &Config, opts: &EvalOptions, engine: &mut Engine) -> Result<EvalReport> {
    let ref_sources: Vec<_> = ds.reference.frames.iter().map(|f| f.source.clone()).collect();
    // RGB frames with no label map and no segmenter to make one: the settings that need no
    // labels run, each of the others is skipped with its reason (the whole command used to stop)
    // (or a map built from such frames)
    let base = match opts.map {
        Some(m) => Encoder::for_map(cfg, m)?,
        None => Encoder::new(cfg)?,
    }
    .with_label_cache(opts.label_cache.clone());
    fn sources(frames: &[crate::dataset::Frame]) -> impl Iterator<Item = &crate::input::FrameSource> {
        frames.iter().map(|f| &f.source)
    }
    let unlabelled_map = opts.map.filter(|m| !m.labelled());
    // the one rule for photos without label maps (`Encoder::labels_rule`): on a map that holds
    // labels, queries no segmenter can label are matched in `hog` alone, every other setting
    // skipped with the reason (never label-free queries against labelled references)
    let query_sources = || ds.queries.iter().flat_map(|q| sources(&q.frames));
    let labelled_refused = match opts.map {
        Some(m) if m.labelled() => base.labels_rule(None, query_sources()).err(),
        _ => None,
    };
    let queries_unlabelled = labelled_refused.is_some() || base.labels_rule(Some(Setting::Hog), query_sources())?;
    let without_labels =
        unlabelled_map.is_some() || (queries_unlabelled && (opts.map.is_some() || base.labels_rule(None, sources(&ds.reference.frames))?));
    let mut skipped = Vec::new();
    let mut settings = opts.settings.clone();
    if without_labels {
        settings.retain(|&s| {
            let why = match (unlabelled_map, &labelled_refused) {
                (Some(m), _) => crate::matching::check_labels(m, s).err().map(|e| e.to_string()),
                (None, Some(_)) => base.labels_rule(Some(s), query_sources()).err().map(|e| e.to_string()),
                (None, _) => s.label_free().map(String::from),
            };
            match why {
                None => true,
                Some(why) => {
                    skipped.push((s, why));
                    false
                }
            }
        });
        if settings.is_empty() {
            if let (Some(m), Some(&(s, _))) = (unlabelled_map, skipped.first()) {
                crate::matching::check_labels(m, s)?;
            }
            if let Some(e) = labelled_refused {
                return Err(e);
            }
            let frame = ds.queries.iter().flat_map(|q| &q.frames).chain(&ds.reference.frames).find_map(|f| f.source.image.clone());
            return Err(Error::NoLabels { image: frame.unwrap_or_else(|| ds.root.clone()) });
        }
        let why = match (unlabelled_map, &labelled_refused) {
            (Some(_), _) => "the map was built without semantic labels",
            (None, Some(_)) => "the map holds semantic labels, but the queries have no label maps and there is no segmenter",
            (None, None) => "no label maps and no segmenter",
        };
        // hog runs only where HOG descriptors exist: a stored map without them skips it below
        let runs = settings.iter().filter(|&&s| s != Setting::Hog || opts.map.is_none_or(|m| m.manifest.hog_dim > 0));
        log::warn!(
            "{why}: running {} only (settings that need no labels; `semlook models` says what is installed)",
            runs.map(|s| s.name()).collect::<Vec<_>>().join(", ")
        );
    }
    let opts = &EvalOptions {
        settings,
        map: opts.map,
        skip_invalid: opts.skip_invalid,
        quiet: opts.quiet,
        sequence: opts.sequence,
        label_cache: opts.label_cache.clone(),
    };
    let wants_hog = opts.settings.contains(&Setting::Hog);
    let owned;
    let mut encoder = base.with_hog(wants_hog && opts.map.is_none_or(|m| m.manifest.hog_dim > 0)).without_labels(without_labels);
    // references encoded here: small frames get compact HOGs, as a map of them would store
    if opts.map.is_none() {
        let small = encoder.small_frames(&ref_sources)?;
        encoder = encoder.with_compact_hog(small);
    }
    let (refs, ref_enc): (&dyn RefSource, EncodingSummary) = match opts.map {
        Some(m) => (m, EncodingSummary::default()),
        None => {
            train_codebook(&mut encoder, &ref_sources, opts.quiet)?;
            let enc = encode_frames(engine, &encoder, &ref_sources, ds.label_format, "references", false, opts.quiet)?;
            let summary = enc.summary();
            owned = enc.set;
            (&owned, summary)
        }
    };
    let ref_to_map = reference_indices(refs, &ref_sources, &ds.root)?;
    let mut results = Vec::new();
    let mut q_times = Vec::new();
    let mut q_wall = 0.0;
    for qt in &ds.queries {
        let gt_ds = ds.ground_truth(qt)?;
        let sources: Vec<_> = qt.frames.iter().map(|f| f.source.clone()).collect();
        let enc = encode_frames(engine, &encoder, &sources, ds.label_format, &format!("queries {}", qt.name), opts.skip_invalid, opts.quiet)?;
        for (i, e) in &enc.skipped {
            log::warn!("skipped query {}: {e}", sources[*i].id);
        }
        let dropped: std::collections::HashSet<usize> = enc.skipped.iter().map(|(i, _)| *i).collect();
        let gt: Vec<Vec<u32>> = gt_ds
            .iter()
            .enumerate()
            .filter(|(i, _)| !dropped.contains(i))
            .map(|(_, g)| g.iter().map(|&i| ref_to_map[i as usize]).collect())
            .collect();
        q_times.extend_from_slice(&enc.times);
        q_wall += enc.wall_ms;
        let pb = crate::progress::bar(opts.settings.len(), &format!("matching {}", qt.name), opts.quiet);
        for setting in &opts.settings {
            match_query_set(engine, refs, &qt.name, &enc.set, &gt, std::slice::from_ref(setting), cfg, opts.sequence, &mut results, &mut skipped)?;
            pb.inc(1);
        }
        pb.finish_and_clear();
    }
    Ok(EvalReport {
        dataset: ds.name.clone(),
        run: RunRecord::new(&encoder, cfg, engine)?,
        references: refs.len(),
        reference_encoding: ref_enc,
        query_encoding: EncodingSummary::new(&q_times, q_wall),
        results,
        skipped,
        without_labels,
    })
}

/// The file stem of an image id (`00` of `ref/00.jpg` and of `00`): how a map built from a
/// folder and a dataset naming files by path find one image.
pub fn id_stem(id: &str) -> Option<String> {
    std::path::Path::new(id).file_stem().map(|s| s.to_string_lossy().into_owned())
}

/// The index in `refs` of every dataset reference: by its id, else (a map built from a folder of
/// images names them by file stem, a dataset by path: `00` against `ref/00.jpg`) by the file stem
/// of its id where exactly one map image has that id.
pub fn reference_indices(refs: &dyn RefSource, sources: &[crate::input::FrameSource], root: &std::path::Path) -> Result<Vec<u32>> {
    let index: HashMap<&str, u32> = (0..refs.len()).map(|i| (refs.id(i), i as u32)).collect();
    let stem = id_stem;
    // file stem -> map index, None where two map images share the stem
    let mut by_stem: HashMap<String, Option<u32>> = HashMap::new();
    for (&id, &i) in &index {
        if let Some(s) = stem(id) {
            by_stem.entry(s).and_modify(|e| *e = None).or_insert(Some(i));
        }
    }
    sources
        .iter()
        .map(|s| {
            if let Some(&i) = index.get(s.id.as_str()) {
                return Ok(i);
            }
            match stem(&s.id).and_then(|st| by_stem.get(&st).copied()) {
                Some(Some(i)) => Ok(i),
                Some(None) => Err(Error::dataset(root, format!("reference {:?}: two images of the map have its file stem", s.id))),
                None => Err(Error::dataset(
                    root,
                    format!(
                        "reference {:?} is not in the map (by id or file stem; the map's images are named like {:?})",
                        s.id,
                        if refs.len() > 0 { refs.id(0) } else { "" }
                    ),
                )),
            }
        })
        .collect()
}

/// Matches one encoded query set (ground truth in map indices) in every setting, appending a
/// report per setting to `results`, or the reason a baseline could not run to `skipped`.
#[allow(clippy::too_many_arguments)]
pub fn match_query_set(
    engine: &mut Engine,
    refs: &dyn RefSource,
    name: &str,
    queries: &DescriptorSet,
    gt: &[Vec<u32>],
    settings: &[Setting],
    cfg: &Config,
    sequence: bool,
    results: &mut Vec<SettingReport>,
    skipped: &mut Vec<(Setting, String)>,
) -> Result<()> {
    let mut index_recall: Option<Vec<(usize, f64)>> = None;
    // per coarse stage (fused or the edge descriptor alone): its recall@10/30/100
    let mut coarse_at: Vec<(bool, Vec<(usize, f64)>)> = Vec::new();
    for &setting in settings {
        if let Some(why) = setting.is_baseline().then(|| crate::matching::baseline::unavailable(refs, queries, setting)).flatten() {
            if !skipped.iter().any(|(s, _)| *s == setting) {
                skipped.push((setting, why));
            }
            continue;
        }
        let (matches, times) = engine.match_batch(refs, queries, setting, cfg)?;
        let mut r = report_matches(engine, refs, name, queries, &matches, gt, setting, cfg, times.coarse_ms + times.fine_ms, sequence)?;
        if times.approximate {
            if index_recall.is_none() {
                index_recall = Some(approximate_recall(refs, queries, cfg, setting)?);
            }
            r.index_recall = index_recall.clone();
        }
        if setting.uses_coarse() {
            let fused = setting.fuses_coarse(cfg.matching.coarse);
            if !coarse_at.iter().any(|(f, _)| *f == fused) {
                coarse_at.push((fused, coarse_recall_at(engine, refs, queries, gt, setting, cfg)?));
            }
            r.coarse_recall_at = coarse_at.iter().find(|(f, _)| *f == fused).map(|(_, v)| v.clone());
        }
        results.push(r);
    }
    Ok(())
}

/// The K of the coarse stage's recall in reports.
pub const COARSE_RECALL_KS: [usize; 3] = [10, 30, 100];

/// Recall@K of `setting`'s coarse stage (as configured: fused or the edge descriptor, exact or
/// through the index) for K in [`COARSE_RECALL_KS`], over the queries with ground truth: its
/// candidate lists made once at the deepest K.
pub fn coarse_recall_at(
    engine: &mut Engine,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    gt: &[Vec<u32>],
    setting: Setting,
    cfg: &Config,
) -> Result<Vec<(usize, f64)>> {
    let mut c = cfg.clone();
    c.matching.top_k = COARSE_RECALL_KS[COARSE_RECALL_KS.len() - 1];
    let (lists, _) = engine.candidates(refs, queries, setting, &c)?;
    let (ranked, gts): (Vec<Vec<u32>>, Vec<Vec<u32>>) =
        lists.iter().zip(gt).filter(|(_, g)| !g.is_empty()).map(|(l, g)| (l.iter().map(|x| x.1).collect(), g.clone())).unzip();
    Ok(COARSE_RECALL_KS.iter().map(|&k| (k, recall_at_n(&ranked, &gts, k))).collect())
}

/// Recall@K (K = 10, 30, 100) of the approximate fused coarse stage against the exact one on the
/// same queries: for each query the share of the exact top-K the approximate top-K holds, averaged
/// (what `index.probe` and `index.shortlist` cost in candidates), for `setting`'s fused coarse
/// stage. Runs the exact scan once.
pub fn approximate_recall(refs: &dyn RefSource, queries: &DescriptorSet, cfg: &Config, setting: Setting) -> Result<Vec<(usize, f64)>> {
    const KS: [usize; 3] = [10, 30, 100];
    let deepest = KS[KS.len() - 1];
    let with = |search| {
        let mut c = cfg.clone();
        c.index.search = search;
        c.matching.top_k = deepest;
        c
    };
    let st = setting;
    let (exact, _) = crate::matching::candidates(&mut crate::matching::CpuStages, refs, queries, st, &with(crate::config::IndexSearch::Exact))?;
    let (approx, _) =
        crate::matching::candidates(&mut crate::matching::CpuStages, refs, queries, st, &with(crate::config::IndexSearch::Approximate))?;
    Ok(KS
        .iter()
        .map(|&k| {
            let n = exact.len().max(1) as f64;
            let sum: f64 = exact
                .iter()
                .zip(&approx)
                .map(|(e, a)| {
                    let want: Vec<u32> = e.iter().take(k).map(|x| x.1).collect();
                    let got: std::collections::HashSet<u32> = a.iter().take(k).map(|x| x.1).collect();
                    if want.is_empty() {
                        1.0
                    } else {
                        want.iter().filter(|r| got.contains(r)).count() as f64 / want.len() as f64
                    }
                })
                .sum();
            (k, sum / n)
        })
        .collect())
}

/// The report of one setting from its matches (`matching_ms`: what matching took), with the
/// sequence matching over the query set in its order when `sequence`.
#[allow(clippy::too_many_arguments)]
pub fn report_matches(
    engine: &mut Engine,
    refs: &dyn RefSource,
    name: &str,
    queries: &DescriptorSet,
    matches: &[crate::matching::QueryMatch],
    gt: &[Vec<u32>],
    setting: Setting,
    cfg: &Config,
    matching_ms: f64,
    sequence: bool,
) -> Result<SettingReport> {
    let mut r = report(name, setting, refs, queries, matches, gt, matching_ms, cfg);
    if sequence {
        r.sequence = Some(sequence_report(engine, refs, queries, matches, gt, setting, cfg)?);
    }
    Ok(r)
}

/// Sequence matching over `queries` in their order, scored with `setting` as a stream would
/// score them (`stream::scored_rows`, one ring), against the ground truth `gt`.
pub fn sequence_report(
    engine: &mut Engine,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    matches: &[crate::matching::QueryMatch],
    gt: &[Vec<u32>],
    setting: Setting,
    cfg: &Config,
) -> Result<SequenceReport> {
    let rows = sequence_rows(engine, refs, queries, matches, setting, cfg)?;
    Ok(sequence_report_from_rows(refs, queries, matches, gt, cfg, &rows))
}

/// Each query's scored places for sequence matching (see `stream::scored_rows`): the part of
/// [`sequence_report`] that depends on the matching and on `sequence.rows` and `widen` only.
pub fn sequence_rows(
    engine: &mut Engine,
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    matches: &[crate::matching::QueryMatch],
    setting: Setting,
    cfg: &Config,
) -> Result<Vec<Vec<(crate::descriptors::source::Place, f32)>>> {
    let full;
    let lists: &[crate::matching::QueryMatch] = match cfg.sequence.rows {
        crate::config::SequenceRows::Candidates => matches,
        crate::config::SequenceRows::Full => {
            let c = Config { matching: crate::config::MatchingConfig { top_k: refs.len().max(1), ..cfg.matching.clone() }, ..cfg.clone() };
            full = engine.match_batch(refs, queries, setting, &c)?.0;
            &full
        }
    };
    let widen = match cfg.sequence.rows {
        crate::config::SequenceRows::Candidates => cfg.sequence.widen,
        crate::config::SequenceRows::Full => 0,
    };
    crate::stream::scored_rows(engine, refs, queries, lists, setting, cfg, widen)
}

/// [`sequence_report`] from the rows of [`sequence_rows`].
pub fn sequence_report_from_rows(
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    matches: &[crate::matching::QueryMatch],
    gt: &[Vec<u32>],
    cfg: &Config,
    rows: &[Vec<(crate::descriptors::source::Place, f32)>],
) -> SequenceReport {
    use crate::stream::sequence::{contributions, SequenceMatcher};
    let lens = |t: u32| refs.traversal_len(t);
    let mut ring = SequenceMatcher::new(&cfg.sequence);
    let (mut outcomes, mut scores, mut correct) = (Vec::new(), Vec::new(), Vec::new());
    let (mut accepted, mut accepted_correct, mut answered) = (0, 0, 0);
    for (q, (row, g)) in rows.iter().zip(gt).enumerate() {
        let m = ring.push(contributions(&cfg.sequence, row, &lens), &lens);
        let best = m.and_then(|m| refs.at(m.place).map(|i| (i as u32, m)));
        let ok = best.is_some_and(|(i, _)| g.contains(&i));
        let acc = best.is_some_and(|(_, m)| m.accepted);
        let answer = match best {
            Some((i, m)) if m.accepted => Some(i),
            _ => matches[q].best().map(|c| c.reference),
        };
        let answer_ok = answer.is_some_and(|i| g.contains(&i));
        outcomes.push(SequenceOutcome {
            query: queries.ids[q].clone(),
            answer: answer.map(|i| refs.id(i as usize).to_string()),
            answer_correct: answer_ok,
            top1: best.map(|(i, _)| refs.id(i as usize).to_string()),
            uniqueness: best.map(|(_, m)| m.uniqueness),
            accepted: acc,
            correct: ok,
        });
        if g.is_empty() {
            continue;
        }
        scores.push(best.map_or(f64::NEG_INFINITY, |(_, m)| m.uniqueness as f64));
        correct.push(ok);
        answered += usize::from(answer_ok);
        accepted += usize::from(acc);
        accepted_correct += usize::from(acc && ok);
    }
    let n = correct.len().max(1) as f64;
    SequenceReport {
        recall_at_1: answered as f64 / n,
        trajectory_recall_at_1: correct.iter().filter(|&&c| c).count() as f64 / n,
        pr: pr_metrics(&scores, &correct),
        accepted,
        accepted_correct,
        accepted_precision: if accepted > 0 { accepted_correct as f64 / accepted as f64 } else { 0.0 },
        accepted_recall: accepted_correct as f64 / n,
        outcomes,
    }
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
        let best_valid = m.ranked.iter().position(|c| g.contains(&c.reference)).map(|r| (refs.id(m.ranked[r].reference as usize).to_string(), r));
        outcomes.push(QueryOutcome {
            query: queries.ids[q].clone(),
            top1: best.map(|b| refs.id(b.reference as usize).to_string()),
            score: best.map(|b| b.score),
            correct: ok,
            valid_references: g.len(),
            best_valid,
            a_valid_reference: g.iter().min().map(|&r| refs.id(r as usize).to_string()),
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
        coarse_recall: setting.uses_coarse().then(|| (cfg.matching.top_k, recall_at_n(&ranked, &gts, cfg.matching.top_k))),
        index_recall: None,
        coarse_recall_at: None,
        matching_ms_per_ref: matching_ms / pairs,
        outcomes,
        sequence: None,
    }
}

impl EvalReport {
    /// The metrics table and the timing table, as plain text.
    pub fn to_table(&self) -> String {
        let mut s = String::new();
        let recall_cols: Vec<usize> = self.results.first().map(|r| r.recall_at.iter().map(|x| x.0).collect()).unwrap_or_default();
        s += &format!("dataset {}: {} references\n{}\n", self.dataset, self.references, self.run.describe());
        s += &format!("{:<12} {:<14} {:>6} {:>7} {:>7}", "query set", "setting", "AUC", "R@100P", "P@100R");
        for n in &recall_cols {
            s += &format!(" {:>6}", format!("R@{n}"));
        }
        s += &format!(" {:>9} {:>10}\n", "coarse@K", "ms/ref");
        for r in &self.results {
            s += &format!(
                "{:<12} {:<14} {:>6.3} {:>7.3} {:>7.3}",
                r.query_set,
                r.setting.name(),
                r.pr.auc,
                r.pr.recall_at_100_precision,
                r.pr.precision_at_100_recall
            );
            for (_, v) in &r.recall_at {
                s += &format!(" {:>6.3}", v);
            }
            let coarse = r.coarse_recall.map_or("-".to_string(), |(k, v)| format!("{v:.3}@{k}"));
            s += &format!(" {:>9} {:>10.4}\n", coarse, r.matching_ms_per_ref);
        }
        if self.results.iter().any(|r| r.sequence.is_some()) {
            s += &format!(
                "\nsequence matching (each query set streamed in its order; AUC by uniqueness):\n{:<12} {:<14} {:>6} {:>7} {:>7} {:>6} {:>9} {:>8} {:>8}\n",
                "query set",
                "setting",
                "R@1",
                "seq R@1",
                "traj.",
                "AUC",
                "accepted",
                "prec.",
                "recall"
            );
            for r in &self.results {
                if let Some(q) = &r.sequence {
                    s += &format!(
                        "{:<12} {:<14} {:>6.3} {:>7.3} {:>7.3} {:>6.3} {:>9} {:>8.3} {:>8.3}\n",
                        r.query_set,
                        r.setting.name(),
                        r.recall_at.first().map_or(0.0, |x| x.1),
                        q.recall_at_1,
                        q.trajectory_recall_at_1,
                        q.pr.auc,
                        q.accepted,
                        q.accepted_precision,
                        q.accepted_recall
                    );
                }
            }
        }
        for r in self.results.iter().filter(|r| r.coarse_recall_at.is_some()) {
            let v: Vec<String> = r.coarse_recall_at.iter().flatten().map(|(k, x)| format!("@{k} {x:.3}")).collect();
            s += &format!("{} {}: coarse stage recall {}\n", r.query_set, r.setting.name(), v.join(", "));
        }
        let mut shown: Vec<&str> = Vec::new();
        for r in self.results.iter().filter(|r| r.index_recall.is_some()) {
            if shown.contains(&r.query_set.as_str()) {
                continue;
            }
            shown.push(&r.query_set);
            let v: Vec<String> = r.index_recall.iter().flatten().map(|(k, x)| format!("@{k} {x:.3}")).collect();
            s += &format!(
                "{}: the coarse stage searched the map's approximate index; its recall against the exact scan {}\n",
                r.query_set,
                v.join(", ")
            );
        }
        for (st, why) in &self.skipped {
            s += &format!("{:<12} {:<14} skipped: {why}\n", "", st.name());
        }
        let e = &self.query_encoding;
        let (m, md) = (&e.mean, &e.median);
        s += &format!(
            "\nencoding, ms per frame ({} query frames; mean / median):\n  file decoding and resizing {:.2} / {:.2} | segmentation {:.2} / {:.2}\n  edge (coarse) {:.2} / {:.2} | forest {:.2} / {:.2} | appearance {:.2} / {:.2} (network {:.2} / {:.2}) | embedding {:.2} / {:.2} | total {:.2} / {:.2}\n  HOG baseline {:.2} / {:.2} | wall clock, frames in parallel: {:.2} per frame\n",
            e.frames,
            m.decode_ms,
            md.decode_ms,
            m.segment_ms,
            md.segment_ms,
            m.global_ms,
            md.global_ms,
            m.forest_ms,
            md.forest_ms,
            m.appearance_ms,
            md.appearance_ms,
            m.network_ms,
            md.network_ms,
            m.embedding_ms,
            md.embedding_ms,
            m.encode_ms(),
            md.encode_ms(),
            m.hog_ms,
            md.hog_ms,
            e.wall_ms_per_frame,
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

/// R@1 and AUC per setting (rows) and query set (columns), side by side for several reports of
/// the same dataset (e.g. real labels vs a segmenter's).
pub fn label_source_table(reports: &[(&str, &EvalReport)]) -> String {
    let mut sets: Vec<&str> = Vec::new();
    let mut settings: Vec<Setting> = Vec::new();
    for (_, r) in reports {
        for s in &r.results {
            if !sets.contains(&s.query_set.as_str()) {
                sets.push(&s.query_set);
            }
            if !settings.contains(&s.setting) {
                settings.push(s.setting);
            }
        }
    }
    let mut out = String::new();
    for (metric, get) in
        [("R@1", (|r: &SettingReport| r.recall_at.first().map_or(0.0, |x| x.1)) as fn(&SettingReport) -> f64), ("AUC", |r: &SettingReport| r.pr.auc)]
    {
        out += &format!("\n{metric}: rows settings, columns query set / label source\n{:<14}", "setting");
        for set in &sets {
            for (name, _) in reports {
                out += &format!(" {:>18}", format!("{set}/{}", name.split(' ').next().unwrap_or(name)));
            }
        }
        out += &format!(" {:>10}\n", "mean");
        for st in &settings {
            out += &format!("{:<14}", st.name());
            let mut all = Vec::new();
            for set in &sets {
                for (_, rep) in reports {
                    match rep.results.iter().find(|r| r.setting == *st && r.query_set == *set) {
                        Some(r) => {
                            all.push(get(r));
                            out += &format!(" {:>18.3}", get(r));
                        }
                        None => out += &format!(" {:>18}", "-"),
                    }
                }
            }
            out += &format!(" {:>10.3}\n", all.iter().sum::<f64>() / all.len().max(1) as f64);
        }
    }
    out
}
