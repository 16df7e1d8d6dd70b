//! Matching throughput on the CPU path.
//! - coarse: SSIM of a batch of queries against maps of 1k and 10k references with streaming
//!   top-K, through the production fast path (`coarse_topk`: `matching::coarse_cpu`) and through
//!   the CPU twins of the kernels the GPU path runs (`coarse_topk_twin`: `ssim_block`, then
//!   `topk_partial` + `topk_merge_lists`), the same batches; throughput counts (query, reference)
//!   comparisons;
//! - fine: tree-set similarity of one query forest against one candidate forest.

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use semlook::config::Config;
use semlook::matching::{coarse_topk, coarse_topk_twin};
use semlook_cli::tools::synth::condition::Condition;
use semlook_kernels::tree_similarity::{tree_similarity, TreeSimScratch};

mod common;

fn bench(c: &mut Criterion) {
    let cfg = Config::without_appearance();
    let images = common::encode_all(&cfg, &common::street_labels(32, 640, 480, Condition::Day));
    let queries = common::map_of(&cfg, &common::encode_all(&cfg, &common::street_labels(4, 640, 480, Condition::Night)), 4);
    let p = cfg.global.ssim_params();
    let mut g = c.benchmark_group("coarse");
    for n in [1_000usize, 10_000] {
        let refs = common::map_of(&cfg, &images, n);
        // a batch of 4 queries per iteration so both cores work; throughput counts comparisons
        g.throughput(Throughput::Elements((n * queries.len()) as u64));
        g.bench_function(format!("coarse_topk (fast path)/{n}_refs_x4_queries"), |b| {
            b.iter(|| coarse_topk(&refs, &queries, &p, cfg.matching.top_k, cfg.matching.tile))
        });
        g.bench_function(format!("coarse_topk_twin (twins of ssim_block + topk_select)/{n}_refs_x4_queries"), |b| {
            b.iter(|| coarse_topk_twin(&refs, &queries, &p, cfg.matching.top_k, cfg.matching.tile))
        });
    }
    // a batch as the engine sees it: 64 queries (one query pass of the fast path) x 10k references
    let refs = common::map_of(&cfg, &images, 10_000);
    let batch = common::map_of(&cfg, &common::encode_all(&cfg, &common::street_labels(8, 640, 480, Condition::Night)), 64);
    g.throughput(Throughput::Elements((10_000 * batch.len()) as u64));
    g.bench_function("coarse_topk (fast path)/10000_refs_x64_queries", |b| {
        b.iter(|| coarse_topk(&refs, &batch, &p, cfg.matching.top_k, cfg.matching.tile))
    });
    // the same on the GPU path, when there is an adapter (lavapipe counts: it says so in the name)
    match semlook::gpu::GpuContext::new(&Default::default()) {
        Ok(ctx) => {
            let name = ctx.info.name.clone();
            let mut stages = semlook::gpu::GpuStages::new(std::sync::Arc::new(ctx));
            let refs = common::map_of(&cfg, &images, 1_000);
            g.throughput(Throughput::Elements((1_000 * queries.len()) as u64));
            g.bench_function(format!("gpu ssim_block + topk_select on {name}/1000_refs_x4_queries"), |b| {
                b.iter(|| semlook::matching::Stages::coarse(&mut stages, &refs, &queries, &p, cfg.matching.top_k, cfg.matching.tile).unwrap())
            });
        }
        Err(e) => eprintln!("GPU benchmark skipped: {e}"),
    }
    g.finish();
    let mut g = c.benchmark_group("fine");
    let mut scratch = TreeSimScratch::default();
    for (name, appearance) in [("forest", false), ("forest+appearance (neutral)", true)] {
        let params = cfg.similarity.tree_params(appearance, cfg.local.neighbours);
        let mut k = 0;
        g.throughput(Throughput::Elements(1));
        g.bench_function(format!("tree_similarity/{name}"), |b| {
            b.iter(|| {
                k = (k + 1) % images.len();
                tree_similarity(&params, queries.forest(k % 4), images[k].forest.as_ref(), &mut scratch)
            })
        });
    }
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(10).measurement_time(std::time::Duration::from_secs(5));
    targets = bench
}
criterion_main!(benches);
