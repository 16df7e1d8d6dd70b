//! GPU executor for the global descriptor: semantic edges, exact EDT and pooling for a batch of
//! label maps of one size, in one submission. Buffers are kept between batches and regrown only
//! when a larger batch arrives. Uploads the label maps, reads back only the pooled descriptors.

use super::context::{GpuContext, GpuError};
use crate::config::GlobalConfig;
use crate::global::pool_params;
use crate::input::LabelMap;
use crate::kernels::abi::Dims;
use crate::kernels::abi::PoolParams;
use crate::kernels::edt;
use std::sync::Arc;

struct Buffers {
    pixels: u64,
    cells: u64,
    labels: wgpu::Buffer,
    used: wgpu::Buffer,
    edges: wgpu::Buffer,
    g: wgpu::Buffer,
    s: wgpu::Buffer,
    t: wgpu::Buffer,
    d2: wgpu::Buffer,
    out: wgpu::Buffer,
}

/// Reusable executor for global-descriptor encoding on the GPU.
pub struct GlobalEncoderGpu {
    ctx: Arc<GpuContext>,
    buffers: Option<Buffers>,
}

impl GlobalEncoderGpu {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        GlobalEncoderGpu { ctx, buffers: None }
    }

    /// Frames of `width` x `height` that fit one batch under the binding limit.
    pub fn max_batch(&self, width: u32, height: u32) -> usize {
        ((self.ctx.binding_limit() / (width as u64 * height as u64 * 4)) as usize).clamp(0, 256)
    }

    /// Pooled global descriptors (`cfg.height` x `cfg.width` each) of label maps that share one size.
    /// `used` flags the classes that make edges.
    pub fn encode(&mut self, maps: &[&LabelMap], used: &[bool; 256], cfg: &GlobalConfig) -> Result<Vec<Vec<f32>>, GpuError> {
        let Some(first) = maps.first() else { return Ok(vec![]) };
        let (w, h) = (first.width(), first.height());
        if let Some(m) = maps.iter().find(|m| (m.width(), m.height()) != (w, h)) {
            return Err(GpuError::Failed {
                what: "encoding".into(),
                reason: format!("label maps of {w}x{h} and {}x{} in one batch (one size per batch)", m.width(), m.height()),
            });
        }
        if w as usize > edt::MAX_SIDE || h as usize > edt::MAX_SIDE {
            return Err(GpuError::Failed { what: "encoding".into(), reason: format!("{w}x{h} exceeds the EDT side limit") });
        }
        let frames = maps.len() as u64;
        let pixels = frames * w as u64 * h as u64;
        let cells = frames * (cfg.width * cfg.height) as u64;
        self.ctx.check_binding("one batch of label maps", pixels * 4)?;
        let ctx = self.ctx.clone();
        let k = &ctx.kernels;
        ctx.scoped("encoding global descriptors", || -> Result<Vec<Vec<f32>>, GpuError> {
            if self.buffers.as_ref().is_some_and(|b| b.pixels < pixels || b.cells < cells) {
                self.buffers = None;
            }
            let b = self.buffers.get_or_insert_with(|| {
                let mk = |l: &str, n: u64| ctx.storage(l, n * 4);
                Buffers {
                    pixels,
                    cells,
                    labels: mk("labels", pixels),
                    used: mk("used classes", 256),
                    edges: mk("edges", pixels),
                    g: mk("edt g", pixels),
                    s: mk("edt s", pixels),
                    t: mk("edt t", pixels),
                    d2: mk("edt d2", pixels),
                    out: mk("global descriptors", cells),
                }
            });
            let mut labels = Vec::with_capacity(pixels as usize);
            for m in maps {
                labels.extend(m.classes().iter().map(|&c| c as u32));
            }
            ctx.write(&b.labels, 0, bytemuck::cast_slice(&labels));
            let used32: Vec<u32> = used.iter().map(|&u| u as u32).collect();
            ctx.write(&b.used, 0, bytemuck::cast_slice(&used32));
            let dims = ctx.uniform("dims", &Dims { width: w, height: h, frames: frames as u32, _pad: 0 });
            let pool = ctx.uniform("pool params", &PoolParams { frames: frames as u32, ..pool_params(cfg, w, h) });
            let dev = &ctx.device;
            let g_edges = k.semantic_edges.bind(dev, &[&dims, &b.labels, &b.used, &b.edges]);
            let g_edt = k.edt_columns.bind(dev, &[&dims, &b.edges, &b.g, &b.s, &b.t, &b.d2]);
            let g_rows = k.edt_rows.bind(dev, &[&dims, &b.edges, &b.g, &b.s, &b.t, &b.d2]);
            let g_pool = k.global_pool.bind(dev, &[&pool, &b.d2, &b.out]);
            let per_frame = (cfg.width * cfg.height) as u32;
            ctx.run(
                "global encoding",
                &[
                    (&k.semantic_edges.pipeline, &g_edges, [w.div_ceil(16), h.div_ceil(16), frames as u32]),
                    (&k.edt_columns.pipeline, &g_edt, [w.div_ceil(64), frames as u32, 1]),
                    (&k.edt_rows.pipeline, &g_rows, [h.div_ceil(64), frames as u32, 1]),
                    (&k.global_pool.pipeline, &g_pool, [per_frame.div_ceil(64), frames as u32, 1]),
                ],
            )?;
            let all: Vec<f32> = ctx.read_back_values(&b.out, cells as usize)?;
            Ok(all.chunks(per_frame as usize).map(|c| c.to_vec()).collect())
        })?
    }

    /// Debug/test access: squared distances of the last batch (frames x pixels).
    pub fn last_d2(&self, pixels: u64) -> Result<Vec<u32>, GpuError> {
        self.read_last(pixels, |b| &b.d2)
    }

    /// Debug/test access: edge flags of the last batch (frames x pixels).
    pub fn last_edges(&self, pixels: u64) -> Result<Vec<u32>, GpuError> {
        self.read_last(pixels, |b| &b.edges)
    }

    fn read_last(&self, pixels: u64, which: impl Fn(&Buffers) -> &wgpu::Buffer) -> Result<Vec<u32>, GpuError> {
        let b = self.buffers.as_ref().ok_or(GpuError::Failed { what: "reading a scratch buffer".into(), reason: "nothing encoded yet".into() })?;
        self.ctx.read_back_values(which(b), pixels as usize)
    }
}
