//! The GPU path: WGSL compute kernels (in `shaders/`) run through wgpu, each held to its CPU twin
//! (same name, binding order and loop shape) by the equivalence tests.
//!
//! | shader | entry points | CPU twin |
//! |---|---|---|
//! | `semantic_edges.wgsl` | `semantic_edges` | `global::semantic_edges::semantic_edges` |
//! | `edt.wgsl` | `edt_columns`, `edt_rows` | `global::edt::{edt_columns, edt_rows}` |
//! | `global_pool.wgsl` | `global_pool` | `global::global_pool::global_pool` |
//! | `ssim_topk.wgsl` | `ssim_tile`, `topk_merge` | `matching::ssim_topk::{ssim_tile, topk_merge}` |
//! | `tree_similarity.wgsl` | `tree_similarity` | `local::tree_similarity::tree_similarity` |
//! | `vlad_accumulate.wgsl` | `vlad_assign`, `vlad_accumulate` | `appearance::vlad::{vlad_assign, vlad_accumulate}` |
//!
//! Residency is explicit: executors own their device buffers and reuse them between batches;
//! uploads and read-backs happen only where their methods say (queries are uploaded once per
//! batch, map tiles are streamed, only top-K lists or pair scores come back).

pub mod coarse;
mod context;
pub mod encode;
pub mod fine;
mod kernels;
pub mod vlad;

pub use context::{GpuContext, GpuError, GpuOptions};
pub use kernels::SHADERS;
