//! Command-line interface: argument parsing and the commands, each a thin layer over the library.

mod commands;

use clap::{Args, Parser, Subcommand};
use semlook::engine::Backend;
use semlook::input::LabelFormat;
use semlook::matching::Setting;
use semlook::synth::condition::Condition;
use std::path::PathBuf;

#[derive(Parser)]
#[command(name = "semlook", version, about = "SemLook visual place recognition: build maps of places from label maps, match queries, evaluate.", long_about = None)]
pub struct Cli {
    /// No progress bars and no informational messages.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// Where encoding and matching run: `cpu`, `gpu` (any adapter, software ones included), or
    /// `auto` (a hardware GPU if there is one, else the CPU).
    #[arg(long, global = true, value_enum, default_value_t = Backend::Auto)]
    pub backend: Backend,
    #[command(subcommand)]
    pub command: Command,
}

#[derive(Subcommand)]
pub enum Command {
    /// Render the synthetic street benchmark (SYNTHIA-like layout that `eval` reads as it is).
    Synth(SynthArgs),
    /// Generate a small synthetic benchmark, build a map, query it and evaluate all settings.
    Demo(DemoArgs),
    /// Build, extend or inspect a map of places.
    #[command(subcommand)]
    Map(MapCommand),
    /// Match query images against a map; prints CSV (or JSON) with the best reference and the top-K.
    Query(QueryArgs),
    /// Evaluate on a dataset: AUC, Recall@100%Precision, Precision@100%Recall, Recall@N, timings.
    Eval(EvalArgs),
    /// Print the default configuration (TOML); edit it and pass it with --config.
    Config,
    /// Large-map batch matching benchmark: coarse matching throughput and peak memory for maps of
    /// 1k to 1M references and query batches of 100 and 1000, on the CPU and on the GPU.
    Bench(BenchArgs),
}

#[derive(Args)]
pub struct BenchArgs {
    /// Map sizes (references); sizes above 10,000 are synthetic maps served from one block of
    /// real descriptors (see `semlook::bench`).
    #[arg(long, value_delimiter = ',', default_value = "1000,10000,100000")]
    pub sizes: Vec<usize>,
    /// Query batch sizes; every row runs its whole batch.
    #[arg(long, value_delimiter = ',', default_value = "100,1000")]
    pub batches: Vec<usize>,
    /// Rows predicted (by an untimed probe) to take longer than this are not run, and the table
    /// says so; no row runs part of its batch.
    #[arg(long, default_value_t = 600.0)]
    pub max_row_seconds: f64,
    /// The GPU's FP32 peak in GFLOP/s, for the fraction of peak where the built-in table does not
    /// know the adapter.
    #[arg(long)]
    pub peak_gflops: Option<f64>,
    /// Leave the GPU out (by default every configuration also runs on the GPU when there is one).
    #[arg(long)]
    pub cpu_only: bool,
    /// One JSON object per row and line (JSON Lines), as rows finish.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Clone)]
pub struct SynthArgs {
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Places along the route (frames per traversal).
    #[arg(long, default_value_t = 150)]
    pub places: usize,
    /// Image size WIDTHxHEIGHT.
    #[arg(long, default_value = "640x480", value_parser = parse_size)]
    pub size: (usize, usize),
    /// Reference condition.
    #[arg(long, value_enum, default_value_t = Condition::Day)]
    pub reference: Condition,
    /// Query conditions (default: overcast, sunset, fog, snow, night).
    #[arg(long = "query", value_enum)]
    pub queries: Vec<Condition>,
    /// Probability that a city block repeats a layout template (perceptual aliasing).
    #[arg(long, default_value_t = 0.6)]
    pub aliasing: f64,
}

#[derive(Args)]
pub struct DemoArgs {
    /// Keep the generated dataset, map and results here (default: a temporary directory).
    #[arg(long)]
    pub out: Option<PathBuf>,
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    #[arg(long, default_value_t = 100)]
    pub places: usize,
    #[arg(long, default_value = "480x360", value_parser = parse_size)]
    pub size: (usize, usize),
    /// Print the evaluation report as JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

/// Models for appearance and segmentation.
#[derive(Args, Clone, Default)]
pub struct ModelArgs {
    /// Use this ONNX keypoint network (SuperPoint output layout) instead of XFeat.
    #[arg(long, value_name = "MODEL.onnx")]
    pub keypoints: Option<PathBuf>,
    /// XFeat weights (default: the ones setup.sh fetched).
    #[arg(long, value_name = "xfeat.pt")]
    pub xfeat_weights: Option<PathBuf>,
    /// Segment RGB images that have no label map with this ONNX network (see [segmentation]).
    #[arg(long, value_name = "MODEL.onnx")]
    pub segmenter: Option<PathBuf>,
    /// Trees without appearance (label maps alone are enough to encode).
    #[arg(long)]
    pub no_appearance: bool,
}

#[derive(Args, Clone)]
pub struct SourceArgs {
    /// A dataset directory: encode its reference traversal (or --traversal).
    #[arg(long, conflicts_with = "images")]
    pub dataset: Option<PathBuf>,
    /// With --dataset: which traversal to encode (default: the dataset's reference).
    #[arg(long, requires = "dataset")]
    pub traversal: Option<String>,
    /// A folder of RGB images (png/jpg).
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// A folder of label maps named like the images (`<stem>.png`); alone, encodes label maps only.
    #[arg(long)]
    pub labels: Option<PathBuf>,
    /// How label files encode classes.
    #[arg(long, value_enum)]
    pub label_format: Option<LabelFormat>,
    /// Skip (and report) images that fail to load instead of stopping.
    #[arg(long)]
    pub skip_invalid: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Subcommand)]
pub enum MapCommand {
    /// Encode images into a new map directory.
    Build {
        #[command(flatten)]
        source: SourceArgs,
        /// Map directory to create.
        #[arg(long)]
        out: PathBuf,
        /// Encoding config (TOML); default: built-in defaults.
        #[arg(long)]
        config: Option<PathBuf>,
        /// Replace an existing map directory (the old one is removed only after the new one is complete).
        #[arg(long)]
        force: bool,
    },
    /// Append images to a map without re-encoding what it holds.
    Add {
        #[command(flatten)]
        source: SourceArgs,
        #[arg(long)]
        map: PathBuf,
    },
    /// Show a map's size, config and segments.
    Info {
        #[arg(long)]
        map: PathBuf,
        #[arg(long)]
        json: bool,
    },
}

#[derive(Args)]
pub struct QueryArgs {
    #[arg(long)]
    pub map: PathBuf,
    #[command(flatten)]
    pub source: SourceArgs,
    #[arg(long, value_enum, default_value_t = Setting::Semlook)]
    pub setting: Setting,
    /// Config for matching (its encoding sections must equal the map's).
    #[arg(long)]
    pub config: Option<PathBuf>,
    /// Print JSON instead of CSV.
    #[arg(long)]
    pub json: bool,
    /// Also write OUT.csv and OUT.json.
    #[arg(long)]
    pub out: Option<PathBuf>,
}

#[derive(Args)]
pub struct EvalArgs {
    #[arg(long)]
    pub dataset: PathBuf,
    /// One setting (default: all).
    #[arg(long, value_enum, conflicts_with = "all_settings")]
    pub setting: Option<Setting>,
    /// All settings (the default).
    #[arg(long)]
    pub all_settings: bool,
    /// Use this map for the references instead of encoding them.
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// Reference traversal (overrides the dataset manifest).
    #[arg(long)]
    pub reference: Option<String>,
    /// Query traversal(s) (overrides the dataset manifest).
    #[arg(long = "query")]
    pub queries: Vec<String>,
    /// Ground truth: references within this distance are correct (overrides the manifest).
    #[arg(long)]
    pub gt_distance: Option<f64>,
    /// Ground truth: and optical axes within this angle (degrees).
    #[arg(long)]
    pub gt_angle: Option<f64>,
    #[arg(long)]
    pub config: Option<PathBuf>,
    #[arg(long)]
    pub json: bool,
    #[arg(long)]
    pub skip_invalid: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s.split_once('x').ok_or("expected WIDTHxHEIGHT, e.g. 640x480")?;
    let p = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("{v:?} is not a whole number"));
    Ok((p(w)?, p(h)?))
}

pub fn run() -> semlook::Result<()> {
    let cli = Cli::parse();
    commands::dispatch(cli)
}
