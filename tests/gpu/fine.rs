//! The fine stage on the device: the map's packed forests resident across batches (counted to
//! the byte), streamed through two slots beyond the budget, the CPU path's lists either way.

use super::{assert_same_lists, gpu, gpu_with, random_forest_set};
use semlook::engine::GpuStages;
use semlook::gpu::GpuOptions;
use semlook::kernels::abi::TreeSimParams;
use semlook::matching::{CpuStages, Stages};

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
