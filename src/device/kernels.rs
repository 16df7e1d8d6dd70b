//! The compute pipelines, created once per context: one per WGSL entry point, each with explicit
//! bind-group layouts whose order is the shader's (and its CPU twin's) binding order. Shaders
//! with a `SUBGROUPS` variant are built in the variant the device can run.

use crate::error::GpuError;
use semlook_kernels::bindings::{Slot, BINDINGS};
use semlook_kernels::wgsl::{preprocess, SHADERS};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;

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
    /// `efficientnet.wgsl`: the whole-image embedding (issue 61).
    pub conv_direct: Kernel,
    pub pointwise: Kernel,
    pub gem_pool: Kernel,
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

/// The kernel `entry` of `file` (its module `m`), its bind groups from [`BINDINGS`].
fn kernel(device: &wgpu::Device, m: &wgpu::ShaderModule, file: &str, entry: &str, made: &Arc<AtomicU64>) -> Result<Kernel, GpuError> {
    let groups = BINDINGS
        .iter()
        .find(|b| b.0 == file && b.1 == entry)
        .ok_or_else(|| GpuError::Shader {
            name: format!("{file}:{entry}"),
            message: "no bind groups listed for this entry point (semlook_kernels::bindings::BINDINGS)".into(),
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
        let eff = m("efficientnet.wgsl")?;
        let ek = |entry: &str| k(&eff, "efficientnet.wgsl", entry);
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
            conv_direct: ek("conv_direct")?,
            pointwise: ek("pointwise")?,
            gem_pool: ek("gem_pool")?,
        })
    }
}
