//! The benchmark runs what its rows name.

use super::*;
use semlook::descriptors::EncodedImage;
use semlook::local::Forest;
use semlook_kernels::ssim::{ssim_stats, SsimScratch};

/// `n` random descriptors at the default size (stats computed).
fn pool(n: usize, seed: u64) -> DescriptorSet {
    let p = semlook::config::GlobalConfig::default().ssim_params();
    let mut rng = semlook::util::SplitMix64::new(seed);
    let mut set = DescriptorSet::new(&p, 1, 0, 0);
    for i in 0..n {
        let g: Vec<f32> = (0..p.len()).map(|_| rng.next_f64() as f32).collect();
        let mut st = vec![0.0; p.stats_len()];
        ssim_stats(&p, &g, &mut st, &mut SsimScratch::default());
        set.push(&EncodedImage {
            id: format!("p{i}"),
            width: 1,
            height: 1,
            global: g,
            global_stats: st,
            forest: Forest { neighbour_slots: 1, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: Default::default(),
            pose: None,
        })
        .unwrap();
    }
    set
}

fn opts(sizes: Vec<usize>, batches: Vec<usize>, max_row_seconds: f64) -> BenchOptions {
    BenchOptions { sizes, batches, max_row_seconds, resident_limit: 40, gpu_peak_gflops: None }
}

/// Every row that runs scores its whole batch (resident and synthetic maps); the JSON object of a
/// row carries the fields the issue asks for.
#[test]
fn rows_run_their_whole_batch() {
    let cfg = Config { matching: semlook::config::MatchingConfig { tile: 16, ..Default::default() }, ..Default::default() };
    let rows = run(&pool(5, 1), &pool(3, 2), &opts(vec![30, 70], vec![1, 7], 1e9), &mut [Engine::cpu()], &cfg, &mut |_| {}).unwrap();
    assert_eq!(rows.len(), 4);
    for r in &rows {
        assert_eq!((r.status.as_str(), r.queries_run), ("ran", r.batch), "{r:?}");
        assert!(r.comparisons_per_s.unwrap() > 0.0 && r.gflops.unwrap() > 0.0 && r.fraction_of_peak.unwrap() > 0.0);
        assert_eq!(r.tiles_copied, 0, "tiles of 16 line up with the block of 16");
        let json = serde_json::to_value(r).unwrap();
        for key in ["map_size", "batch", "backend", "adapter", "queries_run", "comparisons_per_s", "peak_rss_mib"] {
            assert!(json.get(key).is_some(), "{key} missing from {json}");
        }
    }
}

/// A row predicted to exceed the limit runs nothing and says so.
#[test]
fn rows_over_the_limit_are_skipped_not_shrunk() {
    let rows = run(&pool(4, 3), &pool(2, 4), &opts(vec![20], vec![5], 0.0), &mut [Engine::cpu()], &Config::default(), &mut |_| {}).unwrap();
    assert_eq!((rows[0].status.as_str(), rows[0].queries_run, rows[0].comparisons_per_s), ("skipped", 0, None));
    assert!(rows[0].note.contains("not run: predicted"), "{}", rows[0].note);
}

/// A synthetic map serves reference i as block entry i mod block, borrowed where a tile lines up
/// and copied (and counted) where it does not.
#[test]
fn synthetic_tiles_are_the_block_entries() {
    let pool = pool(7, 5);
    let m = SyntheticMap::new(&pool, 100, 10);
    let mut buf = TileBuf::default();
    for (start, end) in [(20, 30), (37, 45)] {
        let (g, st) = m.tile(start, end, &mut buf);
        for (j, i) in (start..end).enumerate() {
            assert_eq!(&g[j * pool.global_len..(j + 1) * pool.global_len], m.block.global(i % 10));
            assert_eq!(&st[j * pool.stats_len..(j + 1) * pool.stats_len], m.block.stats(i % 10));
        }
    }
    assert_eq!(m.take_copied(), 1, "only the tile across the block's end was copied");
}
