//! What sits beside the engine, in the command line's crate: the synthetic benchmark's renderer
//! (`synth`), pictures of every stage, explain sheets and precision-recall charts (`viz`), the
//! large-map matching and store benchmarks with their /proc readers (`bench`, `bench_store`), the
//! stream replay benchmark (`bench_stream`) and the configuration sweeps (`tune`). The engine
//! (crate `semlook`) cannot import them: this crate depends on it, not the other way round.

pub mod bench;
pub mod bench_index;
pub mod bench_store;
pub mod bench_stream;
pub mod synth;
pub mod tune;
pub mod viz;

/// Reads a field of /proc/self/status (`VmHWM:`, `RssAnon:`, ...), in MiB (NaN where there is
/// none: not Linux).
pub(crate) fn status_mib(field: &str) -> f64 {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| s.lines().find(|l| l.starts_with(field)).and_then(|l| l.split_whitespace().nth(1)).and_then(|v| v.parse::<f64>().ok()))
        .map_or(f64::NAN, |kb| kb / 1024.0)
}

/// Resets the kernel's peak-RSS counter (VmHWM) of this process (Linux), so each row reports its
/// own peak.
pub(crate) fn reset_peak() {
    let _ = std::fs::write("/proc/self/clear_refs", "5");
}
