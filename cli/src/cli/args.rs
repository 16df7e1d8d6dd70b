//! The command line's arguments (clap): every command, its options and their help.

use clap::builder::{PossibleValue, PossibleValuesParser, TypedValueParser};
use clap::{Args, Parser, Subcommand};
use semlook::engine::Backend;
use semlook::input::LabelFormat;
use semlook::matching::Setting;
use semlook::Choice;
use semlook_cli::tools::synth::condition::Condition;
use std::path::PathBuf;

/// The parser of a library's closed set of named values ([`Choice`]): its names, each with its
/// help, the values clap offers and lists (the library derives nothing of clap).
fn choice<T: Choice>() -> impl TypedValueParser<Value = T> {
    PossibleValuesParser::new(T::CHOICES.iter().map(|c| PossibleValue::new(c.name()).help(c.help()))).try_map(|name| T::parse_name(&name))
}

#[derive(Parser)]
#[command(name = "semlook", version, about = "SemLook visual place recognition: build maps of places from label maps, match queries, evaluate.", long_about = None)]
pub struct Cli {
    /// No progress bars and no informational messages.
    #[arg(long, short, global = true)]
    pub quiet: bool,
    /// Where encoding and matching run: `cpu`, `gpu` (any adapter, software ones included), or
    /// `auto` (a hardware GPU if there is one, else the CPU; the default). Commands that run on
    /// the CPU only (inspect, map info/remove/compact/verify, synth without --from-camvid, config,
    /// models, dev bench/map-bench/segmenter-accuracy) refuse it rather than ignore it.
    #[arg(long, global = true, value_parser = choice::<Backend>())]
    pub backend: Option<Backend>,
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
    /// Localize a stream of frames against a map as they come, one line per frame (sequence
    /// matching over the last frames; loop closure on a growing map with --loop-closure).
    Localize(LocalizeArgs),
    /// Print the default configuration (TOML); edit it and pass it with --config.
    Config,
    /// The model files: which are installed, where, their SHA-256 (and whether it is the file
    /// `setup.sh` installs), and where each missing one comes from.
    Models {
        /// Print the list as JSON (one object per model file).
        #[arg(long)]
        json: bool,
    },
    /// Pictures of every stage for one frame: image, labels, semantic edges, truncated EDT, global
    /// descriptor, trees with neighbour links, keypoints.
    Inspect(InspectArgs),
    /// Developer tools: benchmarks, configuration sweeps, segmenter accuracy.
    #[command(subcommand)]
    Dev(DevCommand),
}

/// The developer commands (`semlook dev ...`).
#[derive(Subcommand)]
pub enum DevCommand {
    /// Large-map batch matching benchmark: coarse matching throughput and peak memory for maps of
    /// 1k to 1M references and query batches of 100 and 1000, on the CPU and on the GPU.
    Bench(BenchArgs),
    /// Encoding speed on real images: segmentation, then everything else (decoding at the
    /// working size, edges, EDT, objects, forest, keypoint network, VLAD), per-stage medians and
    /// wall clock per frame with frames in parallel.
    BenchEncode(BenchEncodeArgs),
    /// Map-store benchmark: writes a synthetic map of each size through the store, opens it and
    /// runs a coarse pass of a query batch from it; reports build peak RSS, open time, query-pass
    /// memory without mapped file pages, and bytes per reference.
    MapBench(StoreBenchArgs),
    /// Stream benchmark: replays a real sequence through the streaming localizer against stored
    /// maps of each size (the real references plus distractor places), frames/s and p50/p99
    /// latency per stage.
    BenchStream(BenchStreamArgs),
    /// `localize --stdin` against `localize --images` on the same files: frames/s and latency
    /// from a frame's bytes being complete to its answer, each way, and whether the answers are
    /// equal frame for frame.
    BenchPipe(BenchPipeArgs),
    /// Approximate-index benchmark: maps of each size made from a real map's images (appearance
    /// vectors made new per reference), the index built, real query photos through the index and
    /// through the exact scan: build time, bytes per reference, p50/p99 latency, queries/s,
    /// recall@30 of the index against the exact fused top-30, peak RSS.
    IndexBench(IndexBenchArgs),
    /// Sweep configuration values over datasets and tabulate Recall@1 and AUC per setting.
    Tune(TuneArgs),
    /// Accuracy of the segmenter against real label maps (pixel accuracy, IoU per class, mean IoU).
    SegmenterAccuracy(SegAccArgs),
    /// A copy of a ref/ + query/ + ground_truth.csv dataset at another size (every image resized
    /// to WxH, written as PNG; the ground truth's names follow): low-resolution dev checks.
    Downscale(DownscaleArgs),
}

#[derive(Args)]
pub struct DownscaleArgs {
    /// The dataset: ref/, query/ and ground_truth.csv (query,reference paths relative to it).
    #[arg(long)]
    pub dataset: PathBuf,
    /// The size of every image of the copy, WxH (e.g. 64x32).
    #[arg(long)]
    pub size: String,
    /// Folder of the copy (must not exist, or be empty).
    #[arg(long)]
    pub out: PathBuf,
}

#[derive(Args)]
pub struct BenchEncodeArgs {
    /// Folder of images (png/jpg).
    #[arg(long)]
    pub images: PathBuf,
    /// At most this many frames.
    #[arg(long, default_value_t = 60)]
    pub frames: usize,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Print the result as JSON.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

fn parse_search(s: &str) -> std::result::Result<(usize, usize, Option<usize>), String> {
    let parts: Vec<&str> = s.split(':').collect();
    let n = |v: &str| v.parse::<usize>().ok().filter(|&x| x > 0).ok_or_else(|| format!("{v:?} is not a positive number"));
    match parts[..] {
        [a, b] => Ok((n(a)?, n(b)?, None)),
        [a, b, c] => Ok((n(a)?, n(b)?, Some(c.parse::<usize>().map_err(|_| format!("{c:?} is not a number"))?))),
        _ => Err(format!("{s:?}: expected PROBE:SHORTLIST or PROBE:SHORTLIST:POOL")),
    }
}

/// Where a benchmark writes its maps and how it prints its rows.
#[derive(Args)]
pub struct BenchMapsArgs {
    /// Folder for the maps (default: the system temporary folder); each is deleted after its row
    /// unless --keep.
    #[arg(long)]
    pub dir: Option<PathBuf>,
    /// Keep the maps in --dir after the run.
    #[arg(long)]
    pub keep: bool,
    /// One JSON object per row and line.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args)]
pub struct IndexBenchArgs {
    /// A map with labels and appearance (`map build` of real photos) whose images the references
    /// are made from.
    #[arg(long)]
    pub from: PathBuf,
    /// Folder of real query photos (encoded for that map).
    #[arg(long)]
    pub queries: PathBuf,
    /// Map sizes (references).
    #[arg(long, value_delimiter = ',', default_value = "100000,1000000")]
    pub sizes: Vec<usize>,
    /// Queries also scanned exactly, for the recall (evenly spread over the photos).
    #[arg(long, default_value_t = 40)]
    pub exact_queries: usize,
    /// Queries of the batch whose queries/s is measured (the photos cycled).
    #[arg(long, default_value_t = 1000)]
    pub batch: usize,
    /// Exact single queries timed (each scans the whole map alone; the recall's exact rankings
    /// come from one batch).
    #[arg(long, default_value_t = 3)]
    pub exact_timed: usize,
    /// Searches of each map, PROBE:SHORTLIST or PROBE:SHORTLIST:POOL (`index.pool`; 0: the codes
    /// alone choose the shortlist), one row each (default: the config's).
    #[arg(long, value_delimiter = ',', value_parser = parse_search)]
    pub search: Vec<(usize, usize, Option<usize>)>,
    /// Configuration file (TOML) whose `[index]` section builds and searches the index.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub out: BenchMapsArgs,
}

#[derive(Args)]
pub struct BenchPipeArgs {
    /// The map to localize against.
    #[arg(long)]
    pub map: PathBuf,
    /// Folder of images (JPEG or PNG), localized in name order from the folder and piped.
    #[arg(long)]
    pub images: PathBuf,
    /// Which stages rank the map per frame.
    #[arg(long, value_parser = choice::<Setting>(), default_value_t = Setting::RECOMMENDED)]
    pub setting: Setting,
    /// Configuration file (TOML); default: the map's (its encoding, and the query sections it was
    /// built with where they are not the defaults: `map info` says).
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// One JSON object per row and line.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct BenchStreamArgs {
    /// Folder of the reference images the stream was recorded against (the map's real places).
    #[arg(long)]
    pub references: PathBuf,
    /// Folder of the frames replayed, in name order.
    #[arg(long)]
    pub stream: PathBuf,
    /// Folders of other images whose descriptors fill the maps to their sizes (repeatable).
    #[arg(long = "distractors", value_name = "DIR")]
    pub distractors: Vec<PathBuf>,
    /// Map sizes (places).
    #[arg(long, value_delimiter = ',', default_value = "1000,10000,100000")]
    pub sizes: Vec<usize>,
    /// Frames replayed per map (the stream is cycled when shorter).
    #[arg(long, default_value_t = 200)]
    pub frames: usize,
    /// Which stages rank the map per frame.
    #[arg(long, value_parser = choice::<Setting>(), default_value_t = Setting::RECOMMENDED)]
    pub setting: Setting,
    /// Single-frame matching only.
    #[arg(long)]
    pub no_sequence: bool,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    #[command(flatten)]
    pub out: BenchMapsArgs,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct SegAccArgs {
    /// Folder of images.
    #[arg(long)]
    pub images: PathBuf,
    /// Folder of their real label maps (`<stem>.png`).
    #[arg(long, value_name = "DIR")]
    pub labels: PathBuf,
    /// The labels are CamVid's (11 classes, SegNet ids); a Cityscapes segmenter is mapped to them.
    #[arg(long)]
    pub camvid: bool,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Also write the result as JSON to stdout.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct InspectArgs {
    /// The image (png or jpeg).
    pub image: PathBuf,
    /// Its label map (else the segmenter labels it).
    #[arg(long, value_name = "FILE")]
    pub labels: Option<PathBuf>,
    /// Folder for the PNGs (one per stage, and sheet.png with all of them).
    #[arg(long)]
    pub out: PathBuf,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// How label files encode classes (default: auto).
    #[arg(long, value_parser = choice::<LabelFormat>())]
    pub label_format: Option<LabelFormat>,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct TuneArgs {
    /// Dataset directories (any layout `eval --dataset` reads); repeat for several.
    #[arg(long = "dataset", required_unless_present = "segmented")]
    pub datasets: Vec<PathBuf>,
    /// Datasets whose label maps are ignored: every frame segmented (to tune on the segmenter's
    /// labels where real ones exist); repeat for several.
    #[arg(long = "segmented")]
    pub segmented: Vec<PathBuf>,
    /// The sweep file: `[values]` with a list per dotted config key, optional `[base]`.
    #[arg(long)]
    pub sweep: PathBuf,
    /// Configuration file (TOML) the sweep starts from; default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Settings to score, repeated or comma-separated (default: semlook, local, forest, global).
    #[arg(long = "setting", value_parser = choice::<Setting>(), value_delimiter = ',')]
    pub settings: Vec<Setting>,
    /// Also write the table (tab-separated) to this file.
    #[arg(long, value_name = "FILE.tsv")]
    pub table: Option<PathBuf>,
    /// Also stream each query set in its order through sequence matching (`[sequence]`) and
    /// tabulate its R@1 and AUC as a column `<setting>+seq`.
    #[arg(long)]
    pub sequence: bool,
    /// Also print (and with --table write beside it, `.cv.tsv`) the leave-one-set-out
    /// cross-validation: per dataset, the R@1 of the row chosen on the other datasets.
    #[arg(long)]
    pub cross_validate: bool,
    /// Write the features of every candidate pair `verified` re-ranks (coarse terms, tree
    /// similarity, matches, inliers, keypoints, sizes, ground truth) into DIR, one TSV per
    /// dataset, query set and row: what a re-ranking prototype reads.
    #[arg(long, value_name = "DIR")]
    pub candidates: Option<PathBuf>,
    /// Keep the segmenter's label maps in DIR and read them back for the same pixels (same
    /// segmenter file and segmentation config): a second sweep over the same sets skips
    /// segmentation.
    #[arg(long, value_name = "DIR")]
    pub label_cache: Option<PathBuf>,
    /// The null-evidence check (with setting verified): verify each query's candidates against an
    /// unrelated image (a query of the next dataset listed) instead of the query; column
    /// `verified~null` gives the share of queries whose verified order is then fused's (R@1
    /// column) and whose top-1 is (AUC column).
    #[arg(long)]
    pub null_evidence: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct BenchArgs {
    /// Map sizes (references); sizes above 10,000 are synthetic maps served from one block of
    /// real descriptors (see `semlook_cli::tools::bench`).
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
    /// Bytes of map the GPU keeps resident, in MiB (default: half the adapter's largest buffer);
    /// a map beyond it is streamed in every batch.
    #[arg(long)]
    pub resident_budget_mib: Option<u64>,
    /// Largest storage binding the GPU executors use, in MiB (default: the adapter's limit);
    /// lower it to force map and query chunking.
    #[arg(long)]
    pub max_binding_mib: Option<u64>,
    /// One JSON object per row and line (JSON Lines), as rows finish.
    #[arg(long)]
    pub json: bool,
}

#[derive(Args, Clone)]
pub struct SynthArgs {
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Instead of rendering: build the real-label benchmark from a CamVid folder (images/,
    /// labels/): the frames as references, the same frames under controlled changes as queries.
    #[arg(long, value_name = "DIR")]
    pub from_camvid: Option<PathBuf>,
    /// Instead of rendering: a stream benchmark from a dataset directory (any layout `eval`
    /// reads, with ground truth): its references as they are, each query traversal driven again
    /// at a speed swinging between --speed-min and --speed-max with --stops stops (`--seed`).
    #[arg(long, value_name = "DIR", conflicts_with = "from_camvid")]
    pub stream_from: Option<PathBuf>,
    /// With --stream-from: the slowest and fastest speed, in source frames per frame.
    #[arg(long, default_value_t = 0.6, requires = "stream_from")]
    pub speed_min: f64,
    /// With --stream-from: the fastest speed (see --speed-min).
    #[arg(long, default_value_t = 1.4, requires = "stream_from")]
    pub speed_max: f64,
    /// With --stream-from: stops along the route, and frames each lasts.
    #[arg(long, default_value_t = 2, requires = "stream_from")]
    pub stops: usize,
    /// With --stream-from: frames each stop lasts.
    #[arg(long, default_value_t = 20, requires = "stream_from")]
    pub stop_frames: usize,
    /// With --from-camvid: the changes (default: night, fog, blur, shift).
    #[arg(long = "change", value_enum, requires = "from_camvid")]
    pub changes: Vec<semlook_cli::tools::synth::camvid::Change>,
    /// With --from-camvid: keep every N-th frame.
    #[arg(long, default_value_t = 1, requires = "from_camvid")]
    pub step: usize,
    /// With --from-camvid: also evaluate every setting on it, once with the real labels and once
    /// with the segmenter's, and print the tables.
    #[arg(long, requires = "from_camvid")]
    pub evaluate: bool,
    #[command(flatten)]
    pub models: ModelArgs,
    /// Seed of the rendered world (not with --from-camvid).
    #[arg(long, default_value_t = 7, conflicts_with = "from_camvid")]
    pub seed: u64,
    /// Places along the route (frames per traversal; not with --from-camvid).
    #[arg(long, default_value_t = 150, conflicts_with = "from_camvid")]
    pub places: usize,
    /// Image size WIDTHxHEIGHT (not with --from-camvid).
    #[arg(long, default_value = "640x480", value_parser = parse_size, conflicts_with = "from_camvid")]
    pub size: (usize, usize),
    /// Lighting condition of the reference traversal (not with --from-camvid).
    #[arg(long = "reference-condition", value_enum, default_value_t = Condition::Day, conflicts_with = "from_camvid")]
    pub reference: Condition,
    /// Conditions of the query traversals, repeated (default: overcast, sunset, fog, snow, night;
    /// not with --from-camvid).
    #[arg(long = "query-condition", value_enum, conflicts_with = "from_camvid")]
    pub queries: Vec<Condition>,
    /// Probability that a city block repeats a layout template (perceptual aliasing; not with
    /// --from-camvid).
    #[arg(long, default_value_t = 0.6, conflicts_with = "from_camvid")]
    pub aliasing: f64,
}

#[derive(Args)]
pub struct DemoArgs {
    /// Keep the generated dataset, map and results here (default: a temporary directory).
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Seed of the generated places and conditions.
    #[arg(long, default_value_t = 7)]
    pub seed: u64,
    /// Places in the generated dataset (60: the demo is the main job of a fresh machine's first
    /// command, which is to end within five minutes on two cores; 100 took 108 s against 57).
    #[arg(long, default_value_t = 60)]
    pub places: usize,
    /// Frame size of the generated dataset, WxH.
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
    /// Never segment (by default the installed segmenter labels frames without a label map).
    /// Photos none of which has a label map are then encoded without labels, for the settings
    /// that need none (hog, appearance, verified; `eval` skips the others, a map built so refuses
    /// them); a label map missing among others is an error.
    #[arg(long, conflicts_with = "segmenter")]
    pub no_segmenter: bool,
}

#[derive(Args, Clone)]
#[command(group(clap::ArgGroup::new("source").required(true).multiple(true).args(["dataset", "images", "labels"])))]
pub struct SourceArgs {
    /// A dataset directory: encode its reference traversal (or --traversal).
    #[arg(long, conflicts_with = "images")]
    pub dataset: Option<PathBuf>,
    /// With --dataset: which of the dataset's traversals to encode (default: its reference).
    #[arg(long, value_name = "NAME", requires = "dataset")]
    pub traversal: Option<String>,
    /// A folder of RGB images (png/jpg).
    #[arg(long)]
    pub images: Option<PathBuf>,
    /// A folder of label maps named like the images (`<stem>.png`); alone, encodes label maps only.
    #[arg(long, value_name = "DIR")]
    pub labels: Option<PathBuf>,
    /// How label files encode classes.
    #[arg(long, value_parser = choice::<LabelFormat>())]
    pub label_format: Option<LabelFormat>,
    /// Skip (and report) images that fail to load instead of stopping.
    #[arg(long)]
    pub skip_invalid: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

/// Camera poses to store with the places of `map build` / `map add` (the ROS 2 node publishes
/// the matched place's as a PoseStamped). A dataset's own poses (`--dataset`) are stored without
/// these flags.
#[derive(Args, Clone, Default)]
pub struct PoseArgs {
    /// A pose list for the images of --images: one `name numbers...` line per image (`#`
    /// comments), `name` the image's file name or stem; every image needs a line.
    #[arg(long, value_name = "FILE", requires = "images", conflicts_with = "dataset")]
    pub poses: Option<PathBuf>,
    /// Line format of --poses: quat_center (`qw qx qy qz cx cy cz`, world-to-camera rotation and
    /// camera centre; the default), quat_translation (`qw qx qy qz tx ty tz`), matrix_cam_to_world
    /// or matrix_world_to_cam (16 numbers, row-major 4x4).
    #[arg(long, value_name = "FORMAT", requires = "poses", value_parser = parse_pose_format)]
    pub pose_format: Option<semlook::dataset::PoseFormat>,
    /// The times of the images of --images (`name time` lines, seconds, as `localize
    /// --timestamps` reads them): the map stores its traversal's frame interval (their median
    /// step), from which a stream with timestamps derives its sequence velocity range.
    #[arg(long, value_name = "FILE", requires = "images", conflicts_with = "dataset")]
    pub timestamps: Option<PathBuf>,
}

fn parse_pose_format(s: &str) -> Result<semlook::dataset::PoseFormat, String> {
    serde_json::from_value(serde_json::Value::String(s.to_string()))
        .map_err(|_| format!("{s:?} is not a pose format (quat_center, quat_translation, matrix_cam_to_world, matrix_world_to_cam)"))
}

/// How a map stores what it is given.
#[derive(Args, Clone, Default)]
pub struct StoreArgs {
    /// Store global descriptors and appearance vectors as f16 (half the bytes; matching still
    /// computes in f32). Recorded in the map; `map add` follows the map.
    #[arg(long)]
    pub f16: bool,
    /// Most images per segment file (a segment is committed when full; a crash loses at most the
    /// segment in progress). Default 4096, fewer when images are large (64 MiB per segment).
    #[arg(long, value_name = "N", value_parser = parse_positive)]
    pub segment_images: Option<usize>,
}

#[derive(Subcommand)]
pub enum MapCommand {
    /// Encode images into a new map directory, committing a segment at a time.
    Build {
        #[command(flatten)]
        source: SourceArgs,
        /// Map directory to create.
        #[arg(long)]
        map: PathBuf,
        /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
        #[arg(long, value_name = "FILE.toml")]
        config: Option<PathBuf>,
        /// Replace an existing map: the new one is built beside it (same folder, unique name) and
        /// swapped in once complete; no other path is touched.
        #[arg(long, conflicts_with = "resume")]
        force: bool,
        /// Continue an interrupted build: images the map holds are skipped, the rest are added.
        #[arg(long)]
        resume: bool,
        /// Also store each image's VPR-Bench HOG descriptor (35,721 floats), so that the `hog`
        /// baseline can be matched and evaluated against this map.
        #[arg(long)]
        hog: bool,
        /// Name of the map's traversal the images make (a run of frames in order, which sequence
        /// matching follows); default "0". (`--traversal` picks which of a dataset's traversals
        /// is encoded.)
        #[arg(long, value_name = "NAME")]
        map_traversal: Option<String>,
        /// The approximate index of the coarse stage for large maps: `auto` builds one when the
        /// map holds at least `index.min_places` images, `ivf` always (maps with appearance),
        /// `none` never. `semlook map index` builds or drops one later.
        #[arg(long, value_parser = choice::<semlook::batch::IndexPolicy>(), default_value = "auto")]
        index: semlook::batch::IndexPolicy,
        #[command(flatten)]
        store: StoreArgs,
        #[command(flatten)]
        poses: PoseArgs,
    },
    /// Build (or rebuild) a map's approximate index of the coarse stage, or drop it: the model
    /// trained on a sample of the map, each segment's codes, the recall measured; one commit.
    Index {
        /// The map directory.
        #[arg(long)]
        map: PathBuf,
        /// Configuration file (TOML) whose `[index]` section gives the build parameters; default:
        /// built-in defaults.
        #[arg(long, value_name = "FILE.toml")]
        config: Option<PathBuf>,
        /// Drop the index instead (queries scan every reference exactly).
        #[arg(long)]
        drop: bool,
        /// Print the index's record as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Append images to a map without re-encoding what it holds.
    Add {
        #[command(flatten)]
        source: SourceArgs,
        /// The map directory to add to (made by `map build`).
        #[arg(long)]
        map: PathBuf,
        /// Continue an interrupted add: images the map holds are skipped, and the rest continue
        /// the map's last traversal.
        #[arg(long)]
        resume: bool,
        /// The map's traversal the images join: a new one by default (a new run of frames:
        /// sequence matching never crosses from one traversal into another); an existing name
        /// continues it. (`--traversal` picks which of a dataset's traversals is encoded.)
        #[arg(long, value_name = "NAME")]
        map_traversal: Option<String>,
        /// Store the images under ids PREFIX + their file stem (PREFIX + the dataset's id with
        /// --dataset), e.g. to add photos whose names the map holds already.
        #[arg(long, value_name = "PREFIX")]
        id_prefix: Option<String>,
        /// Most images per segment file (see `map build`).
        #[arg(long, value_name = "N", value_parser = parse_positive)]
        segment_images: Option<usize>,
        #[command(flatten)]
        poses: PoseArgs,
    },
    /// Show a map's size, layout, config and segments (reads the manifest; checks nothing).
    Info {
        /// The map directory.
        #[arg(long)]
        map: PathBuf,
        /// Print the information as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Remove images from a map (they leave every query at once; `map compact` frees the space).
    Remove {
        /// The map directory.
        #[arg(long)]
        map: PathBuf,
        /// Image ids, or one file of ids (one per line; empty lines and `#` lines ignored).
        #[arg(long, num_args = 1.., required = true, value_name = "FILE|ID")]
        ids: Vec<String>,
    },
    /// Rewrite the segments that hold removed images or are small; delete files no manifest needs.
    Compact {
        /// The map directory.
        #[arg(long)]
        map: PathBuf,
        /// Print what was rewritten and freed as JSON.
        #[arg(long)]
        json: bool,
    },
    /// Check every file of a map in full (checksums and values); names each damaged file and
    /// exits with status 1 if there is one.
    Verify {
        /// The map directory.
        #[arg(long)]
        map: PathBuf,
        /// Print the check's results as JSON (one entry per file).
        #[arg(long)]
        json: bool,
    },
}

#[derive(Args)]
pub struct StoreBenchArgs {
    /// Map sizes (references).
    #[arg(long, value_delimiter = ',', default_value = "100000")]
    pub sizes: Vec<usize>,
    /// Coarse passes on each map: QUERIES (against every reference) or QUERIES:REFS (against the
    /// first REFS references, streamed from the stored map like the rest).
    #[arg(long, value_delimiter = ',', default_value = "1000")]
    pub passes: Vec<semlook_cli::tools::bench_store::Pass>,
    /// Store f16 (default f32).
    #[arg(long)]
    pub f16: bool,
    /// Query batch sizes for which a pass with stored SSIM statistics (the map in memory) is
    /// timed against one recomputing them per tile (maps up to 50,000 references).
    #[arg(long, value_delimiter = ',')]
    pub stats_comparison: Vec<usize>,
    #[command(flatten)]
    pub out: BenchMapsArgs,
}

#[derive(Args)]
pub struct QueryArgs {
    /// The map directory to query (made by `map build`).
    #[arg(long)]
    pub map: PathBuf,
    #[command(flatten)]
    pub source: SourceArgs,
    /// Which stages rank the map (default: the recommended pipeline, `verified`).
    #[arg(long, value_parser = choice::<Setting>(), default_value_t = Setting::RECOMMENDED)]
    pub setting: Setting,
    /// Config for matching (its encoding sections must equal the map's).
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Print JSON instead of CSV.
    #[arg(long)]
    pub json: bool,
    /// Also write DIR/matches.csv and DIR/matches.json (the folder is created).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    #[command(flatten)]
    pub pairs: PairsArgs,
}

/// hloc's retrieval pairs from a query.
#[derive(Args)]
pub struct PairsArgs {
    /// Also write hloc's retrieval pairs file (`query_name reference_name` per line, each
    /// query's top K), names relative to --pairs-root as hloc names images.
    #[arg(long, value_name = "FILE", requires = "references")]
    pub pairs: Option<PathBuf>,
    /// With --pairs: the folder(s) of the map's reference images (a map stores ids, not file
    /// names); every map image must be found there once.
    #[arg(long = "references", value_name = "DIR", requires = "pairs")]
    pub references: Vec<PathBuf>,
    /// With --pairs: the folder names are relative to (hloc's image_dir); default: the deepest
    /// folder holding the query and reference folders' parents, so names keep their folder
    /// (`ref/00.jpg`), as `python -m semlook.hloc` names the map's images.
    #[arg(long, value_name = "DIR", requires = "pairs")]
    pub pairs_root: Option<PathBuf>,
    /// With --pairs: pairs per query (default: the config's matching.top_k; fewer where the
    /// setting's list is shorter).
    #[arg(long, value_name = "K", requires = "pairs", value_parser = parse_positive)]
    pub pairs_k: Option<usize>,
}

#[derive(Args)]
pub struct LocalizeArgs {
    /// The map (with --loop-closure: created where there is none).
    #[arg(long)]
    pub map: PathBuf,
    /// A folder of frames (png/jpg), in name order (or --timestamps order).
    #[arg(long, conflicts_with = "stdin", required_unless_present = "stdin")]
    pub images: Option<PathBuf>,
    /// Label maps of the frames, `<stem>.png` (else the segmenter labels them).
    #[arg(long, value_name = "DIR", requires = "images")]
    pub labels: Option<PathBuf>,
    /// How label files encode classes.
    #[arg(long, value_parser = choice::<LabelFormat>(), requires = "labels")]
    pub label_format: Option<LabelFormat>,
    /// A file of `name time` lines (seconds) for the frames of --images: they are taken in time
    /// order, and a time going backwards is refused.
    #[arg(long, value_name = "FILE", requires = "images")]
    pub timestamps: Option<PathBuf>,
    /// Read the frames from standard input: JPEG or PNG images one after another (e.g.
    /// `ffmpeg -i video.mp4 -f image2pipe -c:v mjpeg - | semlook localize --stdin ...`).
    #[arg(long)]
    pub stdin: bool,
    /// Which stages rank the map (default: the recommended pipeline, `verified`).
    #[arg(long, value_parser = choice::<Setting>(), default_value_t = Setting::RECOMMENDED)]
    pub setting: Setting,
    /// Single-frame matching only (sequence matching over the last frames is on by default).
    #[arg(long)]
    pub no_sequence: bool,
    /// Loop-closure mode: match each frame against the frames of the map older than the
    /// excluded recent ones (`[stream]` in the config), then add it to the map; prints the
    /// closures found.
    #[arg(long, conflicts_with = "no_sequence")]
    pub loop_closure: bool,
    /// A restarted --loop-closure run: continue the map's last traversal and skip the frames
    /// the map already holds (by id: a file's stem, or frame-N of a pipe, so a restarted pipe
    /// must start from the same first frame); says how many it skipped.
    #[arg(long, requires = "loop_closure")]
    pub resume: bool,
    /// Multiply the sequence velocity range by this (`sequence.velocity_scale`): map positions
    /// per stream frame at the normal speed, e.g. 4 for a camera at a quarter of the map's frame
    /// rate. Default: derived from the timestamps where the map (`map build --timestamps`) and
    /// the stream (--timestamps) both have them, else 1.
    #[arg(long, value_name = "X", conflicts_with = "no_sequence")]
    pub velocity_scale: Option<f64>,
    /// The camera's intrinsics (TOML `.toml` or JSON: fx, fy, cx, cy, width, height of the images
    /// they are for): an accepted match (and a loop closure) then carries the frame's pose
    /// relative to the place's, from the pair's verified keypoint matches (JSON
    /// `relative_pose`: rotation, quaternion, translation_unit, rotation_deg, inliers, matches;
    /// CSV columns `rotation_deg` and `pose_inliers`). Read and checked before the stream starts.
    #[arg(long, value_name = "FILE")]
    pub camera: Option<PathBuf>,
    /// Before each frame, move to the map's newest generation if another writer committed one.
    #[arg(long)]
    pub follow_map: bool,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: the map's (its
    /// encoding, and the query sections it was built with where they are not the defaults).
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// One JSON object per frame and line (JSON Lines), then one with the summary.
    #[arg(long)]
    pub json: bool,
    #[command(flatten)]
    pub models: ModelArgs,
}

#[derive(Args)]
pub struct EvalArgs {
    /// A dataset directory: a semlook-dataset.json manifest, ref/ + query/ + ground_truth.csv,
    /// ref/ + query/ + ground_truth_new.npy (VPR-Bench), database/ + queries/ with UTM file names,
    /// or a SYNTHIA-style tree.
    #[arg(long, required_unless_present = "references", conflicts_with = "references")]
    pub dataset: Option<PathBuf>,
    /// A folder of reference images (the map); with --queries and --ground-truth.
    #[arg(long, requires = "queries_dir")]
    pub references: Option<PathBuf>,
    /// A folder of query images.
    #[arg(long = "queries", value_name = "DIR", requires = "references")]
    pub queries_dir: Option<PathBuf>,
    /// Ground truth for --references/--queries: a CSV of query,reference rows (paths relative to
    /// the CSV's folder) or VPR-Bench's .npy; without it, UTM positions in the file names.
    #[arg(long, requires = "references")]
    pub ground_truth: Option<PathBuf>,
    /// Settings to evaluate, repeated or comma-separated (default: all nine, baselines included).
    #[arg(long = "setting", value_parser = choice::<Setting>(), value_delimiter = ',')]
    pub settings: Vec<Setting>,
    /// Use this map for the references instead of encoding them.
    #[arg(long)]
    pub map: Option<PathBuf>,
    /// With --dataset: the reference traversal (overrides the dataset manifest).
    #[arg(long = "reference-traversal", value_name = "NAME", requires = "dataset")]
    pub reference: Option<String>,
    /// With --dataset: a query traversal, repeated for several (overrides the dataset manifest).
    #[arg(long = "query-traversal", value_name = "NAME", requires = "dataset")]
    pub queries: Vec<String>,
    /// Ground truth: references within this distance are correct (overrides the manifest).
    #[arg(long)]
    pub gt_distance: Option<f64>,
    /// Ground truth: and optical axes within this angle (degrees).
    #[arg(long)]
    pub gt_angle: Option<f64>,
    /// Configuration file (TOML; `semlook config` prints the defaults); default: built-in defaults.
    #[arg(long, value_name = "FILE.toml")]
    pub config: Option<PathBuf>,
    /// Print the evaluation report as JSON (metrics per setting, what was skipped and why).
    #[arg(long)]
    pub json: bool,
    /// Skip (and report) query or reference images that fail to load instead of stopping.
    #[arg(long)]
    pub skip_invalid: bool,
    /// Write sheets (query | top-1 | a valid reference, with labels and scores) for the N worst
    /// queries of the recommended setting (`verified`; else the first setting asked for) into --out.
    #[arg(long, value_name = "N", requires = "out")]
    pub explain: Option<usize>,
    /// Folder for --explain sheets.
    #[arg(long)]
    pub out: Option<PathBuf>,
    /// Draw the precision-recall curve of every setting (PNG and SVG per query set) into DIR.
    #[arg(long, value_name = "DIR")]
    pub plots: Option<PathBuf>,
    /// Also match each query set as a stream in its order (sequence matching over the last
    /// frames, `[sequence]` in the config) and report its R@1 beside the single-frame one.
    #[arg(long)]
    pub sequence: bool,
    /// Keep the segmenter's label maps in DIR and read them back for the same pixels (same
    /// segmenter file and segmentation config): a second evaluation of the same frames skips
    /// segmentation (as `dev tune --label-cache`).
    #[arg(long, value_name = "DIR")]
    pub label_cache: Option<PathBuf>,
    /// Write DIR/index.html, one self-contained page: the metrics table, precision-recall and
    /// recall@N charts, the worst queries' sheets (the N of --explain, else 6) and what ran.
    #[arg(long, value_name = "DIR")]
    pub report: Option<PathBuf>,
    #[command(flatten)]
    pub models: ModelArgs,
}

fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s.split_once('x').ok_or("expected WIDTHxHEIGHT, e.g. 640x480")?;
    let p = |v: &str| v.trim().parse::<usize>().map_err(|_| format!("{v:?} is not a whole number"));
    Ok((p(w)?, p(h)?))
}

/// A count of at least 1 (`--segment-images 0` was taken as 1 without a word).
fn parse_positive(s: &str) -> Result<usize, String> {
    match s.parse::<usize>() {
        Ok(0) => Err("must be at least 1".into()),
        Ok(n) => Ok(n),
        Err(e) => Err(e.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::{choice, Backend, Choice, Cli, LabelFormat, Setting, TypedValueParser};
    use clap::CommandFactory;

    /// Every option and positional of every command says what it does in `--help` (issue 30:
    /// `--json`, `--skip-invalid`, `--map` and others had none in 23 places; seen failing with one
    /// of them removed again, naming it).
    #[test]
    fn every_argument_has_help_text() {
        fn walk(cmd: &clap::Command, path: &str, missing: &mut Vec<String>) {
            for a in cmd.get_arguments() {
                let id = a.get_id().as_str();
                if a.get_help().is_none() && !["help", "version"].contains(&id) {
                    missing.push(format!("{path} --{id}"));
                }
            }
            for sub in cmd.get_subcommands() {
                walk(sub, &format!("{path} {}", sub.get_name()), missing);
            }
        }
        let mut missing = Vec::new();
        walk(&Cli::command(), "semlook", &mut missing);
        assert!(missing.is_empty(), "no help text: {missing:#?}");
    }

    /// The library's named values reach the command line through [`choice`] (issue 58: clap was
    /// derived on the library's types): every name parses to its value, another is refused, and
    /// each option lists every value with its help, in the library's order.
    #[test]
    fn library_choices_parse_by_name_and_list_their_help() {
        fn check<T: Choice + std::fmt::Debug>(command: &[&str], option: &str) {
            let mut cmd = Cli::command();
            cmd.build();
            let mut sub = &cmd;
            for c in command {
                sub = sub.find_subcommand(c).unwrap();
            }
            let arg = sub.get_arguments().find(|a| a.get_long() == Some(option)).unwrap();
            let listed: Vec<(String, String)> = arg
                .get_possible_values()
                .iter()
                .map(|v| (v.get_name().to_string(), v.get_help().map(|h| h.to_string()).unwrap_or_default()))
                .collect();
            let want: Vec<(String, String)> = T::CHOICES.iter().map(|c| (c.name().to_string(), c.help().to_string())).collect();
            assert_eq!(listed, want, "{command:?} --{option}");
            let parser = choice::<T>();
            for &c in T::CHOICES {
                assert_eq!(parser.parse_ref(sub, Some(arg), std::ffi::OsStr::new(c.name())).ok(), Some(c));
            }
            assert!(parser.parse_ref(sub, Some(arg), std::ffi::OsStr::new("nothing-of-the-kind")).is_err());
        }
        check::<Setting>(&["query"], "setting");
        check::<Setting>(&["eval"], "setting");
        check::<Backend>(&[], "backend");
        check::<LabelFormat>(&["query"], "label-format");
        check::<semlook::batch::IndexPolicy>(&["map", "build"], "index");
    }
}
