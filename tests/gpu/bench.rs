//! `semlook dev bench`'s GPU rows on whatever adapter there is (lavapipe in CI: correctness only).

use super::{gpu_with, random_descriptors};
use semlook::config::{Config, GlobalConfig};
use semlook::engine::Engine;
use semlook::gpu::GpuOptions;
use semlook_cli::tools::bench::{run, BenchOptions};

/// CPU and GPU rows at small sizes (8 x 8 descriptors), a resident map (300 references) and a
/// synthetic one (1,200, beyond a 256 KiB binding: several chunks), then the same with a 100 kB
/// resident budget (streamed): every row runs its whole batch; GPU rows name the adapter, say
/// "correctness only" on a software adapter (no peak, no fraction of peak), report the untimed
/// upload, and write no map bytes inside the timed region while the map is resident.
#[test]
fn gpu_rows_run_their_batches_and_say_what_they_measured() {
    for (budget, resident) in [(None, true), (Some(100_000), false)] {
        let Some(ctx) = gpu_with(&GpuOptions { max_binding_size: Some(256 << 10), resident_budget: budget, ..Default::default() }) else { return };
        let cfg = Config { global: GlobalConfig { width: 8, height: 8, ssim_window: 3, ..Default::default() }, ..Config::without_appearance() };
        let (pool, queries) = (random_descriptors(50, &cfg, 301), random_descriptors(20, &cfg, 302));
        let opts = BenchOptions { sizes: vec![300, 1200], batches: vec![5, 40], max_row_seconds: 1e9, resident_limit: 500, gpu_peak_gflops: None };
        let software = ctx.is_software();
        let mut engines = [Engine::cpu(), Engine::with_context(ctx.clone())];
        let rows = run(&pool, &queries, &opts, &mut engines, &cfg, &mut |r| eprintln!("{}", serde_json::to_string(r).unwrap())).unwrap();
        assert_eq!(rows.len(), 8);
        let per_ref = ((pool.global_len + pool.stats_len) * 4) as u64;
        for r in rows.iter().filter(|r| r.backend == "gpu") {
            assert_eq!((r.status.as_str(), r.queries_run), ("ran", r.batch), "{r:?}");
            assert!(r.comparisons_per_s.unwrap() > 0.0 && r.bytes_per_s.unwrap() > 0.0 && r.gflops.unwrap() > 0.0);
            assert_eq!(r.adapter, ctx.describe());
            assert!(r.upload_seconds.is_some());
            assert_eq!(r.map_resident, Some(resident), "{r:?}");
            let written = r.device_bytes_written.unwrap();
            let map = r.map_size as u64 * per_ref;
            if resident {
                assert!(written < map, "{written} bytes written in the timed region, the map is {map}");
            } else {
                assert!(written >= map, "a streamed map is written in every batch");
            }
            if software {
                assert!(r.note.contains("correctness only") && r.peak_gflops.is_none() && r.fraction_of_peak.is_none(), "{r:?}");
            }
            let json = serde_json::to_value(r).unwrap();
            for key in [
                "map_size",
                "batch",
                "backend",
                "adapter",
                "queries_run",
                "comparisons_per_s",
                "peak_rss_mib",
                "bytes_per_s",
                "gflops",
                "fraction_of_peak",
                "device_bytes_written",
            ] {
                assert!(json.get(key).is_some(), "{key} missing from {json}");
            }
        }
    }
}
