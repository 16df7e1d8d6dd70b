//! The verification kernel (`mnn_match.wgsl`) held to its twin: best columns and dot products
//! exactly equal (integer arithmetic, tolerance 0) on random keypoints of awkward counts, and the
//! whole verification (GPU matching, CPU RANSAC) equal to the CPU path on real frames.

use super::{common, gpu};
use semlook::descriptors::keypoints::ImageKeypoints;
use semlook::descriptors::{DescriptorSet, EncodedImage};
use semlook::gpu::MnnGpu;
use semlook::local::Forest;
use semlook::matching::{CpuStages, Stages};
use semlook::util::SplitMix64;
use semlook::verify::best_columns::best_columns;
use semlook_kernels::abi::{MnnPair, MnnParams};
use semlook_kernels::mnn_match::{mnn_match, pack};

/// A set of images with `counts[i]` random keypoints of dimension `dim` (ties included: some
/// descriptors repeat).
fn keypoint_set(counts: &[usize], dim: usize, rng: &mut SplitMix64) -> DescriptorSet {
    let cfg = semlook::config::Config::without_appearance();
    let p = cfg.global.ssim_params();
    let mut set = DescriptorSet::new(&p, 3, 0, 0).with_keypoint_dim(dim);
    for (i, &n) in counts.iter().enumerate() {
        let mut k = ImageKeypoints { dim, ..Default::default() };
        for j in 0..n {
            let d: Vec<i8> = match j % 7 == 6 {
                true => k.descriptors[..dim].to_vec(),
                false => (0..dim).map(|_| (rng.below(200) as i32 - 100) as i8).collect(),
            };
            k.descriptors.extend(d);
            k.xy.extend([rng.below(65536) as u16, rng.below(65536) as u16]);
            k.classes.push(rng.below(19) as u8);
        }
        let img = EncodedImage {
            id: format!("k{i}"),
            width: 8,
            height: 8,
            global: vec![0.5; p.len()],
            global_stats: vec![0.0; p.stats_len()],
            forest: Forest { neighbour_slots: 3, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: k,
            pose: None,
        };
        set.push(&img).unwrap();
    }
    set
}

#[test]
fn mnn_kernel_equals_its_twin_and_the_fast_path_exactly() {
    let Some(ctx) = gpu() else { return };
    let mut rng = SplitMix64::new(3);
    for dim in [64usize, 8] {
        // counts around the kernel's 64-row blocks and 64-column tiles, and empty images
        let queries = keypoint_set(&[1, 63, 64, 65, 130, 0, 7], dim, &mut rng);
        let refs = keypoint_set(&[64, 0, 129, 5, 200], dim, &mut rng);
        let pairs: Vec<(u32, u32)> = (0..queries.len() as u32).flat_map(|q| (0..refs.len() as u32).map(move |r| (q, r))).collect();
        let gpu_best = MnnGpu::new(ctx.clone()).best_columns(&queries, &refs, &pairs).unwrap();
        // the twin over the same table the executor builds
        let words = dim / 4;
        let qw = pack(&queries.keypoint_descriptors);
        let rw = pack(&refs.keypoint_descriptors);
        let table: Vec<MnnPair> = pairs
            .iter()
            .map(|&(q, r)| {
                let (a, b) = (queries.keypoint_offsets[q as usize], queries.keypoint_offsets[q as usize + 1]);
                let (c, d) = (refs.keypoint_offsets[r as usize], refs.keypoint_offsets[r as usize + 1]);
                MnnPair { query_start: a, query_len: b - a, ref_start: c, ref_len: d - c }
            })
            .collect();
        let max = table.iter().map(|t| t.query_len.max(t.ref_len)).max().unwrap() as usize;
        let params = MnnParams { pairs: table.len() as u32, words: words as u32, max_keypoints: max as u32, _pad: 0 };
        let (mut best, mut dot) = (vec![u32::MAX; table.len() * 2 * max], vec![i32::MIN; table.len() * 2 * max]);
        mnn_match(&params, &table, &qw, &rw, &mut best, &mut dot);
        for (p, (&(q, r), g)) in pairs.iter().zip(&gpu_best).enumerate() {
            let (nq, nr) = (table[p].query_len as usize, table[p].ref_len as usize);
            let (q0, r0) = (p * 2 * max, (p * 2 + 1) * max);
            assert_eq!(g.query_best, best[q0..q0 + nq], "dim {dim}, pair ({q}, {r}): query rows");
            assert_eq!(g.query_dot, dot[q0..q0 + nq], "dim {dim}, pair ({q}, {r}): dot products");
            assert_eq!(g.ref_best, best[r0..r0 + nr], "dim {dim}, pair ({q}, {r}): reference rows");
            let fast = best_columns(queries.keypoints(q as usize).descriptors, refs.keypoints(r as usize).descriptors, dim, &mut vec![]);
            assert_eq!(&fast, g, "dim {dim}, pair ({q}, {r}): the fast CPU path");
        }
    }
}

/// Real frames: two Nordland spring/winter views of one place and a third of another; the GPU
/// verification's matches and inliers equal the CPU path's exactly, with mutual nearest
/// neighbours and with the learned matcher (LighterGlue on the device, `lighterglue.wgsl`, against
/// the CPU's `networks::lighterglue`: the same matches, so the same RANSAC inliers).
#[test]
fn verification_on_the_gpu_equals_the_cpu_on_real_frames() {
    let Some(ctx) = gpu() else { return };
    let Some(dir) = common::shared_or_required("data/real-vpr/nordland-spring-winter") else { return };
    let cfg = semlook::config::Config::default();
    let model = match semlook::appearance::AppearanceModel::load(&cfg.appearance, &cfg.models) {
        Ok(Some(m)) => m.with_detection(&cfg.keypoints),
        other => return common::skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (setup.sh): {:?}", other.err())),
    };
    let table = semlook::classes::ClassTable::cityscapes();
    let mut set = DescriptorSet::new(&cfg.global.ssim_params(), 3, 0, 0).with_keypoint_dim(64);
    for name in ["query/020.jpg", "ref/020.jpg", "ref/045.jpg"] {
        let rgb = semlook::input::load_rgb(&dir.join(name)).unwrap();
        let rgb = semlook::input::resize_rgb(&rgb, 640, 360);
        let det = model.features(&rgb).unwrap().detected.unwrap();
        let labels = semlook::input::LabelMap::new(640, 360, vec![2; 640 * 360], &table).unwrap();
        let k = semlook::appearance::verification_keypoints(&det, cfg.keypoints.stored, &labels, 640);
        assert!(k.len() > 100, "{name}: {} keypoints", k.len());
        let p = cfg.global.ssim_params();
        let img = EncodedImage {
            id: name.into(),
            width: 640,
            height: 360,
            global: vec![0.5; p.len()],
            global_stats: vec![0.0; p.stats_len()],
            forest: Forest { neighbour_slots: 3, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: k,
            pose: None,
        };
        set.push(&img).unwrap();
    }
    let pairs = [(0u32, 1u32), (0, 2), (1, 2), (2, 0)];
    let vp = semlook::verify::VerifyParams::new(&cfg.verification);
    let cpu = CpuStages.verify_pairs(&vp, &set, &set, &pairs).unwrap();
    let mut engine = semlook::engine::Engine::with_context(ctx);
    let gpu = engine.gpu_stages().unwrap().verify_pairs(&vp, &set, &set, &pairs).unwrap();
    assert_eq!(gpu, cpu);
    assert!(cpu[0].inliers > 3 * cpu[1].inliers.max(5), "the same place verifies far better than another: {cpu:?}");
    if let Err(e) = semlook::verify::shared_lighterglue() {
        return common::skip_unless_required("REQUIRE_MODELS", format!("LighterGlue weights (setup.sh): {e}"));
    }
    let glue = semlook::verify::VerifyParams { matcher: semlook::config::Matcher::Lighterglue, ..vp };
    let cpu = CpuStages.verify_pairs(&glue, &set, &set, &pairs).unwrap();
    let gpu = engine.gpu_stages().unwrap().verify_pairs(&glue, &set, &set, &pairs).unwrap();
    eprintln!("LighterGlue verification, CPU {cpu:?}, GPU {gpu:?}");
    assert_eq!(gpu, cpu, "LighterGlue on the device verifies as on the CPU");
    assert!(cpu[0].matches > 0 && cpu[0].inliers > cpu[1].inliers, "{cpu:?}");
}
