//! Fuzzing, on stable Rust, of every parser that reads user files: label-map PNGs (grey and
//! palette), RGB images, dataset manifests, ground truth (CSV, VPR-Bench `.npy`), pose lists,
//! config TOML, the pickle machine, `.pt` weights (as XFeat loads and runs them), ONNX keypoint
//! and segmenter models with wrong outputs, keypoint decoding, and the map store's files
//! (manifest, segments, codebook; [`store`]).
//!
//! Each target mutates valid seeds ([`mutate`]: flips, random and boundary values, truncations,
//! extensions, duplicated or deleted ranges, splices; PNG CRCs recomputed) or builds its input
//! from the fuzz bytes (ONNX graphs, `.pt` shapes, config structures). An input passes when it is
//! accepted, or refused with the typed error the target expects, naming the file or field. A
//! panic, an untyped or unnamed error, or a slow input is a failure; the input is saved under
//! `target/tmp/fuzz/`. Allocations are capped ([`cap`]): an input that asks for more aborts the
//! run, and the file `<target>-current.bin` there holds it.
//!
//! `cargo test` runs a short, fixed-seed pass over every target. The long run:
//! `SEMLOOK_FUZZ_SECS=600 cargo test --release --test fuzz -- --ignored --nocapture`
//! (the time is shared by the targets; `SEMLOOK_FUZZ_SEED` picks the seed, else the clock;
//! `SEMLOOK_FUZZ_TARGETS=a,b` runs only those).
//!
//! Adding a parser: write a constructor returning a [`Target`], list it in [`TARGETS`] and give it
//! a quick test.

mod cap;
#[path = "../common/mod.rs"]
mod common;
mod models;
mod mutate;
mod parsers;
mod store;

use semlook::util::SplitMix64;
use std::panic::{catch_unwind, AssertUnwindSafe};
use std::path::PathBuf;
use std::time::{Duration, Instant};

#[global_allocator]
static ALLOC: cap::Capped = cap::Capped;

/// What one input did.
pub enum Verdict {
    /// Parsed (and, where the target goes on, used) without error.
    Accepted,
    /// Refused with the expected typed error, naming its source.
    Refused,
    /// Something the hardening forbids: an untyped or unnamed error, a broken invariant.
    Violation(String),
}

impl Verdict {
    /// `Refused` when `e` is a kind `typed` accepts and its message names `source`.
    pub fn refused(e: &semlook::Error, source: &str, typed: impl Fn(&semlook::Error) -> bool) -> Verdict {
        let text = e.to_string();
        if typed(e) && text.contains(source) {
            Verdict::Refused
        } else {
            Verdict::Violation(format!("unexpected error (wrong kind, or {source:?} not named): {e:?}"))
        }
    }
}

/// A parser under fuzz.
pub struct Target {
    pub name: &'static str,
    /// Valid (or deliberately wrong) inputs the mutations start from.
    pub seeds: Vec<Vec<u8>>,
    /// Run after each mutation (checksums), so mutations reach the parser proper.
    pub fixup: Option<fn(&mut [u8])>,
    /// Inputs of the short pass in `cargo test`.
    pub quick: usize,
    pub run: Run,
}

/// Feeds one input to a target.
pub type Run = Box<dyn Fn(&[u8]) -> Verdict>;
/// Builds a target (`None` when a prerequisite is missing).
pub type Make = fn() -> Option<Target>;

/// Every target: its name and constructor (`None`, after saying why, when a prerequisite such
/// as ONNX Runtime is missing). The extension point for new parsers.
pub const TARGETS: &[(&str, Make)] = &[
    ("label_png_grey", parsers::label_png_grey),
    ("label_png_palette", parsers::label_png_palette),
    ("rgb_image", parsers::rgb_image),
    ("dataset_manifest", parsers::dataset_manifest),
    ("dataset_values", parsers::dataset_values),
    ("ground_truth_csv", parsers::ground_truth_csv),
    ("ground_truth_npy", parsers::ground_truth_npy),
    ("pose_lists", parsers::pose_lists),
    ("config_toml", parsers::config_toml),
    ("config_structured", parsers::config_structured),
    ("pickle", parsers::pickle),
    ("pt_archive", models::pt_archive),
    ("pt_pickle", models::pt_pickle),
    ("pt_shapes", models::pt_shapes),
    ("pt_legacy", models::pt_legacy),
    ("keypoint_decoding", models::keypoint_decoding),
    ("onnx_keypoints", models::onnx_keypoints),
    ("onnx_segmenter", models::onnx_segmenter),
    ("map_manifest", store::map_manifest),
    ("map_manifest_values", store::map_manifest_values),
    ("map_segment", store::map_segment),
    ("map_segment_rehashed", store::map_segment_rehashed),
    ("map_codebook", store::map_codebook),
];

/// Counts of one run of a target.
#[derive(Default)]
struct Stats {
    inputs: usize,
    accepted: usize,
    refused: usize,
    failures: Vec<String>,
    slowest: Duration,
}

/// An input slower than this is reported (a hang in the making).
const SLOW: Duration = Duration::from_secs(10);
/// Inputs kept for further mutation beyond the seeds.
const POOL: usize = 256;

fn out_dir() -> PathBuf {
    let d = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("fuzz");
    let _ = std::fs::create_dir_all(&d);
    d
}

/// Runs `t` on its seeds, then on mutated inputs until `stop` says so.
fn drive(t: &Target, seed: u64, stop: impl Fn(usize) -> bool) -> Stats {
    let mut rng = SplitMix64::new(seed);
    let mut pool = t.seeds.clone();
    let mut st = Stats::default();
    let dir = out_dir();
    let current = dir.join(format!("{}-current.bin", t.name));
    while !stop(st.inputs) {
        let input = match t.seeds.get(st.inputs) {
            Some(s) => s.clone(),
            None if pool.is_empty() => break,
            None => {
                let from = rng.below(pool.len());
                let mut v = mutate::mutate(&mut rng, &pool[from], &t.seeds);
                if let Some(f) = t.fixup {
                    f(&mut v);
                }
                v
            }
        };
        let _ = std::fs::write(&current, &input);
        let start = Instant::now();
        let verdict = catch_unwind(AssertUnwindSafe(|| (t.run)(&input)));
        let took = start.elapsed();
        st.slowest = st.slowest.max(took);
        st.inputs += 1;
        let problem = match verdict {
            Ok(Verdict::Accepted) => {
                st.accepted += 1;
                if pool.len() < POOL {
                    pool.push(input.clone());
                } else {
                    let i = rng.below(POOL);
                    pool[i] = input.clone();
                }
                None
            }
            Ok(Verdict::Refused) => {
                st.refused += 1;
                None
            }
            Ok(Verdict::Violation(m)) => Some(m),
            Err(p) => Some(format!(
                "panic: {}",
                p.downcast_ref::<String>().map(String::as_str).or_else(|| p.downcast_ref::<&str>().copied()).unwrap_or("?")
            )),
        };
        let problem = problem.or_else(|| (took > SLOW).then(|| format!("took {took:?}")));
        if let Some(m) = problem {
            let saved = dir.join(format!("{}-{seed}-{}.bin", t.name, st.inputs));
            let _ = std::fs::write(&saved, &input);
            st.failures.push(format!("{}: {m} (input: {})", t.name, saved.display()));
        }
    }
    st
}

fn report(name: &str, st: &Stats) -> String {
    format!(
        "{name:<20} {:>9} inputs {:>9} accepted {:>9} refused {:>3} failures  slowest {:>8.1} ms",
        st.inputs,
        st.accepted,
        st.refused,
        st.failures.len(),
        st.slowest.as_secs_f64() * 1e3
    )
}

/// The short pass of one target, as part of `cargo test`.
fn quick(name: &str) {
    let Some((_, make)) = TARGETS.iter().find(|(n, _)| *n == name) else { panic!("no target {name}") };
    let Some(t) = make() else { return };
    let n = t.quick;
    let st = drive(&t, 0x5E31_0000 ^ name.len() as u64, |i| i >= n);
    eprintln!("{}", report(name, &st));
    assert!(st.failures.is_empty(), "{}", st.failures.join("\n"));
    assert!(st.accepted + st.refused == st.inputs && st.inputs >= t.seeds.len().min(n));
}

macro_rules! quick_tests {
    ($($name:ident),*) => { $( #[test] fn $name() { quick(stringify!($name)); } )* };
}

quick_tests!(
    label_png_grey,
    label_png_palette,
    rgb_image,
    dataset_manifest,
    dataset_values,
    ground_truth_csv,
    ground_truth_npy,
    pose_lists,
    config_toml,
    config_structured,
    pickle,
    pt_archive,
    pt_pickle,
    pt_shapes,
    pt_legacy,
    keypoint_decoding,
    onnx_keypoints,
    onnx_segmenter,
    map_manifest,
    map_manifest_values,
    map_segment,
    map_segment_rehashed,
    map_codebook
);

/// Every target listed in [`TARGETS`] has a quick test above (a new one must be added to both).
#[test]
fn every_target_has_a_quick_test() {
    let source = include_str!("main.rs");
    let listed = source.split("quick_tests!(").nth(1).and_then(|s| s.split(");").next()).unwrap_or("");
    let names: Vec<&str> = listed.split(',').map(str::trim).collect();
    for (name, _) in TARGETS {
        assert!(names.contains(name), "{name} has no quick test");
    }
}

/// The long run: `SEMLOOK_FUZZ_SECS` seconds shared by all targets.
#[test]
#[ignore]
fn long_run() {
    let secs: f64 = std::env::var("SEMLOOK_FUZZ_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(60.0);
    let seed: u64 = std::env::var("SEMLOOK_FUZZ_SEED")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or_else(|| std::time::SystemTime::now().duration_since(std::time::UNIX_EPOCH).map_or(1, |d| d.as_nanos() as u64));
    let only = std::env::var("SEMLOOK_FUZZ_TARGETS").unwrap_or_default();
    let chosen = |name: &str| only.is_empty() || only.split(',').any(|n| n.trim() == name);
    let targets: Vec<Target> = TARGETS.iter().filter(|(name, _)| chosen(name)).filter_map(|(_, make)| make()).collect();
    let each = Duration::from_secs_f64(secs / targets.len().max(1) as f64);
    eprintln!("fuzzing {} targets for {each:?} each, seed {seed}", targets.len());
    let mut failures = Vec::new();
    let mut total = 0;
    for t in &targets {
        let start = Instant::now();
        let st = drive(t, seed ^ t.name.len() as u64, |_| start.elapsed() >= each);
        eprintln!("{}", report(t.name, &st));
        total += st.inputs;
        failures.extend(st.failures);
    }
    eprintln!("{total} inputs in all, {} failures, seed {seed}", failures.len());
    assert!(failures.is_empty(), "{}", failures.join("\n"));
}
