//! Appearance: the native XFeat forward pass held to the ONNX export, keypoint decoding, VLAD.
//! Tests that need files from ../shared or from `setup.sh` print why they skip when those are
//! absent; under CI (CI set) the setup files must be there.

mod common;

use semlook::appearance::AppearanceModel;
use semlook::config::{AppearanceConfig, AppearanceModelKind, ModelPaths, Sampling};
use semlook::networks::network_input;
use std::path::{Path, PathBuf};

/// `../shared/REL`, required under CI (the real-image guards must run there).
fn shared(rel: &str) -> Option<PathBuf> {
    common::shared_or_required(rel)
}

/// Keypoint sampling: these tests hold the keypoint heads and their decoding (the default,
/// dense sampling, skips those heads).
fn keypoint_config() -> AppearanceConfig {
    AppearanceConfig { sampling: Sampling::Keypoints, ..Default::default() }
}

/// The native model from the setup folder (required under CI).
fn native() -> Option<AppearanceModel> {
    match AppearanceModel::load(&keypoint_config(), &ModelPaths::default()) {
        Ok(m) => m,
        Err(e) => {
            common::skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (setup.sh): {e}"));
            None
        }
    }
}

fn onnx(model: &Path) -> Option<AppearanceModel> {
    let cfg = AppearanceConfig { model: AppearanceModelKind::Onnx, ..keypoint_config() };
    match AppearanceModel::load(&cfg, &ModelPaths { keypoint_onnx: Some(model.into()), ..Default::default() }) {
        Ok(m) => m,
        Err(e) => {
            common::skip_unless_required("REQUIRE_MODELS", format!("ONNX Runtime (setup.sh): {e}"));
            None
        }
    }
}

fn max_diff(a: &semlook::nn::conv::Chw, b: &semlook::nn::conv::Chw) -> f32 {
    assert_eq!((a.c, a.h, a.w), (b.c, b.h, b.w));
    a.data.iter().zip(&b.data).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// Largest |a - b| / max(1, |b|).
fn max_rel_diff(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs() / y.abs().max(1.0)).fold(0.0, f32::max)
}

/// Native XFeat equals the ONNX export on real street frames at two sizes: descriptors,
/// reliability and the decoded keypoint probabilities within 1e-4 (absolute); the raw keypoint
/// logits, which reach |27|, within 1e-4 relative to max(1, |logit|) (a few f32 ulps at that
/// scale; the export itself agrees with PyTorch to 1.5e-4).
#[test]
fn native_xfeat_matches_the_onnx_oracle_on_real_images() {
    let (Some(frames), Some(model)) = (shared("data/street-frames"), shared("models/xfeat.onnx")) else { return };
    let (Some(native), Some(oracle)) = (native(), onnx(&model)) else { return };
    for name in ["frankfurt_000000_000294_leftImg8bit.png", "frankfurt_000000_000576_leftImg8bit.png"] {
        let rgb = image::open(frames.join(name)).unwrap().to_rgb8();
        for (w, h) in [(640u32, 320u32), (512, 384)] {
            let small = image::imageops::resize(&rgb, w, h, image::imageops::FilterType::Triangle);
            let (grey, _, _) = network_input(&small).unwrap();
            let a = native.run(&grey).unwrap();
            let b = oracle.run(&grey).unwrap();
            let d = max_diff(&a.descriptors, &b.descriptors);
            let r = max_diff(a.reliability.as_ref().unwrap(), b.reliability.as_ref().unwrap());
            let k = max_diff(&a.logits, &b.logits);
            let kr = max_rel_diff(&a.logits.data, &b.logits.data);
            let (pa, pb) = (semlook::appearance::keypoints::score_map(&a).unwrap().0, semlook::appearance::keypoints::score_map(&b).unwrap().0);
            let p = pa.iter().zip(&pb).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max);
            eprintln!(
                "{name} at {w}x{h}: max |diff| descriptors {d:.1e}, reliability {r:.1e}, keypoint scores {p:.1e}, logits {k:.1e} (relative {kr:.1e})"
            );
            assert!(d <= 1e-4 && r <= 1e-4 && p <= 1e-4 && kr <= 1e-4, "{name} {w}x{h}: {d} {r} {p} {kr}");
        }
    }
}

fn street_rgb(name: &str, w: u32, h: u32) -> Option<image::RgbImage> {
    let frames = shared("data/street-frames")?;
    let rgb = image::open(frames.join(name)).unwrap().to_rgb8();
    Some(image::imageops::resize(&rgb, w, h, image::imageops::FilterType::Triangle))
}

/// Keypoints on a real frame: at most N, best first, inside the border, unit descriptors, and
/// each one a local maximum of the score map within the NMS radius.
#[test]
fn keypoint_decoding_properties_on_a_real_frame() {
    let (Some(model), Some(rgb)) = (native(), street_rgb("frankfurt_000000_000294_leftImg8bit.png", 640, 480)) else { return };
    let cfg = keypoint_config();
    let (grey, _, _) = network_input(&rgb).unwrap();
    let out = model.run(&grey).unwrap();
    let (scores, h, w) = semlook::appearance::keypoints::score_map(&out).unwrap();
    let k = model.keypoints(&rgb).unwrap();
    assert!(k.len() > 200 && k.len() <= cfg.max_keypoints, "{} keypoints", k.len());
    assert!(k.scores.windows(2).all(|p| p[0] >= p[1]));
    let r = cfg.nms_radius as i64;
    for (i, p) in k.xy.iter().enumerate() {
        let (x, y) = (p[0] as i64, p[1] as i64);
        assert!(x >= cfg.border as i64 && y >= cfg.border as i64 && x < w as i64 - cfg.border as i64 && y < h as i64 - cfg.border as i64);
        assert!(k.scores[i] > cfg.score_threshold as f32);
        for yy in (y - r).max(0)..=(y + r).min(h as i64 - 1) {
            for xx in (x - r).max(0)..=(x + r).min(w as i64 - 1) {
                assert!(scores[(yy * w as i64 + xx) as usize] <= k.scores[i], "keypoint {i} is not a local maximum");
            }
        }
        let n: f32 = k.descriptors[i * k.dim..(i + 1) * k.dim].iter().map(|v| v * v).sum();
        assert!((n - 1.0).abs() < 1e-4);
    }
}

/// `--keypoints xfeat.onnx` (the generic ONNX path) finds the native model's keypoints.
#[test]
fn onnx_keypoint_path_agrees_with_native() {
    let (Some(model_path), Some(rgb)) = (shared("models/xfeat.onnx"), street_rgb("frankfurt_000000_000576_leftImg8bit.png", 512, 256)) else {
        return;
    };
    let (Some(a), Some(b)) = (native(), onnx(&model_path)) else { return };
    let (ka, kb) = (a.keypoints(&rgb).unwrap(), b.keypoints(&rgb).unwrap());
    assert_eq!(ka.dim, kb.dim);
    let set: std::collections::HashSet<(i32, i32)> = kb.xy.iter().map(|p| (p[0].round() as i32, p[1].round() as i32)).collect();
    let shared_kp = ka.xy.iter().filter(|p| set.contains(&(p[0].round() as i32, p[1].round() as i32))).count();
    eprintln!("{} native keypoints, {} ONNX, {shared_kp} identical", ka.len(), kb.len());
    assert!(shared_kp as f64 >= 0.98 * ka.len() as f64);
}

/// VLAD on a real scene (ESPNet labels, XFeat keypoints): the twin equals the definition for
/// every object; objects with keypoints get unit vectors, the others are flagged empty.
#[test]
fn vlad_on_a_real_scene() {
    let Some(rgb) = street_rgb("frankfurt_000000_000294_leftImg8bit.png", 1024, 512) else { return };
    let (Some(model), Some(seg_path)) = (native(), shared("models/espnet_cityscapes.onnx")) else { return };
    let cfg = semlook::config::Config::default();
    let table = semlook::classes::ClassTable::cityscapes();
    let seg = semlook::networks::segmenter::Segmenter::load(&seg_path, &cfg.segmentation, &table, None).unwrap();
    let labels = seg.segment(&rgb, Path::new("frame")).unwrap();
    let objects = semlook::objects::extract_objects(&labels, &table, &cfg.objects);
    let k = model.keypoints(&rgb).unwrap();
    let samples = semlook::appearance::sample_descriptors(&k, 400);
    let cb = semlook::global::vlad::train_codebook(&samples, k.dim, 8, 10, 1).unwrap();
    let (descs, offsets) = semlook::appearance::group_by_object(&k, &objects);
    let vectors = semlook::appearance::object_vlad(&descs, &offsets, &cb, Default::default());
    let present: Vec<bool> = semlook::appearance::object_counts(&offsets).iter().map(|&c| c > 0).collect();
    let with = present.iter().filter(|&&p| p).count();
    assert!(with >= 3, "only {with} objects hold keypoints");
    let per = cb.k * cb.dim;
    for o in 0..objects.objects.len() {
        let v = &vectors[o * per..(o + 1) * per];
        let (a, b) = (offsets[o] as usize, offsets[o + 1] as usize);
        if !present[o] {
            assert!(v.iter().all(|&x| x == 0.0));
            continue;
        }
        // the object's keypoints found here, not through group_by_object: those whose rounded
        // (clamped) pixel the object owns, their descriptors straight from the network's output
        let (w, h) = (objects.width as i64, objects.height as i64);
        let mine: Vec<&[f32]> = (0..k.len())
            .filter(|&i| {
                let (x, y) = ((k.xy[i][0].round() as i64).clamp(0, w - 1), (k.xy[i][1].round() as i64).clamp(0, h - 1));
                objects.object_of_pixel[(y * w + x) as usize] == o as u32
            })
            .map(|i| &k.descriptors[i * k.dim..(i + 1) * k.dim])
            .collect();
        assert_eq!(mine.len(), b - a, "object {o}: keypoints grouped");
        let r = semlook::global::vlad::vlad_reference(&cb.centres, cb.k, cb.dim, &mine, Default::default());
        assert!(v.iter().zip(&r).all(|(x, y)| (*x as f64 - y).abs() < 1e-4));
        assert!((v.iter().map(|x| x * x).sum::<f32>() - 1.0).abs() < 1e-4);
    }
}

/// The appearance half end to end on a small synthetic benchmark: trees carry VLAD vectors, the
/// map keeps the codebook and the network's checksum, and refuses another network.
#[test]
fn appearance_in_maps_and_evaluation() {
    if native().is_none() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    common::tiny_synth(dir.path(), 8, 3);
    let ds = semlook::dataset::Dataset::open(dir.path(), &Default::default()).unwrap();
    let cfg = semlook::config::Config::default();
    let mut enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let refs: Vec<_> = ds.reference.frames.iter().map(|f| f.source.clone()).collect();
    enc.train_codebook(&refs, &|| {}).unwrap();
    let mut engine = semlook::engine::Engine::cpu();
    let encoded = semlook::batch::encode_frames(&mut engine, &enc, &refs, ds.label_format, "refs", false, true).unwrap();
    let (set, summary) = (encoded.set.clone(), encoded.summary().mean);
    assert_eq!(set.appearance_dim, 64 * 64);
    let with = set.tree_has_appearance.iter().filter(|&&p| p == 1).count();
    assert!(with * 2 > set.n_trees(), "{with} of {} trees have appearance", set.n_trees());
    assert!(summary.network_ms > 0.0 && summary.appearance_ms >= summary.network_ms);
    let path = dir.path().join("map");
    let (cb, sha) = enc.appearance_record().unwrap();
    let map = semlook::map::Map::create(&path, &cfg.encoding(), &set, Some((cb, sha))).unwrap();
    let back = semlook::map::Map::open(&path).unwrap();
    assert_eq!(back.codebook(), map.codebook());
    assert_eq!(back.to_descriptor_set().unwrap(), set);
    semlook::encode::Encoder::for_map(&cfg, &back).unwrap();
    assert!(back.check_model(Some("0123456789abcdef")).is_err());
    assert!(back.check_model(None).is_err());
    // a damaged codebook is refused
    let cbf = path.join("codebook.safetensors");
    let mut bytes = std::fs::read(&cbf).unwrap();
    let n = bytes.len();
    bytes[n - 3] ^= 0x10;
    std::fs::write(&cbf, &bytes).unwrap();
    assert!(matches!(semlook::map::Map::open(&path), Err(semlook::Error::CorruptMap { .. })));
    // evaluation with appearance: the settings that use it rank differently from those that do not
    let report = semlook::eval::evaluate(
        &ds,
        &cfg,
        &semlook::eval::EvalOptions {
            settings: vec![semlook::matching::Setting::Forest, semlook::matching::Setting::Local],
            map: None,
            skip_invalid: false,
            quiet: true,
            sequence: false,
            label_cache: None,
        },
        &mut engine,
    )
    .unwrap();
    let scores = |s: semlook::matching::Setting| {
        report.results.iter().filter(|r| r.setting == s).flat_map(|r| r.outcomes.iter().map(|o| o.score.unwrap())).collect::<Vec<f32>>()
    };
    assert_ne!(scores(semlook::matching::Setting::Forest), scores(semlook::matching::Setting::Local));
}

/// Computing HOG too leaves the encoding of a real JPEG frame unchanged, bit for bit (labels from
/// the segmenter, global descriptor, forest, appearance). HOG decodes the full image on its own;
/// when it shared the decode, every stage saw the full decode instead of the scaled JPEG decode,
/// and `eval` of every setting (which computes HOG) reported other `semlook` figures than `eval
/// --setting semlook` on the same frames (Nordland R@1 0.733 against 0.767).
#[test]
fn hog_leaves_the_encoding_of_a_real_frame_unchanged() {
    use semlook::input::{FrameSource, LabelFormat};
    let Some(dir) = shared("data/real-vpr/nordland-spring-winter/query") else { return };
    let Some(cfg) = common::with_real_segmenter(semlook::config::Config::default()) else { return };
    let mut enc = match semlook::encode::Encoder::new(&cfg) {
        Ok(e) => e,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (setup.sh): {e}")),
    };
    let src = FrameSource { id: "q020".into(), image: Some(dir.join("020.jpg")), labels: None };
    if let Err(e) = enc.train_codebook(std::slice::from_ref(&src), &|| {}) {
        return common::skip_unless_required("REQUIRE_MODELS", format!("segmenter / ONNX Runtime (setup.sh): {e}"));
    }
    let with_hog = enc.clone().with_hog(true);
    let mut scratch = Default::default();
    let a = enc.encode_source(&src, LabelFormat::default(), &mut scratch).unwrap().0;
    let b = with_hog.encode_source(&src, LabelFormat::default(), &mut scratch).unwrap().0;
    assert!(a.hog.is_empty() && !b.hog.is_empty());
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    // compared without printing the vectors (thousands of values)
    assert!(bits(&a.global) == bits(&b.global), "global descriptor differs");
    assert!((&a.forest.classes, &a.forest.neighbours) == (&b.forest.classes, &b.forest.neighbours), "trees differ");
    assert!(bits(&a.forest.areas) == bits(&b.forest.areas), "tree areas differ");
    assert!(bits(&a.forest.appearance) == bits(&b.forest.appearance), "tree appearance differs");
    assert!(bits(&a.appearance) == bits(&b.appearance), "image appearance differs");
    // and HOG is still VPR-Bench's: from the full-size decode
    let (full, _) = semlook::input::load_rgb_at_least(&dir.join("020.jpg"), |size| size).unwrap();
    assert!(bits(&b.hog) == bits(&semlook::global::hog::vprbench_hog(&full)), "HOG is not from the full-size decode");
}
