//! The host side of the shaders' structs and limits (`#[repr(C)]`, bytemuck), checked field by
//! field against naga's reflection of the WGSL (`layout_tests`); every executor and the kernel
//! table import them from here.

/// Most neighbour slots the shader's tree record holds: its `MAX_SLOTS`.
pub const MAX_SLOTS: usize = 8;
/// Most trees per forest the shader's per-workgroup flags hold: its `MAX_TREES`.
pub const MAX_TREES: usize = 256;

/// The shader's `Tree`.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub(crate) struct GpuTree {
    pub class_id: u32,
    pub has_app: u32,
    pub area: f32,
    pub cx: f32,
    pub cy: f32,
    pub weight: f32,
    pub nb: [i32; MAX_SLOTS],
}

/// The shader's `FinePass`: one pass at a dynamic offset of the batch's parameter buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub(crate) struct FinePass {
    pub dim: u32,
    pub pairs: u32,
    pub max_trees: u32,
    pub grid: u32,
    pub queries: u32,
    pub refs: u32,
    pub ref_first: u32,
    pub list_first: u32,
    /// Workgroups per row of the dispatch grid (pair = x + y * row).
    pub row: u32,
    /// Where this pass's scores start in `out`.
    pub out_first: u32,
    pub _pad0: u32,
    pub _pad1: u32,
}
