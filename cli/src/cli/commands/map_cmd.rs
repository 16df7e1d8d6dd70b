//! The `map` subcommands: build (streamed into segments, `--resume`, `--force`, `--f16`), add,
//! info, remove, compact, verify, and the store benchmark.

use super::shared::{apply_models, encoding_line, frame_sources_posed, info, load_config, map_config, to_json};
use crate::cli::args::{MapCommand, PoseArgs, SourceArgs, StoreArgs, StoreBenchArgs};
use semlook::batch::{self, IntoOptions};
use semlook::config::Config;
use semlook::encode::Encoder;
use semlook::engine::Engine;
use semlook::error::{Error, Result};
use semlook::map::Map;
use semlook::map::{edit, MapWriter, StoreOptions, TraversalPlan};
use semlook::values::ValueType;
use std::path::Path;

pub fn run(cmd: MapCommand, engine: &dyn Fn() -> Result<Engine>, quiet: bool) -> Result<()> {
    match cmd {
        MapCommand::Build { source, map: out, config, force, resume, hog, map_traversal: traversal, index, store, poses } => {
            build(&mut engine()?, &source, &out, config.as_deref(), &BuildFlags { force, resume, hog, traversal, store, poses, index }, quiet)
        }
        MapCommand::Index { map, config, drop, json } => index(&map, config.as_deref(), drop, json, quiet),
        MapCommand::Add { source, map, resume, segment_images, map_traversal, id_prefix, poses } => {
            let plan = match (map_traversal, resume) {
                (Some(name), _) => TraversalPlan::Named(name),
                (None, true) => TraversalPlan::Last,
                (None, false) => TraversalPlan::New,
            };
            let how = AddFlags { resume, segment_images, plan, id_prefix };
            add(&mut engine()?, &source, &poses, &map, how, quiet)
        }
        MapCommand::Info { map, json } => show(&map, json),
        MapCommand::Remove { map, ids } => remove(&map, &ids, quiet),
        MapCommand::Compact { map, json } => compact(&map, json),
        MapCommand::Verify { map, json } => verify(&map, json),
    }
}

/// The switches of `map build`.
#[derive(Clone, Default)]
pub struct BuildFlags {
    pub force: bool,
    pub resume: bool,
    pub hog: bool,
    /// `--map-traversal`: the map's traversal the images make.
    pub traversal: Option<String>,
    pub store: StoreArgs,
    pub poses: PoseArgs,
    pub index: batch::IndexPolicy,
}

fn store_options(f16: bool, segment_images: Option<usize>) -> StoreOptions {
    let d = StoreOptions::default();
    StoreOptions { values: if f16 { ValueType::F16 } else { ValueType::F32 }, segment_images: segment_images.unwrap_or(d.segment_images).max(1), ..d }
}

pub fn build(engine: &mut Engine, s: &SourceArgs, out: &Path, config: Option<&Path>, f: &BuildFlags, quiet: bool) -> Result<()> {
    let mut cfg = apply_models(load_config(config)?, &s.models);
    let (frames, fmt, poses) = frame_sources_posed(s, Some(&f.poses), &mut cfg, config.is_some())?;
    if frames.is_empty() {
        return Err(Error::invalid("references", "no images found"));
    }
    let frame_interval = f.poses.timestamps.as_ref().map(|t| semlook::stream::input::median_interval(t, &frames)).transpose()?;
    let new = batch::NewMapOptions {
        hog: f.hog,
        store: store_options(f.store.f16, f.store.segment_images),
        traversal: f.traversal.clone(),
        skip_invalid: s.skip_invalid,
        resume: f.resume,
        quiet,
    };
    let opts = batch::BuildOptions { new, index: f.index, frame_interval };
    // the library's job (`batch::build_map`, Python's `Map.build` too); what it does, said here
    let step = |s: batch::BuildStep<'_>| match s {
        batch::BuildStep::Resuming { images, generation } => {
            info(quiet, format!("resuming: the map holds {images} images (generation {generation})"))
        }
        batch::BuildStep::Encoded(r) => report_encoding(r, quiet),
        batch::BuildStep::BuildingIndex { images } => info(quiet, format!("building the index of {images} images")),
        batch::BuildStep::Indexed(ix) => info(quiet, describe_index(&ix.entry, &cfg.global)),
        batch::BuildStep::NullStored(n, ms) => report_null(n, ms, quiet),
    };
    let job = |engine: &mut Engine, dir: &Path| batch::build_map(engine, &cfg, &frames, fmt, Some(&poses), dir, &opts, &step);
    let map = if f.force && out.exists() {
        edit::build_replacing(out, |dir| job(engine, dir))?;
        Map::open(out)?
    } else {
        job(engine, out)?
    };
    info(
        quiet,
        format!(
            "map {}: {} images, {} trees, {} segments ({})",
            out.display(),
            map.len(),
            map.n_trees(),
            map.manifest.segments.len(),
            map.manifest.values.name()
        ),
    );
    Ok(())
}

/// `map add`: measures the null of `verified`'s evidence under `cfg` and stores it in the
/// manifest where the config tests evidence against one ([`Engine::store_null`]; `map build`'s
/// is the library's job, `batch::build_map`); says what it found and what it cost.
fn with_null(engine: &mut Engine, map: Map, cfg: &Config, quiet: bool) -> Result<Map> {
    let (map, stored) = engine.store_null(map, cfg)?;
    if let Some((n, ms)) = &stored {
        report_null(n, *ms, quiet);
    }
    Ok(map)
}

/// What the null of `verified`'s evidence a build or an add stored holds, and what it cost.
fn report_null(n: &semlook::matching::null::NullEvidence, ms: f64, quiet: bool) {
    info(
        quiet,
        format!(
            "null of verified's evidence: {} pairs of other places verified from {} references (median {} inliers, 99th percentile {}){}, {:.1} s, stored in the manifest",
            n.pairs,
            n.sources,
            n.inliers_quantile(0.5),
            n.inliers_quantile(0.99),
            match n.compact_hog.len() {
                0 => String::new(),
                h => format!("; compact HOGs of {h} of those pairs and of {} same-place pairs", n.compact_hog_near.len()),
            },
            ms / 1000.0
        ),
    );
}

/// One line on an index: how it was built and what it measured.
fn describe_index(ix: &semlook::map::manifest::IndexEntry, global: &semlook::config::GlobalConfig) -> String {
    let t = ix.thumb(global);
    let thumbs = match t.dims() {
        (0, _) => "no thumbnails (the shortlist follows the appearance codes alone; `semlook map index` rebuilds with them)".to_string(),
        (w, h) => format!("thumbnails {w}x{h} (global descriptors pooled by {}, {} bytes a reference)", t.pool, t.len()),
    };
    format!(
        "index: IVF over {} dimensions, {} lists, {thumbs}, trained on {} images (sample {}, {} iterations, seed {}); recall@30 {:.3} ({} of {}) with {} and a shortlist of {}, against the exact appearance ranking; built in {:.1} s",
        ix.dims,
        ix.lists,
        ix.trained_on,
        ix.params.sample,
        ix.params.iterations,
        ix.params.seed,
        ix.recall(),
        ix.recall_hits,
        ix.recall_of,
        lists_probed(ix.recall_probe, ix.lists),
        ix.recall_shortlist,
        ix.build_ms as f64 / 1000.0
    )
}

/// How many of an index's `lists` a search asking for `probe` scans, in words: never more than
/// the index has (`index.probe` 112 of an index of 10 lists scans all 10).
pub fn lists_probed(probe: usize, lists: usize) -> String {
    match probe.max(1) {
        p if p >= lists => format!("all {lists} lists probed"),
        p => format!("{p} of {lists} lists probed"),
    }
}

/// `map index`: build (or rebuild) or drop a map's index.
fn index(dir: &Path, config: Option<&Path>, drop: bool, json: bool, quiet: bool) -> Result<()> {
    if drop {
        let dropped = semlook::map::index::drop_index(dir)?;
        info(quiet, if dropped { format!("map {}: index dropped", dir.display()) } else { format!("map {}: had no index", dir.display()) });
        return Ok(());
    }
    let cfg = load_config(config)?;
    let n = Map::open(dir)?.len();
    let r = semlook::map::index::build(dir, &semlook::index::IndexParams::from_config(&cfg.index, n), cfg.index.probe, cfg.index.shortlist)?;
    if json {
        outln!("{}", to_json(&r.entry)?);
    } else {
        let global = semlook::map::manifest::read_existing(dir)?.config.global;
        outln!("map {}: {} ({} segments)", dir.display(), describe_index(&r.entry, &global), r.segments);
    }
    Ok(())
}

/// The settings a map without labels serves (`hog` only when it stores HOG descriptors).
fn label_free_settings(hog: bool) -> String {
    semlook::matching::Setting::served_without_labels(hog).map(|s| s.name()).collect::<Vec<_>>().join(", ")
}

fn report_encoding(r: &batch::IntoReport, quiet: bool) {
    let stored = if r.already_stored > 0 { format!(", {} already stored", r.already_stored) } else { String::new() };
    info(quiet, encoding_line(&format!("{} images{stored}", r.added), &r.summary.mean));
    if !r.invalid.is_empty() {
        info(quiet, format!("skipped {} invalid frames", r.invalid.len()));
    }
}

/// The switches of `map add`.
struct AddFlags {
    resume: bool,
    segment_images: Option<usize>,
    plan: TraversalPlan,
    /// `--id-prefix`: put before every new image's id.
    id_prefix: Option<String>,
}

fn add(engine: &mut Engine, s: &SourceArgs, p: &PoseArgs, dir: &Path, f: AddFlags, quiet: bool) -> Result<()> {
    let AddFlags { resume, segment_images, plan, id_prefix } = f;
    let map = Map::open(dir)?;
    let mut cfg = map_config(&map, None, &s.models)?;
    let (mut frames, fmt, mut poses) = frame_sources_posed(s, Some(p), &mut cfg, true)?;
    if frames.is_empty() {
        return Err(Error::invalid("new images", "no images found"));
    }
    if let Some(prefix) = &id_prefix {
        // the poses follow their images' new ids
        poses = poses.into_iter().map(|(id, pose)| (format!("{prefix}{id}"), pose)).collect();
        for f in &mut frames {
            f.id = format!("{prefix}{}", f.id);
        }
    }
    let encoder = Encoder::for_map(&cfg, &map)?.with_hog(map.manifest.hog_dim > 0);
    drop(map);
    let mut writer = MapWriter::append(dir, store_options(false, segment_images))?.with_traversal(plan)?;
    if let Some(t) = &p.timestamps {
        writer = writer.with_frame_interval(semlook::stream::input::median_interval(t, &frames)?)?;
    }
    let into = IntoOptions { skip_invalid: s.skip_invalid, skip_stored: resume, quiet, poses: Some(&poses) };
    let r = batch::encode_into(engine, &encoder, &frames, fmt, &mut writer, into)?;
    report_encoding(&r, quiet);
    // the add may have taken the map past the size its stored null stands for
    let map = with_null(engine, writer.finish()?, &cfg, quiet)?;
    info(
        quiet,
        format!(
            "map {}: now {} images in {} segments (generation {})",
            dir.display(),
            map.len(),
            map.manifest.segments.len(),
            map.manifest.generation
        ),
    );
    Ok(())
}

fn show(dir: &Path, json: bool) -> Result<()> {
    let map = Map::open(dir)?;
    let m = &map.manifest;
    let bytes: u64 = m.segments.iter().map(|s| s.bytes).sum();
    let removed = m.stored_images() - m.live_images();
    // bytes per stored image, by column, summed over the segments
    let mut columns: Vec<(&str, usize)> = Vec::new();
    for seg in map.segments() {
        for (name, b) in seg.column_bytes() {
            match columns.iter_mut().find(|c| c.0 == name) {
                Some(c) => c.1 += b,
                None => columns.push((name, b)),
            }
        }
    }
    let per = |b: usize| b as f64 / m.stored_images().max(1) as f64;
    let poses = map.pose_counts();
    let by_column: serde_json::Map<String, serde_json::Value> =
        columns.iter().map(|&(n, b)| (n.to_string(), serde_json::json!(per(b).round() as u64))).collect();
    if json {
        let v = serde_json::json!({
            "path": dir,
            "images": map.len(),
            "removed": removed,
            "trees": map.n_trees(),
            "generation": m.generation,
            "values": m.values,
            "bytes": bytes,
            "bytes_per_reference": { "total": per(bytes as usize).round() as u64, "by_column": by_column },
            "segments": m.segments,
            "appearance_dim": m.appearance_dim,
            "hog_dim": m.hog_dim,
            "labels": !m.without_labels,
            "traversals": traversals(&map),
            "poses": { "images": poses.0, "with_orientation": poses.1 },
            "index": m.index,
            "embedding": m.embedding,
            "frame_intervals": m.frame_intervals,
            "null": m.null.as_ref().map(|n| serde_json::json!({
                "images": n.images, "sources": n.evidence.sources, "pairs": n.evidence.pairs,
                "median_inliers": n.evidence.inliers_quantile(0.5), "p99_inliers": n.evidence.inliers_quantile(0.99),
                "compact_hog": n.evidence.compact_hog.len(), "compact_hog_near": n.evidence.compact_hog_near.len(),
            })),
            "config": m.config,
            "profile": m.profile,
        });
        outln!("{}", to_json(&v)?);
    } else {
        outln!(
            "map {}: {} images ({removed} removed, not compacted), {} trees, {} segments, {bytes} bytes ({:.0} per stored image), values {}, generation {}",
            dir.display(),
            map.len(),
            map.n_trees(),
            m.segments.len(),
            bytes as f64 / m.stored_images().max(1) as f64,
            m.values.name(),
            m.generation
        );
        let cols: Vec<String> = columns.iter().map(|&(n, b)| format!("{n} {:.0}", per(b))).collect();
        outln!("bytes per stored image: {:.0} ({})", per(bytes as usize), cols.join(", "));
        if m.without_labels {
            outln!("built without semantic labels: only the settings that need none ({}) match against it", label_free_settings(m.hog_dim > 0));
        }
        let t: Vec<String> = traversals(&map).iter().map(|t| format!("{} ({} images)", t["name"].as_str().unwrap_or(""), t["images"])).collect();
        outln!("traversals: {}", t.join(", "));
        if poses.0 > 0 {
            outln!("poses: {} of {} images ({} with an orientation)", poses.0, map.len(), poses.1);
        }
        match &m.embedding {
            Some(e) => outln!("embeddings: {} values by {} at {} px long side (sha256 {})", e.dim, e.network, e.long_side, e.sha256),
            None => outln!("embeddings: none (the fused score has no embedding term)"),
        }
        match m.frame_intervals.is_empty() {
            true => outln!("timestamps: none stored (a stream's velocity range cannot follow its camera rate)"),
            false => {
                let t: Vec<String> = m.frame_intervals.iter().map(|(t, s)| format!("traversal {t} every {s:.3} s")).collect();
                outln!("timestamps: {}", t.join(", "))
            }
        }
        match &m.null {
            Some(n) => outln!(
                "null of verified's evidence: measured at {} images, {} pairs of other places from {} references, median {} inliers, 99th percentile {} (queries under the config the map was built with test against it; under another, they measure their own)",
                n.images,
                n.evidence.pairs,
                n.evidence.sources,
                n.evidence.inliers_quantile(0.5),
                n.evidence.inliers_quantile(0.99)
            ),
            None => outln!("null of verified's evidence: none stored (queries measure it on first use)"),
        }
        match &m.profile {
            Some(p) => {
                let d = Config::default();
                let differ: Vec<&str> = [
                    ("similarity", p.similarity != d.similarity),
                    ("matching", p.matching != d.matching),
                    ("verification", p.verification != d.verification),
                    ("sequence", p.sequence != d.sequence),
                    ("stream", p.stream != d.stream),
                    ("index", p.index != d.index),
                ]
                .into_iter()
                .filter_map(|(n, differs)| differs.then_some(n))
                .collect();
                outln!(
                    "profile: built with query sections of its own ([{}] differ from the defaults): queries and streams take them unless given a --config",
                    differ.join("], [")
                )
            }
            None => outln!("profile: none (built with the default query sections: queries and streams follow the defaults)"),
        }
        match &m.index {
            Some(ix) => outln!("{}", describe_index(ix, &m.config.global)),
            None => outln!("index: none (every query scans every reference; `semlook map index` builds one)"),
        }
        for s in &m.segments {
            outln!(
                "  {}  {} images ({} removed)  {} bytes  sha256 {}  traversal {}",
                s.file,
                s.images,
                s.removed.len(),
                s.bytes,
                &s.sha256[..16],
                s.traversal
            );
        }
        outln!("(checksums are checked on first use and by `semlook map verify`)");
        outln!("encoding config:\n{}", toml::to_string_pretty(&m.config).map_err(|e| Error::invalid("map config", e.to_string()))?);
    }
    Ok(())
}

/// The map's traversals: name and live images of each.
fn traversals(map: &Map) -> Vec<serde_json::Value> {
    use semlook::descriptors::source::RefSource;
    semlook::map::manifest::traversal_names(&map.manifest)
        .into_iter()
        .enumerate()
        .map(|(t, name)| serde_json::json!({ "name": name, "images": map.traversal_len(t as u32) }))
        .collect()
}

/// Ids from the command line: one value naming an existing file is read as a list of ids.
fn read_ids(values: &[String]) -> Result<Vec<String>> {
    match values {
        [one] if Path::new(one).is_file() => {
            let text = std::fs::read_to_string(one).map_err(|e| Error::io(one, e))?;
            Ok(text.lines().map(str::trim).filter(|l| !l.is_empty() && !l.starts_with('#')).map(String::from).collect())
        }
        _ => Ok(values.to_vec()),
    }
}

fn remove(dir: &Path, values: &[String], quiet: bool) -> Result<()> {
    let ids = read_ids(values)?;
    if ids.is_empty() {
        return Err(Error::invalid("--ids", "no image ids given"));
    }
    let n = edit::remove(dir, &ids)?;
    info(quiet, format!("map {}: removed {n} images (queries no longer return them; `semlook map compact` frees their space)", dir.display()));
    Ok(())
}

fn compact(dir: &Path, json: bool) -> Result<()> {
    let r = edit::compact(dir, StoreOptions::default())?;
    if json {
        outln!("{}", to_json(&r)?);
    } else {
        outln!(
            "map {}: {} -> {} segments, {} removed images dropped, {} -> {} bytes, {} stray files deleted",
            dir.display(),
            r.segments_before,
            r.segments_after,
            r.dropped,
            r.bytes_before,
            r.bytes_after,
            r.stray_files
        );
    }
    Ok(())
}

fn verify(dir: &Path, json: bool) -> Result<()> {
    let mut r = edit::verify(dir)?;
    let model = check_installed_model(&mut r);
    if let (Some(line), false) = (&model, json) {
        outln!("{line}");
    }
    let embedding = check_installed_embedding(&mut r);
    if let (Some(line), false) = (&embedding, json) {
        outln!("{line}");
    }
    if json {
        outln!("{}", to_json(&r)?);
    } else {
        for f in &r.files {
            match &f.problem {
                None => outln!("ok       {}", f.file),
                Some(p) => outln!("DAMAGED  {}: {p}", f.file),
            }
        }
        for l in &r.leftovers {
            outln!("LEFTOVER {l} (an interrupted writer's; the next add, remove or compact removes it)");
        }
        for f in &r.unreferenced {
            outln!("UNREFERENCED {f} (left by a failed write; `semlook map compact` removes them)");
        }
    }
    let damaged: Vec<&str> = r.damaged().map(|f| f.file.as_str()).collect();
    match damaged.first() {
        None => {
            if !json {
                outln!("map {}: {} files sound, {} images (generation {})", dir.display(), r.files.len(), r.images, r.generation);
            }
            Ok(())
        }
        Some(first) => {
            let problem = r.damaged().next().and_then(|f| f.problem.clone()).unwrap_or_default();
            let others =
                if damaged.len() > 1 { format!(" (and {} more damaged: {})", damaged.len() - 1, damaged[1..].join(", ")) } else { String::new() };
            let reason = format!("{problem}{others}");
            // files of the index alone: building it again or dropping it mends the map
            match r.only_index_damaged() {
                true => Err(Error::DamagedIndex { path: dir.join(first), reason, missing: false }),
                false => Err(Error::corrupt(dir.join(first), reason)),
            }
        }
    }
}

pub fn bench(a: &StoreBenchArgs, quiet: bool) -> Result<()> {
    let cfg = Config::default();
    let opts = semlook_cli::tools::bench_store::StoreBenchOptions {
        sizes: a.sizes.clone(),
        passes: a.passes.clone(),
        values: if a.f16 { ValueType::F16 } else { ValueType::F32 },
        dir: a.out.dir.clone().unwrap_or_else(std::env::temp_dir),
        keep: a.out.keep,
        stats_comparison: a.stats_comparison.clone(),
    };
    info(quiet, "rendering and encoding the descriptor pools (64 map frames, 32 query frames)");
    let report = semlook_cli::tools::bench_store::run(&cfg, &opts, &mut |r| {
        if !quiet && !a.out.json {
            eprint!("{}", semlook_cli::tools::bench_store::table(std::slice::from_ref(r)));
        }
    })?;
    if a.out.json {
        outln!("{}", to_json(&report)?);
    } else {
        out!("{}", semlook_cli::tools::bench_store::table(&report.passes));
        if !report.stats_comparison.is_empty() {
            out!(
                "\nSSIM statistics: stored (in memory) vs recomputed per tile\n{}",
                semlook_cli::tools::bench_store::stats_table(&report.stats_comparison)
            );
        }
    }
    Ok(())
}

/// What a query checks of the embedding network, checked by verify too: the file of the name the
/// map recorded is installed and has its SHA-256. A mismatch is a problem of the manifest (queries
/// would be refused); the line says what was checked.
fn check_installed_embedding(r: &mut edit::VerifyReport) -> Option<String> {
    let rec = r.embedding.clone()?;
    let Ok(path) = semlook::nn::onnx::find_model(&rec.network, None, "embedding network") else {
        return Some(format!("model    not checked: no {} installed (queries need the one with sha256 {})", rec.network, rec.sha256));
    };
    match semlook::util::sha256_file(&path) {
        Ok(sha) if sha == rec.sha256 => Some(format!("ok       embedding network {} (sha256 {sha})", path.display())),
        Ok(sha) => {
            let problem = format!(
                "the map's embeddings were made by the network of sha256 {}; the installed {} is {sha}, so queries would be refused",
                rec.sha256,
                path.display()
            );
            r.files.push(edit::FileCheck { file: "manifest.json".into(), problem: Some(problem) });
            None
        }
        Err(e) => Some(format!("model    not checked: {e}")),
    }
}

/// What a query checks of the keypoint network, checked by verify too: the installed network
/// (found as a query finds it) is the one the map's appearance was computed with. A mismatch is
/// reported as a problem of the manifest; the line says what was checked.
fn check_installed_model(r: &mut edit::VerifyReport) -> Option<String> {
    use semlook::config::AppearanceModelKind;
    let want = r.appearance_model.clone()?;
    match r.appearance_kind {
        AppearanceModelKind::Xfeat => {}
        AppearanceModelKind::Onnx => return Some("model    not checked: the map's keypoint network is an ONNX model, which a query names".into()),
        AppearanceModelKind::None => return None,
    }
    let name = semlook::networks::xfeat::XFEAT_WEIGHTS;
    // the folders start with $SEMLOOK_MODELS, as a query's search does
    let found = semlook::nn::onnx::find_model(name, None, "XFeat weights");
    let Ok(path) = found else {
        return Some(format!("model    not checked: no {name} installed (queries need the one with sha256 {want})"));
    };
    match semlook::util::sha256_file(&path) {
        Ok(sha) if sha == want => Some(format!("ok       keypoint network {} (sha256 {sha})", path.display())),
        Ok(sha) => {
            let problem = format!("the map's appearance was computed with the keypoint network of sha256 {want}; the installed {} is {sha}, so queries would be refused", path.display());
            r.files.push(edit::FileCheck { file: "manifest.json".into(), problem: Some(problem) });
            None
        }
        Err(e) => Some(format!("model    not checked: {e}")),
    }
}
