//! The compute pipelines, created once per context: one per WGSL entry point, each with explicit
//! bind-group layouts whose order is the shader's (and its CPU twin's) binding order. Shaders
//! with a `SUBGROUPS` variant are built in the variant the device can run.

use super::wgsl::{preprocess, SHADERS};
use crate::error::GpuError;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

#[derive(Clone, Copy)]
pub(crate) enum Slot {
    Uniform,
    /// A uniform selected per dispatch by a dynamic offset; the binding is `size` bytes.
    UniformAt(u64),
    Read,
    ReadWrite,
}

/// A pipeline and its bind-group layouts (group 0, 1, ...).
pub(crate) struct Kernel {
    pub pipeline: wgpu::ComputePipeline,
    layouts: Vec<(wgpu::BindGroupLayout, Vec<(u32, Slot)>)>,
    /// Bind groups made, shared by every kernel of the context ([`Kernels::bind_groups_created`]).
    made: Arc<AtomicU64>,
}

impl Kernel {
    /// A pipeline of entry point `entry` of `module` with this kernel's bind group layouts (a
    /// bind group made for one serves the other).
    fn sibling(&self, device: &wgpu::Device, module: &wgpu::ShaderModule, file: &str, entry: &str) -> Result<Kernel, GpuError> {
        let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
        let refs: Vec<Option<&wgpu::BindGroupLayout>> = self.layouts.iter().map(|l| Some(&l.0)).collect();
        let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor { label: Some(entry), bind_group_layouts: &refs, immediate_size: 0 });
        let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
            label: Some(entry),
            layout: Some(&pl),
            module,
            entry_point: Some(entry),
            compilation_options: Default::default(),
            cache: None,
        });
        if let Some(e) = pollster::block_on(scope.pop()) {
            return Err(GpuError::Shader { name: format!("{file}:{entry}"), message: e.to_string() });
        }
        Ok(Kernel { pipeline, layouts: self.layouts.clone(), made: self.made.clone() })
    }

    /// A bind group of group `group` with `buffers` bound to its bindings, in order.
    pub fn bind_group(&self, device: &wgpu::Device, group: usize, buffers: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        let (layout, slots) = &self.layouts[group];
        assert_eq!(buffers.len(), slots.len(), "binding count");
        let entries: Vec<wgpu::BindGroupEntry> = slots
            .iter()
            .zip(buffers)
            .map(|(&(binding, slot), b)| wgpu::BindGroupEntry {
                binding,
                resource: match slot {
                    Slot::UniformAt(size) => {
                        wgpu::BindingResource::Buffer(wgpu::BufferBinding { buffer: b, offset: 0, size: std::num::NonZeroU64::new(size) })
                    }
                    _ => b.as_entire_binding(),
                },
            })
            .collect();
        self.made.fetch_add(1, Ordering::Relaxed);
        device.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout, entries: &entries })
    }

    /// A bind group of group 0.
    pub fn bind(&self, device: &wgpu::Device, buffers: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        self.bind_group(device, 0, buffers)
    }
}

pub(crate) struct Kernels {
    made: Arc<AtomicU64>,
    pub semantic_edges: Kernel,
    pub edt_columns: Kernel,
    pub edt_rows: Kernel,
    pub global_pool: Kernel,
    pub ssim_block: Kernel,
    /// `ssim_stats.wgsl`: the SSIM window statistics of encoded descriptors.
    pub stats_row_sums: Kernel,
    pub stats_windows: Kernel,
    pub topk_partial: Kernel,
    pub topk_merge_lists: Kernel,
    pub tree_similarity: Kernel,
    /// Several pairs of small forests per workgroup; the bind group layouts of `tree_similarity`
    /// (one bind group serves both).
    pub tree_similarity_small: Kernel,
    pub vlad_assign: Kernel,
    pub vlad_accumulate: Kernel,
    pub mnn_match: Kernel,
    /// `xfeat.wgsl`: the XFeat network.
    pub instance_norm_partials: Kernel,
    pub instance_norm_stats: Kernel,
    pub instance_norm_apply: Kernel,
    pub avg_pool: Kernel,
    pub space_to_depth8: Kernel,
    pub bilinear_add: Kernel,
    pub conv2d: Kernel,
    /// `lighterglue.wgsl`: the learned matcher.
    pub lg_linear: Kernel,
    pub lg_layer_norm: Kernel,
    pub lg_rotary: Kernel,
    pub lg_attention: Kernel,
    pub lg_row_lse: Kernel,
    pub lg_assignment_best: Kernel,
    pub lg_gather: Kernel,
}

fn module(device: &wgpu::Device, name: &str, subgroups: bool) -> Result<wgpu::ShaderModule, GpuError> {
    let src = SHADERS.iter().find(|s| s.0 == name).expect("known shader").1;
    let text =
        preprocess(src, if subgroups { &["SUBGROUPS"] } else { &[] }).map_err(|e| GpuError::Shader { name: name.into(), message: e.to_string() })?;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let m = device.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some(name), source: wgpu::ShaderSource::Wgsl(text.into()) });
    match pollster::block_on(scope.pop()) {
        Some(e) => Err(GpuError::Shader { name: name.into(), message: e.to_string() }),
        None => Ok(m),
    }
}

fn layout_entry(binding: u32, slot: Slot) -> wgpu::BindGroupLayoutEntry {
    let (ty, dynamic, min) = match slot {
        Slot::Uniform => (wgpu::BufferBindingType::Uniform, false, None),
        Slot::UniformAt(size) => (wgpu::BufferBindingType::Uniform, true, std::num::NonZeroU64::new(size)),
        Slot::Read => (wgpu::BufferBindingType::Storage { read_only: true }, false, None),
        Slot::ReadWrite => (wgpu::BufferBindingType::Storage { read_only: false }, false, None),
    };
    wgpu::BindGroupLayoutEntry {
        binding,
        visibility: wgpu::ShaderStages::COMPUTE,
        ty: wgpu::BindingType::Buffer { ty, has_dynamic_offset: dynamic, min_binding_size: min },
        count: None,
    }
}

fn kernel_counted(
    device: &wgpu::Device,
    module: &wgpu::ShaderModule,
    file: &str,
    entry: &str,
    groups: &[&[(u32, Slot)]],
    made: &Arc<AtomicU64>,
) -> Result<Kernel, GpuError> {
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let layouts: Vec<(wgpu::BindGroupLayout, Vec<(u32, Slot)>)> = groups
        .iter()
        .map(|slots| {
            let entries: Vec<wgpu::BindGroupLayoutEntry> = slots.iter().map(|&(b, s)| layout_entry(b, s)).collect();
            (device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(entry), entries: &entries }), slots.to_vec())
        })
        .collect();
    let refs: Vec<Option<&wgpu::BindGroupLayout>> = layouts.iter().map(|l| Some(&l.0)).collect();
    let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor { label: Some(entry), bind_group_layouts: &refs, immediate_size: 0 });
    let pipeline = device.create_compute_pipeline(&wgpu::ComputePipelineDescriptor {
        label: Some(entry),
        layout: Some(&pl),
        module,
        entry_point: Some(entry),
        compilation_options: Default::default(),
        cache: None,
    });
    if let Some(e) = pollster::block_on(scope.pop()) {
        return Err(GpuError::Shader { name: format!("{file}:{entry}"), message: e.to_string() });
    }
    Ok(Kernel { pipeline, layouts, made: made.clone() })
}

/// Bytes of the per-pass parameters the coarse kernels bind at dynamic offsets.
const PASS: u64 = std::mem::size_of::<crate::kernels::abi::PassParams>() as u64;
/// Bytes of the fine stage's per-pass parameters.
const FINE_PASS: u64 = std::mem::size_of::<crate::kernels::abi::FinePass>() as u64;
/// Bytes of the XFeat kernels' uniforms (each bound at a dynamic offset of one buffer).
const XF_CONV: u64 = std::mem::size_of::<crate::kernels::abi::ConvParams>() as u64;
const XF_MAP: u64 = std::mem::size_of::<crate::kernels::abi::MapParams>() as u64;
const XF_NORM: u64 = std::mem::size_of::<crate::kernels::abi::NormParams>() as u64;
/// Bytes of the LighterGlue kernels' uniform (bound at a dynamic offset of one buffer).
const LG: u64 = std::mem::size_of::<crate::kernels::abi::LgParams>() as u64;

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
pub(crate) const BINDINGS: &[(&str, &str, &[&[(u32, Slot)]])] = &[
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
    ("lighterglue.wgsl", "lg_gather", &[&[(0, UniformAt(LG)), (1, Read), (4, ReadWrite), (5, Read)]]),
];

/// The kernel `entry` of `file` (its module `m`), its bind groups from [`BINDINGS`].
fn kernel(device: &wgpu::Device, m: &wgpu::ShaderModule, file: &str, entry: &str, made: &Arc<AtomicU64>) -> Result<Kernel, GpuError> {
    let groups = BINDINGS
        .iter()
        .find(|b| b.0 == file && b.1 == entry)
        .ok_or_else(|| GpuError::Shader {
            name: format!("{file}:{entry}"),
            message: "no bind groups listed for this entry point (gpu/kernels.rs BINDINGS)".into(),
        })?
        .2;
    kernel_counted(device, m, file, entry, groups, made)
}

/// The one-pair reference kernels of `ssim_topk.wgsl` (`ssim_tile`, `topk_merge`), which no
/// executor runs: built on demand by the device references (`gpu::reference`) and by
/// `create_every_pipeline`, not by every context.
pub(crate) fn reference_kernels(device: &wgpu::Device, subgroups: bool) -> Result<(Kernel, Kernel), GpuError> {
    let made = Arc::new(AtomicU64::new(0));
    let ssim = module(device, "ssim_topk.wgsl", subgroups)?;
    Ok((kernel(device, &ssim, "ssim_topk.wgsl", "ssim_tile", &made)?, kernel(device, &ssim, "ssim_topk.wgsl", "topk_merge", &made)?))
}

impl Kernels {
    /// Bind groups made from any of these kernels so far.
    pub fn bind_groups_created(&self) -> u64 {
        self.made.load(Ordering::Relaxed)
    }

    pub fn new(device: &wgpu::Device, subgroups: bool) -> Result<Kernels, GpuError> {
        let made = Arc::new(AtomicU64::new(0));
        let m = |name| module(device, name, subgroups);
        let (edges, edt, pool, block, topk, tree, vlad) = (
            m("semantic_edges.wgsl")?,
            m("edt.wgsl")?,
            m("global_pool.wgsl")?,
            m("ssim_block.wgsl")?,
            m("topk_select.wgsl")?,
            m("tree_similarity.wgsl")?,
            m("vlad_accumulate.wgsl")?,
        );
        let (mnn, stats, xf, lg) = (m("mnn_match.wgsl")?, m("ssim_stats.wgsl")?, m("xfeat.wgsl")?, m("lighterglue.wgsl")?);
        let k = |module: &wgpu::ShaderModule, file: &str, entry: &str| kernel(device, module, file, entry, &made);
        let xk = |entry: &str| k(&xf, "xfeat.wgsl", entry);
        let lk = |entry: &str| k(&lg, "lighterglue.wgsl", entry);
        let tree_sim = k(&tree, "tree_similarity.wgsl", "tree_similarity")?;
        Ok(Kernels {
            made: made.clone(),
            semantic_edges: k(&edges, "semantic_edges.wgsl", "semantic_edges")?,
            edt_columns: k(&edt, "edt.wgsl", "edt_columns")?,
            edt_rows: k(&edt, "edt.wgsl", "edt_rows")?,
            global_pool: k(&pool, "global_pool.wgsl", "global_pool")?,
            ssim_block: k(&block, "ssim_block.wgsl", "ssim_block")?,
            stats_row_sums: k(&stats, "ssim_stats.wgsl", "stats_row_sums")?,
            stats_windows: k(&stats, "ssim_stats.wgsl", "stats_windows")?,
            topk_partial: k(&topk, "topk_select.wgsl", "topk_partial")?,
            topk_merge_lists: k(&topk, "topk_select.wgsl", "topk_merge_lists")?,
            // one bind group serves both: the small variant shares the layouts
            tree_similarity_small: tree_sim.sibling(device, &tree, "tree_similarity.wgsl", "tree_similarity_small")?,
            tree_similarity: tree_sim,
            vlad_assign: k(&vlad, "vlad_accumulate.wgsl", "vlad_assign")?,
            vlad_accumulate: k(&vlad, "vlad_accumulate.wgsl", "vlad_accumulate")?,
            mnn_match: k(&mnn, "mnn_match.wgsl", "mnn_match")?,
            instance_norm_partials: xk("instance_norm_partials")?,
            instance_norm_stats: xk("instance_norm_stats")?,
            instance_norm_apply: xk("instance_norm_apply")?,
            avg_pool: xk("avg_pool")?,
            space_to_depth8: xk("space_to_depth8")?,
            bilinear_add: xk("bilinear_add")?,
            conv2d: xk("conv2d")?,
            lg_linear: lk("lg_linear")?,
            lg_layer_norm: lk("lg_layer_norm")?,
            lg_rotary: lk("lg_rotary")?,
            lg_attention: lk("lg_attention")?,
            lg_row_lse: lk("lg_row_lse")?,
            lg_assignment_best: lk("lg_assignment_best")?,
            lg_gather: lk("lg_gather")?,
        })
    }
}
