//! # semlook-cli
//!
//! The `semlook` command line (the binary, `src/main.rs` and `src/cli/`) and the developer tools
//! beside the engine ([`tools`]: the synthetic benchmark, pictures, benchmarks, sweeps), which the
//! command line runs and the engine's tests and benchmarks use for their synthetic data. The engine
//! is the `semlook` crate; an application embeds it alone and builds none of this (no clap, no
//! plotters).

pub mod tools;
