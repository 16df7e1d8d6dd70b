//! GPU executor for the coarse stage: the query batch is uploaded once and stays resident; the
//! map is streamed tile by tile (each tile no larger than the binding limit allows); per tile,
//! `ssim_tile` scores all pairs and `topk_merge` folds them into the per-query top-K on the GPU.
//! Only the final K-lists (queries x K) are read back.

use super::context::{GpuContext, GpuError, Reused};
use crate::global::ssim::SsimParams;
use crate::descriptors::DescriptorSet;
use crate::matching::source::{GlobalSource, TileBuf};
use crate::matching::ssim_topk::{TileParams, EMPTY_INDEX, EMPTY_SCORE};
use std::sync::Arc;

/// Largest value of gh x nw the shader's workgroup array holds.
const MAX_ROW_SUMS: u32 = 3840;
/// Most queries per dispatch row (workgroups per dimension).
const MAX_DISPATCH: usize = 65_535;

/// A batch of queries resident on the GPU.
pub struct GpuQueries {
    pub len: usize,
    globals: wgpu::Buffer,
    stats: wgpu::Buffer,
}

pub struct CoarseMatcherGpu {
    ctx: Arc<GpuContext>,
    p: SsimParams,
    params: wgpu::Buffer,
    tile_globals: Reused,
    tile_stats: Reused,
    scores: Reused,
    top_s: Reused,
    top_i: Reused,
}

impl CoarseMatcherGpu {
    pub fn new(ctx: Arc<GpuContext>, p: SsimParams) -> Result<Self, GpuError> {
        if p.gh * p.nw > MAX_ROW_SUMS {
            return Err(GpuError::LimitsTooSmall {
                adapter: ctx.describe(),
                what: "SSIM row sums in workgroup memory (global height x valid windows per row)".into(),
                needed: (p.gh * p.nw) as u64,
                available: MAX_ROW_SUMS as u64,
            });
        }
        let params = ctx.uniform("ssim params", &p);
        Ok(CoarseMatcherGpu { ctx, p, params, tile_globals: Reused::default(), tile_stats: Reused::default(), scores: Reused::default(), top_s: Reused::default(), top_i: Reused::default() })
    }

    /// Uploads a query batch (explicitly: it stays on the GPU until dropped).
    pub fn upload_queries(&self, queries: &DescriptorSet) -> Result<GpuQueries, GpuError> {
        let ctx = &self.ctx;
        ctx.check_binding("query descriptors", (queries.globals.len() * 4) as u64)?;
        ctx.check_binding("query statistics", (queries.global_stats.len() * 4) as u64)?;
        if queries.len() > MAX_DISPATCH {
            return Err(GpuError::LimitsTooSmall { adapter: ctx.describe(), what: "queries per batch".into(), needed: queries.len() as u64, available: MAX_DISPATCH as u64 });
        }
        ctx.scoped("uploading queries", || {
            let globals = ctx.storage("query descriptors", (queries.globals.len() * 4) as u64);
            let stats = ctx.storage("query stats", (queries.global_stats.len() * 4) as u64);
            ctx.queue.write_buffer(&globals, 0, bytemuck::cast_slice(&queries.globals));
            ctx.queue.write_buffer(&stats, 0, bytemuck::cast_slice(&queries.global_stats));
            GpuQueries { len: queries.len(), globals, stats }
        })
    }

    /// References per tile for `queries` queries: the largest count whose descriptors, stats and
    /// score block each fit one binding, capped by `max_tile`.
    pub fn tile_len(&self, queries: usize, max_tile: usize) -> usize {
        let lim = self.ctx.binding_limit() as usize;
        let per_ref = (self.p.len() * 4).max(self.p.stats_len() * 4).max(queries * 4);
        (lim / per_ref).min(max_tile).min(MAX_DISPATCH).max(1)
    }

    /// The `k` best references of every query, best first, streaming `refs` in tiles.
    pub fn topk(&mut self, queries: &GpuQueries, refs: &dyn GlobalSource, k: usize, max_tile: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let ctx = self.ctx.clone();
        let kr = &ctx.kernels;
        let nq = queries.len;
        let tile = self.tile_len(nq, max_tile).min(refs.len().max(1));
        let (len, slen) = (self.p.len(), self.p.stats_len());
        if (tile * len * 4) as u64 > ctx.binding_limit() || (tile * slen * 4) as u64 > ctx.binding_limit() {
            return Err(GpuError::LimitsTooSmall { adapter: ctx.describe(), what: "one reference per tile".into(), needed: (slen * 4) as u64, available: ctx.binding_limit() });
        }
        let params = &self.params;
        let (tgb, tsb) = (&mut self.tile_globals, &mut self.tile_stats);
        let (sb, tsc, tic) = (&mut self.scores, &mut self.top_s, &mut self.top_i);
        ctx.scoped("coarse matching", || -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
            let tg = tgb.get(&ctx, "tile descriptors", (tile * len * 4) as u64);
            let ts = tsb.get(&ctx, "tile stats", (tile * slen * 4) as u64);
            let scores = sb.get(&ctx, "tile scores", (nq * tile * 4) as u64);
            let top_s = tsc.upload(&ctx, "top-k scores", bytemuck::cast_slice(&vec![EMPTY_SCORE; nq * k]));
            let top_i = tic.upload(&ctx, "top-k indices", bytemuck::cast_slice(&vec![EMPTY_INDEX; nq * k]));
            let mut buf = TileBuf::default();
            let mut start = 0;
            while start < refs.len() {
                let end = (start + tile).min(refs.len());
                let (g, st) = refs.tile(start, end, &mut buf);
                ctx.queue.write_buffer(tg, 0, bytemuck::cast_slice(g));
                ctx.queue.write_buffer(ts, 0, bytemuck::cast_slice(st));
                let tp = TileParams { queries: nq as u32, tile_len: (end - start) as u32, tile_start: start as u32, k: k as u32 };
                let tpb = ctx.uniform("tile params", &tp);
                let g1 = kr.ssim_tile.bind(&ctx.device, &[params, &tpb, &queries.globals, &queries.stats, tg, ts, scores]);
                let g2 = kr.topk_merge.bind(&ctx.device, &[&tpb, scores, top_s, top_i]);
                ctx.run(
                    "coarse tile",
                    &[(&kr.ssim_tile.pipeline, &g1, [(end - start) as u32, nq as u32, 1]), (&kr.topk_merge.pipeline, &g2, [(nq as u32).div_ceil(64), 1, 1])],
                );
                ctx.check_lost()?;
                start = end;
            }
            ctx.read_topk(top_s, top_i, nq, k)
        })?
    }
}

/// Runs the `topk_merge` kernel alone: folds `scores` (tile scores, query-major) into the K-lists
/// `top_s` / `top_i` (queries x k, best first) and reads them back. It lets tests feed the
/// kernel scores no SSIM produces (NaN) and compare with its twin `ssim_topk::topk_merge`.
pub fn merge_scores(ctx: &GpuContext, tp: &TileParams, scores: &[f32], top_s: &[f32], top_i: &[u32]) -> Result<(Vec<f32>, Vec<u32>), GpuError> {
    let n = tp.queries as usize * tp.k as usize;
    ctx.scoped("merging scores", || -> Result<(Vec<f32>, Vec<u32>), GpuError> {
        let upload = |label: &str, data: &[u8]| {
            let b = ctx.storage(label, data.len() as u64);
            ctx.queue.write_buffer(&b, 0, data);
            b
        };
        let (sb, tsb, tib) = (upload("scores", bytemuck::cast_slice(scores)), upload("top-k scores", bytemuck::cast_slice(&top_s[..n])), upload("top-k indices", bytemuck::cast_slice(&top_i[..n])));
        let tpb = ctx.uniform("tile params", tp);
        let g = ctx.kernels.topk_merge.bind(&ctx.device, &[&tpb, &sb, &tsb, &tib]);
        ctx.run("topk merge", &[(&ctx.kernels.topk_merge.pipeline, &g, [tp.queries.div_ceil(64), 1, 1])]);
        Ok((ctx.read_back_values(&tsb, n)?, ctx.read_back_values(&tib, n)?))
    })?
}
