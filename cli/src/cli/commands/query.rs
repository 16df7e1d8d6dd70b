//! `query`: frames matched against a map, the results as CSV and JSON.

use super::*;

pub(super) fn encode_sources(
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
pub(super) fn query_outputs(
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
pub(super) fn query_frames(s: &SourceArgs, cfg: &Config) -> Result<(Vec<FrameSource>, LabelFormat)> {
    frame_sources(s, &mut cfg.clone(), true)
}

pub(super) fn run_query(
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

pub(super) fn query(engine: &mut Engine, a: &QueryArgs, quiet: bool) -> Result<()> {
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
