//! The coarse stage's SSIM kernel on one thread:
//! - one pair: the twin `ssim_pair` (the straightforward form the shader mirrors) against the
//!   fast path's `ssim_pair_fast`, with the best instruction set pulp finds and with its scalar
//!   fallback; throughput counts pairs;
//! - one descriptor's terms for the fast path, from its stored stats or from the descriptor
//!   alone (a store that keeps no stats); throughput counts descriptors.
//!
//! Inputs are real global descriptors of rendered street frames (64x48, 7x7 windows).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use semlook::config::Config;
use semlook::global::ssim_fast::{ssim_pair_fast, terms_from_descriptor, terms_from_stats, FastLayout, FastScratch};
use semlook::kernels::abi::SsimParams;
use semlook::kernels::ssim::{ssim_pair, SsimScratch};
use semlook::tools::synth::condition::Condition;

mod common;

struct Fast<'a> {
    p: &'a SsimParams,
    l: &'a FastLayout,
    x: &'a [f32],
    tx: &'a [f32],
    y: &'a [f32],
    ty: &'a [f32],
    s: &'a mut FastScratch,
}

impl pulp::WithSimd for Fast<'_> {
    type Output = f32;
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> f32 {
        ssim_pair_fast(simd, self.p, self.l, self.x, self.tx, self.y, self.ty, self.s)
    }
}

fn bench(c: &mut Criterion) {
    let cfg = Config::without_appearance();
    let images = common::encode_all(&cfg, &common::street_labels(2, 640, 480, Condition::Day));
    let p = SsimParams::new(&cfg.global);
    let l = FastLayout::new(&p);
    let (x, y) = (&images[0], &images[1]);
    let (mut tx, mut ty) = (vec![0.0; l.terms_len()], vec![0.0; l.terms_len()]);
    terms_from_stats(&l, &x.global_stats, &mut tx);
    terms_from_stats(&l, &y.global_stats, &mut ty);
    let mut g = c.benchmark_group("ssim pair (1 thread)");
    g.throughput(Throughput::Elements(1));
    let mut scratch = SsimScratch::default();
    g.bench_function("twin ssim_pair", |b| b.iter(|| ssim_pair(&p, &x.global, &x.global_stats, &y.global, &y.global_stats, &mut scratch)));
    let mut fs = FastScratch::new(&l);
    for (name, arch) in [(format!("{:?}", pulp::Arch::new()), pulp::Arch::new()), ("Scalar".to_string(), pulp::Arch::Scalar)] {
        g.bench_function(format!("ssim_pair_fast {}", name.split('(').next().unwrap_or("?")), |b| {
            b.iter(|| arch.dispatch(Fast { p: &p, l: &l, x: &x.global, tx: &tx, y: &y.global, ty: &ty, s: &mut fs }))
        });
    }
    g.finish();
    let mut g = c.benchmark_group("fast-path terms (1 thread)");
    g.throughput(Throughput::Elements(1));
    g.bench_function("terms_from_stats", |b| b.iter(|| terms_from_stats(&l, &x.global_stats, &mut tx)));
    let (mut st, mut sc) = (vec![0.0; p.stats_len()], SsimScratch::default());
    g.bench_function("terms_from_descriptor", |b| b.iter(|| terms_from_descriptor(&p, &l, &x.global, &mut st, &mut sc, &mut tx)));
    g.finish();
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = bench
}
criterion_main!(benches);
