//! The CPU twins of the WGSL kernels, one file per shader: `shaders/X.wgsl` and `kernels::X` hold
//! the same entry points under the same names, with the same bindings (arguments) and the same
//! loop shape (an outer loop over the dispatch's invocations, the shader's body inside), so that
//! the device is held to them by the tests in `tests/gpu/`. Where the CPU path runs something
//! faster than a twin, that fast path lives with its stage (`global::ssim_fast`,
//! `matching::coarse_cpu`, `verify::best_columns`) and is held to the twin by tests too.
//!
//! [`abi`] holds the structs and limits the host writes into the shaders' uniforms and buffers,
//! shared by the twins and the GPU executors (`crate::gpu`); `shaders/abi.wgsl` is its WGSL side,
//! included by the shaders that share a struct.
//!
//! The twins import only the bottom of the crate (configuration, value views, utilities); every
//! stage imports them, none of them imports a stage.

pub mod abi;
pub mod edt;
pub mod global_pool;
pub mod lighterglue;
pub mod mnn_match;
pub mod semantic_edges;
pub mod ssim;
pub mod ssim_block;
pub mod ssim_stats;
pub mod ssim_topk;
#[cfg(test)]
pub(crate) mod test_data;
pub mod topk_select;
pub mod tree_similarity;
pub mod vlad_accumulate;
pub mod xfeat;
