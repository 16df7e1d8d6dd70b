//! The compute pipelines, created once per context: one per WGSL entry point, each with an
//! explicit bind-group layout whose order is the shader's (and its CPU twin's) binding order.

use super::context::GpuError;

/// WGSL sources, by file name.
pub const SHADERS: [(&str, &str); 6] = [
    ("semantic_edges.wgsl", include_str!("../../shaders/semantic_edges.wgsl")),
    ("edt.wgsl", include_str!("../../shaders/edt.wgsl")),
    ("global_pool.wgsl", include_str!("../../shaders/global_pool.wgsl")),
    ("ssim_topk.wgsl", include_str!("../../shaders/ssim_topk.wgsl")),
    ("tree_similarity.wgsl", include_str!("../../shaders/tree_similarity.wgsl")),
    ("vlad_accumulate.wgsl", include_str!("../../shaders/vlad_accumulate.wgsl")),
];

#[derive(Clone, Copy)]
pub(crate) enum Slot {
    Uniform,
    Read,
    ReadWrite,
}

/// A pipeline and its bind-group layout.
pub(crate) struct Kernel {
    pub pipeline: wgpu::ComputePipeline,
    pub layout: wgpu::BindGroupLayout,
    /// Binding numbers, in layout order.
    bindings: Vec<u32>,
}

impl Kernel {
    /// A bind group with `buffers` bound to this kernel's bindings, in order.
    pub fn bind(&self, device: &wgpu::Device, buffers: &[&wgpu::Buffer]) -> wgpu::BindGroup {
        assert_eq!(buffers.len(), self.bindings.len(), "binding count");
        let entries: Vec<wgpu::BindGroupEntry> = self
            .bindings
            .iter()
            .zip(buffers)
            .map(|(&binding, b)| wgpu::BindGroupEntry { binding, resource: b.as_entire_binding() })
            .collect();
        device.create_bind_group(&wgpu::BindGroupDescriptor { label: None, layout: &self.layout, entries: &entries })
    }
}

pub(crate) struct Kernels {
    pub semantic_edges: Kernel,
    pub edt_columns: Kernel,
    pub edt_rows: Kernel,
    pub global_pool: Kernel,
    pub ssim_tile: Kernel,
    pub topk_merge: Kernel,
    pub tree_similarity: Kernel,
    pub vlad_assign: Kernel,
    pub vlad_accumulate: Kernel,
}

fn module(device: &wgpu::Device, name: &str) -> Result<wgpu::ShaderModule, GpuError> {
    let src = SHADERS.iter().find(|s| s.0 == name).expect("known shader").1;
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let m = device.create_shader_module(wgpu::ShaderModuleDescriptor { label: Some(name), source: wgpu::ShaderSource::Wgsl(src.into()) });
    match pollster::block_on(scope.pop()) {
        Some(e) => Err(GpuError::Shader { name: name.into(), message: e.to_string() }),
        None => Ok(m),
    }
}

fn kernel(device: &wgpu::Device, module: &wgpu::ShaderModule, file: &str, entry: &str, slots: &[(u32, Slot)]) -> Result<Kernel, GpuError> {
    let entries: Vec<wgpu::BindGroupLayoutEntry> = slots
        .iter()
        .map(|&(binding, slot)| wgpu::BindGroupLayoutEntry {
            binding,
            visibility: wgpu::ShaderStages::COMPUTE,
            ty: wgpu::BindingType::Buffer {
                ty: match slot {
                    Slot::Uniform => wgpu::BufferBindingType::Uniform,
                    Slot::Read => wgpu::BufferBindingType::Storage { read_only: true },
                    Slot::ReadWrite => wgpu::BufferBindingType::Storage { read_only: false },
                },
                has_dynamic_offset: false,
                min_binding_size: None,
            },
            count: None,
        })
        .collect();
    let scope = device.push_error_scope(wgpu::ErrorFilter::Validation);
    let layout = device.create_bind_group_layout(&wgpu::BindGroupLayoutDescriptor { label: Some(entry), entries: &entries });
    let pl = device.create_pipeline_layout(&wgpu::PipelineLayoutDescriptor { label: Some(entry), bind_group_layouts: &[Some(&layout)], immediate_size: 0 });
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
    Ok(Kernel { pipeline, layout, bindings: slots.iter().map(|s| s.0).collect() })
}

impl Kernels {
    pub fn new(device: &wgpu::Device) -> Result<Kernels, GpuError> {
        use Slot::*;
        let edges = module(device, "semantic_edges.wgsl")?;
        let edt = module(device, "edt.wgsl")?;
        let pool = module(device, "global_pool.wgsl")?;
        let ssim = module(device, "ssim_topk.wgsl")?;
        let tree = module(device, "tree_similarity.wgsl")?;
        let vlad = module(device, "vlad_accumulate.wgsl")?;
        let edt_slots = [(0, Uniform), (1, Read), (2, ReadWrite), (3, ReadWrite), (4, ReadWrite), (5, ReadWrite)];
        Ok(Kernels {
            semantic_edges: kernel(device, &edges, "semantic_edges.wgsl", "semantic_edges", &[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite)])?,
            edt_columns: kernel(device, &edt, "edt.wgsl", "edt_columns", &edt_slots)?,
            edt_rows: kernel(device, &edt, "edt.wgsl", "edt_rows", &edt_slots)?,
            global_pool: kernel(device, &pool, "global_pool.wgsl", "global_pool", &[(0, Uniform), (1, Read), (2, ReadWrite)])?,
            ssim_tile: kernel(
                device,
                &ssim,
                "ssim_topk.wgsl",
                "ssim_tile",
                &[(0, Uniform), (1, Uniform), (2, Read), (3, Read), (4, Read), (5, Read), (6, ReadWrite)],
            )?,
            topk_merge: kernel(device, &ssim, "ssim_topk.wgsl", "topk_merge", &[(1, Uniform), (6, ReadWrite), (7, ReadWrite), (8, ReadWrite)])?,
            tree_similarity: kernel(
                device,
                &tree,
                "tree_similarity.wgsl",
                "tree_similarity",
                &[(0, Uniform), (1, Uniform), (2, Read), (3, Read), (4, Read), (5, Read), (6, Read), (7, ReadWrite), (8, ReadWrite)],
            )?,
            vlad_assign: kernel(device, &vlad, "vlad_accumulate.wgsl", "vlad_assign", &[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite)])?,
            vlad_accumulate: kernel(
                device,
                &vlad,
                "vlad_accumulate.wgsl",
                "vlad_accumulate",
                &[(0, Uniform), (1, Read), (2, Read), (3, ReadWrite), (4, Read), (5, ReadWrite)],
            )?,
        })
    }
}
