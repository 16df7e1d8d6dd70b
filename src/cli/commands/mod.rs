//! The commands behind the CLI.

mod dev;
mod localize;
mod map_cmd;
mod pairs;
mod shared;

use shared::{
    apply_models, check_output_dir, check_output_file, coarse_search, frame_sources, info, load_config, map_config, to_json, warn_if_no_index,
    write_file,
};

use super::args::*;
use semlook::batch::encode_frames;
use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions};
use semlook::descriptors::source::RefSource;
use semlook::descriptors::DescriptorSet;
use semlook::encode::Encoder;
use semlook::engine::{Backend, Engine};
use semlook::error::{Error, Result};
use semlook::eval::{evaluate, EvalOptions, EvalReport, RunRecord, DEFAULT_SETTINGS};
use semlook::gpu::GpuOptions;
use semlook::input::{FrameSource, LabelFormat};
use semlook::map::Map;
use semlook::matching::{QueryMatch, Setting};
use semlook::progress;
use semlook::tools::synth::condition::Condition;
use semlook::tools::synth::{self, SynthConfig};
use std::path::Path;
use std::time::Instant;

/// Why `command` takes no `--backend`, or `None` where it runs on the backend given.
fn ignores_backend(command: &Command) -> Option<&'static str> {
    match command {
        Command::Dev(DevCommand::Bench(_)) => Some("dev bench times the CPU and, unless --cpu-only, every GPU row itself"),
        Command::Map(MapCommand::Build { .. } | MapCommand::Add { .. }) => None,
        Command::Dev(DevCommand::MapBench(_)) => Some("dev map-bench measures the store on the CPU"),
        Command::Map(_) => Some("this map command reads and writes files only"),
        Command::Inspect(_) => Some("inspect runs the CPU stages to draw them"),
        Command::Dev(DevCommand::SegmenterAccuracy(_)) => Some("dev segmenter-accuracy runs the segmenter, which runs on the CPU"),
        Command::Synth(a) if a.from_camvid.is_none() => Some("synth renders (or writes a stream manifest) on the CPU"),
        Command::Config => Some("config prints the defaults"),
        Command::Models { .. } => Some("models lists files"),
        _ => None,
    }
}

pub fn dispatch(cli: Cli) -> Result<()> {
    let quiet = cli.quiet;
    if let (Some(backend), Some(why)) = (cli.backend, ignores_backend(&cli.command)) {
        return Err(Error::invalid(format!("--backend {}", format!("{backend:?}").to_lowercase()), format!("does not apply here: {why}")));
    }
    let backend = cli.backend.unwrap_or(Backend::DEFAULT);
    let engine = || -> Result<Engine> {
        let (engine, fallback) = Engine::new(backend, &GpuOptions::default())?;
        if let Some(why) = fallback {
            info(quiet, format!("backend auto: {why}"));
        }
        info(quiet, format!("backend: {}", engine.describe()));
        Ok(engine)
    };
    match cli.command {
        Command::Synth(a) => match (&a.from_camvid, &a.stream_from) {
            (Some(dir), _) => camvid_cmd(dir, &a, &engine, quiet),
            (None, Some(dir)) => stream_synth_cmd(dir, &a, quiet),
            (None, None) => synth_cmd(&a, quiet),
        },
        Command::Demo(a) => demo(&a, &mut engine()?, quiet),
        Command::Map(m) => map_cmd::run(m, &engine, quiet),
        Command::Query(a) => query(&mut engine()?, &a, quiet),
        Command::Eval(a) => eval_cmd(&mut engine()?, &a, quiet),
        Command::Localize(a) => localize::run(engine()?, &a, quiet),
        Command::Inspect(a) => inspect_cmd(&a, quiet),
        Command::Dev(d) => dev::run(d, &engine, quiet),
        Command::Config => {
            out!("{}", Config::default().to_toml()?);
            Ok(())
        }
        Command::Models { json } => models_cmd(json),
    }
}

fn synth_config(a: &SynthArgs) -> SynthConfig {
    let mut c = SynthConfig {
        seed: a.seed,
        places: a.places,
        width: a.size.0,
        height: a.size.1,
        reference: a.reference,
        aliasing: a.aliasing,
        ..Default::default()
    };
    if !a.queries.is_empty() {
        c.queries = a.queries.clone();
    }
    c
}

/// `synth --from-camvid`: the real-label benchmark, and with --evaluate its two evaluations.
fn camvid_cmd(camvid: &Path, a: &SynthArgs, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    use semlook::tools::synth::camvid::{self, Change};
    let changes = if a.changes.is_empty() { Change::ALL.to_vec() } else { a.changes.clone() };
    let t = Instant::now();
    let pb = progress::bar(0, "frames", quiet);
    let n = camvid::generate(camvid, &a.out, &changes, a.step, &|| pb.inc(1))?;
    pb.finish_and_clear();
    info(quiet, format!("wrote {n} frames x {} traversals to {} in {:.1} s", 1 + changes.len(), a.out.display(), t.elapsed().as_secs_f64()));
    if !a.evaluate {
        return Ok(());
    }
    let cfg = apply_models(Config::camvid(), &a.models);
    let ds = Dataset::open(&a.out, &DatasetOptions::default())?;
    let mut engine = engine()?;
    let opts = EvalOptions { settings: Setting::ALL.to_vec(), map: None, skip_invalid: false, quiet, sequence: false, label_cache: None };
    info(quiet, "evaluating with the real labels");
    let real = evaluate(&ds, &cfg, &opts, &mut engine)?;
    info(quiet, "evaluating with the segmenter's labels");
    let seg = evaluate(&ds.without_labels(), &cfg, &opts, &mut engine)?;
    write_file(&a.out.join("eval-real-labels.json"), &to_json(&real)?)?;
    write_file(&a.out.join("eval-segmenter-labels.json"), &to_json(&seg)?)?;
    out!("{}", semlook::eval::label_source_table(&[("real labels", &real), ("segmenter labels", &seg)]));
    out!("\nsegmenter run:\n{}", seg.run.describe());
    Ok(())
}

/// `synth --stream-from`: a dataset's query traversals driven again at varying speed, with stops.
fn stream_synth_cmd(dir: &Path, a: &SynthArgs, quiet: bool) -> Result<()> {
    use semlook::tools::synth::stream::{write, StreamProfile};
    let ds = Dataset::open(dir, &DatasetOptions::default())?;
    let p = StreamProfile { speed_min: a.speed_min, speed_max: a.speed_max, stops: a.stops, stop_frames: a.stop_frames, seed: a.seed };
    let n = write(&ds, &a.out, &p)?;
    info(quiet, format!("wrote {} ({} query frames over {} traversals)", a.out.join(semlook::dataset::MANIFEST).display(), n, ds.queries.len()));
    Ok(())
}

fn synth_cmd(a: &SynthArgs, quiet: bool) -> Result<()> {
    let cfg = synth_config(a);
    cfg.validate()?;
    let t = Instant::now();
    let pb = progress::bar(cfg.places * (1 + cfg.queries.len()), "rendering", quiet);
    synth::generate(&cfg, &a.out, &|| pb.inc(1))?;
    pb.finish_and_clear();
    info(quiet, format!("wrote {} frames to {} in {:.1} s", cfg.places * (1 + cfg.queries.len()), a.out.display(), t.elapsed().as_secs_f64()));
    Ok(())
}

fn encode_sources(
    engine: &mut Engine,
    encoder: &Encoder,
    frames: &[FrameSource],
    fmt: LabelFormat,
    what: &str,
    skip: bool,
    quiet: bool,
) -> Result<DescriptorSet> {
    if frames.is_empty() {
        return Err(Error::invalid(what, "no images found"));
    }
    let enc = encode_frames(engine, encoder, frames, fmt, what, skip, quiet)?;
    for (i, e) in &enc.skipped {
        log::warn!("skipped {}: {e}", frames[*i].id);
    }
    info(quiet, shared::encoding_line(&format!("{} {what}", enc.set.len()), &enc.summary().mean));
    Ok(enc.set)
}

/// An id inside the `top_k` column's `id:score;...` list, with `%`, `:` and `;` percent-escaped
/// (`%25`, `%3A`, `%3B`) so the list splits back into the ids it holds.
pub fn escape_top_k_id(id: &str) -> String {
    id.replace('%', "%25").replace(':', "%3A").replace(';', "%3B")
}

/// CSV and JSON renderings of query results. The CSV starts with `#` comment lines naming what
/// ran, then a table written by a CSV writer (fields quoted where they hold `,`, `"` or a line
/// break); in the `top_k` column ids are escaped by [`escape_top_k_id`]. The JSON is
/// `{run, setting, queries: [...]}`.
fn query_outputs(
    refs: &dyn RefSource,
    queries: &DescriptorSet,
    matches: &[QueryMatch],
    run: &RunRecord,
    setting: Setting,
) -> Result<(String, String)> {
    let mut csv: String = run.describe().lines().map(|l| format!("# {l}\n")).collect();
    csv += &format!("# setting: {setting}\n");
    let mut table = csv::WriterBuilder::new().from_writer(Vec::new());
    let row =
        |t: &mut csv::Writer<Vec<u8>>, fields: &[&str]| t.write_record(fields).map_err(|e| Error::invalid("query results as CSV", e.to_string()));
    row(&mut table, &["query", "best_reference", "score", "coarse", "fine", "top_k"])?;
    let mut rows = Vec::new();
    let f = |v: Option<f32>| v.map_or(String::new(), |x| format!("{x:.6}"));
    for (q, m) in matches.iter().enumerate() {
        let best = m.best();
        let topk: Vec<String> = m.ranked.iter().map(|c| format!("{}:{:.6}", escape_top_k_id(refs.id(c.reference as usize)), c.score)).collect();
        let score = best.map_or(String::new(), |b| format!("{:.6}", b.score));
        let (coarse, fine) = (f(best.and_then(|b| b.coarse)), f(best.and_then(|b| b.fine)));
        row(&mut table, &[&queries.ids[q], best.map_or("", |b| refs.id(b.reference as usize)), &score, &coarse, &fine, &topk.join(";")])?;
        rows.push(serde_json::json!({
            "query": queries.ids[q],
            "best_reference": best.map(|b| refs.id(b.reference as usize).to_string()),
            "score": best.map(|b| b.score),
            "top_k": m.ranked.iter().map(|c| serde_json::json!({
                "reference": refs.id(c.reference as usize), "score": c.score, "coarse": c.coarse, "fine": c.fine, "inliers": c.inliers
            })).collect::<Vec<_>>(),
        }));
    }
    let table = table.into_inner().map_err(|e| Error::invalid("query results as CSV", e.to_string()))?;
    csv += &String::from_utf8(table).map_err(|e| Error::invalid("query results as CSV", e.to_string()))?;
    let doc = serde_json::json!({ "run": run, "setting": setting, "queries": rows });
    Ok((csv, to_json(&doc)?))
}

/// The query frames a source names, read with the config's label ids.
fn query_frames(s: &SourceArgs, cfg: &Config) -> Result<(Vec<FrameSource>, LabelFormat)> {
    frame_sources(s, &mut cfg.clone(), true)
}

fn run_query(
    engine: &mut Engine,
    map: &Map,
    cfg: &Config,
    (frames, fmt): (&[FrameSource], LabelFormat),
    s: &SourceArgs,
    setting: Setting,
    quiet: bool,
) -> Result<(DescriptorSet, Vec<QueryMatch>, RunRecord)> {
    semlook::matching::check_labels(map, setting)?;
    warn_if_no_index(cfg, Some(map));
    let encoder = Encoder::for_map(cfg, map)?.for_setting(setting);
    // photos without label maps: segmented, or label-free where nothing reads labels, else refused
    // here, before any encoding
    let label_free = encoder.labels_rule(Some(setting), frames)?;
    let encoder = encoder.without_labels(label_free || map.manifest.without_labels);
    let queries = encode_sources(engine, &encoder, frames, fmt, "queries", s.skip_invalid, quiet)?;
    let t = Instant::now();
    let (matches, times) = engine.match_batch(map, &queries, setting, cfg)?;
    info(
        quiet,
        format!("matched {} queries against {} references ({setting}) in {:.1} ms", queries.len(), map.len(), t.elapsed().as_secs_f64() * 1e3),
    );
    let w_embedding = semlook::matching::FusedWeights::of(map, &queries, cfg, setting).embedding;
    info(quiet, format!("coarse search: {}", coarse_search(Some(map), map.len(), cfg, setting, times.approximate, w_embedding)));
    Ok((queries, matches, RunRecord::new(&encoder, cfg, engine)?))
}

fn query(engine: &mut Engine, a: &QueryArgs, quiet: bool) -> Result<()> {
    // every output is checked before the minutes of encoding
    if let Some(dir) = &a.out {
        check_output_dir(dir, "--out")?;
    }
    if let Some(f) = &a.pairs.pairs {
        check_output_file(f, "--pairs")?;
    }
    let map = Map::open(&a.map)?;
    // without --config, the map's encoding and default matching parameters
    let cfg = map_config(&map, a.config.as_deref(), &a.source.models)?;
    let (frames, fmt) = query_frames(&a.source, &cfg)?;
    // hloc's names are found before the minutes of encoding, so that a bad name stops at once
    let names = a.pairs.pairs.as_ref().map(|_| pairs::PairNames::find(&a.pairs, &map, &frames, cfg.matching.top_k)).transpose()?;
    let (queries, matches, run) = run_query(engine, &map, &cfg, (&frames, fmt), &a.source, a.setting, quiet)?;
    let (csv, json) = query_outputs(&map, &queries, &matches, &run, a.setting)?;
    if let Some(dir) = &a.out {
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        write_file(&dir.join("matches.csv"), &csv)?;
        write_file(&dir.join("matches.json"), &json)?;
    }
    if let (Some(names), Some(path)) = (&names, &a.pairs.pairs) {
        let n = names.write(path, &queries, &matches)?;
        info(quiet, format!("wrote {n} retrieval pairs (hloc) to {}", path.display()));
    }
    if a.json {
        outln!("{json}");
    } else {
        out!("{csv}");
    }
    Ok(())
}

/// The dataset an `eval` names: a dataset directory, or a reference and a query folder.
fn eval_dataset(a: &EvalArgs) -> Result<Dataset> {
    let opts = DatasetOptions { reference: a.reference.clone(), queries: a.queries.clone(), max_distance: a.gt_distance, max_angle_deg: a.gt_angle };
    Dataset::open_any(a.dataset.as_deref(), a.references.as_deref(), a.queries_dir.as_deref(), a.ground_truth.as_deref(), &opts)
}

fn eval_cmd(engine: &mut Engine, a: &EvalArgs, quiet: bool) -> Result<()> {
    // every output is checked before the minutes of encoding and matching
    for (dir, flag) in [(&a.out, "--out"), (&a.plots, "--plots"), (&a.report, "--report")] {
        if let Some(d) = dir {
            check_output_dir(d, flag)?;
        }
    }
    let ds = eval_dataset(a)?;
    let map = a.map.as_deref().map(Map::open).transpose()?;
    let mut cfg = match &map {
        Some(m) => map_config(m, a.config.as_deref(), &a.models)?,
        None => apply_models(load_config(a.config.as_deref())?, &a.models),
    };
    if a.config.is_none() && map.is_none() {
        cfg = ds.adapt_config(cfg);
    }
    let settings = if a.settings.is_empty() { DEFAULT_SETTINGS.to_vec() } else { dedup(&a.settings) };
    warn_if_no_index(&cfg, map.as_ref());
    let report = evaluate(
        &ds,
        &cfg,
        &EvalOptions {
            settings: settings.clone(),
            map: map.as_ref(),
            skip_invalid: a.skip_invalid,
            quiet,
            sequence: a.sequence,
            label_cache: a.label_cache.clone(),
        },
        engine,
    )?;
    for line in eval_coarse_searches(&report, map.as_ref(), &cfg) {
        info(quiet, line);
    }
    print_report(&report, a.json)?;
    if let Some(dir) = &a.plots {
        for f in semlook::tools::viz::plots::write_pr_plots(&report, dir)? {
            info(quiet, format!("wrote {}", f.display()));
        }
    }
    if a.explain.is_none() && a.report.is_none() {
        return Ok(());
    }
    let setting = if settings.contains(&Setting::RECOMMENDED) { Setting::RECOMMENDED } else { settings[0] };
    // frames are loaded again as they were encoded (without labels where the run had none)
    let encoder = match &map {
        Some(m) => Encoder::for_map(&cfg, m)?,
        None => Encoder::new(&cfg)?,
    }
    .without_labels(report.without_labels);
    if let (Some(n), Some(dir)) = (a.explain, &a.out) {
        for f in semlook::tools::viz::explain(&report, setting, &ds, &encoder, n, dir)? {
            info(quiet, format!("wrote {}", f.display()));
        }
    }
    if let Some(dir) = &a.report {
        use semlook::tools::viz::report::{ReportInputs, WorstQuery};
        let worst = semlook::tools::viz::worst_queries(&report, setting)
            .into_iter()
            .take(a.explain.unwrap_or(REPORT_WORST))
            .map(|w| {
                // a frame that cannot be drawn costs its sheet, not the page
                let sheet = semlook::tools::viz::worst_sheet(w, setting, &ds, &encoder, 320);
                WorstQuery { query_set: w.0, outcome: w.1, sheet }
            })
            .collect();
        let inputs = ReportInputs { setting, worst, command: command_line() };
        info(quiet, format!("wrote {}", semlook::tools::viz::report::write(&report, &inputs, dir)?.display()));
    }
    Ok(())
}

/// The info lines on which coarse search each setting of `report` ran (`coarse search: ...`),
/// settings that ran the same one on one line (named where the lines differ).
fn eval_coarse_searches(report: &EvalReport, map: Option<&Map>, cfg: &Config) -> Vec<String> {
    let mut searches: Vec<(String, Vec<&str>)> = Vec::new();
    for r in &report.results {
        // queries are encoded for the map, with its embedding network
        let w_embedding = match map.is_some_and(|m| m.manifest.embedding.is_some()) && r.setting.embeds() {
            true => cfg.matching.w_embedding as f32,
            false => 0.0,
        };
        let s = coarse_search(map, report.references, cfg, r.setting, r.index_recall.is_some(), w_embedding);
        match searches.iter_mut().find(|(x, _)| *x == s) {
            Some((_, names)) if !names.contains(&r.setting.name()) => names.push(r.setting.name()),
            Some(_) => {}
            None => searches.push((s, vec![r.setting.name()])),
        }
    }
    match searches.len() {
        1 => vec![format!("coarse search: {}", searches[0].0)],
        _ => searches.into_iter().map(|(s, names)| format!("coarse search: {s} ({})", names.join(", "))).collect(),
    }
}

/// `settings` in the order given, each once.
fn dedup(settings: &[Setting]) -> Vec<Setting> {
    let mut out: Vec<Setting> = Vec::new();
    for s in settings {
        if !out.contains(s) {
            out.push(*s);
        }
    }
    out
}

/// Worst queries shown by `eval --report` without `--explain N`.
const REPORT_WORST: usize = 6;

/// The command as typed (arguments with spaces quoted), for the report's record of what ran.
fn command_line() -> String {
    let args = std::env::args().skip(1).map(|a| if a.contains(char::is_whitespace) || a.is_empty() { format!("{a:?}") } else { a });
    std::iter::once("semlook".to_string()).chain(args).collect::<Vec<_>>().join(" ")
}

fn print_report(report: &EvalReport, json: bool) -> Result<()> {
    if json {
        outln!("{}", to_json(report)?);
    } else {
        out!("{}", report.to_table());
    }
    Ok(())
}

fn demo(a: &DemoArgs, engine: &mut Engine, quiet: bool) -> Result<()> {
    let t0 = Instant::now();
    let (dir, temporary) = match &a.out {
        Some(d) => (d.clone(), false),
        None => (std::env::temp_dir().join(format!("semlook-demo-{}", std::process::id())), true),
    };
    let data = dir.join("dataset");
    let sargs = SynthArgs {
        out: data.clone(),
        seed: a.seed,
        places: a.places,
        size: a.size,
        reference: Condition::Day,
        queries: vec![],
        aliasing: 0.6,
        from_camvid: None,
        stream_from: None,
        speed_min: 0.6,
        speed_max: 1.4,
        stops: 2,
        stop_frames: 20,
        changes: vec![],
        step: 1,
        evaluate: false,
        models: a.models.clone(),
    };
    let scfg = synth_config(&sargs);
    info(
        quiet,
        format!(
            "[1/4] rendering the synthetic benchmark: {} places x {} traversals at {}x{} (seed {})",
            scfg.places,
            1 + scfg.queries.len(),
            scfg.width,
            scfg.height,
            scfg.seed
        ),
    );
    synth_cmd(&sargs, quiet)?;
    let map_dir = dir.join("map");
    let _ = std::fs::remove_dir_all(&map_dir);
    info(quiet, "[2/4] building the map from the reference traversal");
    let src = SourceArgs {
        dataset: Some(data.clone()),
        traversal: None,
        images: None,
        labels: None,
        label_format: None,
        skip_invalid: false,
        models: a.models.clone(),
    };
    map_cmd::build(engine, &src, &map_dir, None, &map_cmd::BuildFlags { hog: true, ..Default::default() }, quiet)?;
    let map = Map::open(&map_dir)?;
    let cfg = map_config(&map, None, &a.models)?;
    let hardest = scfg.queries.last().ok_or_else(|| Error::invalid("demo", "no query condition"))?.name();
    info(quiet, format!("[3/4] querying the map with the {hardest} traversal (setting {})", Setting::RECOMMENDED));
    let qsrc = SourceArgs { traversal: Some(hardest.to_string()), ..src };
    let (frames, fmt) = query_frames(&qsrc, &cfg)?;
    let (queries, matches, run) = run_query(engine, &map, &cfg, (&frames, fmt), &qsrc, Setting::RECOMMENDED, quiet)?;
    let (csv, json) = query_outputs(&map, &queries, &matches, &run, Setting::RECOMMENDED)?;
    let results = dir.join("results");
    std::fs::create_dir_all(&results).map_err(|e| Error::io(&results, e))?;
    write_file(&results.join(format!("query-{hardest}.csv")), &csv)?;
    write_file(&results.join(format!("query-{hardest}.json")), &json)?;
    info(quiet, "[4/4] evaluating every setting on every query traversal");
    let ds = Dataset::open(&data, &DatasetOptions::default())?;
    let report = evaluate(
        &ds,
        &cfg,
        &EvalOptions { settings: Setting::ALL.to_vec(), map: Some(&map), skip_invalid: false, quiet, sequence: false, label_cache: None },
        engine,
    )?;
    write_file(&results.join("eval.json"), &to_json(&report)?)?;
    print_report(&report, a.json)?;
    if !a.json {
        outln!("{}", report.summary_table());
    }
    if temporary {
        let _ = std::fs::remove_dir_all(&dir);
    } else {
        info(quiet, format!("dataset, map and results kept in {}", dir.display()));
    }
    info(quiet, format!("demo finished in {:.1} s", t0.elapsed().as_secs_f64()));
    Ok(())
}

fn inspect_cmd(a: &InspectArgs, quiet: bool) -> Result<()> {
    let cfg = apply_models(load_config(a.config.as_deref())?, &a.models);
    let encoder = Encoder::new(&cfg)?;
    let id = a.image.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let src = FrameSource { id, image: Some(a.image.clone()), labels: a.labels.clone() };
    let panels = semlook::tools::viz::inspect(&encoder, &src, a.label_format.unwrap_or_default())?;
    let files = semlook::tools::viz::write_panels(&panels, &a.out)?;
    for f in &files {
        info(quiet, format!("wrote {}", f.display()));
    }
    Ok(())
}

fn models_cmd(json: bool) -> Result<()> {
    let all = semlook::models::installed();
    if json {
        outln!("{}", to_json(&all)?);
        return Ok(());
    }
    // one aligned row per file (status, name, where or what), details indented below
    let width = all.iter().map(|m| m.name.len()).max().unwrap_or(0);
    let (mut missing, mut absent) = (0, 0);
    for m in &all {
        match (&m.path, &m.sha256) {
            (Some(p), Some(sha)) => {
                outln!("ok       {:width$}  {}", m.name, p.display());
                let note = if m.pinned == Some(true) { "" } else { "  (not the file setup.sh installs: another build, untested)" };
                outln!("         {:width$}  {} bytes, sha256 {sha}{note}", "", m.bytes.unwrap_or(0));
            }
            _ => {
                if m.optional {
                    absent += 1;
                } else {
                    missing += 1;
                }
                outln!("{} {:width$}  {}", if m.optional { "absent  " } else { "MISSING " }, m.name, m.role);
                outln!("         {:width$}  comes from: {}", "", m.source);
            }
        }
    }
    let dirs: Vec<String> = semlook::nn::onnx::model_dirs().iter().map(|d| d.display().to_string()).collect();
    outln!("looked in, in order: {}", dirs.join(", "));
    if missing + absent > 0 {
        outln!(
            "to install what is missing: `bash setup.sh` in the repository (or put the files in a folder and set {}){}",
            semlook::nn::onnx::MODELS_ENV,
            if all.iter().any(|m| m.name == semlook::segmentation::DEFAULT_SEGMENTER && m.path.is_none()) {
                "; without the segmenter, photos that have no label maps are encoded without labels (settings hog, appearance, verified)"
            } else {
                ""
            }
        );
    }
    Ok(())
}
