//! The developer commands (`semlook dev ...`): benchmarks, sweeps and the segmenter's accuracy.

use super::map_cmd;
use super::shared::{apply_models, info, load_config, to_json, write_file};
use crate::cli::args::*;
use semlook::batch::encode_frames;
use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions};
use semlook::encode::Encoder;
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::gpu::GpuOptions;
use semlook::input::{FrameSource, LabelFormat};
use semlook::matching::Setting;
use semlook::progress;
use semlook_cli::tools::synth::condition::Condition;
use std::path::Path;
use std::time::Instant;

/// Runs one `semlook dev` command; `engine` makes the engine for those that encode.
pub fn run(cmd: DevCommand, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    match cmd {
        DevCommand::Bench(a) => bench_cmd(&a, quiet),
        DevCommand::BenchEncode(a) => bench_encode_cmd(&a, &mut engine()?, quiet),
        DevCommand::MapBench(a) => map_cmd::bench(&a, quiet),
        DevCommand::Tune(a) => tune_cmd(&a, &mut engine()?, quiet),
        DevCommand::BenchStream(a) => bench_stream_cmd(&a, engine, quiet),
        DevCommand::BenchPipe(a) => bench_pipe_cmd(&a, engine, quiet),
        DevCommand::IndexBench(a) => index_bench_cmd(&a, &mut engine()?, quiet),
        DevCommand::SegmenterAccuracy(a) => segacc_cmd(&a, quiet),
        DevCommand::Downscale(a) => downscale_cmd(&a, quiet),
    }
}

/// `semlook dev downscale`: every image of ref/ and query/ resized to the size asked for (a
/// triangle filter whose support grows with the reduction: an average over each output pixel's
/// footprint), written as PNG, and the ground truth with the new names.
fn downscale_cmd(a: &DownscaleArgs, quiet: bool) -> Result<()> {
    let bad = |reason: String| Error::invalid("--size", reason);
    let (w, h) = a.size.split_once('x').ok_or_else(|| bad(format!("{:?}: expected WxH, e.g. 64x32", a.size)))?;
    let (w, h): (u32, u32) = (w.parse().map_err(|_| bad(format!("width {w:?}")))?, h.parse().map_err(|_| bad(format!("height {h:?}")))?);
    if w == 0 || h == 0 {
        return Err(bad("a side of 0".into()));
    }
    let gt_in = a.dataset.join("ground_truth.csv");
    let gt = std::fs::read_to_string(&gt_in).map_err(|e| Error::io(&gt_in, e))?;
    super::shared::check_output_dir(&a.out, "--out")?;
    let png = |rel: &str| Path::new(rel).with_extension("png").to_string_lossy().into_owned();
    let mut n = 0;
    for sub in ["ref", "query"] {
        let dir = a.out.join(sub);
        std::fs::create_dir_all(&dir).map_err(|e| Error::io(&dir, e))?;
        for img in semlook::dataset::image_files(&a.dataset.join(sub))? {
            let rgb = semlook::input::load_rgb(&img)?;
            let small = image::imageops::resize(&rgb, w, h, image::imageops::FilterType::Triangle);
            let name = img.file_name().map(|f| png(&f.to_string_lossy())).unwrap_or_default();
            let out = dir.join(name);
            small.save(&out).map_err(|e| Error::invalid(out.display().to_string(), e.to_string()))?;
            n += 1;
        }
    }
    let mut text = String::new();
    for (i, line) in gt.lines().enumerate() {
        match (i, line.split_once(',')) {
            (0, _) | (_, None) => text += line,
            (_, Some((q, r))) => text += &format!("{},{}", png(q.trim()), png(r.trim())),
        }
        text.push('\n');
    }
    write_file(&a.out.join("ground_truth.csv"), &text)?;
    info(quiet, format!("{n} images at {w}x{h} -> {}", a.out.display()));
    Ok(())
}

/// Two timed phases: the segmenter on every frame (labels written at full size to a temporary
/// folder), then encoding of the frames with those label maps: everything but segmentation.
fn bench_encode_cmd(a: &BenchEncodeArgs, engine: &mut Engine, quiet: bool) -> Result<()> {
    use semlook::encode::StageTimes;
    let cfg = apply_models(load_config(a.config.as_deref())?, &a.models);
    let images: Vec<_> = semlook::dataset::image_files(&a.images)?.into_iter().take(a.frames).collect();
    if images.is_empty() {
        return Err(Error::invalid(a.images.display().to_string(), "no images"));
    }
    let sources: Vec<FrameSource> =
        images.iter().map(|p| FrameSource { id: p.display().to_string(), image: Some(p.clone()), labels: None }).collect();
    let mut encoder = Encoder::new(&cfg)?;
    semlook::batch::train_codebook(&mut encoder, &sources, quiet)?;
    // phase 1: segmentation alone, frames in parallel, label maps at the image size
    let tmp = std::env::temp_dir().join(format!("semlook-bench-encode-{}", std::process::id()));
    std::fs::create_dir_all(&tmp).map_err(|e| Error::io(&tmp, e))?;
    let t = Instant::now();
    let pb = progress::bar(sources.len(), "segmenting", quiet);
    let seg_times: Vec<Result<(f64, std::path::PathBuf)>> = {
        use rayon::prelude::*;
        sources
            .par_iter()
            .enumerate()
            .map(|(i, s)| {
                let path = s.image.clone().unwrap_or_default();
                let rgb = semlook::input::load_rgb(&path)?;
                let seg = encoder.frames().segmenter_for(&path)?;
                let t = Instant::now();
                let labels = seg.segment(&rgb, &path)?;
                let ms = t.elapsed().as_secs_f64() * 1e3;
                let out = tmp.join(format!("{i:06}.png"));
                let ids = image::GrayImage::from_fn(labels.width(), labels.height(), |x, y| image::Luma([labels.get(x, y)]));
                ids.save(&out).map_err(|e| Error::invalid(out.display().to_string(), e.to_string()))?;
                pb.inc(1);
                Ok((ms, out))
            })
            .collect()
    };
    pb.finish_and_clear();
    let seg_wall = t.elapsed().as_secs_f64() * 1e3 / sources.len() as f64;
    let mut labelled = Vec::new();
    let mut seg_ms = Vec::new();
    for (s, r) in sources.iter().zip(seg_times) {
        let (ms, path) = r?;
        seg_ms.push(StageTimes { segment_ms: ms, ..Default::default() });
        labelled.push(FrameSource { labels: Some(path), ..s.clone() });
    }
    // phase 2: everything else, with those label maps (train ids: the default class table's)
    let enc = encode_frames(engine, &encoder, &labelled, LabelFormat::Auto, "encoding", false, quiet)?;
    let _ = std::fs::remove_dir_all(&tmp);
    let summary = enc.summary();
    let seg = semlook::batch::EncodingSummary::new(&seg_ms, seg_wall * sources.len() as f64);
    let size = semlook::input::image_size(&images[0])?;
    if a.json {
        outln!(
            "{}",
            to_json(
                &serde_json::json!({ "frames": sources.len(), "image_size": size, "backend": engine.describe(), "segmentation": seg, "everything_else": summary })
            )?
        );
    } else {
        let (m, md) = (summary.mean, summary.median);
        outln!("{} frames of {}x{}; backend {}", sources.len(), size.0, size.1, engine.describe());
        outln!(
            "segmentation ({}): median {:.1} ms per frame, wall clock {:.1} ms per frame (frames in parallel)",
            encoder.frames().segmenter().map_or("-".into(), |s| s.path().display().to_string()),
            seg.median.segment_ms,
            seg.wall_ms_per_frame
        );
        outln!("everything but segmentation: wall clock {:.1} ms per frame (frames in parallel)", summary.wall_ms_per_frame);
        outln!("  per frame, median (mean): decode+resize {:.1} ({:.1}) | edges+EDT+pool {:.1} ({:.1}) | objects+forest {:.1} ({:.1}) | appearance {:.1} ({:.1}), of which network {:.1} ({:.1}) | embedding {:.1} ({:.1}) | sum {:.1} ({:.1})",
            md.decode_ms, m.decode_ms, md.global_ms, m.global_ms, md.forest_ms, m.forest_ms, md.appearance_ms, m.appearance_ms, md.network_ms, m.network_ms, md.embedding_ms, m.embedding_ms, md.without_segmentation_ms(), m.without_segmentation_ms());
    }
    Ok(())
}

fn segacc_cmd(a: &SegAccArgs, quiet: bool) -> Result<()> {
    let base = if a.camvid { Config::camvid() } else { load_config(a.config.as_deref())? };
    let cfg = apply_models(base, &a.models);
    let encoder = Encoder::new(&cfg)?;
    let table = encoder.class_table().clone();
    let images = semlook::dataset::image_files(&a.images)?;
    if images.is_empty() {
        return Err(Error::invalid(a.images.display().to_string(), "no images"));
    }
    let pb = progress::bar(images.len(), "segmenting", quiet);
    let mut confusion = semlook::eval::segmenter::Confusion::new(table.len());
    for img in &images {
        let stem = img.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
        let real = semlook::input::load_label_map(&a.labels.join(format!("{stem}.png")), &table, LabelFormat::Auto)?;
        let rgb = semlook::input::load_rgb(img)?;
        let seg = encoder.frames().segmenter_for(img)?;
        let predicted = seg.segment(&rgb, img)?;
        confusion.add(&real, &predicted)?;
        pb.inc(1);
    }
    pb.finish_and_clear();
    let r = confusion.report(&table);
    if a.json {
        outln!("{}", to_json(&r)?);
    } else {
        out!("{} images\n{}", images.len(), r.to_table());
    }
    Ok(())
}

fn tune_cmd(a: &TuneArgs, engine: &mut Engine, quiet: bool) -> Result<()> {
    let base = apply_models(load_config(a.config.as_deref())?, &a.models);
    let text = std::fs::read_to_string(&a.sweep).map_err(|e| Error::io(&a.sweep, e))?;
    let sweep = semlook_cli::tools::tune::Sweep::parse(&text, &a.sweep.display().to_string(), &base)?;
    let mut datasets: Vec<Dataset> = a.datasets.iter().map(|d| Dataset::open(d, &DatasetOptions::default())).collect::<Result<_>>()?;
    for d in &a.segmented {
        let mut ds = Dataset::open(d, &DatasetOptions::default())?.without_labels();
        ds.name += " (segmented)";
        datasets.push(ds);
    }
    let settings = if a.settings.is_empty() { vec![Setting::Semlook, Setting::Local, Setting::Forest, Setting::Global] } else { a.settings.clone() };
    let n = sweep.combinations().len();
    info(quiet, format!("{n} configurations x {} datasets", datasets.len()));
    let pb = progress::bar(0, "frames", quiet);
    let opts = semlook_cli::tools::tune::TuneOptions {
        sequence: a.sequence,
        candidates: a.candidates.clone(),
        label_cache: a.label_cache.clone(),
        null_evidence: a.null_evidence,
    };
    let rows = semlook_cli::tools::tune::run(&datasets, &sweep, &settings, &opts, engine, &|| pb.inc(1), &mut |ds, row| {
        let vals: Vec<String> = row.values.iter().map(|(k, v)| format!("{k}={v}")).collect();
        let r: Vec<String> = row.results.iter().filter(|r| r.0 == ds).map(|r| format!("{} {:.3}", r.1, r.2)).collect();
        pb.suspend(|| info(quiet, format!("{ds}: {} -> R@1 {}", vals.join(" "), r.join(", "))));
    })?;
    pb.finish_and_clear();
    let table = semlook_cli::tools::tune::table(&rows);
    if let Some(file) = &a.table {
        write_file(file, &table)?;
    }
    out!("{table}");
    if a.cross_validate {
        let cv = semlook_cli::tools::tune::cross_validation_table(&rows, &semlook_cli::tools::tune::cross_validate(&rows));
        if let Some(file) = &a.table {
            write_file(&file.with_extension("cv.tsv"), &cv)?;
        }
        out!("\nleave-one-set-out cross-validation (each set's R@1 with the row chosen on the others):\n{cv}");
    }
    Ok(())
}

fn index_bench_cmd(a: &IndexBenchArgs, engine: &mut Engine, quiet: bool) -> Result<()> {
    use semlook_cli::tools::bench_index::{run, table, IndexBenchOptions};
    let cfg = load_config(a.config.as_deref())?;
    let files = semlook::dataset::image_files(&a.queries)?;
    if files.is_empty() {
        return Err(Error::invalid(a.queries.display().to_string(), "no images (png, jpg) in this folder"));
    }
    let queries = files
        .into_iter()
        .map(|p| FrameSource { id: p.file_stem().unwrap_or_default().to_string_lossy().into_owned(), image: Some(p), labels: None })
        .collect();
    let opts = IndexBenchOptions {
        from: a.from.clone(),
        queries,
        sizes: a.sizes.clone(),
        exact_queries: a.exact_queries,
        batch: a.batch.max(1),
        searches: a.search.clone(),
        exact_timed: a.exact_timed,
        dir: a.out.dir.clone().unwrap_or_else(std::env::temp_dir),
        keep: a.out.keep,
        quiet,
    };
    let json = a.out.json;
    let rows = run(&cfg, &opts, engine, &mut |r| {
        if json {
            let _ = writeln_row(r);
        } else {
            info(quiet, format!("{} references done", r.map_size));
        }
    })?;
    if !json {
        out!("{}", table(&rows));
    }
    Ok(())
}

fn bench_stream_cmd(a: &BenchStreamArgs, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    use semlook_cli::tools::bench_stream::{run, table, StreamBenchOptions};
    let cfg = apply_models(load_config(a.config.as_deref())?, &a.models);
    let frames = |dir: &Path| -> Result<Vec<FrameSource>> {
        let files = semlook::dataset::image_files(dir)?;
        if files.is_empty() {
            return Err(Error::invalid(dir.display().to_string(), "no images (png, jpg) in this folder"));
        }
        Ok(files
            .into_iter()
            .map(|p| FrameSource { id: p.file_stem().unwrap_or_default().to_string_lossy().into_owned(), image: Some(p), labels: None })
            .collect())
    };
    let mut distractors = Vec::new();
    for (k, d) in a.distractors.iter().enumerate() {
        distractors.extend(frames(d)?.into_iter().map(|mut f| {
            f.id = format!("{k}/{}", f.id);
            f
        }));
    }
    let opts = StreamBenchOptions {
        references: frames(&a.references)?,
        stream: frames(&a.stream)?,
        distractors,
        sizes: a.sizes.clone(),
        frames: a.frames,
        setting: a.setting,
        sequence: !a.no_sequence,
        dir: a.out.dir.clone().unwrap_or_else(std::env::temp_dir),
        keep: a.out.keep,
        quiet,
    };
    let json = a.out.json;
    let rows = run(&cfg, &opts, engine, &mut |r| {
        if json {
            let _ = writeln_row(r);
        } else {
            info(quiet, format!("{} places: {:.2} frames/s, p50 {:.1} ms, p99 {:.1} ms", r.map_size, r.frames_per_s, r.p50.total_ms, r.p99.total_ms));
        }
    })?;
    if !json {
        out!("{}", table(&rows));
    }
    Ok(())
}

fn bench_pipe_cmd(a: &BenchPipeArgs, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    use semlook_cli::tools::bench_stream::{pipe_table, pipe_vs_folder};
    let map = semlook::map::Map::open(&a.map)?;
    let cfg = super::shared::map_config(&map, a.config.as_deref(), &a.models)?;
    drop(map);
    let opts = semlook::stream::StreamOptions { setting: a.setting, ..Default::default() };
    info(quiet, format!("{} against {}: from the folder, then piped", a.images.display(), a.map.display()));
    let (rows, differ) = pipe_vs_folder(&a.map, &a.images, Some(cfg), opts, engine)?;
    if a.json {
        for r in &rows {
            writeln_row(r)?;
        }
    } else {
        out!("{}", pipe_table(&rows));
    }
    match differ {
        None => {
            info(quiet, "the answers are equal frame for frame");
            Ok(())
        }
        Some(d) => Err(Error::invalid("bench-pipe", format!("the piped frames were answered otherwise: {d}"))),
    }
}

fn writeln_row(r: &impl serde::Serialize) -> Result<()> {
    outln!("{}", serde_json::to_string(r).map_err(|e| Error::invalid("JSON output", e.to_string()))?);
    Ok(())
}

fn bench_cmd(a: &BenchArgs, quiet: bool) -> Result<()> {
    let cfg = Config::default();
    let opts = semlook_cli::tools::bench::BenchOptions {
        sizes: a.sizes.clone(),
        batches: a.batches.clone(),
        max_row_seconds: a.max_row_seconds,
        resident_limit: semlook_cli::tools::bench::RESIDENT_LIMIT,
        gpu_peak_gflops: a.peak_gflops,
    };
    opts.validate()?;
    info(quiet, "rendering and encoding the descriptor pools (64 map frames, 32 query frames)");
    let pool = semlook_cli::tools::bench::street_descriptors(&cfg, 64, Condition::Day, 0)?;
    let queries = semlook_cli::tools::bench::street_descriptors(&cfg, 32, Condition::Night, 5)?;
    let mut engines = vec![Engine::cpu()];
    if !a.cpu_only {
        let gopts = GpuOptions {
            resident_budget: a.resident_budget_mib.map(|m| m << 20),
            max_binding_size: a.max_binding_mib.map(|m| m << 20),
            ..Default::default()
        };
        match Engine::new(semlook::engine::Backend::Gpu, &gopts) {
            Ok((e, _)) => engines.push(e),
            Err(e) => info(quiet, format!("no GPU run: {e}")),
        }
    }
    for e in &engines {
        info(quiet, format!("backend: {}", e.describe()));
    }
    let mut shown = false;
    // the first failed write of a row (a closed pipe), returned once the run is over
    let mut write_err: Option<Error> = None;
    let rows = semlook_cli::tools::bench::run(&pool, &queries, &opts, &mut engines, &cfg, &mut |r| {
        if a.json {
            match serde_json::to_string(r) {
                Ok(line) => {
                    if write_err.is_none() {
                        write_err = crate::cli::output::write_out(format_args!("{line}\n")).err();
                    }
                }
                Err(e) => log::error!("bench row: {e}"),
            }
        } else if !quiet {
            let t = semlook_cli::tools::bench::table(std::slice::from_ref(r));
            eprint!("{}", if shown { t.lines().nth(1).unwrap_or("").to_string() + "\n" } else { t });
            shown = true;
        }
    })?;
    if let Some(e) = write_err {
        return Err(e);
    }
    if !a.json {
        out!("{}{}", semlook_cli::tools::bench::table(&rows), semlook_cli::tools::bench::legend(&rows));
    }
    Ok(())
}
