//! Helpers shared by the integration tests.
#![allow(dead_code)]

use semlook::config::Config;
use semlook::descriptors::DescriptorSet;
use semlook::encode::Encoder;
use semlook::input::LabelMap;
use semlook_cli::tools::synth::{self, SynthConfig};
use std::path::Path;
use std::sync::atomic::{AtomicUsize, Ordering};

pub mod glue;

static SKIPS: AtomicUsize = AtomicUsize::new(0);

/// Says that the running test skips, and why, on a line that starts with `SKIPPED` and counts the
/// skips of this test binary so far. Written to stderr directly, past the harness's output
/// capture, so it shows in a plain `cargo test`; `.ci/run` sums these lines.
pub fn skip(reason: impl std::fmt::Display) {
    use std::io::Write;
    let n = SKIPS.fetch_add(1, Ordering::Relaxed) + 1;
    let test = std::thread::current().name().unwrap_or("?").to_string();
    let binary = module_path!().split("::").next().unwrap_or("?");
    let _ = writeln!(std::io::stderr(), "SKIPPED ({n} in {binary}): {test}: {reason}");
}

/// Whether a missing resource must fail the test: under CI (`CI` set) or with `var`=1 (e.g.
/// `REQUIRE_GPU=1`).
pub fn required(var: &str) -> bool {
    std::env::var_os("CI").is_some() || std::env::var(var).is_ok_and(|v| v == "1")
}

/// [`skip`], or a failure when [`required`]`(var)`.
pub fn skip_unless_required(var: &str, reason: impl std::fmt::Display) {
    if required(var) {
        panic!("required here (CI or {var}=1) but missing: {reason}");
    }
    skip(reason);
}

/// `cfg` with the real default segmenter named explicitly, from `../shared/models` (the reference
/// export of the authors' checkpoint), for a test that needs real labels of real photos. Tests never
/// reach the segmenter a machine happened to install: where `../shared` is absent the test skips with
/// the reason (or fails under CI / REQUIRE_SHARED=1), as it does on a fresh machine.
pub fn with_real_segmenter(mut cfg: Config) -> Option<Config> {
    cfg.models.segmenter_onnx = Some(real_segmenter()?);
    Some(cfg)
}

/// The real default segmenter's file, named explicitly from `../shared/models` ([`with_real_segmenter`];
/// for a command line, `--segmenter` it); else the test skips (fails under CI / REQUIRE_SHARED=1).
pub fn real_segmenter() -> Option<std::path::PathBuf> {
    shared_or_required(&format!("models/{}", semlook::networks::segmenter::DEFAULT_SEGMENTER))
}

/// Whether the XFeat weights setup.sh installs are found; if not, the test skips with the reason
/// (or fails under CI or REQUIRE_MODELS=1) and should return.
pub fn has_xfeat() -> bool {
    match semlook::nn::onnx::find_model(semlook::networks::xfeat::XFEAT_WEIGHTS, None, "XFeat") {
        Ok(_) => true,
        Err(e) => {
            skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (run setup.sh): {e}"));
            false
        }
    }
}

/// A small synthetic dataset: `places` frames per traversal at 160x120, two query conditions.
pub fn tiny_synth(dir: &Path, places: usize, seed: u64) -> SynthConfig {
    let cfg = SynthConfig {
        seed,
        places,
        width: 160,
        height: 120,
        queries: vec![semlook_cli::tools::synth::condition::Condition::Overcast, semlook_cli::tools::synth::condition::Condition::Night],
        ..Default::default()
    };
    synth::generate(&cfg, dir, &|| {}).unwrap();
    cfg
}

/// Deterministic label maps with a few rectangles of different classes.
pub fn label_maps(n: usize, w: u32, h: u32) -> Vec<LabelMap> {
    let table = semlook::classes::ClassTable::cityscapes();
    (0..n)
        .map(|k| {
            let mut rng = semlook::util::SplitMix64::new(k as u64 + 1);
            let mut c = vec![10u8; (w * h) as usize];
            for y in h / 2..h {
                for x in 0..w {
                    c[(y * w + x) as usize] = 0;
                }
            }
            for _ in 0..6 {
                let (x0, y0) = (rng.below(w as usize - 10) as u32, rng.below(h as usize - 10) as u32);
                let (bw, bh) = (5 + rng.below(w as usize / 3) as u32, 5 + rng.below(h as usize / 3) as u32);
                let class = [2u8, 8, 13, 5, 1, 9][rng.below(6)];
                for y in y0..(y0 + bh).min(h) {
                    for x in x0..(x0 + bw).min(w) {
                        c[(y * w + x) as usize] = class;
                    }
                }
            }
            LabelMap::new(w, h, c, &table).unwrap()
        })
        .collect()
}

/// Encodes label maps into a descriptor set with ids `prefix{i}`.
pub fn encode(cfg: &Config, maps: &[LabelMap], prefix: &str) -> DescriptorSet {
    let enc = Encoder::new(cfg).unwrap();
    let mut set = enc.descriptor_set();
    let mut scratch = Default::default();
    for (i, m) in maps.iter().enumerate() {
        set.push(&enc.encode_labels(&format!("{prefix}{i}"), m, &mut scratch).unwrap().0).unwrap();
    }
    set
}

/// Every file under `dir` with its bytes, sorted by path.
pub fn snapshot(dir: &Path) -> Vec<(String, Vec<u8>)> {
    let mut out = vec![];
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else {
                out.push((p.strip_prefix(dir).unwrap().display().to_string(), std::fs::read(&p).unwrap()));
            }
        }
    }
    out.sort();
    out
}

/// A rendered street scene's label map (day condition), the "real scene" of the GPU tests.
pub fn street_scene(w: usize, h: usize) -> LabelMap {
    let cfg = SynthConfig { places: 3, width: w, height: h, ..Default::default() };
    let scene = synth::Scene::new(&cfg);
    let dynamic = synth::dynamic_objects(&scene.world, cfg.seed, 0, cfg.persistence);
    let f = synth::render_frame(&cfg, &scene, &dynamic, 0, 1, semlook_cli::tools::synth::condition::Condition::Day);
    LabelMap::new(w as u32, h as u32, f.labels, &semlook::classes::ClassTable::cityscapes()).unwrap()
}

/// `../shared/REL` (the real data and models beside the repository) when it is there; else the
/// test skips with the reason, or fails under CI (`CI` set) or with REQUIRE_SHARED=1, where the
/// real-image guards must run.
pub fn shared_or_required(rel: &str) -> Option<std::path::PathBuf> {
    let p = repo().join("../shared").join(rel);
    if p.exists() {
        return Some(p);
    }
    skip_unless_required("REQUIRE_SHARED", format!("{} is absent", p.display()));
    None
}

/// Edits the text of map `dir`'s manifest.json with `edit` and seals it again with the checksum of
/// the new content, as a writer would: for tests of what the checks after the checksum refuse.
pub fn edit_sealed_manifest(dir: &Path, edit: impl FnOnce(&str) -> String) {
    let path = dir.join("manifest.json");
    let text = edit(&std::fs::read_to_string(&path).unwrap());
    let parsed: semlook::map::manifest::Manifest = serde_json::from_str(&text).unwrap();
    std::fs::write(&path, parsed.to_json().unwrap()).unwrap();
}

/// A path as the `&str` a command line takes.
pub fn p(path: &Path) -> &str {
    path.to_str().unwrap()
}

/// Flips the bits `mask` of the byte `from_end` bytes before the end of `path` (a file damaged on
/// disk); returns the file's bytes as they were.
pub fn damage(path: &Path, from_end: usize, mask: u8) -> Vec<u8> {
    let good = std::fs::read(path).unwrap();
    let mut bad = good.clone();
    let k = bad.len() - from_end;
    bad[k] ^= mask;
    std::fs::write(path, &bad).unwrap();
    good
}

/// The repository's root (the workspace's, where Cargo.lock is), whichever package's tests
/// include these helpers (the engine's `tests/`, the command line's `cli/tests/`).
pub fn repo() -> &'static Path {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest.ancestors().find(|d| d.join("Cargo.lock").is_file()).unwrap_or(manifest)
}
