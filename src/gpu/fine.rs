//! GPU executor for the fine stage: tree-set similarity, with the map's forests resident.
//!
//! What is uploaded when:
//! - the map's forests (tree records with their weights, appearance, spans), packed and uploaded
//!   once in chunks the first time a batch meets the map (key: the map's [`SourceKey`] with
//!   sampled forests and the tree-weight rule); streamed through two slots beyond the budget;
//! - per batch: the queries' packed forests, in chunks within the binding limits, then per query
//!   chunk one lookup buffer (the queries' spans, then any listed pairs) and the parameters of
//!   all its passes in one write (dynamic offsets);
//! - back: the listed pairs' scores (once per query chunk), or only the K-lists of the
//!   whole-map top-K, whose pair scores stay on the device and go through `topk_select`.
//!
//! A pass is a run of pairs within one map chunk, bounded by the scratch binding (each pair owns
//! 2 x max_trees^2 floats); its grid has `row` workgroups per row.

use super::buffers::{PassBuffer, Reused};
use super::context::{GpuContext, GpuError};
use super::fine_pack::{forest_key, pack, plan_chunks, ForestChunks, Packed};
use super::resident::{ChunkPlan, Resident};
use super::topk::{bytes_per_query, TopK, MAX_PASS_REFS};
use crate::descriptors::DescriptorSet;
use crate::kernels::abi::PassParams;
use crate::kernels::abi::TreeSimParams;
use crate::kernels::abi::{FinePass, MAX_SLOTS, MAX_TREES};
use crate::kernels::topk_select::SEG;
use crate::matching::source::{RefSource, SourceKey};
use std::sync::Arc;

pub struct FineMatcherGpu {
    ctx: Arc<GpuContext>,
    map: Resident,
    /// The map last planned: its key, chunks and largest forest.
    planned: Option<(SourceKey, Vec<ChunkPlan>, usize)>,
    lookup: Reused,
    q_trees: Reused,
    q_app: Reused,
    scratch: Reused,
    out: Reused,
    passes: PassBuffer<FinePass>,
    topk_passes: PassBuffer<PassParams>,
    topk: TopK,
}

/// What one query chunk runs: its queries and, per pass, the map chunk and parameters.
struct Work {
    queries: std::ops::Range<usize>,
    /// Listed pairs (query in chunk, reference in map chunk), grouped by map chunk.
    list: Vec<[u32; 2]>,
    passes: Vec<(usize, FinePass, PassParams)>,
    out_len: usize,
}

impl FineMatcherGpu {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let (passes, topk_passes) = (PassBuffer::new(&ctx), PassBuffer::new(&ctx));
        FineMatcherGpu {
            ctx,
            map: Resident::default(),
            planned: None,
            lookup: Reused::default(),
            q_trees: Reused::default(),
            q_app: Reused::default(),
            scratch: Reused::default(),
            out: Reused::default(),
            passes,
            topk_passes,
            topk: TopK::default(),
        }
    }

    /// Bytes of the last map's packed forests on the device (or streamed through it).
    pub fn map_bytes(&self) -> u64 {
        self.map.bytes()
    }

    /// Whether the last map's forests were kept resident (false: streamed).
    pub fn map_is_resident(&self) -> bool {
        !self.map.is_streaming()
    }

    /// Forgets the resident forests: the next batch uploads them again.
    pub fn forget_map(&mut self) {
        self.map.forget(&self.ctx);
        self.planned = None;
    }

    /// Checks the batch, makes the map's forests ready and returns the largest forest of both.
    fn prepare(&mut self, p: &TreeSimParams, queries: &DescriptorSet, refs: &dyn RefSource) -> Result<usize, GpuError> {
        let ctx = self.ctx.clone();
        if queries.neighbour_slots > MAX_SLOTS || queries.appearance_dim != refs.appearance_dim() {
            return Err(GpuError::Failed {
                what: "fine matching".into(),
                reason: format!("neighbour slots above {MAX_SLOTS} or appearance sizes differ"),
            });
        }
        let key = forest_key(refs, p);
        let planned = match self.planned.take() {
            Some(old) if old.0 == key => old,
            _ => {
                let (plans, max) = plan_chunks(&ctx, refs, ctx.binding_limit())?;
                (key, plans, max)
            }
        };
        let (_, plans, map_max) = self.planned.insert(planned);
        let qmax = (0..queries.len()).map(|i| queries.forest(i).len()).max().unwrap_or(0);
        let max_trees = qmax.max(*map_max).max(1);
        if max_trees > MAX_TREES {
            return Err(GpuError::LimitsTooSmall {
                adapter: ctx.describe(),
                what: "trees per forest".into(),
                needed: max_trees as u64,
                available: MAX_TREES as u64,
            });
        }
        ctx.check_binding("one pair's similarity matrices", Self::per_pair(max_trees))?;
        let data = ForestChunks { refs, params: *p };
        let bind = |b: &[&wgpu::Buffer]| ctx.kernels.tree_similarity.bind_group(&ctx.device, 1, b);
        self.map.prepare(&ctx, key, || plans.clone(), &data, &bind)?;
        Ok(max_trees)
    }

    fn per_pair(max_trees: usize) -> u64 {
        (2 * max_trees * max_trees * 4) as u64
    }

    /// Query chunks: consecutive queries whose packed forests (and `extra(q)` lookup entries
    /// each) fit the bindings, at most `cap` queries each.
    fn query_chunks(&self, queries: &DescriptorSet, cap: usize, extra: &dyn Fn(usize) -> usize) -> Result<Vec<std::ops::Range<usize>>, GpuError> {
        let lim = self.ctx.binding_limit();
        let dim = queries.appearance_dim;
        let (mut out, mut start, mut trees, mut look) = (Vec::new(), 0, 0usize, 0usize);
        for q in 0..queries.len() {
            let (t, l) = (queries.forest(q).len(), 1 + extra(q));
            let bytes = |trees: usize, look: usize| super::fine_pack::packed_bytes(look, trees, dim).into_iter().max().unwrap_or(0);
            if bytes(t, l) > lim {
                return Err(GpuError::LimitsTooSmall {
                    adapter: self.ctx.describe(),
                    what: format!("query {q}'s forest and pairs in one binding"),
                    needed: bytes(t, l),
                    available: lim,
                });
            }
            if q - start == cap || bytes(trees + t, look + l) > lim {
                out.push(start..q);
                (start, trees, look) = (q, 0, 0);
            }
            (trees, look) = (trees + t, look + l);
        }
        if queries.len() > start {
            out.push(start..queries.len());
        }
        Ok(out)
    }

    /// Pairs per pass: as many as the scratch binding holds, within the dispatch grid.
    fn pairs_per_pass(&self, max_trees: usize) -> usize {
        let g = self.ctx.max_workgroups() as u64;
        ((self.ctx.binding_limit() / Self::per_pair(max_trees)).min(g * g) as usize).max(1)
    }

    /// Scores of `pairs` (query index, reference index), in order.
    pub fn score_pairs(
        &mut self,
        p: &TreeSimParams,
        queries: &DescriptorSet,
        refs: &dyn RefSource,
        pairs: &[(u32, u32)],
    ) -> Result<Vec<f32>, GpuError> {
        if pairs.is_empty() {
            return Ok(Vec::new());
        }
        let max_trees = self.prepare(p, queries, refs)?;
        let per_pass = self.pairs_per_pass(max_trees);
        let mut by_query = vec![Vec::new(); queries.len()];
        for (i, &(q, r)) in pairs.iter().enumerate() {
            by_query[q as usize].push((r as usize, i));
        }
        let plans = self.map.plans().to_vec();
        let chunk_of = |r: usize| plans.partition_point(|c| c.first <= r) - 1;
        let mut scores = vec![0.0f32; pairs.len()];
        for qs in self.query_chunks(queries, usize::MAX, &|q| by_query[q].len())? {
            // the chunk's pairs grouped by map chunk, remembering where each came from
            let mut listed: Vec<(usize, [u32; 2], usize)> = qs
                .clone()
                .flat_map(|q| by_query[q].iter().map(move |&(r, i)| (q, r, i)))
                .map(|(q, r, i)| {
                    let c = chunk_of(r);
                    (c, [(q - qs.start) as u32, (r - plans[c].first) as u32], i)
                })
                .collect();
            listed.sort_by_key(|e| e.0);
            let mut passes = Vec::new();
            let mut at = 0;
            while at < listed.len() {
                let c = listed[at].0;
                let end = (at..listed.len()).find(|&j| listed[j].0 != c || j - at == per_pass).unwrap_or(listed.len());
                let fp = FinePass { pairs: (end - at) as u32, list_first: at as u32, out_first: at as u32, ..Default::default() };
                passes.push((c, fp, PassParams::default()));
                at = end;
            }
            let work = Work { queries: qs, list: listed.iter().map(|e| e.1).collect(), passes, out_len: listed.len() };
            let got = self.run(p, queries, refs, max_trees, &work, None)?;
            for (e, s) in listed.iter().zip(got) {
                scores[e.2] = s;
            }
        }
        Ok(scores)
    }

    /// For settings without a coarse stage: the `k` best references of every query over the
    /// whole map, by tree similarity (the pair scores never leave the device).
    pub fn topk_all(&mut self, p: &TreeSimParams, queries: &DescriptorSet, refs: &dyn RefSource, k: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        if queries.is_empty() || refs.is_empty() || k == 0 {
            return Ok(vec![Vec::new(); queries.len()]);
        }
        let max_trees = self.prepare(p, queries, refs)?;
        let (lim, g) = (self.ctx.binding_limit(), self.ctx.max_workgroups() as usize);
        let per_pass = self.pairs_per_pass(max_trees);
        let [part, top] = bytes_per_query(k, SEG);
        let cap = per_pass.min(g).min((lim / top.max(part)) as usize).min((lim / (4 * SEG as u64)).max(1) as usize).max(1);
        let plans = self.map.plans().to_vec();
        let mut lists = Vec::with_capacity(queries.len());
        for qs in self.query_chunks(queries, cap, &|_| 0)? {
            let nq = qs.len();
            let run = (per_pass / nq)
                .min(MAX_PASS_REFS)
                .min(g * SEG)
                .min((lim / (4 * nq as u64)) as usize)
                .min((lim / (nq as u64 * part)) as usize * SEG)
                .max(1);
            let mut passes = Vec::new();
            let mut parity = 0;
            for (c, plan) in plans.iter().enumerate() {
                for start in (0..plan.len).step_by(run) {
                    let refs_n = run.min(plan.len - start);
                    let fp = FinePass { grid: 1, pairs: (nq * refs_n) as u32, refs: refs_n as u32, ref_first: start as u32, ..Default::default() };
                    let ps = PassParams {
                        queries: nq as u32,
                        refs: refs_n as u32,
                        ref_index: (plan.first + start) as u32,
                        k: k as u32,
                        segs: refs_n.div_ceil(SEG) as u32,
                        parity,
                        fresh: passes.is_empty() as u32,
                        ..Default::default()
                    };
                    passes.push((c, fp, ps));
                    parity ^= 1;
                }
            }
            let work = Work { queries: qs, list: Vec::new(), passes, out_len: nq * run };
            self.run(p, queries, refs, max_trees, &work, Some(k))?;
            lists.extend(self.topk.read(&self.ctx, nq, k, parity)?);
        }
        Ok(lists)
    }

    /// Runs one query chunk's passes; returns `out` read back (listed pairs), or nothing when
    /// `topk` is given (the scores went through the top-K kernels).
    fn run(
        &mut self,
        p: &TreeSimParams,
        queries: &DescriptorSet,
        refs: &dyn RefSource,
        max_trees: usize,
        w: &Work,
        topk: Option<usize>,
    ) -> Result<Vec<f32>, GpuError> {
        let ctx = self.ctx.clone();
        let dim = refs.appearance_dim();
        let q: Packed = pack(w.queries.clone().map(|i| queries.forest(i)), dim, p);
        let row = ctx.max_workgroups();
        let nq = w.queries.len() as u32;
        let fps: Vec<FinePass> =
            w.passes.iter().map(|(_, fp, _)| FinePass { dim: dim as u32, max_trees: max_trees as u32, queries: nq, row, ..*fp }).collect();
        let data = ForestChunks { refs, params: *p };
        let bind = |b: &[&wgpu::Buffer]| ctx.kernels.tree_similarity.bind_group(&ctx.device, 1, b);
        ctx.scoped("fine matching", || -> Result<Vec<f32>, GpuError> {
            let mut look: Vec<[u32; 2]> = q.spans.clone();
            look.extend_from_slice(&w.list);
            let params = ctx.uniform("tree sim params", p);
            let lookup = self.lookup.upload(&ctx, "queries' spans and pairs", bytemuck::cast_slice(&look));
            let qt = self.q_trees.upload(&ctx, "query trees", bytemuck::cast_slice(&q.trees));
            let qa = self.q_app.upload(&ctx, "query appearance", bytemuck::cast_slice(&q.app));
            let most = fps.iter().map(|f| f.pairs as u64).max().unwrap_or(1);
            let scratch = self.scratch.get(&ctx, "pair matrices", most * Self::per_pair(max_trees));
            let out = self.out.get(&ctx, "pair scores", (w.out_len * 4) as u64);
            let pbuf = self.passes.write(&ctx, &fps);
            let group = ctx.kernels.tree_similarity.bind(&ctx.device, &[&params, pbuf, lookup, qt, qa, scratch, out]);
            let tps: Vec<PassParams> = w.passes.iter().map(|e| e.2).collect();
            let g_topk = match topk {
                Some(k) => {
                    let tbuf = self.topk_passes.write(&ctx, &tps);
                    Some(self.topk.begin(&ctx, nq as usize, k, w.out_len / nq.max(1) as usize, tbuf, out))
                }
                None => None,
            };
            let mut i = 0;
            for c in 0..self.map.chunk_count() {
                if w.passes[i..].first().is_none_or(|e| e.0 != c) {
                    continue;
                }
                let chunk = self.map.chunk(&ctx, c, &data, &bind)?;
                let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("fine chunk") });
                {
                    let mut pass = ctx.begin_pass(&mut enc, "fine chunk")?;
                    while i < w.passes.len() && w.passes[i].0 == c {
                        let n = fps[i].pairs;
                        pass.set_pipeline(&ctx.kernels.tree_similarity.pipeline);
                        pass.set_bind_group(0, Some(&group), &[self.passes.offset(i)]);
                        pass.set_bind_group(1, Some(&chunk), &[]);
                        pass.dispatch_workgroups(n.min(row), n.div_ceil(row), 1);
                        if let Some(g) = &g_topk {
                            TopK::record(&ctx, &mut pass, g, self.topk_passes.offset(i), &tps[i]);
                        }
                        i += 1;
                    }
                }
                ctx.queue.submit([enc.finish()]);
                ctx.check_lost()?;
            }
            match topk {
                Some(_) => Ok(Vec::new()),
                None => ctx.read_back_values(out, w.out_len),
            }
        })?
    }
}
