//! `eval`: a dataset's queries against its references (or a map), the report and its sheets.

use super::*;

/// The dataset an `eval` names: a dataset directory, or a reference and a query folder.
pub(super) fn eval_dataset(a: &EvalArgs) -> Result<Dataset> {
    let opts = DatasetOptions { reference: a.reference.clone(), queries: a.queries.clone(), max_distance: a.gt_distance, max_angle_deg: a.gt_angle };
    Dataset::open_any(a.dataset.as_deref(), a.references.as_deref(), a.queries_dir.as_deref(), a.ground_truth.as_deref(), &opts)
}

pub(super) fn eval_cmd(engine: &mut Engine, a: &EvalArgs, quiet: bool) -> Result<()> {
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
        for f in semlook_cli::tools::viz::plots::write_pr_plots(&report, dir)? {
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
        for f in semlook_cli::tools::viz::explain(&report, setting, &ds, &encoder, n, dir)? {
            info(quiet, format!("wrote {}", f.display()));
        }
    }
    if let Some(dir) = &a.report {
        use semlook_cli::tools::viz::report::{ReportInputs, WorstQuery};
        let worst = semlook_cli::tools::viz::worst_queries(&report, setting)
            .into_iter()
            .take(a.explain.unwrap_or(REPORT_WORST))
            .map(|w| {
                // a frame that cannot be drawn costs its sheet, not the page
                let sheet = semlook_cli::tools::viz::worst_sheet(w, setting, &ds, &encoder, 320);
                WorstQuery { query_set: w.0, outcome: w.1, sheet }
            })
            .collect();
        let inputs = ReportInputs { setting, worst, command: command_line() };
        info(quiet, format!("wrote {}", semlook_cli::tools::viz::report::write(&report, &inputs, dir)?.display()));
    }
    Ok(())
}

/// The info lines on which coarse search each setting of `report` ran (`coarse search: ...`),
/// settings that ran the same one on one line (named where the lines differ).
pub(super) fn eval_coarse_searches(report: &EvalReport, map: Option<&Map>, cfg: &Config) -> Vec<String> {
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
pub(super) fn dedup(settings: &[Setting]) -> Vec<Setting> {
    let mut out: Vec<Setting> = Vec::new();
    for s in settings {
        if !out.contains(s) {
            out.push(*s);
        }
    }
    out
}

/// Worst queries shown by `eval --report` without `--explain N`.
pub(super) const REPORT_WORST: usize = 6;

/// The command as typed (arguments with spaces quoted), for the report's record of what ran.
pub(super) fn command_line() -> String {
    let args = std::env::args().skip(1).map(|a| if a.contains(char::is_whitespace) || a.is_empty() { format!("{a:?}") } else { a });
    std::iter::once("semlook".to_string()).chain(args).collect::<Vec<_>>().join(" ")
}

pub(super) fn print_report(report: &EvalReport, json: bool) -> Result<()> {
    if json {
        outln!("{}", to_json(report)?);
    } else {
        out!("{}", report.to_table());
    }
    Ok(())
}
