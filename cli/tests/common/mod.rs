//! Helpers of the command line's tests: the engine tests' helpers (`tests/common`, shared) and the
//! `semlook` binary of this package.
#![allow(dead_code)]

#[path = "../../../tests/common/mod.rs"]
mod shared;
pub use shared::*;

/// Runs the `semlook` binary with `args`.
pub fn cli(args: &[&str]) -> std::process::Output {
    std::process::Command::new(bin()).args(args).output().expect("binary runs")
}

/// The `semlook` binary under test: this build's, or `$SEMLOOK_TEST_BIN` (an older build, to
/// see a new test fail on what it was written against).
pub fn bin() -> std::path::PathBuf {
    std::env::var_os("SEMLOOK_TEST_BIN").filter(|b| !b.is_empty()).map_or_else(|| env!("CARGO_BIN_EXE_semlook").into(), Into::into)
}

/// The stdout of a `semlook` run that must succeed.
pub fn cli_ok(args: &[&str]) -> String {
    let out = cli(args);
    assert!(out.status.success(), "semlook {args:?} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    String::from_utf8(out.stdout).unwrap()
}
