//! SSIM statistics of a stored map's descriptors, computed on the device as its chunks are
//! uploaded (`ssim_stats.wgsl`, the encoder's kernels): a map that does not store them (format 4
//! stores the descriptors alone) sends its descriptors only, 12.3 kB a reference at the default
//! size instead of 31.8 kB with their statistics, and the host computes none.

use super::context::{GpuContext, GpuError};
use semlook_kernels::abi::{Dims, SsimParams};

/// References one run computes: bounds the row-sum scratch (2 x gh x nw floats a reference,
/// 22 kB at the default size: 5.6 MB for a run) and keeps a run's grid within any device's
/// workgroups per dimension.
pub(crate) const RUN: usize = 256;

/// The kernels' uniforms and scratch, kept by the coarse matcher.
pub(crate) struct StatsOnDevice {
    p: SsimParams,
    ssim: wgpu::Buffer,
    dims: wgpu::Buffer,
    rows: wgpu::Buffer,
}

impl StatsOnDevice {
    pub fn new(ctx: &GpuContext, p: SsimParams) -> StatsOnDevice {
        let ssim = ctx.uniform("map statistics: ssim params", &p);
        let dims = ctx.uniform_buffer("map statistics: run", std::mem::size_of::<Dims>() as u64);
        let rows = ctx.storage("map statistics: row sums", (2 * RUN * p.gh as usize * p.nw as usize * 4) as u64);
        StatsOnDevice { p, ssim, dims, rows }
    }

    /// Fills `stats` with the statistics of the `count` descriptors in `desc`, a run at a time.
    pub fn compute(&self, ctx: &GpuContext, desc: &wgpu::Buffer, stats: &wgpu::Buffer, count: usize) -> Result<(), GpuError> {
        let k = &ctx.kernels;
        let bound = [&self.ssim, &self.dims, desc, &self.rows, stats];
        let (g1, g2) = (k.stats_row_sums.bind(&ctx.device, &bound), k.stats_windows.bind(&ctx.device, &bound));
        let (rows_x, windows) = ((self.p.gh * self.p.nw).div_ceil(64), (self.p.windows() as u32).div_ceil(64));
        for first in (0..count).step_by(RUN) {
            let n = RUN.min(count - first) as u32;
            ctx.write(&self.dims, 0, bytemuck::bytes_of(&Dims { frames: n, first: first as u32, ..Default::default() }));
            ctx.run("map statistics", &[(&k.stats_row_sums.pipeline, &g1, [rows_x, n, 1]), (&k.stats_windows.pipeline, &g2, [windows, n, 1])])?;
        }
        Ok(())
    }
}
