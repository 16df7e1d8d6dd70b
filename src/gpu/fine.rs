//! GPU executor for the fine stage: tree-set similarity of many (query forest, reference forest)
//! pairs. The forests taking part are packed into the shader's tree layout and uploaded; each
//! pair gets one workgroup; the pair scores are read back. For settings without a coarse stage,
//! the map is processed in tiles whose scores stay on the GPU and go through the same
//! `topk_merge` kernel as the coarse stage.

use super::context::{GpuContext, GpuError, Reused};
use crate::local::tree_similarity::TreeSimParams;
use crate::local::ForestRef;
use crate::descriptors::DescriptorSet;
use crate::matching::source::RefSource;
use crate::matching::ssim_topk::{TileParams, EMPTY_INDEX, EMPTY_SCORE};
use std::sync::Arc;

/// Most neighbour slots the shader's tree record holds.
pub const MAX_SLOTS: usize = 8;
/// Most trees per forest the shader's per-workgroup flags hold.
pub const MAX_TREES: usize = 256;

#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
struct GpuTree {
    class_id: u32,
    has_app: u32,
    area: f32,
    cx: f32,
    cy: f32,
    weight: f32,
    nb: [i32; MAX_SLOTS],
}

#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
struct Pair {
    q_start: u32,
    q_count: u32,
    r_start: u32,
    r_count: u32,
}

#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
struct BatchDims {
    dim: u32,
    pairs: u32,
    max_trees: u32,
    _pad: u32,
}

/// Forests packed for the shader: tree records, appearance, and where each forest starts.
struct Packed {
    trees: Vec<GpuTree>,
    app: Vec<f32>,
    /// (start, count) per forest
    spans: Vec<(u32, u32)>,
    max_trees: usize,
}

fn pack<'a>(forests: impl Iterator<Item = ForestRef<'a>>, dim: usize, params: &TreeSimParams) -> Packed {
    let mut p = Packed { trees: vec![], app: vec![], spans: vec![], max_trees: 0 };
    for f in forests {
        p.spans.push((p.trees.len() as u32, f.len() as u32));
        p.max_trees = p.max_trees.max(f.len());
        for t in 0..f.len() {
            let mut nb = [-1i32; MAX_SLOTS];
            nb[..f.neighbour_slots].copy_from_slice(&f.neighbours[t * f.neighbour_slots..(t + 1) * f.neighbour_slots]);
            p.trees.push(GpuTree {
                class_id: f.classes[t] as u32,
                has_app: f.has_appearance[t] as u32,
                area: f.areas[t],
                cx: f.centroids[2 * t],
                cy: f.centroids[2 * t + 1],
                weight: params.tree_weight(f.areas[t], f.descriptors[t]),
                nb,
            });
        }
        if dim > 0 {
            f.appearance.extend_into(&mut p.app);
        }
    }
    p
}

/// Buffers kept between batches.
#[derive(Default)]
struct Buffers {
    q_trees: Reused,
    q_app: Reused,
    r_trees: Reused,
    r_app: Reused,
    pairs: Reused,
    scratch: Reused,
    out: Reused,
    top_s: Reused,
    top_i: Reused,
}

pub struct FineMatcherGpu {
    ctx: Arc<GpuContext>,
    buffers: Buffers,
}

impl FineMatcherGpu {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        FineMatcherGpu { ctx, buffers: Buffers::default() }
    }

    fn check(&self, queries: &DescriptorSet, refs: &dyn RefSource) -> Result<(), GpuError> {
        if queries.neighbour_slots > MAX_SLOTS || queries.appearance_dim != refs.appearance_dim() {
            return Err(GpuError::Failed { what: "fine matching".into(), reason: "neighbour slots above 8 or appearance sizes differ".into() });
        }
        Ok(())
    }

    /// Scores of `pairs` (query index, reference index).
    pub fn score_pairs(&mut self, p: &TreeSimParams, queries: &DescriptorSet, refs: &dyn RefSource, pairs: &[(u32, u32)]) -> Result<Vec<f32>, GpuError> {
        self.check(queries, refs)?;
        // gather only the references that take part
        let mut slot = std::collections::HashMap::new();
        let mut order = Vec::new();
        for &(_, r) in pairs {
            slot.entry(r).or_insert_with(|| {
                order.push(r);
                order.len() as u32 - 1
            });
        }
        let dim = refs.appearance_dim();
        let q = pack((0..queries.len()).map(|i| queries.forest(i)), dim, p);
        let r = pack(order.iter().map(|&i| refs.forest(i as usize)), dim, p);
        let list: Vec<Pair> = pairs
            .iter()
            .map(|&(qi, ri)| {
                let (qs, qc) = q.spans[qi as usize];
                let (rs, rc) = r.spans[slot[&ri] as usize];
                Pair { q_start: qs, q_count: qc, r_start: rs, r_count: rc }
            })
            .collect();
        self.run(p, &q, &r, &list, dim, None)
    }

    /// For settings without a coarse stage: the `k` best references of every query over the
    /// whole map, by tree similarity, tiled over the map.
    pub fn topk_all(&mut self, p: &TreeSimParams, queries: &DescriptorSet, refs: &dyn RefSource, k: usize, max_tile: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        self.check(queries, refs)?;
        let ctx = self.ctx.clone();
        let dim = refs.appearance_dim();
        let q = pack((0..queries.len()).map(|i| queries.forest(i)), dim, p);
        let nq = queries.len();
        let max_trees = (0..refs.len()).map(|i| refs.forest(i).len()).max().unwrap_or(0).max(q.max_trees).max(1);
        let per_pair = (2 * max_trees * max_trees * 4) as u64;
        let pairs_fit = (ctx.binding_limit() / per_pair).max(1) as usize;
        let tile = (pairs_fit / nq.max(1)).min(max_tile).min(refs.len()).max(1);
        let mut top_s_buf = std::mem::take(&mut self.buffers.top_s);
        let mut top_i_buf = std::mem::take(&mut self.buffers.top_i);
        let result = ctx.scoped("fine matching (whole map)", || -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
            let top_s = top_s_buf.upload(&ctx, "top-k scores", bytemuck::cast_slice(&vec![EMPTY_SCORE; nq * k]));
            let top_i = top_i_buf.upload(&ctx, "top-k indices", bytemuck::cast_slice(&vec![EMPTY_INDEX; nq * k]));
            let mut start = 0;
            while start < refs.len() {
                let end = (start + tile).min(refs.len());
                let r = pack((start..end).map(|i| refs.forest(i)), dim, p);
                let mut list = Vec::with_capacity(nq * (end - start));
                for qi in 0..nq {
                    for ri in 0..end - start {
                        let (qs, qc) = q.spans[qi];
                        let (rs, rc) = r.spans[ri];
                        list.push(Pair { q_start: qs, q_count: qc, r_start: rs, r_count: rc });
                    }
                }
                let tp = TileParams { queries: nq as u32, tile_len: (end - start) as u32, tile_start: start as u32, k: k as u32 };
                self.run(p, &q, &r, &list, dim, Some((&tp, top_s, top_i)))?;
                start = end;
            }
            ctx.read_topk(top_s, top_i, nq, k)
        });
        self.buffers.top_s = top_s_buf;
        self.buffers.top_i = top_i_buf;
        result?
    }

    /// Runs `list` in chunks that fit the scratch binding and returns the scores. With `merge`, the
    /// scores (laid out queries x tile) are folded into the given top-K buffers on the GPU instead
    /// and not read back (the result is then empty).
    fn run(&mut self, p: &TreeSimParams, q: &Packed, r: &Packed, list: &[Pair], dim: usize, merge: Option<(&TileParams, &wgpu::Buffer, &wgpu::Buffer)>) -> Result<Vec<f32>, GpuError> {
        let ctx = self.ctx.clone();
        let kr = &ctx.kernels;
        let max_trees = q.max_trees.max(r.max_trees).max(1);
        if max_trees > MAX_TREES {
            return Err(GpuError::LimitsTooSmall { adapter: ctx.describe(), what: "trees per forest".into(), needed: max_trees as u64, available: MAX_TREES as u64 });
        }
        let per_pair = (2 * max_trees * max_trees * 4) as u64;
        ctx.check_binding("one pair's similarity matrices", per_pair)?;
        for (what, bytes) in [("query trees", q.trees.len() * 52), ("reference trees", r.trees.len() * 52), ("query appearance", q.app.len() * 4), ("reference appearance", r.app.len() * 4)] {
            ctx.check_binding(what, bytes as u64)?;
        }
        let chunk = if merge.is_some() { list.len() } else { ((ctx.binding_limit() / per_pair) as usize).min(list.len()).max(1) };
        let b = &mut self.buffers;
        ctx.scoped("fine matching", || -> Result<Vec<f32>, GpuError> {
            let params = ctx.uniform("tree sim params", p);
            let qt = b.q_trees.upload(&ctx, "query trees", bytemuck::cast_slice(&q.trees));
            let qa = b.q_app.upload(&ctx, "query appearance", bytemuck::cast_slice(&q.app));
            let rt = b.r_trees.upload(&ctx, "reference trees", bytemuck::cast_slice(&r.trees));
            let ra = b.r_app.upload(&ctx, "reference appearance", bytemuck::cast_slice(&r.app));
            let scratch = b.scratch.get(&ctx, "pair matrices", chunk as u64 * per_pair);
            let out = b.out.get(&ctx, "pair scores", (chunk * 4) as u64);
            let mut scores = Vec::with_capacity(if merge.is_some() { 0 } else { list.len() });
            for part in list.chunks(chunk) {
                let dims = ctx.uniform("batch dims", &BatchDims { dim: dim as u32, pairs: part.len() as u32, max_trees: max_trees as u32, _pad: 0 });
                let pairs = b.pairs.upload(&ctx, "pairs", bytemuck::cast_slice(part));
                let g = kr.tree_similarity.bind(&ctx.device, &[&params, &dims, pairs, qt, qa, rt, ra, scratch, out]);
                let n = part.len() as u32;
                let grid = [n.min(65_535), n.div_ceil(65_535), 1];
                match merge {
                    Some((tp, ts, ti)) => {
                        let tpb = ctx.uniform("tile params", tp);
                        let g2 = kr.topk_merge.bind(&ctx.device, &[&tpb, out, ts, ti]);
                        ctx.run("fine tile", &[(&kr.tree_similarity.pipeline, &g, grid), (&kr.topk_merge.pipeline, &g2, [tp.queries.div_ceil(64), 1, 1])]);
                    }
                    None => {
                        ctx.run("fine pairs", &[(&kr.tree_similarity.pipeline, &g, grid)]);
                        scores.extend(ctx.read_back_values::<f32>(out, part.len())?);
                    }
                }
                ctx.check_lost()?;
            }
            Ok(scores)
        })?
    }
}
