//! The coarse stage's SSIM kernel on one thread:
//! - the twin `ssim_pair` (the straightforward form the shader mirrors), one pair;
//! - the fast path's `ssim_lanes_fast`: one query against a group of references side by side
//!   (8 with AVX2), with the best instruction set pulp finds and with its scalar fallback (one
//!   lane); throughput counts pairs;
//! - one query's lane terms for the fast path, from its stats record; throughput counts queries.
//!
//! Inputs are real global descriptors of rendered street frames (64x48, 7x7 windows).

use criterion::{criterion_group, criterion_main, Criterion, Throughput};
use semlook::config::Config;
use semlook::global::ssim_fast::{
    interleave, query_lane_terms, query_lane_terms_len, ref_lane_terms, ref_lane_terms_len, ssim_lanes_fast, LaneScratch,
};
use semlook_cli::tools::synth::condition::Condition;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::ssim::{ssim_pair, SsimScratch};

mod common;

/// One call of the lane kernel, dispatched to an instruction set.
struct Lanes<'a> {
    p: &'a SsimParams,
    x: &'a [f32],
    xt: &'a [f32],
    refs: &'a [f32],
    stats: &'a [f32],
    y: &'a mut Vec<f32>,
    ys: &'a mut Vec<f32>,
    s: &'a mut LaneScratch,
    out: &'a mut [f32],
}

impl pulp::WithSimd for Lanes<'_> {
    type Output = usize;
    /// Interleaves the group once (as a task does once per query pass), then scores it.
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> usize {
        let (len, lanes) = (self.p.len(), S::F32_LANES);
        if self.y.len() != len * lanes {
            self.y.resize(len * lanes, 0.0);
            self.ys.resize(ref_lane_terms_len(self.p, lanes), 0.0);
            interleave(self.refs, len, lanes, lanes, self.y);
            ref_lane_terms(self.p, self.stats, lanes, lanes, self.ys);
        }
        ssim_lanes_fast(simd, self.p, self.x, self.xt, self.y, self.ys, self.s, self.out);
        lanes
    }
}

fn bench(c: &mut Criterion) {
    let cfg = Config::without_appearance();
    let images = common::encode_all(&cfg, &common::street_labels(2, 640, 480, Condition::Day));
    let p = cfg.global.ssim_params();
    let (x, y) = (&images[0], &images[1]);
    let mut xt = vec![0.0; query_lane_terms_len(&p)];
    query_lane_terms(&p, &x.global_stats, &mut xt);
    // 16 references (enough for any vector width): y and x alternately
    let refs: Vec<f32> = (0..16).flat_map(|i| if i % 2 == 0 { y.global.clone() } else { x.global.clone() }).collect();
    let stats: Vec<f32> = (0..16).flat_map(|i| if i % 2 == 0 { y.global_stats.clone() } else { x.global_stats.clone() }).collect();
    let mut g = c.benchmark_group("ssim pair (1 thread)");
    g.throughput(Throughput::Elements(1));
    let mut scratch = SsimScratch::default();
    g.bench_function("twin ssim_pair", |b| b.iter(|| ssim_pair(&p, &x.global, &x.global_stats, &y.global, &y.global_stats, &mut scratch)));
    g.finish();
    for (name, arch) in [(format!("{:?}", pulp::Arch::new()), pulp::Arch::new()), ("Scalar".to_string(), pulp::Arch::Scalar)] {
        let (mut yl, mut ysl, mut ls, mut out) = (Vec::new(), Vec::new(), LaneScratch::default(), vec![0.0f32; 16]);
        let mut call =
            || arch.dispatch(Lanes { p: &p, x: &x.global, xt: &xt, refs: &refs, stats: &stats, y: &mut yl, ys: &mut ysl, s: &mut ls, out: &mut out });
        let lanes = call();
        let mut g = c.benchmark_group("ssim pair (1 thread)");
        g.throughput(Throughput::Elements(lanes as u64));
        g.bench_function(format!("ssim_lanes_fast {} ({lanes} pairs a call)", name.split('(').next().unwrap_or("?")), |b| b.iter(&mut call));
        g.finish();
    }
    let mut g = c.benchmark_group("fast-path terms (1 thread)");
    g.throughput(Throughput::Elements(1));
    g.bench_function("query_lane_terms", |b| b.iter(|| query_lane_terms(&p, &x.global_stats, &mut xt)));
    g.finish();
    // what a task pays once per group of 8 references and query pass (and a single query per group)
    let mut g = c.benchmark_group("fast-path group preparation (1 thread)");
    g.throughput(Throughput::Elements(8));
    let (mut yl, mut yt) = (vec![0.0; p.len() * 8], vec![0.0; ref_lane_terms_len(&p, 8)]);
    g.bench_function("interleave + ref_lane_terms, 8 references", |b| {
        b.iter(|| {
            interleave(&refs, p.len(), 8, 8, &mut yl);
            ref_lane_terms(&p, &stats, 8, 8, &mut yt);
        })
    });
    g.finish();
}

/// The index's thumbnails ([`semlook::index::thumb`]): one query's thumbnail against 2,000
/// references' (real descriptors, pooled by 2 and 4), as the index's pool re-ranking scores them,
/// on one thread; throughput counts references.
fn thumbnails(c: &mut Criterion) {
    use semlook::index::thumb::{ThumbScorer, ThumbSpec};
    let cfg = Config::without_appearance();
    let images = common::encode_all(&cfg, &common::street_labels(2, 640, 480, Condition::Day));
    let one = rayon::ThreadPoolBuilder::new().num_threads(1).build().expect("a thread pool");
    for pool in [2, 4] {
        let spec = ThumbSpec { width: cfg.global.width, height: cfg.global.height, pool };
        let mut thumbs: Vec<Vec<u8>> = Vec::new();
        for i in 0..2000 {
            let mut t = Vec::new();
            spec.thumbnail(&images[i % 2].global, &mut t);
            thumbs.push(t);
        }
        let mut scorer = ThumbScorer::new(&spec, &cfg.global);
        scorer.set_query(&images[0].global);
        let mut g = c.benchmark_group("index thumbnails (1 thread)");
        g.throughput(Throughput::Elements(thumbs.len() as u64));
        let (w, h) = spec.dims();
        g.bench_function(format!("ThumbScorer::score, {w}x{h} (pooled by {pool}), 2,000 references"), |b| {
            b.iter(|| one.install(|| scorer.score(thumbs.iter().map(Vec::as_slice)).len()))
        });
        g.finish();
    }
}

criterion_group! {
    name = benches;
    config = Criterion::default().sample_size(20).measurement_time(std::time::Duration::from_secs(3));
    targets = bench, thumbnails
}
criterion_main!(benches);
