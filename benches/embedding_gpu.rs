//! Group `embedding_forward`: the whole-image embedding network (EfficientNet-Lite1 + GeM, run
//! from its checkpoint) on the device (`device WxH`: `networks::embedding::EmbedderGpu::forward`;
//! one frame's upload, the network's dispatches in one submission and the read-back of the pooled
//! values) and natively on the CPU (`cpu native WxH`: `EfficientNetLite::forward`), at 448x336 (the
//! working size of a 640x480 frame) and 448x252 (of a 1920x1080 one). Needs the checkpoint
//! (setup.sh) and a hardware adapter; on a software one (lavapipe) it says so and runs nothing
//! unless SEMLOOK_BENCH_SOFTWARE=1 (seconds per frame there: correctness only).

use criterion::{criterion_group, criterion_main, Criterion};
use semlook::gpu::{GpuContext, GpuOptions};
use semlook::networks::embedding::{EfficientNetLite, EmbedderGpu, EMBEDDING_CHECKPOINT};
use semlook::nn::conv::Chw;
use std::sync::Arc;

fn bench(c: &mut Criterion) {
    let net = match semlook::nn::onnx::find_model(EMBEDDING_CHECKPOINT, None, "embedding checkpoint").and_then(|p| EfficientNetLite::load(&p)) {
        Ok(n) => n,
        Err(e) => return eprintln!("embedding_gpu benchmarks skipped: {e}"),
    };
    let ctx = match GpuContext::new(&GpuOptions::default()) {
        Ok(c) => Arc::new(c),
        Err(e) => return eprintln!("embedding_gpu benchmarks skipped: {e}"),
    };
    if ctx.is_software() && std::env::var("SEMLOOK_BENCH_SOFTWARE").as_deref() != Ok("1") {
        return eprintln!("embedding_gpu benchmarks skipped: {} is a software adapter (SEMLOOK_BENCH_SOFTWARE=1 runs them anyway)", ctx.describe());
    }
    let gpu = EmbedderGpu::new(ctx.clone(), &net).unwrap();
    eprintln!("embedding_gpu: the device is {}", ctx.describe());
    let mut g = c.benchmark_group("embedding_forward");
    g.sample_size(10);
    for (w, h) in [(448usize, 336usize), (448, 252)] {
        let mut rng = semlook::util::SplitMix64::new(1);
        let rgb = Chw { c: 3, h, w, data: (0..3 * w * h).map(|_| (rng.next_u64() % 256) as f32).collect() };
        gpu.forward(&rgb).unwrap();
        g.bench_function(format!("device {w}x{h}"), |b| b.iter(|| gpu.forward(&rgb).unwrap()));
        g.bench_function(format!("cpu native {w}x{h}"), |b| b.iter(|| net.forward(&rgb).unwrap()));
    }
    g.finish();
}

criterion_group!(benches, bench);
criterion_main!(benches);
