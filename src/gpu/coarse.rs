//! GPU executor for the coarse stage, with the map resident on the device.
//!
//! What is uploaded when:
//! - the map (descriptors and SSIM statistics), once, in chunks of at most one binding each, the
//!   first time a batch meets it; later batches against the same map ([`SourceKey`]) upload none
//!   of it. A map beyond the budget is streamed through two chunk slots (`gpu::resident`);
//! - per batch: the queries, in chunks sized so that every binding and every dispatch dimension
//!   stays within the device's limits (any batch size runs), the parameters of all the chunk's
//!   passes in one write (one buffer, dynamic offsets), and the empty running lists;
//! - back: only the K-lists.
//!
//! Per pass (some queries x a run of one map chunk's references): `ssim_block` scores the block
//! grid, `topk_partial` and `topk_merge_lists` fold the scores into the running lists. Each map
//! chunk's passes go in one compute pass and one submission (timed where the adapter has
//! timestamps). No buffer or bind group is created per pass: bind groups are made once per
//! resident chunk and once per query chunk.

use super::resident::{ChunkData, ChunkPlan, Resident};
use super::topk::{bytes_per_query, TopK, MAX_PASS_REFS};
use crate::descriptors::source::{GlobalSource, SourceKey, TileBuf};
use crate::descriptors::DescriptorSet;
use crate::device::buffers::{PassBuffer, Reused};
use crate::device::context::{GpuContext, GpuError};
use crate::device::stats::StatsOnDevice;
use semlook_kernels::abi::PassParams;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::ssim_block::block_shape;
use semlook_kernels::topk_select::SEG;
use std::sync::Arc;

/// Executor of the coarse stage (SSIM top-K of queries against a map) on the device, the map
/// kept resident between batches.
pub struct CoarseMatcherGpu {
    ctx: Arc<GpuContext>,
    p: SsimParams,
    /// References and queries per workgroup.
    shape: (u32, u32),
    params: wgpu::Buffer,
    /// Computes the statistics of a map that does not store them, as its chunks are uploaded.
    stats: Arc<StatsOnDevice>,
    map: Resident,
    queries: Reused,
    query_stats: Reused,
    scores: Reused,
    passes: PassBuffer<PassParams>,
    topk: TopK,
}

/// A map's references written chunk by chunk: descriptors, then statistics (those the source
/// holds, or computed on the device from the descriptors for a source that does not store them).
struct MapChunks<'a> {
    refs: &'a dyn GlobalSource,
    stats: &'a StatsOnDevice,
}

impl ChunkData for MapChunks<'_> {
    fn write(&self, ctx: &GpuContext, plan: &ChunkPlan, buffers: &[&wgpu::Buffer]) -> Result<(), GpuError> {
        let mut buf = TileBuf::default();
        let (start, end) = (plan.first, plan.first + plan.len);
        if self.refs.stores_stats() {
            let (g, s) = self.refs.tile(start, end, &mut buf);
            ctx.write(buffers[0], 0, bytemuck::cast_slice(g));
            ctx.write(buffers[1], 0, bytemuck::cast_slice(s));
        } else {
            ctx.write(buffers[0], 0, bytemuck::cast_slice(self.refs.globals_tile(start, end, &mut buf)));
            self.stats.compute(ctx, buffers[0], buffers[1], plan.len)?;
        }
        Ok(())
    }
}

impl CoarseMatcherGpu {
    /// An executor on `ctx` for descriptors of `p`'s sizes; fails on a lost device or when the
    /// SSIM block kernel's workgroup arrays cannot hold them.
    pub fn new(ctx: Arc<GpuContext>, p: SsimParams) -> Result<Self, GpuError> {
        // Its parameter buffer is written here, outside any error scope: refuse a lost device first.
        ctx.check_lost()?;
        let shape = block_shape(&p).ok_or_else(|| GpuError::LimitsTooSmall {
            adapter: ctx.describe(),
            what: "the SSIM block kernel's workgroup arrays (descriptor width, and window x valid windows per row)".into(),
            needed: (p.gw.max(p.win * p.nw)) as u64,
            available: semlook_kernels::ssim_block::PROD_CAP.min(semlook_kernels::ssim_block::RING_CAP) as u64,
        })?;
        let params = ctx.uniform("ssim params", &p);
        let stats = Arc::new(StatsOnDevice::new(&ctx, p));
        let passes = PassBuffer::new(&ctx);
        Ok(CoarseMatcherGpu {
            ctx,
            p,
            shape,
            params,
            stats,
            map: Resident::default(),
            queries: Reused::default(),
            query_stats: Reused::default(),
            scores: Reused::default(),
            passes,
            topk: TopK::default(),
        })
    }

    /// References per map chunk: as many as one binding holds (descriptors and stats alike).
    pub fn chunk_len(&self) -> usize {
        (self.ctx.binding_limit() as usize / (self.p.len().max(self.p.stats_len()) * 4)).max(1)
    }

    /// Bytes of the last map's descriptors and SSIM statistics on the device (or streamed through it).
    pub fn map_bytes(&self) -> u64 {
        self.map.bytes()
    }

    /// Whether the last map was kept resident (false: it was streamed).
    pub fn map_is_resident(&self) -> bool {
        !self.map.is_streaming()
    }

    /// Forgets the resident map: the next batch uploads its map again.
    pub fn forget_map(&mut self) {
        self.map.forget(&self.ctx);
    }

    /// Queries per chunk of a batch and references per pass, within every binding and dispatch
    /// limit; a typed error if the device cannot take one query or one reference.
    pub fn plan(&self, k: usize) -> Result<(usize, usize), GpuError> {
        let (lim, groups) = (self.ctx.binding_limit(), self.ctx.max_workgroups() as u64);
        let too_small =
            |what: &str, needed: u64| GpuError::LimitsTooSmall { adapter: self.ctx.describe(), what: what.into(), needed, available: lim };
        let per_ref = (self.p.len().max(self.p.stats_len()) * 4) as u64;
        if per_ref > lim {
            return Err(too_small("one reference's descriptor or SSIM statistics in one binding", per_ref));
        }
        let [_, top] = bytes_per_query(k, 1);
        if top > lim {
            return Err(too_small("one query's top-K list in one binding", top));
        }
        let qc = groups.min(lim / per_ref).min(lim / top).min((lim / (SEG as u64 * 4)).max(1)) as usize;
        let part = bytes_per_query(k, SEG)[0];
        let pass = (self.chunk_len() as u64)
            .min(MAX_PASS_REFS as u64)
            .min(groups * self.shape.0 as u64)
            .min(groups * SEG as u64)
            .min(lim / (qc as u64 * 4))
            .min((lim / (qc as u64 * part)).max(1) * SEG as u64);
        if qc as u64 * part > lim || pass == 0 {
            return Err(too_small("the scores and partial top-K lists of one query", part.max(4)));
        }
        Ok((qc, pass as usize))
    }

    /// Makes `refs` the map on the device: uploads it (once per [`SourceKey`]) when it fits the
    /// budget, else prepares to stream it. A batch against the same map afterwards uploads none
    /// of it; [`CoarseMatcherGpu::topk`] calls this itself. Returns whether the map is resident.
    pub fn upload_map(&mut self, refs: &dyn GlobalSource) -> Result<bool, GpuError> {
        let n = refs.len();
        let chunk = self.chunk_len();
        let (lb, sb) = ((self.p.len() * 4) as u64, (self.p.stats_len() * 4) as u64);
        let plans = || -> Vec<ChunkPlan> {
            (0..n)
                .step_by(chunk)
                .map(|first| {
                    let len = chunk.min(n - first);
                    ChunkPlan { first, len, bytes: vec![len as u64 * lb, len as u64 * sb] }
                })
                .collect()
        };
        let ctx = self.ctx.clone();
        let bind = |b: &[&wgpu::Buffer]| ctx.kernels.ssim_block.bind_group(&ctx.device, 1, b);
        self.map.prepare(&ctx, SourceKey::of(refs), plans, &MapChunks { refs, stats: &self.stats }, &bind)?;
        Ok(self.map_is_resident())
    }

    /// The `k` best references of every query, best first (ties to the lower index).
    pub fn topk(&mut self, queries: &DescriptorSet, refs: &dyn GlobalSource, k: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let (nq, n) = (queries.len(), refs.len());
        if nq == 0 || n == 0 || k == 0 {
            return Ok(vec![Vec::new(); nq]);
        }
        let (qc, pass_refs) = self.plan(k)?;
        self.upload_map(refs)?;
        let ctx = self.ctx.clone();
        let stats = self.stats.clone();
        let data = MapChunks { refs, stats: &stats };
        let bind = |b: &[&wgpu::Buffer]| ctx.kernels.ssim_block.bind_group(&ctx.device, 1, b);
        let mut lists = Vec::with_capacity(nq);
        for q0 in (0..nq).step_by(qc) {
            let q1 = (q0 + qc).min(nq);
            lists.extend(self.query_chunk(queries, q0..q1, k, pass_refs, &data, &bind)?);
        }
        Ok(lists)
    }

    /// Queries `qs` against the whole map.
    fn query_chunk(
        &mut self,
        queries: &DescriptorSet,
        qs: std::ops::Range<usize>,
        k: usize,
        pass_refs: usize,
        data: &MapChunks,
        bind: &dyn Fn(&[&wgpu::Buffer]) -> wgpu::BindGroup,
    ) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let ctx = self.ctx.clone();
        let nq = qs.len();
        let (rb, qb) = self.shape;
        // every pass of this query chunk, map chunk by map chunk
        let mut passes: Vec<(usize, PassParams)> = Vec::new();
        let mut parity = 0;
        for (c, plan) in self.map.plans().iter().enumerate() {
            for start in (0..plan.len).step_by(pass_refs) {
                let refs = pass_refs.min(plan.len - start);
                let ps = PassParams {
                    queries: nq as u32,
                    refs: refs as u32,
                    ref_first: start as u32,
                    ref_index: (plan.first + start) as u32,
                    rb,
                    qb,
                    k: k as u32,
                    segs: refs.div_ceil(SEG) as u32,
                    parity,
                    fresh: passes.is_empty() as u32,
                    ..Default::default()
                };
                passes.push((c, ps));
                parity ^= 1;
            }
        }
        ctx.scoped("coarse matching", || -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
            let (len, slen) = (self.p.len(), self.p.stats_len());
            let qg = self.queries.upload(&ctx, "query descriptors", bytemuck::cast_slice(&queries.globals[qs.start * len..qs.end * len]));
            let qst = self.query_stats.upload(&ctx, "query statistics", bytemuck::cast_slice(&queries.global_stats[qs.start * slen..qs.end * slen]));
            let scores = self.scores.get(&ctx, "pass scores", (nq * pass_refs * 4) as u64);
            let entries: Vec<PassParams> = passes.iter().map(|p| p.1).collect();
            let pbuf = self.passes.write(&ctx, &entries);
            let g_ssim = ctx.kernels.ssim_block.bind(&ctx.device, &[&self.params, pbuf, qg, qst, scores]);
            let g_topk = self.topk.begin(&ctx, nq, k, pass_refs, pbuf, scores);
            let mut i = 0;
            for c in 0..self.map.chunk_count() {
                let chunk = self.map.chunk(&ctx, c, data, bind)?;
                let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("coarse chunk") });
                {
                    let mut pass = ctx.begin_pass(&mut enc, "coarse chunk")?;
                    while i < passes.len() && passes[i].0 == c {
                        let (off, ps) = (self.passes.offset(i), passes[i].1);
                        pass.set_pipeline(&ctx.kernels.ssim_block.pipeline);
                        pass.set_bind_group(0, Some(&g_ssim), &[off]);
                        pass.set_bind_group(1, Some(&chunk), &[]);
                        pass.dispatch_workgroups(ps.queries.div_ceil(qb), ps.refs.div_ceil(rb), 1);
                        TopK::record(&ctx, &mut pass, &g_topk, off, &ps);
                        i += 1;
                    }
                }
                ctx.queue.submit([enc.finish()]);
                ctx.check_lost()?;
            }
            self.topk.read(&ctx, nq, k, (passes.len() % 2) as u32)
        })?
    }
}
