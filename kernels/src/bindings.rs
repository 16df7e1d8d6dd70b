//! Every entry point's bind groups as the host binds them: the one statement of the slots. The
//! pipelines (`semlook::gpu`) are built from [`BINDINGS`], and this crate's layout tests hold it to
//! naga's reflection of every shader, without an adapter.

/// How the host binds one binding of an entry point.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Slot {
    /// A uniform buffer, bound whole.
    Uniform,
    /// A uniform selected per dispatch by a dynamic offset; the binding is `size` bytes.
    UniformAt(u64),
    /// A read-only storage buffer.
    Read,
    /// A read-write storage buffer.
    ReadWrite,
}

/// Bytes of the per-pass parameters the coarse kernels bind at dynamic offsets.
const PASS: u64 = std::mem::size_of::<crate::abi::PassParams>() as u64;
/// Bytes of the fine stage's per-pass parameters.
const FINE_PASS: u64 = std::mem::size_of::<crate::abi::FinePass>() as u64;
/// Bytes of the XFeat convolution's uniform (each XFeat uniform is bound at a dynamic offset of one buffer).
const XF_CONV: u64 = std::mem::size_of::<crate::abi::ConvParams>() as u64;
/// Bytes of the XFeat map kernels' uniform.
const XF_MAP: u64 = std::mem::size_of::<crate::abi::MapParams>() as u64;
/// Bytes of the XFeat normalisation kernels' uniform.
const XF_NORM: u64 = std::mem::size_of::<crate::abi::NormParams>() as u64;
/// Bytes of the LighterGlue kernels' uniform (bound at a dynamic offset of one buffer).
const LG: u64 = std::mem::size_of::<crate::abi::LgParams>() as u64;
/// Bytes of the embedding kernels' uniforms (each bound at a dynamic offset of one buffer).
const EFF_CONV: u64 = std::mem::size_of::<crate::abi::EffConvParams>() as u64;
const EFF_POINT: u64 = std::mem::size_of::<crate::abi::EffPointParams>() as u64;
const EFF_GEM: u64 = std::mem::size_of::<crate::abi::GemParams>() as u64;

use Slot::{Read, ReadWrite, Uniform, UniformAt};
const EDT: &[(u32, Slot)] = &[(0, Uniform), (1, Read), (2, ReadWrite), (3, ReadWrite), (4, ReadWrite), (5, ReadWrite)];
const STATS: &[(u32, Slot)] = &[(0, Uniform), (1, Uniform), (2, Read), (3, ReadWrite), (4, ReadWrite)];
const TOPK: &[(u32, Slot)] = &[(0, UniformAt(PASS)), (1, Read), (2, ReadWrite), (3, ReadWrite), (4, ReadWrite)];
const TREE: &[&[(u32, Slot)]] = &[
    &[(0, Uniform), (1, UniformAt(FINE_PASS)), (2, Read), (3, Read), (4, Read), (5, ReadWrite), (6, ReadWrite)],
    &[(0, Read), (1, Read), (2, Read)],
];
const XF_MAP1: &[(u32, Slot)] = &[(5, UniformAt(XF_MAP)), (6, Read), (9, ReadWrite)];

/// Every entry point's bind groups as the host binds them (file, entry, group 0, group 1, ...:
/// each a list of (binding, slot)); where a pass's parameters come from one buffer at dynamic
/// offsets, the uniform is `UniformAt` its size. The only statement of the slots: kernels are
/// built from it, and `layout_tests` holds it to naga's reflection of every shader (the address
/// space and access of each binding an entry point uses), without an adapter.
pub const BINDINGS: &[(&str, &str, &[&[(u32, Slot)]])] = &[
    ("semantic_edges.wgsl", "semantic_edges", &[&[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite)]]),
    ("edt.wgsl", "edt_columns", &[EDT]),
    ("edt.wgsl", "edt_rows", &[EDT]),
    ("global_pool.wgsl", "global_pool", &[&[(0, Uniform), (1, Read), (2, ReadWrite)]]),
    ("ssim_topk.wgsl", "ssim_tile", &[&[(0, Uniform), (1, Uniform), (2, Read), (3, Read), (4, Read), (5, Read), (6, ReadWrite)]]),
    ("ssim_topk.wgsl", "topk_merge", &[&[(1, Uniform), (6, ReadWrite), (7, ReadWrite), (8, ReadWrite)]]),
    ("ssim_block.wgsl", "ssim_block", &[&[(0, Uniform), (1, UniformAt(PASS)), (2, Read), (3, Read), (4, ReadWrite)], &[(0, Read), (1, Read)]]),
    ("ssim_stats.wgsl", "stats_row_sums", &[STATS]),
    ("ssim_stats.wgsl", "stats_windows", &[STATS]),
    ("topk_select.wgsl", "topk_partial", &[TOPK]),
    ("topk_select.wgsl", "topk_merge_lists", &[TOPK]),
    ("tree_similarity.wgsl", "tree_similarity", TREE),
    ("tree_similarity.wgsl", "tree_similarity_small", TREE),
    ("vlad_accumulate.wgsl", "vlad_assign", &[&[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite)]]),
    ("vlad_accumulate.wgsl", "vlad_accumulate", &[&[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite), (4, Read), (5, ReadWrite)]]),
    ("mnn_match.wgsl", "mnn_match", &[&[(0, Uniform), (1, Read), (2, Read), (3, Read), (4, ReadWrite), (5, ReadWrite)]]),
    ("xfeat.wgsl", "instance_norm_partials", &[&[(10, UniformAt(XF_NORM)), (11, Read), (12, ReadWrite)]]),
    ("xfeat.wgsl", "instance_norm_stats", &[&[(10, UniformAt(XF_NORM)), (13, Read), (14, ReadWrite)]]),
    ("xfeat.wgsl", "instance_norm_apply", &[&[(10, UniformAt(XF_NORM)), (11, Read), (15, Read), (16, ReadWrite)]]),
    ("xfeat.wgsl", "avg_pool", &[XF_MAP1]),
    ("xfeat.wgsl", "space_to_depth8", &[XF_MAP1]),
    ("xfeat.wgsl", "bilinear_add", &[&[(5, UniformAt(XF_MAP)), (6, Read), (7, Read), (8, Read), (9, ReadWrite)]]),
    ("xfeat.wgsl", "conv2d", &[&[(0, UniformAt(XF_CONV)), (1, Read), (2, Read), (3, Read), (4, ReadWrite)]]),
    ("lighterglue.wgsl", "lg_linear", &[&[(0, UniformAt(LG)), (1, Read), (2, Read), (3, Read), (4, ReadWrite)]]),
    ("lighterglue.wgsl", "lg_layer_norm", &[&[(0, UniformAt(LG)), (3, Read), (4, ReadWrite)]]),
    ("lighterglue.wgsl", "lg_rotary", &[&[(0, UniformAt(LG)), (1, Read), (2, Read), (4, ReadWrite)]]),
    ("lighterglue.wgsl", "lg_attention", &[&[(0, UniformAt(LG)), (1, Read), (2, Read), (4, ReadWrite), (5, Read)]]),
    ("lighterglue.wgsl", "lg_row_lse", &[&[(0, UniformAt(LG)), (1, Read), (2, Read), (4, ReadWrite), (5, Read)]]),
    ("lighterglue.wgsl", "lg_assignment_best", &[&[(0, UniformAt(LG)), (1, Read), (2, Read), (4, ReadWrite), (5, Read), (6, ReadWrite)]]),
    ("efficientnet.wgsl", "conv_direct", &[&[(0, UniformAt(EFF_CONV)), (1, Read), (2, Read), (3, Read), (4, ReadWrite)]]),
    ("efficientnet.wgsl", "pointwise", &[&[(5, UniformAt(EFF_POINT)), (6, Read), (7, Read), (8, Read), (9, Read), (10, ReadWrite)]]),
    ("efficientnet.wgsl", "gem_pool", &[&[(11, UniformAt(EFF_GEM)), (12, Read), (13, ReadWrite)]]),
    ("lighterglue.wgsl", "lg_gather", &[&[(0, UniformAt(LG)), (1, Read), (4, ReadWrite), (5, Read)]]),
];
