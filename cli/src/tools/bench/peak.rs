//! The peaks the benchmark divides by.
//! - CPU: measured, not a data-sheet figure: an FMA loop on one thread with the widest vectors
//!   `pulp` finds, [`ACCUMULATORS`] independent chains (2 flops per lane per FMA), best of
//!   `RUNS`, times the worker threads. It is what these cores sustain on dense multiply-adds;
//!   an SSIM comparison also needs additions and a division per window, so it cannot reach it.
//! - GPU: FP32 (non-tensor) data-sheet peaks of a few datacentre parts, or `--peak-gflops`.
//!   Software adapters (lavapipe, llvmpipe) have none: their rows are correctness only.

use semlook::engine::Engine;
use semlook::matching::coarse_cpu::CoarseCpu;
use semlook_kernels::abi::SsimParams;
use std::time::Instant;

/// Independent FMA chains per thread: latency 4 cycles x 2 FMA pipes needs 8; 12 leaves margin
/// and, with the two operands, fits the 16 vector registers of AVX2.
pub const ACCUMULATORS: usize = 12;

/// Seconds one measurement runs (after a short calibration run).
const MEASURE_S: f64 = 0.05;

/// Measurements, of which the best counts: short enough together (0.25 s) to run before every
/// benchmark, enough for one of them to find the core free on a busy machine.
const RUNS: usize = 5;

/// FP32 peaks (GFLOP/s) by adapter name, most specific first: vendor data sheets, boost clock.
const GPU_PEAKS: [(&str, f64); 5] = [("H100 PCIe", 51_200.0), ("H200", 66_900.0), ("H100", 66_900.0), ("A100", 19_500.0), ("L40S", 91_600.0)];

/// A benchmark device: what a row names and divides by.
#[derive(Debug, Clone)]
pub struct Device {
    pub backend: String,
    pub adapter: String,
    pub peak_gflops: Option<f64>,
    pub peak_source: Option<String>,
    pub note: String,
}

impl Device {
    /// The device an engine runs on; `gpu_peak` overrides the table for a hardware GPU.
    pub fn of(engine: &mut Engine, p: &SsimParams, gpu_peak: Option<f64>) -> Device {
        match engine.gpu_stages() {
            Some(g) => {
                let (adapter, name) = (g.ctx.describe(), g.ctx.info.name.clone());
                if g.ctx.is_software() {
                    return Device {
                        backend: "gpu".into(),
                        adapter,
                        peak_gflops: None,
                        peak_source: None,
                        note: "correctness only (software adapter)".into(),
                    };
                }
                let (peak, source) = match (gpu_peak, GPU_PEAKS.iter().find(|(n, _)| name.contains(n))) {
                    (Some(v), _) => (Some(v), Some(format!("{v:.0} GFLOP/s (given)"))),
                    (None, Some((n, v))) => (Some(*v), Some(format!("{v:.0} GFLOP/s ({n} FP32 data sheet)"))),
                    (None, None) => (None, None),
                };
                Device { backend: "gpu".into(), adapter, peak_gflops: peak, peak_source: source, note: String::new() }
            }
            None => {
                let peak = cpu_peak_gflops();
                let adapter = format!("{} ({} threads, SIMD {})", cpu_model(), rayon::current_num_threads(), CoarseCpu::new(p).describe_simd());
                Device {
                    backend: "cpu".into(),
                    adapter,
                    peak_gflops: Some(peak),
                    peak_source: Some(format!("{peak:.0} GFLOP/s measured (one thread's FMA loop x {} threads)", rayon::current_num_threads())),
                    note: String::new(),
                }
            }
        }
    }
}

/// The processor's model name (Linux), else "cpu".
pub fn cpu_model() -> String {
    std::fs::read_to_string("/proc/cpuinfo")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with("model name")).and_then(|l| l.split(':').nth(1)).map(|v| v.trim().to_string()))
        .unwrap_or_else(|| "cpu".into())
}

/// FMA throughput of one thread, GFLOP/s: the best of `RUNS` runs of `MEASURE_S` each (other
/// processes on the machine can only lower a run, never raise it).
pub fn thread_peak_gflops() -> f64 {
    let arch = pulp::Arch::new();
    let run = |iters: usize| {
        let t = Instant::now();
        let (lanes, _) = arch.dispatch(Fma { iters });
        ((2 * lanes * ACCUMULATORS * iters) as f64, t.elapsed().as_secs_f64())
    };
    let (_, s) = run(100_000);
    let iters = ((100_000.0 * MEASURE_S / s.max(1e-9)) as usize).max(100_000);
    (0..RUNS).map(|_| run(iters)).map(|(f, s)| f / s / 1e9).fold(0.0, f64::max)
}

/// The CPU's peak for the benchmark: one thread's FMA throughput times the worker threads
/// (each worker on a core of its own).
pub fn cpu_peak_gflops() -> f64 {
    thread_peak_gflops() * rayon::current_num_threads() as f64
}

/// `iters` rounds of one FMA on each accumulator; returns the lane count and a sum that keeps
/// the work live.
struct Fma {
    iters: usize,
}

impl pulp::WithSimd for Fma {
    type Output = (usize, f32);

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) -> (usize, f32) {
        let (a, b) = (simd.splat_f32s(0.999_999), simd.splat_f32s(1e-7));
        let mut acc = [simd.splat_f32s(1.0); ACCUMULATORS];
        for _ in 0..self.iters {
            for x in acc.iter_mut() {
                *x = simd.mul_add_f32s(*x, a, b);
            }
        }
        let s = acc.iter().fold(simd.splat_f32s(0.0), |s, x| simd.add_f32s(s, *x));
        (S::F32_LANES, std::hint::black_box(simd.reduce_sum_f32s(s)))
    }
}
