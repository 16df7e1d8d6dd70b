//! The coarse stage with the map resident on the device: what is uploaded when, limits that force
//! every kind of chunking, a large batch, both reductions, timing, NaN, a real scene.

use super::{assert_same_lists, gpu, gpu_with, random_descriptors};
use semlook::config::{Config, GlobalConfig};
use semlook::descriptors::DescriptorSet;
use semlook::engine::Engine;
use semlook::gpu::GpuStages;
use semlook::gpu::{GpuContext, GpuOptions};
use semlook::matching::{coarse_topk, coarse_topk_twin, Setting, Stages};
use std::sync::Arc;

fn bytes_of(set: &DescriptorSet) -> u64 {
    ((set.globals.len() + set.global_stats.len()) * 4) as u64
}

/// Bytes a coarse batch writes besides the map: its queries and one parameter entry per pass (no
/// empty top-K lists: a query chunk's first pass does not read them).
fn batch_bytes(ctx: &GpuContext, q: &DescriptorSet, passes: u64) -> u64 {
    bytes_of(q) + passes * (std::mem::size_of::<semlook_kernels::abi::PassParams>() as u64).next_multiple_of(ctx.uniform_offset_alignment() as u64)
}

/// Two consecutive batches against the same map: the first uploads the map, the second writes
/// only its queries, lists and pass parameters (counted to the byte). A different map (same size)
/// is uploaded again; both batches' lists equal the CPU twin's.
#[test]
fn the_map_is_uploaded_once_across_batches() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let (refs, other) = (random_descriptors(40, &cfg, 21), random_descriptors(40, &cfg, 31));
    let (q1, q2) = (random_descriptors(5, &cfg, 22), random_descriptors(7, &cfg, 23));
    let mut stages = GpuStages::new(ctx.clone());
    let k = 6;
    let b0 = ctx.bytes_uploaded();
    let l1 = stages.coarse(&refs, &q1, &p, k, 4096).unwrap();
    let b1 = ctx.bytes_uploaded();
    let l2 = stages.coarse(&refs, &q2, &p, k, 4096).unwrap();
    let b2 = ctx.bytes_uploaded();
    assert!(stages.coarse_map_is_resident());
    assert!(b1 - b0 >= bytes_of(&refs), "first batch: {} bytes, the map alone is {}", b1 - b0, bytes_of(&refs));
    assert_eq!(b2 - b1, batch_bytes(&ctx, &q2, 1), "second batch wrote more than its queries and parameters (map: {} bytes)", bytes_of(&refs));
    assert_same_lists(&l1, &coarse_topk_twin(&refs, &q1, &p, k, 4096), 1e-5, "first batch");
    assert_same_lists(&l2, &coarse_topk_twin(&refs, &q2, &p, k, 4096), 1e-5, "second batch");
    let l3 = stages.coarse(&other, &q2, &p, k, 4096).unwrap();
    let b3 = ctx.bytes_uploaded();
    assert_eq!(b3 - b2, bytes_of(&other) + batch_bytes(&ctx, &q2, 1), "a different map is uploaded once");
    assert_same_lists(&l3, &coarse_topk_twin(&other, &q2, &p, k, 4096), 1e-5, "other map");
    // a map grown by one reference is another map
    let mut grown = refs.clone();
    grown.append(&other.slice(0, 1)).unwrap();
    stages.coarse(&grown, &q2, &p, k, 4096).unwrap();
    assert!(ctx.bytes_uploaded() - b3 >= bytes_of(&grown), "a grown map is uploaded again");
}

/// A budget smaller than the map: the map is streamed through two slots (uploaded with every
/// batch), and the lists are the same.
#[test]
fn a_map_beyond_the_budget_is_streamed() {
    let Some(ctx) = gpu_with(&GpuOptions { resident_budget: Some(100_000), max_binding_size: Some(256 * 1024), ..Default::default() }) else {
        return;
    };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let (refs, q) = (random_descriptors(30, &cfg, 41), random_descriptors(4, &cfg, 42));
    let mut stages = GpuStages::new(ctx.clone());
    for batch in 0..2 {
        let b = ctx.bytes_uploaded();
        let l = stages.coarse(&refs, &q, &p, 5, 4096).unwrap();
        assert!(!stages.coarse_map_is_resident(), "30 references (950 KB) do not fit 100 KB");
        assert!(ctx.bytes_uploaded() - b >= bytes_of(&refs), "batch {batch}: the streamed map is uploaded");
        assert_same_lists(&l, &coarse_topk_twin(&refs, &q, &p, 5, 4096), 1e-5, "streamed");
    }
}

/// A 256 KiB binding limit and 3 workgroups per dimension: queries in chunks of 3, map chunks of
/// 13 references, passes of 6 (the block grid's limit): the twin's lists.
#[test]
fn batches_are_chunked_past_binding_and_dispatch_limits() {
    let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(256 * 1024), max_workgroups: Some(3), ..Default::default() }) else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let (refs, q) = (random_descriptors(40, &cfg, 51), random_descriptors(10, &cfg, 52));
    let m = semlook::gpu::CoarseMatcherGpu::new(ctx.clone(), p).unwrap();
    let (qc, pass) = m.plan(7).unwrap();
    assert_eq!((qc, pass, m.chunk_len()), (3, 6, 13));
    let mut stages = GpuStages::new(ctx);
    let l = stages.coarse(&refs, &q, &p, 7, 4096).unwrap();
    assert_same_lists(&l, &coarse_topk_twin(&refs, &q, &p, 7, 4096), 1e-5, "chunked");
}

/// Descriptors of 8 x 8 with a 3 x 3 window (916 counted operations a comparison, against 80,676
/// at the default 64 x 48): a large batch is affordable on a software adapter.
fn small_config() -> Config {
    Config { global: GlobalConfig { width: 8, height: 8, ssim_window: 3, ..Default::default() }, ..Config::without_appearance() }
}

/// 6,000 references x 1,000 queries (6M comparisons, 8 x 8 descriptors) through the engine's GPU
/// path with `auto`'s fall-back on, under a 256 KiB binding limit and 400 workgroups per
/// dimension, so the map is cut into 7 binding-sized chunks, the batch into 3 query chunks and
/// the passes by the dispatch limit: it stays on the device (the engine did not fall back) and
/// the lists equal the fast CPU path's (ties to the lower index, scores within 1e-5). Then the
/// same batch with a 1 MB resident budget (the map is 3.3 MB): streamed through two slots,
/// the same lists bit for bit. The full size (1M x 1000 at 64 x 48) is
/// `full_size_one_million_references_by_1000_queries`, for a real device.
#[test]
fn a_large_batch_runs_on_the_device_without_falling_back() {
    let limits = GpuOptions { max_binding_size: Some(256 << 10), max_workgroups: Some(400), ..Default::default() };
    let Some(ctx) = gpu_with(&limits) else { return };
    let cfg = small_config();
    let p = cfg.global.ssim_params();
    let (refs, q) = (random_descriptors(6_000, &cfg, 61), random_descriptors(1_000, &cfg, 62));
    let m = semlook::gpu::CoarseMatcherGpu::new(ctx.clone(), p).unwrap();
    let (qc, _) = m.plan(cfg.matching.top_k).unwrap();
    let (chunks, qchunks) = (refs.len().div_ceil(m.chunk_len()), q.len().div_ceil(qc));
    assert!(chunks > 1 && qchunks > 1, "{chunks} map chunks, {qchunks} query chunks");
    let mut engine = Engine::with_context(ctx.clone()).fall_back_to_cpu(true);
    let t = std::time::Instant::now();
    let (gpu, _) = engine.match_batch(&refs, &q, Setting::Global, &cfg).unwrap();
    eprintln!(
        "{} x {} ({chunks} map chunks, {qchunks} query chunks) on {}: {:.1} s (correctness only)",
        refs.len(),
        q.len(),
        ctx.describe(),
        t.elapsed().as_secs_f64()
    );
    assert!(engine.is_gpu(), "the engine fell back to the CPU");
    assert!(engine.gpu_stages().unwrap().coarse_map_is_resident());
    let cpu = coarse_topk(&refs, &q, &p, cfg.matching.top_k, cfg.matching.tile);
    let lists: Vec<Vec<(f32, u32)>> = gpu.iter().map(|m| m.ranked.iter().map(|c| (c.score, c.reference)).collect()).collect();
    assert_same_lists(&lists, &cpu, 1e-5, "6k x 1k");
    let exact = lists.iter().zip(&cpu).filter(|(a, b)| a == b).count();
    eprintln!("{exact} of {} lists equal the CPU's bit for bit", cpu.len());
    let Some(small) = gpu_with(&GpuOptions { resident_budget: Some(1_000_000), ..limits }) else { return };
    let mut stages = GpuStages::new(small.clone());
    let b = small.bytes_uploaded();
    let streamed = stages.coarse(&refs, &q, &p, cfg.matching.top_k, cfg.matching.tile).unwrap();
    assert!(!stages.coarse_map_is_resident(), "3.3 MB of map over a 1 MB budget");
    assert!(small.bytes_uploaded() - b >= qchunks as u64 * bytes_of(&refs), "streamed once per query chunk");
    assert_eq!(streamed, lists, "streamed and resident maps give the same lists");
}

/// Subgroup reductions (where the adapter has them) and the workgroup-memory tree select the
/// same entries: identical lists, bit for bit.
#[test]
fn subgroup_and_workgroup_reductions_give_the_same_lists() {
    let (Some(a), Some(b)) = (gpu(), gpu_with(&GpuOptions { subgroups: false, ..Default::default() })) else { return };
    if !a.uses_subgroups() {
        return crate::common::skip(format!("{} has no subgroup operations", a.describe()));
    }
    assert!(!b.uses_subgroups());
    let cfg = small_config();
    let p = cfg.global.ssim_params();
    let (refs, q) = (random_descriptors(3000, &cfg, 71), random_descriptors(9, &cfg, 72));
    let run = |ctx: &Arc<GpuContext>| GpuStages::new(ctx.clone()).coarse(&refs, &q, &p, 40, 4096).unwrap();
    assert_eq!(run(&a), run(&b));
}

/// Where the adapter has timestamp queries, a batch reports its kernel time.
#[test]
fn kernels_are_timed_where_the_adapter_has_timestamps() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config::without_appearance();
    let (refs, q) = (random_descriptors(20, &cfg, 81), random_descriptors(3, &cfg, 82));
    let mut stages = GpuStages::new(ctx.clone());
    ctx.take_kernel_seconds().unwrap();
    stages.coarse(&refs, &q, &cfg.global.ssim_params(), 5, 4096).unwrap();
    match ctx.take_kernel_seconds().unwrap() {
        Some(s) => assert!(s > 0.0 && s < 60.0, "{s} s"),
        None => assert!(!ctx.has_timestamps()),
    }
}

/// The parallel top-K on the device keeps what the streaming fold keeps, bit for bit: NaN
/// (quiet, signalling, negative) skipped, ties to the lower index, both zeros, infinities, the
/// empty score never kept, passes of several segments.
#[test]
fn parallel_top_k_on_the_device_keeps_what_the_fold_keeps() {
    let Some(ctx) = gpu() else { return };
    use semlook_kernels::abi::TileParams;
    use semlook_kernels::abi::{EMPTY_INDEX, EMPTY_SCORE};
    use semlook_kernels::ssim_topk::{topk_lists, topk_merge};
    let mut rng = semlook::util::SplitMix64::new(91);
    let specials = [f32::NAN, f32::from_bits(0x7f80_0001), f32::from_bits(0xffc0_0000), f32::INFINITY, f32::NEG_INFINITY, EMPTY_SCORE, -0.0, 0.0];
    let (nq, n) = (3, 2500);
    let scores: Vec<f32> =
        (0..nq * n).map(|_| if rng.chance(0.3) { specials[rng.below(specials.len())] } else { rng.below(7) as f32 / 6.0 - 0.5 }).collect();
    for (k, pass) in [(1, 2500), (10, 2100), (37, 700), (5, 1)] {
        let gpu = semlook::gpu::reference::select_topk(&ctx, &scores, nq, k, pass).unwrap();
        let (mut ts, mut ti) = (vec![EMPTY_SCORE; nq * k], vec![EMPTY_INDEX; nq * k]);
        topk_merge(&TileParams { queries: nq as u32, tile_len: n as u32, tile_start: 0, k: k as u32 }, &scores, &mut ts, &mut ti);
        let bits = |l: &[Vec<(f32, u32)>]| l.iter().map(|q| q.iter().map(|&(s, i)| (s.to_bits(), i)).collect::<Vec<_>>()).collect::<Vec<_>>();
        assert_eq!(bits(&gpu), bits(&topk_lists(k, &ts, &ti)), "k {k}, passes of {pass}");
    }
}

/// On rendered street scenes (the synthetic benchmark's descriptors), every score of the block
/// kernel against the one-pair kernel `ssim_tile` on the same device and against the twin, and
/// `ssim_tile`'s against the twin, within 1e-5 (k = every reference, so the lists hold every score).
#[test]
fn block_kernel_equals_the_pair_kernel_on_street_scenes() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    use semlook_cli::tools::synth::condition::Condition;
    let refs = semlook_cli::tools::bench::street_descriptors(&cfg, 12, Condition::Day, 0).unwrap();
    let q = semlook_cli::tools::bench::street_descriptors(&cfg, 5, Condition::Night, 5).unwrap();
    let lists = GpuStages::new(ctx.clone()).coarse(&refs, &q, &p, refs.len(), 4096).unwrap();
    let pair = semlook::gpu::reference::ssim_tile_scores(&ctx, &p, (&q.globals, &q.global_stats), (&refs.globals, &refs.global_stats)).unwrap();
    let twin = coarse_topk_twin(&refs, &q, &p, refs.len(), 4096);
    let (mut worst, mut exact) = (0.0f32, 0);
    for (qi, (l, t)) in lists.iter().zip(&twin).enumerate() {
        assert_eq!(l.len(), refs.len());
        for &(s, r) in l {
            let want = t.iter().find(|e| e.1 == r).unwrap().0;
            let pair = pair[qi * refs.len() + r as usize];
            worst = worst.max((s - want).abs()).max((s - pair).abs()).max((pair - want).abs());
            exact += (s.to_bits() == want.to_bits()) as usize;
        }
    }
    eprintln!("street scenes: worst difference {worst:e}, {exact} of {} scores equal to the twin's bits", q.len() * refs.len());
    assert!(worst <= 1e-5, "{worst}");
}

/// Limits too small for one reference are a typed error (not a panic, not a silent CPU run).
#[test]
fn limits_too_small_for_one_reference_name_the_resource() {
    let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(16 * 1024), ..Default::default() }) else { return };
    let cfg = Config::without_appearance();
    let m = semlook::gpu::CoarseMatcherGpu::new(ctx, cfg.global.ssim_params()).unwrap();
    match m.plan(10) {
        Err(semlook::gpu::GpuError::LimitsTooSmall { what, needed, .. }) => {
            assert!(what.contains("one reference") && needed == 19_488, "{what} {needed}")
        }
        other => panic!("{other:?}"),
    }
}

/// The lists are ordered by score, then by the lower index: `list` sorted that way is itself.
fn ordered_by_score_then_index(list: &[(f32, u32)]) -> bool {
    list.windows(2).all(|w| w[0].0 > w[1].0 || (w[0].0 == w[1].0 && w[0].1 < w[1].1))
}

/// Exact ties (every reference three times in the map): the GPU, the fast CPU path and the twin
/// give the same lists, each tie broken by the lower index, scores within 1e-5.
#[test]
fn ties_go_to_the_lower_index_on_every_path() {
    let Some(ctx) = gpu() else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let base = random_descriptors(25, &cfg, 101);
    let mut refs = base.clone();
    refs.append(&base).unwrap();
    refs.append(&base).unwrap();
    let q = random_descriptors(6, &cfg, 102);
    let k = 12;
    let gpu = GpuStages::new(ctx).coarse(&refs, &q, &p, k, 4096).unwrap();
    let (fast, twin) = (coarse_topk(&refs, &q, &p, k, 4096), coarse_topk_twin(&refs, &q, &p, k, 4096));
    assert_eq!(fast, twin, "the fast path equals the twin bit for bit");
    for (qi, l) in gpu.iter().enumerate() {
        assert!(ordered_by_score_then_index(l), "query {qi}: {l:?}");
        // every score comes in a tie of three, listed as i, i + 25, i + 50
        for t in l.chunks(3) {
            assert_eq!(t.iter().map(|e| e.1 % 25).collect::<Vec<_>>(), vec![t[0].1; t.len()], "query {qi}: {l:?}");
            assert!(t.iter().all(|e| e.0.to_bits() == t[0].0.to_bits()));
        }
    }
    assert_same_lists(&gpu, &twin, 1e-5, "ties");
    let exact = gpu.iter().zip(&twin).filter(|(a, b)| a.iter().map(|e| e.1).eq(b.iter().map(|e| e.1))).count();
    eprintln!("ties: {exact} of {} lists list the twin's references in its order", gpu.len());
}

/// A real scene: the 233 CamVid test frames' real label maps (two drives, dusk and daylight;
/// `../shared/data/camvid-test`, skipped visibly when absent), encoded at the default size; even
/// frames are the map, odd frames the queries. The GPU's lists equal the fast CPU path's and
/// the twin's (same references in the same order unless tied within 1e-5, scores within 1e-5);
/// the fast path equals the twin bit for bit.
#[test]
fn coarse_lists_on_real_camvid_labels_equal_both_cpu_paths() {
    let Some(dir) = crate::common::shared_or_required("data/camvid-test/labels") else { return };
    let entries = std::fs::read_dir(&dir).unwrap();
    let Some(ctx) = gpu() else { return };
    let mut files: Vec<_> = entries.map(|e| e.unwrap().path()).filter(|p| p.extension().is_some_and(|x| x == "png")).collect();
    files.sort();
    let cfg = Config {
        appearance: semlook::config::AppearanceConfig { model: semlook::config::AppearanceModelKind::None, ..Default::default() },
        ..Config::camvid()
    };
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let (mut refs, mut q) = (enc.descriptor_set(), enc.descriptor_set());
    let mut scratch = Default::default();
    for (i, f) in files.iter().enumerate() {
        let labels = semlook::input::load_label_map(f, enc.class_table(), Default::default()).unwrap();
        let (img, _) = enc.encode_labels(&f.display().to_string(), &labels, &mut scratch).unwrap();
        if i % 2 == 0 {
            refs.push(&img).unwrap()
        } else {
            q.push(&img).unwrap()
        }
    }
    assert!(refs.len() > 100 && q.len() > 100, "{} frames", files.len());
    let p = cfg.global.ssim_params();
    let k = cfg.matching.top_k;
    let gpu = GpuStages::new(ctx.clone()).coarse(&refs, &q, &p, k, 4096).unwrap();
    let (fast, twin) = (coarse_topk(&refs, &q, &p, k, 4096), coarse_topk_twin(&refs, &q, &p, k, 4096));
    assert_eq!(fast, twin, "fast path vs twin on real labels");
    assert_same_lists(&gpu, &twin, 1e-5, "CamVid: GPU vs twin");
    assert_same_lists(&gpu, &fast, 1e-5, "CamVid: GPU vs fast CPU path");
    let worst = gpu.iter().zip(&twin).flat_map(|(a, b)| a.iter().zip(b).map(|(x, y)| (x.0 - y.0).abs())).fold(0.0f32, f32::max);
    let same = gpu.iter().zip(&twin).filter(|(a, b)| a.iter().map(|e| e.1).eq(b.iter().map(|e| e.1))).count();
    eprintln!(
        "CamVid ({} refs x {} queries, k {k}) on {}: {same} of {} lists identical, worst score difference {worst:e}",
        refs.len(),
        q.len(),
        ctx.describe(),
        q.len()
    );
}

/// The full size of the issue: 1,000,000 references (default 64 x 48 descriptors, 31.8 GB with
/// their statistics) x 1,000 queries through the GPU executor, no CPU fall-back possible (the
/// executor returns an error, it has none); 8 queries' lists checked against the fast CPU path.
/// For a real device (on lavapipe it would take days):
/// `cargo test --release --test gpu -- --ignored --nocapture full_size`
/// (the timed figure: `semlook dev bench --sizes 1000000 --batches 1000 --json`).
#[test]
#[ignore = "full size for a real GPU: cargo test --release --test gpu -- --ignored --nocapture full_size"]
fn full_size_one_million_references_by_1000_queries() {
    let Some(ctx) = gpu_with(&GpuOptions { allow_software: false, ..Default::default() }) else { return };
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    use semlook_cli::tools::synth::condition::Condition;
    let pool = semlook_cli::tools::bench::street_descriptors(&cfg, 64, Condition::Day, 0).unwrap();
    let qpool = semlook_cli::tools::bench::street_descriptors(&cfg, 32, Condition::Night, 5).unwrap();
    let map = semlook_cli::tools::bench::SyntheticMap::new(&pool, 1_000_000, 4096);
    let q = semlook_cli::tools::bench::resident_map(&qpool, 1000);
    let mut stages = GpuStages::new(ctx.clone());
    let t = std::time::Instant::now();
    let resident = stages.upload_coarse_map(&map, &p).unwrap();
    eprintln!("map uploaded in {:.1} s (resident: {resident}) on {}", t.elapsed().as_secs_f64(), ctx.describe());
    let b = ctx.bytes_uploaded();
    let t = std::time::Instant::now();
    let lists = stages.coarse(&map, &q, &p, cfg.matching.top_k, cfg.matching.tile).unwrap();
    let s = t.elapsed().as_secs_f64();
    eprintln!("1M x 1000: {s:.1} s, {:.3e} comparisons/s, {} bytes written in the batch", 1e9 / s, ctx.bytes_uploaded() - b);
    assert_eq!(lists.len(), 1000);
    let few = q.slice(0, 8);
    let cpu = coarse_topk(&map, &few, &p, cfg.matching.top_k, cfg.matching.tile);
    assert_same_lists(&lists[..8], &cpu, 1e-5, "1M x 1000, first 8 queries");
}

/// A stored map does not store its references' SSIM statistics (format 4): the device computes
/// them from the descriptors as the chunks are uploaded (`gpu::stats`, `ssim_stats.wgsl`), so
/// the first batch sends the descriptors alone (less than descriptors and statistics together),
/// in runs of 256 references (300 here: two runs); the lists equal the CPU path's on the map.
#[test]
fn a_stored_map_sends_its_descriptors_alone() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let p = cfg.global.ssim_params();
    let set = random_descriptors(300, &cfg, 41);
    let path = dir.path().join("m");
    semlook::map::Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    let map = semlook::map::Map::open(&path).unwrap();
    assert!(!semlook::descriptors::source::GlobalSource::stores_stats(&map));
    let q = random_descriptors(4, &cfg, 42);
    let mut stages = GpuStages::new(ctx.clone());
    let b0 = ctx.bytes_uploaded();
    let lists = stages.coarse(&map, &q, &p, 7, 4096).unwrap();
    let sent = ctx.bytes_uploaded() - b0;
    let descriptors = (map.len() * p.len() * 4) as u64;
    let with_stats = (map.len() * (p.len() + p.stats_len()) * 4) as u64;
    assert!(sent >= descriptors && sent < descriptors + batch_bytes(&ctx, &q, 1) + 1024, "sent {sent} bytes; the descriptors are {descriptors}");
    assert!(sent < with_stats, "the statistics crossed too ({sent} bytes)");
    assert_same_lists(&lists, &coarse_topk_twin(&map, &q, &p, 7, 4096), 1e-5, "stored map, statistics from the device");
}
