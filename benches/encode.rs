//! Encoding time per frame at 640x480 (no network): global descriptor, forest, and both; then the
//! networks' rows (XFeat and VLAD, the whole-image embedding) where setup.sh installed them.
//! Target (issue 2): <= 10 ms per frame, median, on 2 cores (one frame runs on one core).

use criterion::{criterion_group, criterion_main, Criterion};
use semlook::config::Config;
use semlook::encode::Encoder;
use semlook::global::{encode_global, GlobalScratch};
use semlook_cli::tools::synth::condition::Condition;

mod common;

fn bench(c: &mut Criterion) {
    let cfg = Config::without_appearance();
    let maps = common::street_labels(4, 640, 480, Condition::Day);
    let enc = Encoder::new(&cfg).unwrap();
    let table = enc.class_table().clone();
    let p = cfg.global.ssim_params();
    let mut g = c.benchmark_group("encode_640x480");
    let mut scratch = GlobalScratch::default();
    let mut k = 0;
    g.bench_function("total", |b| {
        b.iter(|| {
            k = (k + 1) % maps.len();
            enc.encode_labels("x", &maps[k], &mut scratch).unwrap()
        })
    });
    let (mut d, mut s) = (vec![0.0; p.len()], vec![0.0; p.stats_len()]);
    g.bench_function("global (edges, EDT, pooling, SSIM stats)", |b| {
        b.iter(|| encode_global(&maps[0], &table.used_mask(), &cfg.global, &mut scratch, &mut d, &mut s).unwrap())
    });
    g.bench_function("forest (objects, trees)", |b| {
        b.iter(|| {
            let o = semlook::objects::extract_objects(&maps[0], &table, &cfg.objects);
            semlook::local::build_forest(&o, &cfg.local)
        })
    });
    // appearance, reported apart from the rest as the paper's Table 2 does (needs setup.sh)
    match semlook::appearance::AppearanceModel::load(&Default::default(), &Default::default()) {
        Ok(Some(model)) => {
            let scfg = semlook_cli::tools::synth::SynthConfig { places: 3, width: 640, height: 480, ..Default::default() };
            let scene = semlook_cli::tools::synth::Scene::new(&scfg);
            let dynamic = semlook_cli::tools::synth::dynamic_objects(&scene.world, scfg.seed, 0, scfg.persistence);
            let f = semlook_cli::tools::synth::render_frame(&scfg, &scene, &dynamic, 0, 1, Condition::Day);
            let rgb = image::RgbImage::from_raw(640, 480, f.rgb).unwrap();
            let (grey, _, _) = semlook::networks::network_input(&rgb).unwrap();
            // the network as encoding runs it (dense descriptors for VLAD and the keypoint heads
            // for the stored verification keypoints), and without the heads (appearance alone)
            let kp = Config::default().keypoints;
            let with_heads =
                semlook::appearance::AppearanceModel::load(&Default::default(), &Default::default()).unwrap().unwrap().with_detection(&kp);
            g.bench_function("appearance: XFeat network with the keypoint heads (native)", |b| b.iter(|| with_heads.run(&grey).unwrap()));
            g.bench_function("appearance: XFeat network, dense descriptors only (native)", |b| b.iter(|| model.run(&grey).unwrap()));
            // decoding needs the heads' outputs
            let out = with_heads.run(&grey).unwrap();
            // the decoding as the configuration sets it (`[appearance]`, and `[keypoints]` below)
            let params = semlook::appearance::keypoints::KeypointParams::appearance(&Config::default().appearance);
            g.bench_function("appearance: keypoint decoding (keypoints::extract, keypoint sampling)", |b| {
                b.iter(|| semlook::appearance::keypoints::extract(&out, &params).unwrap())
            });
            let Some(detect) = semlook::appearance::keypoints::KeypointParams::verification(&kp) else {
                return eprintln!("keypoint detection benchmark skipped: the config stores no verification keypoints");
            };
            g.bench_function("appearance: verification keypoints (keypoints::detect)", |b| {
                b.iter(|| semlook::appearance::keypoints::detect(&out, &detect).unwrap())
            });
            let k = model.keypoints(&rgb).unwrap();
            let objects = semlook::objects::extract_objects(&maps[1], &table, &cfg.objects);
            let cb = semlook::global::vlad::train_codebook(&semlook::appearance::sample_descriptors(&k, 512), k.dim, 16, 10, 1).unwrap();
            g.bench_function("appearance: VLAD per object (CPU)", |b| {
                b.iter(|| {
                    let (d, o) = semlook::appearance::group_by_object(&k, &objects);
                    semlook::appearance::object_vlad(&d, &o, &cb, Default::default())
                })
            });
        }
        other => eprintln!("appearance benchmarks skipped: {:?}", other.err()),
    }
    // the whole-image embedding of a 640 x 480 frame (the fused coarse stage's embedding term;
    // needs setup.sh), one call with ONNX Runtime's threads for the whole machine
    match semlook::networks::embedding::from_config(&Default::default(), &Default::default()) {
        Ok(Some(e)) => {
            let rgb = image::RgbImage::from_fn(640, 480, |x, y| image::Rgb([(x % 256) as u8, (y % 256) as u8, ((x ^ y) % 256) as u8]));
            g.bench_function("embedding: EfficientNet-Lite1 + GeM at 448 x 336 (ONNX Runtime)", |b| b.iter(|| e.embed(&rgb).unwrap()));
        }
        other => eprintln!("embedding benchmark skipped: {:?}", other.err().map_or("not installed".to_string(), |e| e.to_string())),
    }
    // the same network run natively from its checkpoint (issue 61 part 1; the same input)
    let native = semlook::networks::embedding::EMBEDDING_CHECKPOINT;
    match semlook::nn::onnx::find_model(native, None, "embedding checkpoint").and_then(|p| semlook::networks::embedding::Embedder::new(&p, None, 448))
    {
        Ok(e) => {
            let rgb = image::RgbImage::from_fn(640, 480, |x, y| image::Rgb([(x % 256) as u8, (y % 256) as u8, ((x ^ y) % 256) as u8]));
            g.bench_function("embedding: EfficientNet-Lite1 + GeM at 448 x 336 (native, from the checkpoint)", |b| b.iter(|| e.embed(&rgb).unwrap()));
        }
        Err(e) => eprintln!("native embedding benchmark skipped: {e}"),
    }
    g.finish();
    streamed_frame(c);
}

/// A stream's frame (CamVid's first photo, 960x720, worked at 640x480) encoded alone, as a stream
/// encodes it, with the real-time profile (configs/stream-realtime.toml: no labels, XFeat, VLAD,
/// the embedding at 320): the embedding on a thread beside the appearance stage (the default), and
/// after it ([`Encoder::embedding_beside`] off). Needs setup.sh's networks and ../shared's CamVid.
fn streamed_frame(c: &mut Criterion) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let photo = root.join("../shared/data/camvid-test/images/0001TP_008550.png");
    let cfg = match Config::load(&root.join("configs/stream-realtime.toml")) {
        Ok(cfg) if photo.exists() => cfg,
        _ => return eprintln!("streamed-frame benchmark skipped: no ../shared/data/camvid-test or no profile"),
    };
    let mut enc = match Encoder::new(&cfg) {
        Ok(e) if e.appearance().is_some() && e.embedding_record().is_some() => e.without_labels(true),
        _ => return eprintln!("streamed-frame benchmark skipped: XFeat or the embedding network not installed (setup.sh)"),
    };
    let src = semlook::input::FrameSource { id: "frame".into(), image: Some(photo), labels: None };
    let loaded = enc.frames().load(&src, Default::default()).unwrap();
    let a = enc.appearance_mut().unwrap();
    let kps = a.model().keypoints(loaded.rgb.as_ref().unwrap()).unwrap();
    a.train_codebook_from(&[&kps]).unwrap();
    let after = enc.clone().embedding_beside(false);
    let mut g = c.benchmark_group("encode_streamed_frame_640x480_realtime_profile");
    g.bench_function("embedding beside the appearance stage (default)", |b| {
        b.iter(|| enc.encode_loaded("frame", &loaded, &mut Default::default()).unwrap())
    });
    g.bench_function("embedding after the appearance stage", |b| b.iter(|| after.encode_loaded("frame", &loaded, &mut Default::default()).unwrap()));
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(4));
    targets = bench
}
criterion_main!(benches);
