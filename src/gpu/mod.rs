//! The GPU path: WGSL compute kernels (in `shaders/`, with their CPU twins in the `semlook-kernels`
//! crate) run through wgpu, each held to its twin (same name, binding order and loop shape) by the
//! equivalence tests. The twins below are `semlook_kernels::` paths.
//!
//! | shader | entry points | CPU twin |
//! |---|---|---|
//! | `semantic_edges.wgsl` | `semantic_edges` | `kernels::semantic_edges::semantic_edges` |
//! | `edt.wgsl` | `edt_columns`, `edt_rows` | `kernels::edt::{edt_columns, edt_rows}` |
//! | `global_pool.wgsl` | `global_pool` | `kernels::global_pool::global_pool` |
//! | `ssim_stats.wgsl` | `stats_row_sums`, `stats_windows` | `kernels::ssim_stats::{stats_row_sums, stats_windows}` |
//! | `ssim_topk.wgsl` | `ssim_tile`, `topk_merge` (one-pair references, `gpu::reference`) | `kernels::ssim_topk::{ssim_tile, topk_merge}` |
//! | `ssim_block.wgsl` | `ssim_block` | `kernels::ssim_block::ssim_block` |
//! | `topk_select.wgsl` | `topk_partial`, `topk_merge_lists` | `kernels::topk_select::{topk_partial, topk_merge_lists}` |
//! | `tree_similarity.wgsl` | `tree_similarity`, `tree_similarity_small` | `kernels::tree_similarity::{tree_similarity, tree_similarity_small}` |
//! | `vlad_accumulate.wgsl` | `vlad_assign`, `vlad_accumulate` | `kernels::vlad_accumulate::{vlad_assign, vlad_accumulate}` |
//! | `mnn_match.wgsl` | `mnn_match` | `kernels::mnn_match::mnn_match` |
//! | `xfeat.wgsl` | `instance_norm_partials`, `instance_norm_stats`, `instance_norm_apply`, `avg_pool`, `space_to_depth8`, `bilinear_add`, `conv2d` | `kernels::xfeat::*` (same names) |
//! | `lighterglue.wgsl` | `lg_*` | `kernels::lighterglue::*` (same names) |
//! | `efficientnet.wgsl` | `conv_direct`, `pointwise`, `gem_pool` | `kernels::efficientnet::*` (same names) |
//!
//! Residency is explicit: executors own their device buffers and reuse them between batches;
//! the map (coarse: descriptors and statistics; fine: packed forests) is uploaded once and kept
//! while its key stays the same, within the context's budget (`gpu::resident`); queries are
//! uploaded once per batch; only top-K lists or pair scores come back.

mod appearance;
mod coarse;
mod embedding;
mod encode;
mod fine;
mod fine_pack;
/// Test hook, not the API: device runs of the one-pair reference kernels the equivalence tests
/// hold the production kernels to.
#[doc(hidden)]
pub mod reference;
mod resident;
mod stages;
mod topk;
mod verify;
mod vlad;

pub use crate::device::context::{GpuContext, GpuCounters, GpuError, GpuOptions, RESIDENT_FRACTION};
// what a network's device executor (`networks::xfeat::XFeatGpu`, `networks::embedding::EmbedderGpu`) did
pub use crate::device::executor::ExecutorCounters;
pub use stages::GpuStages;
// the stage executors `GpuStages` composes, each usable alone on a host's context (its buffers kept
// between calls): the global descriptors, VLAD, the coarse scan, the tree similarity, the
// keypoint matching of verification
pub use coarse::CoarseMatcherGpu;
pub use encode::GlobalEncoderGpu;
pub use fine::{FineCounters, FineMatcherGpu};
pub use verify::MnnGpu;
pub use vlad::VladGpu;

/// Creates every kernel's pipeline on `device` (with or without the subgroup variants) and drops
/// them: the driver checks each bind group layout against its shader's bindings. A test hook;
/// contexts build their pipelines once, themselves.
#[doc(hidden)]
pub fn create_every_pipeline(device: &wgpu::Device, subgroups: bool) -> Result<(), GpuError> {
    crate::device::kernels::Kernels::new(device, subgroups)?;
    crate::device::kernels::reference_kernels(device, subgroups).map(|_| ())
}
