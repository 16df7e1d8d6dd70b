//! GPU executor for the global descriptor and its SSIM statistics: semantic edges, exact EDT,
//! pooling and the window statistics for a batch of label maps of one size, in one submission.
//!
//! Kept between batches (kornia-rs-style): the buffers (regrown only when a batch needs more),
//! the uniforms (rewritten only when a batch's sizes change), the bind groups, and the flags of
//! the classes that make edges (uploaded when they change). A batch uploads its label maps, one
//! byte per pixel, and reads back its descriptors and statistics in one read-back.

use crate::config::GlobalConfig;
use crate::device::context::{GpuContext, GpuError};
use crate::global::pool_params;
use crate::input::LabelMap;
use semlook_kernels::abi::{Dims, PoolParams, SsimParams};
use semlook_kernels::edt;
use std::sync::Arc;

struct Buffers {
    pixels: u64,
    cells: u64,
    windows: u64,
    labels: wgpu::Buffer,
    used: wgpu::Buffer,
    edges: wgpu::Buffer,
    d2: wgpu::Buffer,
    out: wgpu::Buffer,
    stats: wgpu::Buffer,
    /// The EDT's and the statistics' intermediates, only bound (kept with their bind groups).
    _scratch: [wgpu::Buffer; 4],
    dims: wgpu::Buffer,
    pool: wgpu::Buffer,
    ssim: wgpu::Buffer,
    /// Bind groups of semantic_edges, edt_columns, edt_rows, global_pool, stats_row_sums and
    /// stats_windows, made once with the buffers.
    groups: [wgpu::BindGroup; 6],
}

/// What the uniforms and the class flags on the device hold now.
#[derive(Clone, Copy, PartialEq)]
struct Written {
    dims: Dims,
    pool: PoolParams,
    ssim: SsimParams,
    used: [bool; 256],
}

/// Reusable executor for global-descriptor encoding on the GPU.
pub struct GlobalEncoderGpu {
    ctx: Arc<GpuContext>,
    buffers: Option<Buffers>,
    written: Option<Written>,
    /// The batch's class ids, one byte per pixel (kept, so a batch allocates nothing).
    packed: Vec<u8>,
}

impl GlobalEncoderGpu {
    /// An executor on `ctx`; its buffers are made with the first batch.
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        GlobalEncoderGpu { ctx, buffers: None, written: None, packed: Vec::new() }
    }

    /// Frames of `width` x `height` that fit one batch under the binding limit.
    pub fn max_batch(&self, width: u32, height: u32) -> usize {
        ((self.ctx.binding_limit() / (width as u64 * height as u64 * 4)) as usize).clamp(0, 256)
    }

    /// Pooled global descriptors (`cfg.height` x `cfg.width` each) of label maps that share one
    /// size, each with its SSIM window statistics ([means | variances]). `used` flags the classes
    /// that make edges.
    pub fn encode(&mut self, maps: &[&LabelMap], used: &[bool; 256], cfg: &GlobalConfig) -> Result<Vec<(Vec<f32>, Vec<f32>)>, GpuError> {
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
        let ssim = cfg.ssim_params();
        let frames = maps.len() as u64;
        let pixels = frames * w as u64 * h as u64;
        let per_frame = (cfg.width * cfg.height) as u64;
        let (cells, windows) = (frames * per_frame, frames * ssim.windows() as u64);
        self.ctx.check_binding("one batch of label maps", pixels * 4)?;
        let ctx = self.ctx.clone();
        let now = Written {
            dims: Dims { width: w, height: h, frames: frames as u32, first: 0 },
            pool: PoolParams { frames: frames as u32, ..pool_params(cfg, w, h) },
            ssim,
            used: *used,
        };
        ctx.scoped("encoding global descriptors", || -> Result<Vec<(Vec<f32>, Vec<f32>)>, GpuError> {
            if self.buffers.as_ref().is_some_and(|b| b.pixels < pixels || b.cells < cells || b.windows < windows) {
                self.buffers = None;
            }
            if self.buffers.is_none() {
                self.buffers = Some(Self::allocate(&ctx, pixels, cells, windows, ssim.gh as u64 * ssim.nw as u64 * frames));
                self.written = None;
            }
            let b = self.buffers.as_ref().expect("allocated above");
            let old = self.written.replace(now);
            let changed = |f: fn(&Written) -> &[u8]| old.as_ref().is_none_or(|o| f(o) != f(&now));
            if changed(|w| bytemuck::bytes_of(&w.dims)) {
                ctx.write(&b.dims, 0, bytemuck::bytes_of(&now.dims));
            }
            if changed(|w| bytemuck::bytes_of(&w.pool)) {
                ctx.write(&b.pool, 0, bytemuck::bytes_of(&now.pool));
            }
            if changed(|w| bytemuck::bytes_of(&w.ssim)) {
                ctx.write(&b.ssim, 0, bytemuck::bytes_of(&now.ssim));
            }
            if old.is_none_or(|o| o.used != now.used) {
                let used32: Vec<u32> = used.iter().map(|&u| u as u32).collect();
                ctx.write(&b.used, 0, bytemuck::cast_slice(&used32));
            }
            self.packed.clear();
            for m in maps {
                self.packed.extend_from_slice(m.classes());
            }
            self.packed.resize(self.packed.len().next_multiple_of(4), 0);
            ctx.write(&b.labels, 0, &self.packed);
            let k = &ctx.kernels;
            let (f, rows_x) = (frames as u32, ssim.gh * ssim.nw);
            ctx.run(
                "global encoding",
                &[
                    (&k.semantic_edges.pipeline, &b.groups[0], [w.div_ceil(16), h.div_ceil(16), f]),
                    (&k.edt_columns.pipeline, &b.groups[1], [w.div_ceil(64), f, 1]),
                    (&k.edt_rows.pipeline, &b.groups[2], [h.div_ceil(64), f, 1]),
                    (&k.global_pool.pipeline, &b.groups[3], [(per_frame as u32).div_ceil(64), f, 1]),
                    (&k.stats_row_sums.pipeline, &b.groups[4], [rows_x.div_ceil(64), f, 1]),
                    (&k.stats_windows.pipeline, &b.groups[5], [(ssim.windows() as u32).div_ceil(64), f, 1]),
                ],
            )?;
            let stats_len = ssim.stats_len();
            let back = ctx.read_back_many(&[(&b.out, cells * 4), (&b.stats, windows * 2 * 4)])?;
            let (desc, stats): (&[f32], &[f32]) = (bytemuck::cast_slice(&back[0]), bytemuck::cast_slice(&back[1]));
            Ok((0..frames as usize)
                .map(|i| {
                    let d = &desc[i * per_frame as usize..(i + 1) * per_frame as usize];
                    (d.to_vec(), stats[i * stats_len..(i + 1) * stats_len].to_vec())
                })
                .collect())
        })?
    }

    /// Buffers and bind groups for batches of up to `pixels` label pixels, `cells` descriptor
    /// cells, `windows` SSIM windows and `row_sums` row sums.
    fn allocate(ctx: &GpuContext, pixels: u64, cells: u64, windows: u64, row_sums: u64) -> Buffers {
        let mk = |l: &str, n: u64| ctx.storage(l, n * 4);
        let labels = ctx.storage("labels (one byte per pixel)", pixels.next_multiple_of(4));
        let (used, edges, g, s, t, d2) =
            (mk("used classes", 256), mk("edges", pixels), mk("edt g", pixels), mk("edt s", pixels), mk("edt t", pixels), mk("edt d2", pixels));
        let (out, rows, stats) = (mk("global descriptors", cells), mk("ssim row sums", 2 * row_sums), mk("ssim stats", 2 * windows));
        let uniform = |l: &str, bytes: usize| ctx.uniform_buffer(l, bytes as u64);
        let dims = uniform("dims", std::mem::size_of::<Dims>());
        let pool = uniform("pool params", std::mem::size_of::<PoolParams>());
        let ssim = uniform("ssim params", std::mem::size_of::<SsimParams>());
        let (k, dev) = (&ctx.kernels, &ctx.device);
        let groups = [
            k.semantic_edges.bind(dev, &[&dims, &labels, &used, &edges]),
            k.edt_columns.bind(dev, &[&dims, &edges, &g, &s, &t, &d2]),
            k.edt_rows.bind(dev, &[&dims, &edges, &g, &s, &t, &d2]),
            k.global_pool.bind(dev, &[&pool, &d2, &out]),
            k.stats_row_sums.bind(dev, &[&ssim, &dims, &out, &rows, &stats]),
            k.stats_windows.bind(dev, &[&ssim, &dims, &out, &rows, &stats]),
        ];
        Buffers { pixels, cells, windows, labels, used, edges, d2, out, stats, _scratch: [g, s, t, rows], dims, pool, ssim, groups }
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
