//! The fine stage on the device: the map's packed forests resident across batches (counted to
//! the byte; a stored map keyed by its generation, no forest read after the first batch),
//! streamed through two slots beyond the budget, the CPU path's lists either way.

use super::{assert_same_lists, gpu, gpu_with, random_forest_set};
use semlook::config::Config;
use semlook::engine::GpuStages;
use semlook::gpu::GpuOptions;
use semlook::kernels::abi::TreeSimParams;
use semlook::kernels::tree_similarity::ForestRef;
use semlook::matching::source::{GlobalSource, RefSource, TileBuf};
use semlook::matching::{CpuStages, Setting, Stages};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The same batch twice against the same map: the second writes exactly the map's packed
/// forests less than the first (everything else it writes, queries, lookups, parameters, empty
/// lists, is the same). Listed pairs against the resident map then upload none of it; another
/// tree-weight rule (other packed weights) is another map, uploaded again.
#[test]
fn forests_are_uploaded_once_across_batches() {
    let Some(ctx) = gpu() else { return };
    let refs = random_forest_set(40, 16, 201);
    let q = random_forest_set(5, 16, 202);
    let sim = semlook::config::SimilarityConfig::default();
    let p = TreeSimParams::new(&sim, true, 3);
    let mut stages = GpuStages::new(ctx.clone());
    let b0 = ctx.bytes_uploaded();
    let l1 = stages.fine_topk(&p, &refs, &q, 6, 4096).unwrap();
    let b1 = ctx.bytes_uploaded();
    let l2 = stages.fine_topk(&p, &refs, &q, 6, 4096).unwrap();
    let b2 = ctx.bytes_uploaded();
    let map = stages.map_bytes().1;
    assert!(stages.fine_map_is_resident() && map > 0);
    assert_eq!((b1 - b0) - (b2 - b1), map, "first batch {} bytes, second {}, forests {map}", b1 - b0, b2 - b1);
    assert_eq!(l1, l2);
    assert_same_lists(&l1, &CpuStages.fine_topk(&p, &refs, &q, 6, 4096).unwrap(), 1e-5, "resident forests");
    let pairs: Vec<(u32, u32)> = (0..5).flat_map(|qi| (0..40).step_by(3).map(move |r| (qi, r))).collect();
    let s = stages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
    let b3 = ctx.bytes_uploaded();
    assert!(b3 - b2 < map, "listed pairs re-uploaded the forests ({} bytes)", b3 - b2);
    let c = CpuStages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
    assert!(s.iter().zip(&c).all(|(a, b)| (a - b).abs() <= 1e-5));
    let other = TreeSimParams::new(&semlook::config::SimilarityConfig { tree_weight: semlook::config::TreeWeight::SqrtArea, ..sim }, true, 3);
    stages.fine_topk(&other, &refs, &q, 6, 4096).unwrap();
    assert!(ctx.bytes_uploaded() - b3 >= map, "forests with other weights are another map");
}

/// A budget below the map's forests: they are streamed, uploaded with every batch, and the
/// lists are the CPU path's; several map chunks under a small binding limit.
#[test]
fn forests_beyond_the_budget_are_streamed() {
    let Some(ctx) = gpu_with(&GpuOptions { resident_budget: Some(20_000), max_binding_size: Some(64 * 1024), ..Default::default() }) else { return };
    let refs = random_forest_set(60, 16, 211);
    let q = random_forest_set(4, 16, 212);
    let p = TreeSimParams::new(&Default::default(), true, 3);
    let mut stages = GpuStages::new(ctx.clone());
    let cpu = CpuStages.fine_topk(&p, &refs, &q, 7, 4096).unwrap();
    for batch in 0..2 {
        let b = ctx.bytes_uploaded();
        let l = stages.fine_topk(&p, &refs, &q, 7, 4096).unwrap();
        let map = stages.map_bytes().1;
        assert!(map > 20_000 && !stages.fine_map_is_resident(), "{map} bytes of forests over a 20 kB budget");
        assert!(ctx.bytes_uploaded() - b >= map, "batch {batch}: the streamed forests are uploaded");
        assert_same_lists(&l, &cpu, 1e-5, "streamed forests");
    }
}

/// Every (query, reference) pair in grid order (query-major), as a whole-map pass takes them.
fn grid(nq: usize, nr: usize) -> Vec<(u32, u32)> {
    (0..nq as u32).flat_map(|q| (0..nr as u32).map(move |r| (q, r))).collect()
}

fn worst(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max)
}

/// A stored map is keyed by its identity and generation: after the first batch, a fine batch
/// against it reads none of its forests (nothing is hashed) and uploads none of them; adding to
/// it or removing from it (a new generation) uploads it again; the lists are the CPU path's.
#[test]
fn a_stored_maps_forests_are_keyed_by_its_generation() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let cfg = Config::without_appearance();
    let set = crate::common::encode(&cfg, &crate::common::label_maps(12, 80, 60), "r");
    let queries = crate::common::encode(&cfg, &crate::common::label_maps(3, 80, 60), "q");
    let mut map = semlook::map::Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    let p = semlook::matching::tree_params(&cfg, Setting::Forest, map.neighbour_slots()).unwrap();
    let mut stages = GpuStages::new(ctx.clone());
    let batch = |stages: &mut GpuStages, map: &semlook::map::Map| {
        let counted = Counted { src: map, reads: AtomicUsize::new(0) };
        let b = ctx.bytes_uploaded();
        let lists = stages.fine_topk(&p, &counted, &queries, 5, 4096).unwrap();
        assert_same_lists(&lists, &CpuStages.fine_topk(&p, map, &queries, 5, 4096).unwrap(), 1e-5, "stored map");
        let s = stages.fine_pairs(&p, &counted, &queries, &grid(queries.len(), map.len())).unwrap();
        assert!(worst(&s, &CpuStages.fine_pairs(&p, map, &queries, &grid(queries.len(), map.len())).unwrap()) <= 1e-5);
        (counted.reads.load(Ordering::Relaxed), ctx.bytes_uploaded() - b)
    };
    let (reads, bytes) = batch(&mut stages, &map);
    let forests = stages.map_bytes().1;
    assert!(reads >= map.len() && bytes >= forests, "first batch: {reads} forest reads, {bytes} bytes");
    let (reads, bytes) = batch(&mut stages, &map);
    assert_eq!(reads, 0, "a batch against the same stored map read its forests (hashing them for a key)");
    assert!(bytes < forests, "the forests were uploaded again ({bytes} bytes)");
    map.add(&crate::common::encode(&cfg, &crate::common::label_maps(2, 70, 50), "new")).unwrap();
    let (reads, bytes) = batch(&mut stages, &map);
    assert!(reads >= map.len() && bytes >= stages.map_bytes().1, "after an add: {reads} reads, {bytes} bytes");
    drop(map);
    semlook::map::edit::remove(&path, &["r3".to_string()]).unwrap();
    let map = semlook::map::Map::open(&path).unwrap();
    let (reads, bytes) = batch(&mut stages, &map);
    assert!(reads >= map.len() && bytes >= stages.map_bytes().1, "after a removal: {reads} reads, {bytes} bytes");
}

/// A reference source that counts its forest reads (everything else as the source says, its
/// generation included).
struct Counted<'a> {
    src: &'a dyn RefSource,
    reads: AtomicUsize,
}

impl GlobalSource for Counted<'_> {
    fn len(&self) -> usize {
        self.src.len()
    }
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        self.src.tile(start, end, buf)
    }
    fn check(&self) -> semlook::Result<()> {
        self.src.check()
    }
    fn generation(&self) -> Option<u64> {
        self.src.generation()
    }
}

impl RefSource for Counted<'_> {
    fn id(&self, i: usize) -> &str {
        self.src.id(i)
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        self.reads.fetch_add(1, Ordering::Relaxed);
        self.src.forest(i)
    }
    fn neighbour_slots(&self) -> usize {
        self.src.neighbour_slots()
    }
    fn appearance_dim(&self) -> usize {
        self.src.appearance_dim()
    }
    fn image_appearance(&self, i: usize) -> semlook::values::Values<'_> {
        self.src.image_appearance(i)
    }
    fn hog_dim(&self) -> usize {
        self.src.hog_dim()
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        self.src.image_hog(i)
    }
    fn keypoint_dim(&self) -> usize {
        self.src.keypoint_dim()
    }
    fn keypoints(&self, i: usize) -> semlook::descriptors::keypoints::KeypointsRef<'_> {
        self.src.keypoints(i)
    }
}
