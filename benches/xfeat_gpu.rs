//! Group `xfeat_forward_with_heads`: the XFeat network on the device (`device WxH`:
//! `networks::xfeat::XFeatGpu::forward_with` with the keypoint heads, as encoding with verification
//! keypoints runs it; one frame's upload, the 33 dispatches and the read-back of descriptors,
//! reliability and logits) and on the CPU (`cpu fast path WxH`: `XFeat::forward_with`), at
//! 640x480 and at 1920x1056 (a 1920x1080 frame rounded down to multiples of 32, as
//! `appearance::network_input` does). Needs the XFeat weights (setup.sh) and a hardware adapter;
//! on a software one (lavapipe) it says so and runs nothing unless SEMLOOK_BENCH_SOFTWARE=1
//! (seconds per frame there: correctness only).

use criterion::{criterion_group, criterion_main, Criterion};
use semlook::gpu::{GpuContext, GpuOptions};
use semlook::networks::xfeat::XFeatGpu;
use semlook::nn::conv::Chw;
use std::sync::Arc;

fn bench(c: &mut Criterion) {
    let model = match semlook::appearance::AppearanceModel::load(&Default::default(), &Default::default()) {
        Ok(Some(m)) if m.xfeat().is_some() => m,
        other => return eprintln!("xfeat_gpu benchmarks skipped: no XFeat weights ({:?})", other.err()),
    };
    let net = model.xfeat().expect("checked");
    let ctx = match GpuContext::new(&GpuOptions::default()) {
        Ok(c) => Arc::new(c),
        Err(e) => return eprintln!("xfeat_gpu benchmarks skipped: {e}"),
    };
    if ctx.is_software() && std::env::var("SEMLOOK_BENCH_SOFTWARE").as_deref() != Ok("1") {
        return eprintln!("xfeat_gpu benchmarks skipped: {} is a software adapter (SEMLOOK_BENCH_SOFTWARE=1 runs them anyway)", ctx.describe());
    }
    let x = XFeatGpu::new(ctx.clone(), net).unwrap();
    eprintln!("xfeat_gpu: the device is {}", ctx.describe());
    let mut g = c.benchmark_group("xfeat_forward_with_heads");
    g.sample_size(10);
    for (w, h) in [(640usize, 480usize), (1920, 1056)] {
        let mut rng = semlook::util::SplitMix64::new(1);
        let grey = Chw { c: 1, h, w, data: (0..w * h).map(|_| rng.next_f64() as f32).collect() };
        x.forward_with(&grey, true).unwrap();
        g.bench_function(format!("device {w}x{h}"), |b| b.iter(|| x.forward_with(&grey, true).unwrap()));
        g.bench_function(format!("cpu fast path {w}x{h}"), |b| b.iter(|| net.forward_with(&grey, true).unwrap()));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
