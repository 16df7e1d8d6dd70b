//! The commands behind the CLI.

mod demo;
mod dev;
mod eval;
mod localize;
mod map_cmd;
mod pairs;
mod query;
mod shared;
mod synthetic;

use shared::{
    apply_models, check_output_dir, check_output_file, coarse_search, frame_sources, info, load_config, map_config, to_json, warn_if_no_index,
    write_file,
};

use super::args::*;
use demo::demo;
use eval::{eval_cmd, print_report};
use query::{query, query_frames, query_outputs, run_query};
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
use semlook_cli::tools::synth::condition::Condition;
use semlook_cli::tools::synth::{self, SynthConfig};
use std::path::Path;
use std::time::Instant;
use synthetic::{camvid_cmd, stream_synth_cmd, synth_cmd, synth_config};

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

fn inspect_cmd(a: &InspectArgs, quiet: bool) -> Result<()> {
    let cfg = apply_models(load_config(a.config.as_deref())?, &a.models);
    let encoder = Encoder::new(&cfg)?;
    let id = a.image.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let src = FrameSource { id, image: Some(a.image.clone()), labels: a.labels.clone() };
    let panels = semlook_cli::tools::viz::inspect(&encoder, &src, a.label_format.unwrap_or_default())?;
    let files = semlook_cli::tools::viz::write_panels(&panels, &a.out)?;
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
            if all.iter().any(|m| m.name == semlook::networks::segmenter::DEFAULT_SEGMENTER && m.path.is_none()) {
                "; without the segmenter, photos that have no label maps are encoded without labels (settings hog, appearance, verified)"
            } else {
                ""
            }
        );
    }
    Ok(())
}
