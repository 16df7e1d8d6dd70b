//! The GPU encoding path streams its frames and keeps its resources (issue 19 part 1): a
//! repeated batch creates no buffer or bind group and uploads only its frames (one byte per
//! label pixel); the VLAD executor uploads its centres only when the codebook changes; frames
//! are decoded `STREAM_FRAMES` at a time, so peak memory does not grow with their number; and on
//! real CamVid frames the GPU path's labels, descriptors and top-K equal the CPU path's.

use super::common;
use super::gpu;
use semlook::config::{AppearanceConfig, AppearanceModelKind, Config};
use semlook::descriptors::EncodedImage;
use semlook::encode::Encoder;
use semlook::engine::{Engine, STREAM_FRAMES};
use semlook::input::{FrameSource, LabelFormat};
use semlook::matching::Setting;
use std::path::Path;

/// `n` label-map PNGs of `w` x `h` in `dir` (eight different scenes, repeated), as frames.
fn label_frames(dir: &Path, n: usize, w: u32, h: u32, tag: &str) -> Vec<FrameSource> {
    std::fs::create_dir_all(dir).unwrap();
    let scenes = common::label_maps(8, w, h);
    (0..n)
        .map(|i| {
            let m = &scenes[i % scenes.len()];
            let path = dir.join(format!("{tag}{i:04}.png"));
            image::GrayImage::from_fn(w, h, |x, y| image::Luma([m.get(x, y)])).save(&path).unwrap();
            FrameSource { id: format!("{tag}{i:04}"), image: None, labels: Some(path) }
        })
        .collect()
}

fn encode(engine: &mut Engine, enc: &Encoder, frames: &[FrameSource]) -> Vec<EncodedImage> {
    engine.encode_all(enc, frames, LabelFormat::default(), &|| {}).unwrap().into_iter().map(|r| r.unwrap().0).collect()
}

/// The second of two encoding batches of one size creates no buffer and no bind group, uploads
/// exactly its label maps (one byte per pixel, the batch rounded up to a word) and reads back
/// exactly its descriptors and SSIM statistics; the results equal the CPU path's.
#[test]
fn a_second_batch_creates_nothing_and_uploads_only_its_frames() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let enc = Encoder::new(&cfg).unwrap();
    let (w, h) = (97, 61);
    let (a, b) = (label_frames(dir.path(), 3, w, h, "a"), label_frames(&dir.path().join("b"), 3, w, h, "b"));
    let mut engine = Engine::with_context(ctx.clone());
    let start = ctx.counters();
    encode(&mut engine, &enc, &a);
    let first = ctx.counters() - start;
    assert!(first.buffers_created > 0 && first.bind_groups_created > 0, "the first batch made nothing: {first:?}");
    let before = ctx.counters();
    let got = encode(&mut engine, &enc, &b);
    let second = ctx.counters() - before;
    let p = cfg.global.ssim_params();
    assert_eq!(second.buffers_created, 0, "{second:?}");
    assert_eq!(second.bind_groups_created, 0, "{second:?}");
    assert_eq!(second.bytes_uploaded, (3 * w as u64 * h as u64).next_multiple_of(4), "{second:?}");
    assert_eq!(second.bytes_read_back, 3 * (p.len() + p.stats_len()) as u64 * 4, "{second:?}");
    let cpu = encode(&mut Engine::cpu(), &enc, &b);
    for (g, c) in got.iter().zip(&cpu) {
        assert_eq!(g.forest, c.forest, "{}: forests", g.id);
        let worst =
            g.global.iter().chain(&g.global_stats).zip(c.global.iter().chain(&c.global_stats)).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(worst <= 1e-5, "{}: descriptors or statistics differ by {worst}", g.id);
    }
}

/// The VLAD executor keeps its centres, uniform and bind groups: a second batch of the same
/// shape uploads only its descriptors and run offsets and creates nothing; another codebook's
/// centres are uploaded once.
#[test]
fn vlad_uploads_its_centres_once_per_codebook() {
    use semlook::global::vlad::{Codebook, VladNorm};
    let Some(ctx) = gpu() else { return };
    let mut rng = semlook::util::SplitMix64::new(3);
    let (k, dim) = (8, 16);
    let mut random = |n: usize| (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect::<Vec<f32>>();
    let cb = Codebook { k, dim, centres: random(k * dim) };
    let other = Codebook { k, dim, centres: random(k * dim) };
    // two frames: 3 objects + the image run each, 20 descriptors
    let (d1, d2) = (random(20 * dim), random(20 * dim));
    let offsets: Vec<u32> = vec![0, 5, 12, 20, 40];
    // each frame's descriptors by object, then all of them (the image run)
    let (f1, f2) = ([d1.as_slice(), &d1].concat(), [d2.as_slice(), &d2].concat());
    let mut vlad = semlook::gpu::VladGpu::new(ctx.clone());
    let run = |vlad: &mut semlook::gpu::VladGpu, cb: &Codebook, frames: [&[f32]; 2]| {
        vlad.run(cb, VladNorm::default(), &frames.map(|d| (d, offsets.as_slice()))).unwrap()
    };
    let first = run(&mut vlad, &cb, [&f1, &f2]);
    let before = ctx.counters();
    let second = run(&mut vlad, &cb, [&f2, &f1]);
    let d = ctx.counters() - before;
    let frame_bytes = (2 * f1.len() * 4 + (2 * (offsets.len() - 1) + 1) * 4) as u64;
    assert_eq!((d.buffers_created, d.bind_groups_created), (0, 0), "{d:?}");
    assert_eq!(d.bytes_uploaded, frame_bytes, "only the descriptors and the run offsets: {d:?}");
    assert!(first[0] == second[1] && first[1] == second[0], "the same frames in the other order");
    let before = ctx.counters();
    run(&mut vlad, &other, [&f2, &f1]);
    let d = ctx.counters() - before;
    assert_eq!(d.bytes_uploaded, frame_bytes + (k * dim * 4) as u64, "another codebook's centres are uploaded: {d:?}");
}

/// Frames are decoded `STREAM_FRAMES` at a time whatever their number, and come back in order.
#[test]
fn frames_are_decoded_a_chunk_at_a_time() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let frames = label_frames(dir.path(), 2 * STREAM_FRAMES + 5, 64, 48, "f");
    let enc = Encoder::new(&Config::without_appearance()).unwrap();
    let mut engine = Engine::with_context(ctx);
    let got = encode(&mut engine, &enc, &frames);
    assert_eq!(got.iter().map(|g| g.id.as_str()).collect::<Vec<_>>(), frames.iter().map(|f| f.id.as_str()).collect::<Vec<_>>());
    assert_eq!(engine.gpu_stages().unwrap().decoded_peak(), STREAM_FRAMES);
}

/// Peak memory of a GPU encoding does not grow with the number of frames: the same run on 100
/// and on 500 frames of 480x360 (each decoded frame holds 173 kB of labels; 400 more frames held
/// at once would add 69 MB) differ in peak resident memory by less than 30 MB (the 400 more
/// descriptors returned take about 13 MB). Each run is a child process of this test binary
/// (`SEMLOOK_STREAM_CHILD`), which prints its peak (VmHWM).
#[test]
fn peak_memory_does_not_grow_with_the_frame_count() {
    if let Ok(job) = std::env::var("SEMLOOK_STREAM_CHILD") {
        let (dir, n) = job.split_once(':').unwrap();
        let frames: Vec<FrameSource> = (0..n.parse::<usize>().unwrap())
            .map(|i| FrameSource { id: format!("f{i:04}"), image: None, labels: Some(Path::new(dir).join(format!("f{i:04}.png"))) })
            .collect();
        let ctx = gpu().expect("the parent found an adapter");
        let enc = Encoder::new(&Config::without_appearance()).unwrap();
        let got = encode(&mut Engine::with_context(ctx), &enc, &frames);
        assert_eq!(got.len(), frames.len());
        let status = std::fs::read_to_string("/proc/self/status").unwrap();
        let hwm = status.lines().find_map(|l| l.strip_prefix("VmHWM:")).unwrap().trim().trim_end_matches(" kB").trim().to_string();
        println!("VMHWM_KB={hwm}");
        return;
    }
    if !cfg!(target_os = "linux") {
        return common::skip("reads /proc/self/status");
    }
    let Some(_ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    label_frames(dir.path(), 500, 480, 360, "f");
    let peak = |n: usize| -> f64 {
        let out = std::process::Command::new(std::env::current_exe().unwrap())
            .args(["--exact", "stream::peak_memory_does_not_grow_with_the_frame_count", "--nocapture", "--test-threads=1"])
            .env("SEMLOOK_STREAM_CHILD", format!("{}:{n}", dir.path().display()))
            .output()
            .unwrap();
        let text = String::from_utf8_lossy(&out.stdout);
        let kb = text.split("VMHWM_KB=").nth(1).map(|s| s.chars().take_while(char::is_ascii_digit).collect::<String>());
        let kb = kb.unwrap_or_else(|| panic!("child for {n} frames: {text}\n{}", String::from_utf8_lossy(&out.stderr)));
        kb.parse::<f64>().unwrap() / 1024.0
    };
    let (small, large) = (peak(100), peak(500));
    eprintln!("GPU encoding peak resident memory: {small:.0} MiB for 100 frames, {large:.0} MiB for 500 (480x360 label maps)");
    assert!(large - small < 30.0, "peak memory grew by {:.0} MiB from 100 to 500 frames", large - small);
}

/// On real CamVid frames (real labels; `../shared`, required under CI) the GPU path encodes what
/// the CPU path does (labels as given, forests equal, descriptors and statistics within 1e-5)
/// and both engines give the same top-K in the coarse and the fine settings.
#[test]
fn real_camvid_frames_encode_and_match_alike_on_both_paths() {
    let Some(dir) = common::shared_or_required("data/camvid-test/labels") else { return };
    let Some(ctx) = gpu() else { return };
    let mut files: Vec<_> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "png")).collect();
    files.sort();
    let cfg = Config { appearance: AppearanceConfig { model: AppearanceModelKind::None, ..Default::default() }, ..Config::camvid() };
    let enc = Encoder::new(&cfg).unwrap();
    let frames: Vec<FrameSource> = files
        .iter()
        .step_by(6)
        .map(|f| FrameSource { id: f.file_stem().unwrap().to_string_lossy().into(), image: None, labels: Some(f.clone()) })
        .collect();
    let mut gpu_engine = Engine::with_context(ctx);
    let (g, c) = (encode(&mut gpu_engine, &enc, &frames), encode(&mut Engine::cpu(), &enc, &frames));
    assert!(g.len() >= 30, "{} frames", g.len());
    for (a, b) in g.iter().zip(&c) {
        assert_eq!((a.width, a.height), (b.width, b.height));
        assert_eq!(a.forest, b.forest, "{}: forests (from the labels)", a.id);
        let worst =
            a.global.iter().chain(&a.global_stats).zip(b.global.iter().chain(&b.global_stats)).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(worst <= 1e-5, "{}: descriptors or statistics differ by {worst}", a.id);
    }
    let set = |imgs: &[EncodedImage], even: bool| {
        let mut s = enc.descriptor_set();
        imgs.iter().enumerate().filter(|(i, _)| (i % 2 == 0) == even).for_each(|(_, e)| s.push(e).unwrap());
        s
    };
    let (refs, queries) = (set(&c, true), set(&g, false));
    for setting in [Setting::Global, Setting::GlobalForest, Setting::Forest] {
        let (on_gpu, _) = gpu_engine.match_batch(&refs, &queries, setting, &cfg).unwrap();
        let (on_cpu, _) = Engine::cpu().match_batch(&refs, &queries, setting, &cfg).unwrap();
        for (q, (a, b)) in on_gpu.iter().zip(&on_cpu).enumerate() {
            let ids = |m: &semlook::matching::QueryMatch| m.ranked.iter().map(|c| c.reference).collect::<Vec<_>>();
            assert_eq!(ids(a), ids(b), "{setting}: query {q}'s ranking");
        }
    }
}

/// Real CamVid photos without their labels: the segmenter labels them and XFeat describes them,
/// on the device for the GPU engine. Forests (from the segmenter's labels) are equal, global
/// descriptors within 1e-5, appearance vectors (stored as int8 blocks) equal but for single
/// rounding steps, the verification keypoints at the same positions, and the recommended
/// setting's rankings identical.
#[test]
fn real_camvid_photos_segmented_and_described_alike_on_both_paths() {
    let Some(dir) = common::shared_or_required("data/camvid-test/images") else { return };
    let Some(ctx) = gpu() else { return };
    let mut files: Vec<_> =
        std::fs::read_dir(&dir).unwrap().map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "png")).collect();
    files.sort();
    let frames: Vec<FrameSource> = files
        .iter()
        .step_by(29)
        .take(8)
        .map(|f| FrameSource { id: f.file_stem().unwrap().to_string_lossy().into(), image: Some(f.clone()), labels: None })
        .collect();
    let Some(cfg) = common::with_real_segmenter(Config::default()) else { return };
    let mut enc = match Encoder::new(&cfg) {
        Ok(e) => e,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("an encoder with appearance: {e}")),
    };
    if let Err(e) = enc.train_codebook(&frames, &|| {}) {
        return common::skip_unless_required("REQUIRE_MODELS", format!("the codebook (segmenter and XFeat): {e}"));
    }
    let mut gpu_engine = Engine::with_context(ctx);
    let (g, c) = (encode(&mut gpu_engine, &enc, &frames), encode(&mut Engine::cpu(), &enc, &frames));
    assert_eq!(gpu_engine.gpu_stages().unwrap().network_frames(), frames.len() as u64, "the network ran on the device");
    for (a, b) in g.iter().zip(&c) {
        assert_eq!(a.forest.classes, b.forest.classes, "{}: the objects of the segmenter's labels", a.id);
        assert_eq!(a.keypoints.xy, b.keypoints.xy, "{}: verification keypoints", a.id);
        let worst = a.global.iter().zip(&b.global).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max);
        assert!(worst <= 1e-5, "{}: global descriptors differ by {worst}", a.id);
        for (x, y) in a.appearance.chunks(64).zip(b.appearance.chunks(64)) {
            let step = y.iter().fold(0.0f32, |m, v| m.max(v.abs())) / 63.5;
            assert!(x.iter().zip(y).all(|(p, q)| (p - q).abs() <= step * 1.001), "{}: appearance beyond one int8 step", a.id);
        }
    }
    let set = |imgs: &[EncodedImage], even: bool| {
        let mut s = enc.descriptor_set();
        imgs.iter().enumerate().filter(|(i, _)| (i % 2 == 0) == even).for_each(|(_, e)| s.push(e).unwrap());
        s
    };
    let (refs, queries) = (set(&c, true), set(&g, false));
    let (on_gpu, _) = gpu_engine.match_batch(&refs, &queries, Setting::RECOMMENDED, &cfg).unwrap();
    let (on_cpu, _) = Engine::cpu().match_batch(&refs, &queries, Setting::RECOMMENDED, &cfg).unwrap();
    for (q, (a, b)) in on_gpu.iter().zip(&on_cpu).enumerate() {
        let ids = |m: &semlook::matching::QueryMatch| m.ranked.iter().map(|c| c.reference).collect::<Vec<_>>();
        assert_eq!(ids(a), ids(b), "verified: query {q}'s ranking");
    }
}
