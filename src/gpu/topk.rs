//! The device side of the streaming top-K, shared by the coarse and fine stages: per pass, the
//! scores (queries x refs, query-major) go through `topk_partial` (segment lists) and
//! `topk_merge_lists` (into the running lists, ping-pong between two buffers). Only the final
//! K-lists are read back.

use crate::device::buffers::Reused;
use crate::device::context::{GpuContext, GpuError};
use semlook_kernels::abi::Entry;
use semlook_kernels::abi::PassParams;
use semlook_kernels::topk_select::{MAX_LISTS, SEG};

/// References one pass may cover: the merge takes the running list and `MAX_LISTS - 1` segments.
pub(crate) const MAX_PASS_REFS: usize = (MAX_LISTS - 1) * SEG;

/// Buffers of the running lists and partial lists, kept between batches.
#[derive(Default)]
pub(crate) struct TopK {
    partial: Reused,
    top_a: Reused,
    top_b: Reused,
}

/// Bytes of one query's share of the top-K buffers for passes of at most `pass_refs` references.
pub(crate) fn bytes_per_query(k: usize, pass_refs: usize) -> [u64; 2] {
    let e = std::mem::size_of::<Entry>() as u64;
    [pass_refs.div_ceil(SEG) as u64 * k as u64 * e, k as u64 * e]
}

impl TopK {
    /// Binds the running lists of `nq` queries with `params` (the batch's pass parameters) and
    /// `scores`: the bind group of both kernels for this query chunk. Nothing is written: the
    /// chunk's first pass is `fresh` and does not read the lists.
    pub fn begin(
        &mut self,
        ctx: &GpuContext,
        nq: usize,
        k: usize,
        pass_refs: usize,
        params: &wgpu::Buffer,
        scores: &wgpu::Buffer,
    ) -> wgpu::BindGroup {
        let [part, top] = bytes_per_query(k, pass_refs);
        let partial = self.partial.get(ctx, "partial top-k lists", nq as u64 * part);
        let top_a = self.top_a.get(ctx, "running top-k lists", nq as u64 * top);
        let top_b = self.top_b.get(ctx, "running top-k lists", nq as u64 * top);
        ctx.kernels.topk_partial.bind(&ctx.device, &[params, scores, partial, top_a, top_b])
    }

    /// Records the selection and the merge of one pass whose parameters are at `offset`.
    pub fn record(ctx: &GpuContext, pass: &mut wgpu::ComputePass, group: &wgpu::BindGroup, offset: u32, ps: &PassParams) {
        let k = &ctx.kernels;
        pass.set_pipeline(&k.topk_partial.pipeline);
        pass.set_bind_group(0, Some(group), &[offset]);
        pass.dispatch_workgroups(ps.segs, ps.queries, 1);
        pass.set_pipeline(&k.topk_merge_lists.pipeline);
        pass.set_bind_group(0, Some(group), &[offset]);
        pass.dispatch_workgroups(ps.queries.div_ceil(64), 1, 1);
    }

    /// The K-lists of `nq` queries after passes ending with `parity` (the next pass's input),
    /// best first, empty slots dropped.
    pub fn read(&self, ctx: &GpuContext, nq: usize, k: usize, parity: u32) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let buf = if parity == 0 { &self.top_a } else { &self.top_b };
        let buf = buf.current().ok_or_else(|| GpuError::Failed { what: "reading top-k lists".into(), reason: "no lists on the device".into() })?;
        let entries: Vec<Entry> = bytemuck::pod_collect_to_vec(&ctx.read_back(buf, (nq * k * 8) as u64)?[..nq * k * 8]);
        Ok(entries.chunks(k.max(1)).map(|l| l.iter().filter(|e| e.index != Entry::EMPTY.index).map(|e| (e.score, e.index)).collect()).collect())
    }
}
