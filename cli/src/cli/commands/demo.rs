//! `demo`: the synthetic benchmark made, mapped, queried and evaluated in one command.

use super::*;

pub(super) fn demo(a: &DemoArgs, engine: &mut Engine, quiet: bool) -> Result<()> {
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
