//! What the commands share: messages, config and model flags, the frames a source names, JSON.

use crate::cli::args::{ModelArgs, PoseArgs, SourceArgs};
use semlook::batch::PlacePoses;
use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions};
use semlook::error::{Error, Result};
use semlook::input::{FrameSource, LabelFormat};
use semlook::map::Map;
use semlook::matching::Setting;
use std::path::Path;

pub fn info(quiet: bool, msg: impl AsRef<str>) {
    if !quiet {
        use std::io::Write;
        // a closed standard error loses the message, never the command
        let _ = writeln!(std::io::stderr(), "{}", msg.as_ref());
    }
}

/// The line the commands that encode images print after it (`query`, `eval`'s maps, `map build`
/// and `add`): `what` encoded, then per image the encoding (descriptors: its stages, which add up
/// to it where they run one after another) and apart the loading (decoding and segmentation), which runs on the loader threads
/// beside the encoding, so that a segmentation longer than the encoding is not read as part of it.
pub fn encoding_line(what: &str, m: &semlook::encode::StageTimes) -> String {
    format!(
        "encoded {what}: per image, encoding {:.2} ms (edge {:.2}, forest {:.2}, appearance {:.2} of which network {:.2}, embedding {:.2}); loading {:.2} ms on the loader threads beside it (decoding {:.2}, segmentation {:.2})",
        m.encode_ms(),
        m.global_ms,
        m.forest_ms,
        m.appearance_ms,
        m.network_ms,
        m.embedding_ms,
        m.decode_ms + m.segment_ms,
        m.decode_ms,
        m.segment_ms
    )
}

pub fn load_config(path: Option<&Path>) -> Result<Config> {
    match path {
        Some(p) => Config::load(p),
        None => Ok(Config::default()),
    }
}

/// Pretty JSON of a report.
pub fn to_json<T: serde::Serialize + ?Sized>(v: &T) -> Result<String> {
    serde_json::to_string_pretty(v).map_err(|e| Error::invalid("JSON output", e.to_string()))
}

/// Applies the model flags to a config.
pub fn apply_models(mut cfg: Config, m: &ModelArgs) -> Config {
    use semlook::config::AppearanceModelKind;
    if let Some(k) = &m.keypoints {
        cfg.appearance.model = AppearanceModelKind::Onnx;
        cfg.models.keypoint_onnx = Some(k.clone());
    }
    // option, then $SEMLOOK_MODELS, then the config key, then the data folders (in the library)
    if let Some(w) = m.xfeat_weights.clone().or_else(|| semlook::nn::onnx::env_model(semlook::networks::xfeat::XFEAT_WEIGHTS)) {
        cfg.models.xfeat_weights = Some(w);
    }
    if let Some(s) = &m.segmenter {
        cfg.models.segmenter_onnx = Some(s.clone());
    }
    if m.no_appearance {
        cfg.appearance.model = AppearanceModelKind::None;
    }
    if m.no_segmenter {
        cfg.models.default_segmenter = false;
    }
    cfg
}

/// Frames named by the source arguments, with the label format to read them with. Where the
/// frames come from a dataset whose labels use other ids, `cfg`'s label ids follow the dataset
/// unless `keep_ids` (the user gave a config).
pub fn frame_sources(s: &SourceArgs, cfg: &mut Config, keep_ids: bool) -> Result<(Vec<FrameSource>, LabelFormat)> {
    frame_sources_posed(s, None, cfg, keep_ids).map(|(frames, fmt, _)| (frames, fmt))
}

/// [`frame_sources`] with the poses to store with them (frame id -> pose): the dataset's own
/// (`--dataset`), or `--poses`' lines for the images of `--images`; read and matched to every
/// frame before any is encoded, so a pose list that misses an image fails at once, naming it.
pub fn frame_sources_posed(
    s: &SourceArgs,
    p: Option<&PoseArgs>,
    cfg: &mut Config,
    keep_ids: bool,
) -> Result<(Vec<FrameSource>, LabelFormat, PlacePoses)> {
    if let Some(dir) = &s.dataset {
        let ds = Dataset::open(dir, &DatasetOptions::default())?;
        if let (Some(ids), false) = (&ds.label_ids, keep_ids) {
            cfg.classes.label_ids = ids.clone();
        }
        let trav = match &s.traversal {
            None => &ds.reference,
            Some(name) if *name == ds.reference.name => &ds.reference,
            Some(name) => ds.queries.iter().find(|q| q.name == *name).ok_or_else(|| Error::dataset(dir, format!("no traversal named {name:?}")))?,
        };
        let frames = trav.frames.iter().map(|f| f.source.clone()).collect();
        let poses = trav.frames.iter().filter_map(|f| Some((f.source.id.clone(), f.pose?.place_pose()))).collect();
        return Ok((frames, s.label_format.unwrap_or(ds.label_format), poses));
    }
    if s.images.is_none() && s.labels.is_none() {
        return Err(Error::invalid("arguments", "give --dataset, --images or --labels"));
    }
    let frames = semlook::dataset::frames_from_folders(s.images.as_deref(), s.labels.as_deref())?;
    let poses = match p.and_then(|p| p.poses.as_ref().map(|f| (f, p.pose_format))) {
        Some((file, format)) => pose_list_for(&frames, file, format.unwrap_or(semlook::dataset::PoseFormat::QuatCenter))?,
        None => PlacePoses::new(),
    };
    Ok((frames, s.label_format.unwrap_or_default(), poses))
}

/// The pose of every frame from a pose list; fails naming the first image it has no line for.
fn pose_list_for(frames: &[FrameSource], file: &Path, format: semlook::dataset::PoseFormat) -> Result<PlacePoses> {
    let list = semlook::dataset::read_pose_list(file, format)?;
    let mut out = PlacePoses::new();
    let mut missing = Vec::new();
    for f in frames {
        match f.image.as_deref().and_then(|img| semlook::dataset::pose_of_image(&list, img)) {
            Some(p) => {
                out.insert(f.id.clone(), p.place_pose());
            }
            None => missing.push(&f.id),
        }
    }
    if let Some(first) = missing.first() {
        let also = if missing.len() > 1 { format!(" (and {} more)", missing.len() - 1) } else { String::new() };
        return Err(Error::invalid(
            format!("--poses {}", file.display()),
            format!("has no line for image {first:?}{also}: every image needs a pose"),
        ));
    }
    Ok(out)
}

/// The config for queries of a map: the map's encoding, `config`'s matching (or the defaults),
/// model paths from the flags.
pub fn map_config(map: &Map, config: Option<&Path>, models: &ModelArgs) -> Result<Config> {
    let base = match config {
        Some(p) => Config::load(p)?,
        None => map.query_config(),
    };
    let mut cfg = apply_models(base, models);
    if config.is_none() && models.keypoints.is_none() && !models.no_appearance {
        cfg.appearance.model = map.manifest.config.appearance.model;
    }
    Ok(cfg)
}

/// Fails before any work unless `dir` can be the output folder `flag` names: a folder, or
/// nothing yet in a folder that exists.
pub fn check_output_dir(dir: &Path, flag: &str) -> Result<()> {
    if dir.exists() && !dir.is_dir() {
        return Err(Error::invalid(format!("{flag} {}", dir.display()), "is a file, not a folder"));
    }
    if !dir.exists() {
        let parent = dir.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
        if !parent.is_dir() {
            return Err(Error::invalid(format!("{flag} {}", dir.display()), format!("its folder {} does not exist", parent.display())));
        }
    }
    Ok(())
}

/// Fails before any work unless `file` can be the output file `flag` names: not a folder, in a
/// folder that exists.
pub fn check_output_file(file: &Path, flag: &str) -> Result<()> {
    if file.is_dir() {
        return Err(Error::invalid(format!("{flag} {}", file.display()), "is a folder, not a file"));
    }
    let parent = file.parent().filter(|p| !p.as_os_str().is_empty()).unwrap_or(Path::new("."));
    if !parent.is_dir() {
        return Err(Error::invalid(format!("{flag} {}", file.display()), format!("its folder {} does not exist", parent.display())));
    }
    Ok(())
}

/// Which coarse search a match of `setting` against `map` (`places` references; none: references
/// encoded in memory) ran, in the words of the info line after `coarse search: `: the map's
/// index where `approximate` (`MatchTimes::approximate`) says it was searched, with what it
/// probed and shortlisted (`w_embedding`: the fused score's embedding weight for these queries),
/// else the exact scan.
pub fn coarse_search(map: Option<&Map>, places: usize, cfg: &Config, setting: Setting, approximate: bool, w_embedding: f32) -> String {
    let at_least = semlook::matching::list_len(setting, cfg);
    let plan = map
        .filter(|_| approximate)
        .and_then(|m| m.index_plan(cfg.index.probe, cfg.index.shortlist, at_least, cfg.matching.w_global as f32, w_embedding));
    match plan {
        Some(p) => format!("index (probe {} of {} lists, shortlist {})", p.probed, p.lists, p.shortlist),
        None => format!("exact scan of {places} places"),
    }
}

/// Warns where the config asks for the approximate index (`index.search = "approximate"`) and
/// the references have none, so the coarse search scans every place (`map`: the map matched
/// against; none: references encoded in memory).
pub fn warn_if_no_index(cfg: &Config, map: Option<&Map>) {
    if cfg.index.search != semlook::config::IndexSearch::Approximate {
        return;
    }
    match map {
        Some(m) if m.index().is_none() => log::warn!(
            "index.search = \"approximate\", but map {} has no index: the coarse search scans every place (`semlook map index --map {}` builds one)",
            m.path.display(),
            m.path.display()
        ),
        None => log::warn!(
            "index.search = \"approximate\", but the references are encoded here, without an index: the coarse search scans every place (`semlook map index` builds one for a map given with --map)"
        ),
        Some(_) => {}
    }
}

/// Writes `text` to `path`; an error names the file.
pub fn write_file(path: &Path, text: &str) -> Result<()> {
    std::fs::write(path, text).map_err(|e| Error::io(path, e))
}
