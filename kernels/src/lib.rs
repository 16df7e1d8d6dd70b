//! # semlook-kernels
//!
//! The WGSL compute kernels of semlook and their CPU twins, one file per shader: `shaders/X.wgsl`
//! (in the repository's `shaders/`, included by [`wgsl`]) and `semlook_kernels::X` hold the same
//! entry points under the same names, with the same bindings (arguments) and the same loop shape
//! (an outer loop over the dispatch's invocations, the shader's body inside), so that the device is
//! held to them by semlook's GPU tests. Where the CPU path runs something faster than a twin, that
//! fast path lives with its stage in semlook (`global::ssim_fast`, `matching::coarse_cpu`,
//! `verify::best_columns`) and is held to the twin by tests too.
//!
//! - [`wgsl`]: the shader sources and their preprocessor; the build script validates every variant
//!   of every shader with naga, so a shader error fails the build (as `vello_shaders` does).
//! - [`abi`]: the structs and limits the host writes into the shaders' uniforms and buffers
//!   (`shaders/abi.wgsl` is its WGSL side), [`bindings`]: every entry point's bind groups. The
//!   layout tests hold both to naga's reflection of the WGSL, field by field, without an adapter.
//! - [`values`]: the value views the twins read (f32, f16, int8 blocks), [`rng`]: the seeded
//!   generator of the twins' property tests.
//!
//! This crate depends on no part of semlook: semlook's GPU executors (`semlook::gpu`) build their
//! pipelines from [`wgsl`] and [`bindings`], and its configuration makes the [`abi`] structs.

// every public item is documented; clippy -D warnings (the test command) turns this into an error
#![warn(missing_docs)]

pub mod abi;
pub mod bindings;
pub mod edt;
pub mod efficientnet;
pub mod global_pool;
pub mod lighterglue;
pub mod mnn_match;
pub mod rng;
pub mod semantic_edges;
pub mod ssim;
pub mod ssim_block;
pub mod ssim_stats;
pub mod ssim_topk;
pub mod topk_select;
pub mod tree_similarity;
pub mod values;
pub mod vlad_accumulate;
pub mod wgsl;
pub mod xfeat;

#[cfg(test)]
mod layout_tests;
/// Descriptors for property tests of the coarse kernels and of the fast paths held to them
/// (feature `test-data`: semlook's own tests use it).
#[cfg(any(test, feature = "test-data"))]
pub mod test_data;
