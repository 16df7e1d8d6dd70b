//! Encoding time per frame at 640x480 (no network): global descriptor, forest, and both.
//! Target (issue 2): <= 10 ms per frame, median, on 2 cores (one frame runs on one core).

use criterion::{criterion_group, criterion_main, Criterion};
use semlook::config::Config;
use semlook::encode::Encoder;
use semlook::global::{encode_global, ssim::SsimParams, GlobalScratch};
use semlook::synth::condition::Condition;

mod common;

fn bench(c: &mut Criterion) {
    let cfg = Config::without_appearance();
    let maps = common::street_labels(4, 640, 480, Condition::Day);
    let enc = Encoder::new(&cfg).unwrap();
    let table = enc.class_table().clone();
    let p = SsimParams::new(&cfg.global);
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
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(30).measurement_time(std::time::Duration::from_secs(4));
    targets = bench
}
criterion_main!(benches);
