//! GPU kernels held to their CPU twins (on lavapipe in CI; on a real GPU where there is one).
//! On a machine without any adapter the tests print why they skip; under CI (CI set) or with
//! REQUIRE_GPU=1 a missing adapter is a failure, so CI cannot pass without running them.

mod bench;
#[path = "../common/mod.rs"]
mod common;
mod embedding;
mod fine;
mod lighterglue;
mod resident;
mod stream;
mod verify;
mod xfeat;

use semlook::gpu::{GpuContext, GpuOptions};
use std::sync::Arc;

pub fn gpu_with(opts: &GpuOptions) -> Option<Arc<GpuContext>> {
    match GpuContext::new(opts) {
        Ok(c) => {
            eprintln!("GPU tests on {}", c.describe());
            Some(Arc::new(c))
        }
        // a kernel the driver refuses is a bug of ours, never a missing adapter
        Err(e @ semlook::gpu::GpuError::Shader { .. }) => panic!("{e}"),
        Err(e) => {
            // Printed past the output capture and counted, so a plain `cargo test` shows it.
            common::skip_unless_required("REQUIRE_GPU", format!("no GPU adapter ({e})"));
            None
        }
    }
}

pub fn gpu() -> Option<Arc<GpuContext>> {
    gpu_with(&GpuOptions::default())
}

/// Every kernel's pipeline is created on the adapter, without subgroups and (where the adapter
/// has them) with: the driver checks each bind group layout against the shader's bindings, which
/// build.rs's naga validation of the WGSL alone cannot (a wrong slot here fails this test).
#[test]
fn every_kernel_pipeline_is_created_on_the_adapter() {
    let Some(ctx) = gpu() else { return };
    semlook::gpu::create_every_pipeline(&ctx.device, false).unwrap_or_else(|e| panic!("without subgroups: {e}"));
    if ctx.uses_subgroups() {
        semlook::gpu::create_every_pipeline(&ctx.device, true).unwrap_or_else(|e| panic!("with subgroups: {e}"));
    }
}

#[test]
fn global_encoding_matches_the_cpu_twins() {
    let Some(ctx) = gpu() else { return };
    let cfg = semlook::config::Config::without_appearance();
    let table = semlook::classes::ClassTable::cityscapes();
    let maps = common::label_maps(3, 97, 61);
    let refs: Vec<&semlook::input::LabelMap> = maps.iter().collect();
    let mut enc = semlook::gpu::GlobalEncoderGpu::new(ctx);
    let out = enc.encode(&refs, &table.used_mask(), &cfg.global).unwrap();
    let d2 = enc.last_d2(3 * 97 * 61).unwrap();
    let mut scratch = semlook::global::GlobalScratch::default();
    let p = cfg.global.ssim_params();
    for (i, m) in maps.iter().enumerate() {
        let (mut d, mut s) = (vec![0.0; p.len()], vec![0.0; p.stats_len()]);
        semlook::global::encode_global(m, &table.used_mask(), &cfg.global, &mut scratch, &mut d, &mut s).unwrap();
        assert_eq!(&d2[i * 97 * 61..(i + 1) * 97 * 61], scratch_d2(&scratch), "frame {i}: squared distances differ");
        let worst = d.iter().zip(&out[i].0).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-5, "frame {i}: pooled values differ by {worst}");
        stats_match_the_twins(&p, &out[i], &format!("frame {i}"));
    }
}

/// The device's SSIM statistics of an encoded descriptor against the twins (`stats_row_sums`,
/// `stats_windows`) run on the very descriptor the device pooled: within 1e-6 (the same sums in
/// the same order; a device may fuse a multiply-add).
pub fn stats_match_the_twins(p: &SsimParams, (desc, stats): &(Vec<f32>, Vec<f32>), what: &str) {
    use semlook_kernels::ssim_stats::{stats_row_sums, stats_windows};
    let mut rows = vec![0.0; 2 * p.gh as usize * p.nw as usize];
    let mut want = vec![0.0; p.stats_len()];
    let dims = semlook_kernels::abi::Dims { frames: 1, ..Default::default() };
    stats_row_sums(p, &dims, desc, &mut rows);
    stats_windows(p, &dims, &rows, &mut want);
    assert_eq!(stats.len(), want.len(), "{what}: stats length");
    let worst = stats.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
    assert!(worst <= 1e-6, "{what}: SSIM statistics differ from the twins' by {worst}");
}

fn scratch_d2(s: &semlook::global::GlobalScratch) -> &[u32] {
    s.d2()
}

use semlook::config::Config;
use semlook::descriptors::DescriptorSet;
use semlook::engine::{Backend, Engine};
use semlook::local::Forest;
use semlook::matching::{coarse_topk_twin, match_batch, Setting, Stages};
use semlook::util::SplitMix64;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::tree_similarity::{tree_similarity, TreeSimScratch};

/// Random label maps of awkward sizes: thin, odd, a single class (no edges), many classes.
fn random_maps(seed: u64) -> Vec<semlook::input::LabelMap> {
    let t = semlook::classes::ClassTable::cityscapes();
    let mut rng = SplitMix64::new(seed);
    let sizes = [(1u32, 1u32), (1, 17), (23, 1), (5, 9), (33, 31), (64, 3), (40, 40)];
    sizes
        .iter()
        .enumerate()
        .map(|(k, &(w, h))| {
            let classes = if k == 4 {
                vec![2u8; (w * h) as usize]
            } else {
                let n = 1 + rng.below(5);
                (0..w * h)
                    .map(|_| {
                        let c = rng.below(n + 1) as u8;
                        if c == n as u8 {
                            255
                        } else {
                            c
                        }
                    })
                    .collect()
            };
            semlook::input::LabelMap::new(w, h, classes, &t).unwrap()
        })
        .collect()
}

fn cpu_global(m: &semlook::input::LabelMap, cfg: &Config) -> (Vec<u32>, Vec<u32>, Vec<f32>) {
    let table = semlook::classes::ClassTable::cityscapes();
    let p = cfg.global.ssim_params();
    let mut scratch = semlook::global::GlobalScratch::default();
    let (mut d, mut s) = (vec![0.0; p.len()], vec![0.0; p.stats_len()]);
    semlook::global::encode_global(m, &table.used_mask(), &cfg.global, &mut scratch, &mut d, &mut s).unwrap();
    (scratch.edges().to_vec(), scratch.d2().to_vec(), d)
}

/// Edges and squared distances exactly equal; pooled values within 1e-5 (f32 sqrt and summation
/// order on the GPU), on random maps of awkward sizes and on a rendered 640x480 street scene.
#[test]
fn edges_and_edt_are_exact_and_pooling_within_1e_5() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config { global: semlook::config::GlobalConfig { width: 16, height: 12, ..Default::default() }, ..Default::default() };
    let mut enc = semlook::gpu::GlobalEncoderGpu::new(ctx);
    let used = semlook::classes::ClassTable::cityscapes().used_mask();
    let mut maps = random_maps(1);
    maps.extend(random_maps(2));
    let street = common::street_scene(640, 480);
    let full = Config::without_appearance();
    for (i, m) in maps.iter().chain(std::iter::once(&street)).enumerate() {
        let c = if i == maps.len() { &full } else { &cfg };
        let out = enc.encode(&[m], &used, &c.global).unwrap();
        let px = (m.width() * m.height()) as u64;
        let (edges, d2, pooled) = cpu_global(m, c);
        assert_eq!(enc.last_edges(px).unwrap(), edges, "map {i} ({}x{}): edges", m.width(), m.height());
        let gd2 = enc.last_d2(px).unwrap();
        let inf2 = ((m.width() + m.height()) as u64).pow(2) as u32;
        if edges.iter().any(|&e| e != 0) {
            assert_eq!(gd2, d2, "map {i}: squared distances");
        } else {
            assert!(gd2.iter().all(|&v| v >= inf2), "map {i}: no edges but finite distances");
        }
        let worst = pooled.iter().zip(&out[0].0).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
        assert!(worst <= 1e-5, "map {i}: pooled values differ by {worst}");
        stats_match_the_twins(&c.global.ssim_params(), &out[0], &format!("map {i}"));
    }
}

pub fn random_descriptors(n: usize, cfg: &Config, seed: u64) -> DescriptorSet {
    let p = cfg.global.ssim_params();
    let mut set = DescriptorSet::new(&p, 3, 0, 0);
    let mut rng = SplitMix64::new(seed);
    for i in 0..n {
        // smooth random fields, like distance maps
        let (fx, fy, ph) = (rng.range(0.05, 0.4), rng.range(0.05, 0.4), rng.range(0.0, 6.0));
        let g: Vec<f32> = (0..p.len())
            .map(|k| {
                let (x, y) = ((k % p.gw as usize) as f64, (k / p.gw as usize) as f64);
                (0.5 + 0.5 * (fx * x + ph).sin() * (fy * y).cos()) as f32
            })
            .collect();
        let mut stats = vec![0.0; p.stats_len()];
        semlook_kernels::ssim::ssim_stats(&p, &g, &mut stats, &mut Default::default());
        let img = semlook::descriptors::EncodedImage {
            id: format!("r{i}"),
            width: 64,
            height: 48,
            global: g,
            global_stats: stats,
            forest: Forest { neighbour_slots: 3, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: Default::default(),
            pose: None,
        };
        set.push(&img).unwrap();
    }
    set
}

/// Batched SSIM and streaming top-K: scores within 1e-5 of the CPU twin, the same K-lists where
/// scores are not tied within that tolerance.
#[test]
fn coarse_top_k_matches_the_cpu_twin() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let refs = random_descriptors(150, &cfg, 3);
    let queries = random_descriptors(9, &cfg, 4);
    let mut stages = semlook::gpu::GpuStages::new(ctx);
    for (k, tile) in [(10, 4096), (7, 16), (1, 1)] {
        let gpu = stages.coarse(&refs, &queries, &p, k, tile).unwrap();
        let cpu = coarse_topk_twin(&refs, &queries, &p, k, tile);
        assert_same_lists(&gpu, &cpu, 1e-5, &format!("k {k}, tile {tile}"));
    }
}

pub fn assert_same_lists(gpu: &[Vec<(f32, u32)>], cpu: &[Vec<(f32, u32)>], tol: f32, what: &str) {
    assert_eq!(gpu.len(), cpu.len());
    for (q, (g, c)) in gpu.iter().zip(cpu).enumerate() {
        assert_eq!(g.len(), c.len(), "{what}: query {q} list length");
        for (j, (a, b)) in g.iter().zip(c).enumerate() {
            assert!((a.0 - b.0).abs() <= tol, "{what}: query {q} rank {j}: {} vs {}", a.0, b.0);
            // the same reference unless its neighbours in the CPU list are tied within tolerance
            let tied = c.iter().filter(|x| (x.0 - b.0).abs() <= tol).count() > 1;
            assert!(a.1 == b.1 || tied, "{what}: query {q} rank {j}: reference {} vs {}", a.1, b.1);
        }
    }
}

pub fn random_forest_set(n: usize, dim: usize, seed: u64) -> DescriptorSet {
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let mut set = DescriptorSet::new(&p, 3, dim, 0);
    let mut rng = SplitMix64::new(seed);
    for i in 0..n {
        let trees = rng.below(30);
        let mut f = Forest { neighbour_slots: 3, ..Default::default() };
        for t in 0..trees {
            f.classes.push(rng.below(4) as u8);
            f.areas.push(rng.range(0.001, 0.3) as f32);
            f.centroids.extend([rng.next_f64() as f32, rng.next_f64() as f32]);
            for _ in 0..3 {
                f.neighbours.push(if trees > 1 && rng.chance(0.8) { ((t + 1 + rng.below(trees - 1)) % trees) as i32 } else { -1 });
            }
        }
        let mut app = vec![0.0f32; trees * dim];
        let mut counts = vec![0u32; trees];
        for t in 0..trees {
            if rng.chance(0.8) && dim > 0 {
                counts[t] = 1 + rng.below(40) as u32;
                let v: Vec<f32> = (0..dim).map(|_| rng.normal() as f32).collect();
                let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                app[t * dim..(t + 1) * dim].iter_mut().zip(&v).for_each(|(a, b)| *a = b / norm);
            }
        }
        f.set_appearance(dim, app, counts, 1).unwrap();
        let img = semlook::descriptors::EncodedImage {
            id: format!("f{i}"),
            width: 10,
            height: 10,
            global: vec![0.5; p.len()],
            global_stats: vec![0.0; p.stats_len()],
            forest: f,
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: Default::default(),
            pose: None,
        };
        set.push(&img).unwrap();
    }
    set
}

/// Tree-set similarity of random forest pairs (empty forests, missing appearance, all options)
/// within 1e-5 of the CPU twin; the whole-map fine top-K gives the same lists.
#[test]
fn tree_similarity_matches_the_cpu_twin() {
    let Some(ctx) = gpu() else { return };
    let refs = random_forest_set(40, 16, 5);
    let queries = random_forest_set(6, 16, 6);
    let mut stages = semlook::gpu::GpuStages::new(ctx);
    let pairs: Vec<(u32, u32)> = (0..6).flat_map(|q| (0..40).map(move |r| (q, r))).collect();
    let variants = [
        semlook::config::SimilarityConfig::default(),
        semlook::config::SimilarityConfig {
            position: semlook::config::PositionSimilarity::Gaussian,
            missing_appearance: semlook::config::MissingAppearance::Drop,
            ..Default::default()
        },
        semlook::config::SimilarityConfig { assignment: semlook::config::Assignment::BestMatch, ..Default::default() },
        semlook::config::SimilarityConfig {
            tree_weight: semlook::config::TreeWeight::Descriptors,
            normalise: semlook::config::Normalise::GeometricMean,
            ..Default::default()
        },
        semlook::config::SimilarityConfig {
            tree_weight: semlook::config::TreeWeight::SqrtArea,
            assignment: semlook::config::Assignment::BestMatch,
            ..Default::default()
        },
        semlook::config::SimilarityConfig {
            tree_weight: semlook::config::TreeWeight::Area,
            w_area: 0.0,
            w_position: 0.0,
            missing_appearance: semlook::config::MissingAppearance::Drop,
            ..Default::default()
        },
        semlook::config::SimilarityConfig { class_match: semlook::config::ClassMatch::Category, ..Default::default() },
    ];
    let table = semlook::classes::ClassTable::cityscapes();
    for (v, sim) in variants.iter().enumerate() {
        for appearance in [false, true] {
            // trees pair by class, or (the last variant) by Cityscapes category
            let p = sim.tree_params_over(appearance, 3, &table.category_key());
            let gpu = stages.fine_pairs(&p, &refs, &queries, &pairs).unwrap();
            let mut scratch = TreeSimScratch::default();
            for (i, &(q, r)) in pairs.iter().enumerate() {
                let c = tree_similarity(&p, queries.forest(q as usize), refs.forest(r as usize), &mut scratch);
                assert!((gpu[i] - c).abs() <= 1e-5, "variant {v}, appearance {appearance}, pair {q}-{r}: {} vs {c}", gpu[i]);
            }
            let g = stages.fine_topk(&p, &refs, &queries, 5, 7).unwrap();
            let c = semlook::matching::CpuStages.fine_topk(&p, &refs, &queries, 5, 7).unwrap();
            assert_same_lists(&g, &c, 1e-5, &format!("fine top-k, variant {v}"));
        }
    }
}

/// A binding limit far below the map forces many tiles (and several fine chunks); results
/// still equal the CPU path.
#[test]
fn tiling_under_a_small_binding_limit() {
    let limit = 64 * 1024; // 64 KiB: 2 references' stats per tile
    let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(limit), ..Default::default() }) else { return };
    assert_eq!(ctx.binding_limit(), limit);
    let cfg = Config::without_appearance();
    let refs = random_descriptors(23, &cfg, 8);
    let queries = random_descriptors(3, &cfg, 9);
    let m = semlook::gpu::CoarseMatcherGpu::new(ctx.clone(), cfg.global.ssim_params()).unwrap();
    let chunk = m.chunk_len();
    assert!(chunk < refs.len() / 4, "chunks of {chunk} references do not split the map");
    let mut stages = semlook::gpu::GpuStages::new(ctx);
    let gpu = stages.coarse(&refs, &queries, &cfg.global.ssim_params(), 10, 4096).unwrap();
    assert_same_lists(&gpu, &coarse_topk_twin(&refs, &queries, &cfg.global.ssim_params(), 10, 4096), 1e-5, "small binding limit");
    let frefs = random_forest_set(30, 0, 10);
    let fq = random_forest_set(4, 0, 11);
    let p = cfg.similarity.tree_params(false, 3);
    let g = stages.fine_topk(&p, &frefs, &fq, 10, 4096).unwrap();
    let c = semlook::matching::CpuStages.fine_topk(&p, &frefs, &fq, 10, 4096).unwrap();
    assert_same_lists(&g, &c, 1e-5, "fine under a small binding limit");
}

/// Limits too small for even one reference are a typed error, not a panic.
#[test]
fn too_small_limits_are_a_typed_error() {
    let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(4096), ..Default::default() }) else { return };
    // the coarse stage of the edge descriptor alone runs on the device (the fused one reads the
    // appearance vectors on the CPU)
    let mut cfg = Config::without_appearance();
    cfg.matching.coarse = semlook::config::CoarseStage::Global;
    let refs = random_descriptors(3, &cfg, 1);
    let mut stages = semlook::gpu::GpuStages::new(ctx);
    let err = stages.coarse(&refs, &refs, &cfg.global.ssim_params(), 2, 10).unwrap_err();
    assert!(matches!(err, semlook::Error::Gpu(semlook::gpu::GpuError::LimitsTooSmall { .. })), "{err}");
}

/// End to end: every setting gives the same metrics, top-1 references and scores (1e-4: the XFeat
/// network runs on the device, its descriptors within 2e-5 of the CPU's) on the GPU as on the
/// CPU, on the synthetic benchmark, with XFeat appearance (the network and VLAD through the GPU
/// kernels) when the weights are there.
#[test]
fn end_to_end_matching_equals_the_cpu_path() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    common::tiny_synth(dir.path(), 10, 21);
    let ds = semlook::dataset::Dataset::open(dir.path(), &Default::default()).unwrap();
    let cfg = if semlook::nn::onnx::find_model(semlook::networks::xfeat::XFEAT_WEIGHTS, None, "XFeat").is_ok() {
        Config::default()
    } else {
        assert!(std::env::var_os("CI").is_none(), "setup.sh must provide the XFeat weights under CI");
        eprintln!("note: no XFeat weights, end-to-end comparison without appearance");
        Config::without_appearance()
    };
    let mut gpu_engine = Engine::with_context(ctx);
    let opts = |s| semlook::eval::EvalOptions { settings: s, map: None, skip_invalid: false, quiet: true, sequence: false, label_cache: None };
    let g = semlook::eval::evaluate(&ds, &cfg, &opts(Setting::ALL.to_vec()), &mut gpu_engine).unwrap();
    let c = semlook::eval::evaluate(&ds, &cfg, &opts(Setting::ALL.to_vec()), &mut Engine::cpu()).unwrap();
    for (a, b) in g.results.iter().zip(&c.results) {
        assert_eq!((&a.query_set, a.setting), (&b.query_set, b.setting));
        assert_eq!(a.pr, b.pr, "{} {}: metrics", a.query_set, a.setting);
        assert_eq!(a.recall_at, b.recall_at);
        for (x, y) in a.outcomes.iter().zip(&b.outcomes) {
            assert_eq!(x.top1, y.top1, "{} {} {}", a.query_set, a.setting, x.query);
            assert!(
                (x.score.unwrap() - y.score.unwrap()).abs() <= 1e-4,
                "{} {} {}: scores {:?} and {:?}",
                a.query_set,
                a.setting,
                x.query,
                x.score,
                y.score
            );
        }
    }
    assert!(g.run.backend.starts_with("gpu:") && c.run.backend.starts_with("cpu"));
}

/// A device made the way a host application makes its own (not through `GpuContext`); without
/// an adapter, `gpu()` reports the skip (or fails under CI).
fn host_device() -> Option<(wgpu::Adapter, wgpu::Device, wgpu::Queue)> {
    let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
    desc.backends = wgpu::Backends::PRIMARY;
    let instance = wgpu::Instance::new(desc);
    let Some(adapter) = pollster::block_on(instance.enumerate_adapters(wgpu::Backends::PRIMARY)).into_iter().next() else {
        gpu();
        return None;
    };
    let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor::default())).unwrap();
    Some((adapter, device, queue))
}

/// The engine runs inside a device the host application created.
#[test]
fn embedding_in_a_host_device() {
    let Some((adapter, device, queue)) = host_device() else { return };
    let ctx = GpuContext::from_device(device, queue, adapter.get_info(), &GpuOptions::default()).unwrap();
    let mut engine = Engine::with_context(Arc::new(ctx));
    let cfg = Config::without_appearance();
    let refs = common::encode(&cfg, &common::label_maps(8, 80, 60), "r");
    let queries = common::encode(&cfg, &common::label_maps(3, 80, 60), "r");
    let (g, _) = engine.match_batch(&refs, &queries, Setting::Semlook, &cfg).unwrap();
    let (c, _) = match_batch(&refs, &queries, Setting::Semlook, &cfg).unwrap();
    for (a, b) in g.iter().zip(&c) {
        assert_eq!(a.best().unwrap().reference, b.best().unwrap().reference);
    }
}

/// Embedding leaves the host's device-lost callback in place (wgpu keeps one per device, so
/// installing ours would drop the host's), and a loss the host forwards makes the engine refuse
/// work with `DeviceLost`.
#[test]
fn embedding_keeps_the_hosts_device_lost_callback() {
    let Some((adapter, device, queue)) = host_device() else { return };
    let host_saw = Arc::new(std::sync::Mutex::new(None::<String>));
    let sink = host_saw.clone();
    device.set_device_lost_callback(move |reason, msg| *sink.lock().unwrap() = Some(format!("{reason:?}: {msg}")));
    let ctx = Arc::new(GpuContext::from_device(device.clone(), queue, adapter.get_info(), &GpuOptions::default()).unwrap());
    device.destroy();
    let _ = device.poll(wgpu::PollType::wait_indefinitely());
    let seen = host_saw.lock().unwrap().clone();
    assert!(seen.as_deref().is_some_and(|m| m.contains("Destroyed")), "host callback replaced: {seen:?}");
    ctx.report_device_lost(seen.unwrap());
    let mut engine = Engine::with_context(ctx);
    let cfg = Config::without_appearance();
    let refs = common::encode(&cfg, &common::label_maps(4, 80, 60), "r");
    let err = engine.match_batch(&refs, &refs, Setting::Global, &cfg).map(|_| ()).unwrap_err();
    assert!(err.to_string().contains("lost"), "{err}");
}

/// `auto` never picks a software adapter; with only lavapipe it falls back to the CPU and says why.
#[test]
fn auto_prefers_hardware_and_falls_back_with_a_reason() {
    let Some(ctx) = gpu() else { return };
    let (engine, why) = Engine::new(Backend::Auto, &GpuOptions::default()).unwrap();
    if ctx.is_software() && !engine.is_gpu() {
        assert!(why.unwrap().contains("CPU"));
    } else {
        assert!(engine.is_gpu() && why.is_none());
    }
    assert!(engine.describe().starts_with(if engine.is_gpu() { "gpu:" } else { "cpu" }));
}

/// Per frame: descriptors and per-object offsets.
type VladFrames = Vec<(Vec<f32>, Vec<u32>)>;

fn random_vlad_frames(k: usize, d: usize, seed: u64) -> (semlook::global::vlad::Codebook, VladFrames) {
    let mut rng = SplitMix64::new(seed);
    let centres: Vec<f32> = (0..k * d).map(|_| rng.normal() as f32).collect();
    let frames = (0..3)
        .map(|_| {
            let objects = 1 + rng.below(6);
            let mut offsets = vec![0u32];
            for _ in 0..objects {
                let c = if rng.chance(0.3) { 0 } else { rng.below(9) as u32 };
                offsets.push(offsets.last().unwrap() + c);
            }
            let n = *offsets.last().unwrap() as usize;
            ((0..n * d).map(|_| rng.normal() as f32).collect(), offsets)
        })
        .collect();
    (semlook::global::vlad::Codebook { k, dim: d, centres }, frames)
}

/// VLAD assignment and aggregation on the GPU within 1e-5 of the CPU twin (empty objects,
/// dimensions that are not multiples of the 64 lanes, every combination of intra and power
/// normalisation).
#[test]
fn vlad_kernels_match_the_cpu_twin() {
    let Some(ctx) = gpu() else { return };
    let mut vg = semlook::gpu::VladGpu::new(ctx);
    for (i, &(k, d, power, intra)) in
        [(16usize, 64usize, false, true), (5, 37, true, true), (3, 100, false, false), (64, 64, true, false), (1, 1, false, true)].iter().enumerate()
    {
        let norm = semlook::global::vlad::VladNorm { intra, power };
        let (cb, frames) = random_vlad_frames(k, d, i as u64 + 40);
        let inputs: Vec<(&[f32], &[u32])> = frames.iter().map(|(a, b)| (a.as_slice(), b.as_slice())).collect();
        let gpu = vg.run(&cb, norm, &inputs).unwrap();
        for (f, (descs, offsets)) in frames.iter().enumerate() {
            let cv = semlook::appearance::object_vlad(descs, offsets, &cb, norm);
            assert_eq!(gpu[f].len(), cv.len(), "case {i} frame {f}: vector count");
            let worst = gpu[f].iter().zip(&cv).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max);
            assert!(worst <= 1e-5, "case {i} frame {f}: VLAD differs by {worst}");
        }
    }
}

/// A library caller's inconsistent batch gets a typed error (these were an assert and reads past
/// the descriptors): label maps of two sizes in one encoding batch; VLAD runs that are empty, do
/// not start at 0 or run past the descriptors, a partial descriptor, a codebook of the wrong size.
#[test]
fn inconsistent_batches_are_refused_with_typed_errors() {
    let Some(ctx) = gpu() else { return };
    let table = semlook::classes::ClassTable::cityscapes();
    let a = semlook::input::LabelMap::new(8, 6, vec![0; 48], &table).unwrap();
    let b = semlook::input::LabelMap::new(6, 8, vec![0; 48], &table).unwrap();
    let mut enc = semlook::gpu::GlobalEncoderGpu::new(ctx.clone());
    let err = enc.encode(&[&a, &b], &table.used_mask(), &semlook::config::Config::default().global).unwrap_err();
    assert!(err.to_string().contains("one size per batch"), "{err}");
    let (cb, frames) = random_vlad_frames(4, 8, 3);
    let (descs, offsets) = frames.iter().find(|f| !f.0.is_empty()).map(|f| (&f.0, &f.1)).unwrap();
    let mut past = offsets.clone();
    *past.last_mut().unwrap() += 1;
    let norm = semlook::global::vlad::VladNorm { intra: true, power: false };
    let mut vg = semlook::gpu::VladGpu::new(ctx);
    for (what, d, o) in [
        ("no runs", &descs[..], &[][..]),
        ("runs from 1", descs, &[1, 2][..]),
        ("runs past the end", descs, &past[..]),
        ("a partial descriptor", &descs[..descs.len().saturating_sub(1)], offsets),
    ] {
        let err = vg.run(&cb, norm, &[(d, o)]).unwrap_err();
        assert!(err.to_string().contains("VLAD aggregation"), "{what}: {err}");
    }
    let short = semlook::global::vlad::Codebook { centres: cb.centres[1..].to_vec(), ..cb.clone() };
    assert!(vg.run(&short, norm, &[(descs, offsets)]).is_err(), "a codebook of the wrong size");
    assert_eq!(vg.run(&cb, norm, &[(descs, offsets)]).unwrap().len(), 1);
}

/// Every encoding kernel on a real street frame (Cityscapes, segmented by ESPNet, 2048x1024):
/// edges and squared distances exact, pooling within 1e-5, VLAD of its XFeat keypoints within 1e-5.
#[test]
fn kernels_on_a_real_street_frame() {
    let (Some(model), Some(frame)) = (
        common::shared_or_required("models/espnet_cityscapes.onnx"),
        common::shared_or_required("data/street-frames/frankfurt_000000_000576_leftImg8bit.png"),
    ) else {
        return;
    };
    let Some(ctx) = gpu() else { return };
    let cfg = Config::default();
    let table = semlook::classes::ClassTable::cityscapes();
    let seg = match semlook::networks::segmenter::Segmenter::load(&model, &cfg.segmentation, &table, None) {
        Ok(s) => s,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("the ESPNet segmenter does not load: {e}")),
    };
    let rgb = image::open(&frame).unwrap().to_rgb8();
    let labels = seg.segment(&rgb, &frame).unwrap();
    let mut enc = semlook::gpu::GlobalEncoderGpu::new(ctx.clone());
    let out = enc.encode(&[&labels], &table.used_mask(), &cfg.global).unwrap();
    let px = (labels.width() * labels.height()) as u64;
    let (edges, d2, pooled) = cpu_global(&labels, &cfg);
    assert!(edges.iter().filter(|&&e| e == 1).count() > 10_000, "a real frame has many semantic edges");
    assert_eq!(enc.last_edges(px).unwrap(), edges);
    assert_eq!(enc.last_d2(px).unwrap(), d2);
    assert!(pooled.iter().zip(&out[0].0).all(|(a, b)| (a - b).abs() <= 1e-5));
    stats_match_the_twins(&cfg.global.ssim_params(), &out[0], "the real street frame");
    let Ok(Some(xfeat)) = semlook::appearance::AppearanceModel::load(&cfg.appearance, &cfg.models) else {
        return common::skip_unless_required("REQUIRE_MODELS", "no XFeat weights (run setup.sh): the VLAD part of the test");
    };
    let small = image::imageops::resize(&rgb, 1024, 512, image::imageops::FilterType::Triangle);
    let small_labels = seg.segment(&small, &frame).unwrap();
    let objects = semlook::objects::extract_objects(&small_labels, &table, &cfg.objects);
    let k = xfeat.keypoints(&small).unwrap();
    let cb = semlook::global::vlad::train_codebook(&semlook::appearance::sample_descriptors(&k, 512), k.dim, 16, 10, 2).unwrap();
    let (descs, offsets) = semlook::appearance::group_by_object(&k, &objects);
    let norm = semlook::global::vlad::VladNorm::from_config(&cfg.appearance);
    let cv = semlook::appearance::object_vlad(&descs, &offsets, &cb, norm);
    let g = semlook::gpu::VladGpu::new(ctx).run(&cb, norm, &[(&descs, &offsets)]).unwrap();
    assert!(g[0].iter().zip(&cv).all(|(a, b)| (a - b).abs() <= 1e-5));
}

/// A GPU failure during work: a typed error for `gpu`, a warning and the CPU path for `auto`.
#[test]
fn auto_falls_back_to_the_cpu_when_the_gpu_fails_mid_run() {
    let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(4096), ..Default::default() }) else { return };
    // the coarse stage of the edge descriptor alone runs on the device (the fused one reads the
    // appearance vectors on the CPU)
    let mut cfg = Config::without_appearance();
    cfg.matching.coarse = semlook::config::CoarseStage::Global;
    let refs = common::encode(&cfg, &common::label_maps(5, 64, 48), "r");
    let mut strict = Engine::with_context(ctx.clone());
    assert!(matches!(strict.match_batch(&refs, &refs, Setting::Semlook, &cfg), Err(semlook::Error::Gpu(_))));
    let mut auto = Engine::with_context(ctx).fall_back_to_cpu(true);
    let (m, _) = auto.match_batch(&refs, &refs, Setting::Semlook, &cfg).unwrap();
    assert_eq!(m, match_batch(&refs, &refs, Setting::Semlook, &cfg).unwrap().0);
    assert!(!auto.is_gpu(), "the engine continues on the CPU");
}

/// NaN scores are skipped by the GPU `topk_merge` as by its CPU twin: the same K-lists, bit for
/// bit, from tiles with NaNs first, last, between equal scores, in place of every score, and
/// (quiet and signalling, either sign) against lists that already hold entries.
#[test]
fn topk_merge_skips_nan_like_its_twin() {
    let Some(ctx) = gpu() else { return };
    use semlook_kernels::abi::TileParams;
    use semlook_kernels::abi::{EMPTY_INDEX, EMPTY_SCORE};
    use semlook_kernels::ssim_topk::topk_merge;
    let (nan, snan, neg_nan) = (f32::NAN, f32::from_bits(0x7f80_0001), f32::from_bits(0xffc0_0000));
    let rows: [[f32; 6]; 5] = [
        [nan, 0.5, 0.2, 0.9, 0.1, 0.3],
        [0.4, 0.4, snan, 0.4, -0.2, nan],
        [nan; 6],
        [neg_nan, -1.0, 0.7, neg_nan, 0.8, 0.0],
        [0.9, 0.95, nan, 0.05, snan, 0.6],
    ];
    let scores: Vec<f32> = rows.iter().flatten().copied().collect();
    let k = 4;
    // lists that already hold one entry each (from an earlier tile), then empty slots
    let mut ts = vec![EMPTY_SCORE; rows.len() * k];
    let mut ti = vec![EMPTY_INDEX; rows.len() * k];
    for q in 0..rows.len() {
        ts[q * k] = 0.45;
        ti[q * k] = 1000 + q as u32;
    }
    let tp = TileParams { queries: rows.len() as u32, tile_len: 6, tile_start: 20, k: k as u32 };
    let (gs, gi) = semlook::gpu::reference::merge_scores(&ctx, &tp, &scores, &ts, &ti).unwrap();
    topk_merge(&tp, &scores, &mut ts, &mut ti);
    assert!(ts.iter().all(|s| !s.is_nan()), "the twin keeps no NaN: {ts:?}");
    assert_eq!(gi, ti, "indices (GPU {gs:?}, CPU {ts:?})");
    assert_eq!(gs.iter().map(|s| s.to_bits()).collect::<Vec<_>>(), ts.iter().map(|s| s.to_bits()).collect::<Vec<_>>(), "scores");
}
