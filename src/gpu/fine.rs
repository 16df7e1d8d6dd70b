//! GPU executor for the fine stage: tree-set similarity, with the map's forests resident.
//!
//! What is uploaded when:
//! - the map's forests (tree records with their weights, appearance, spans), packed and uploaded
//!   once in chunks the first time a batch meets the map (key: `forest_key`, a stored map's
//!   identity and generation with the tree-weight rule; an in-memory set's cheap sampled key);
//!   streamed through two slots beyond the budget. Each reference's tree count is read with
//!   them, once per key, and decides which kernel scores its pairs;
//! - per batch: the queries' packed forests, in chunks within the binding limits, then per query
//!   chunk one lookup buffer (the queries' spans, then any listed pairs) and the parameters of
//!   all its dispatches in one write (dynamic offsets);
//! - back: the listed pairs' scores (once per query chunk), or only the K-lists of the
//!   whole-map top-K, whose pair scores stay on the device and go through `topk_select`.
//!
//! Two kernels share the passes: `tree_similarity_small` takes [`PAIRS_PER_GROUP`] pairs per
//! workgroup and scores those that [`fits_small`] (the common case: tens of trees) in workgroup
//! memory, several at a time; `tree_similarity` scores each of the others in a workgroup of its
//! own with 2 x max_trees^2 floats of global scratch. Listed pairs are sorted into the two; a
//! whole-map pass runs the first over every pair of its grid, then the second over the grid's
//! large pairs, listed (where they are few) or by the grid with `skip_small`, in dispatches
//! bounded by the scratch binding.

use super::fine_pack::{forest_key, pack, plan_chunks, ChunkedForests, ForestChunks, Packed};
use super::resident::Resident;
use super::topk::{bytes_per_query, TopK, MAX_PASS_REFS};
use crate::descriptors::source::{RefSource, SourceKey};
use crate::descriptors::DescriptorSet;
use crate::device::buffers::{PassBuffer, Reused};
use crate::device::context::{GpuContext, GpuError};
use semlook_kernels::abi::PassParams;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::abi::{FinePass, MAX_SLOTS, MAX_TREES};
use semlook_kernels::topk_select::SEG;
use semlook_kernels::tree_similarity::{fits_small, PAIRS_PER_GROUP, SMALL_CELLS, SMALL_TREES};
use std::sync::Arc;

/// What the fine stage's dispatches did since the executor was made (counted on the host).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct FineCounters {
    /// Pairs scored by `tree_similarity_small` (several to a workgroup, in workgroup memory).
    pub small_pairs: u64,
    /// Pairs scored by `tree_similarity` (a workgroup each, global scratch).
    pub large_pairs: u64,
    /// Workgroups dispatched of `tree_similarity_small` and of `tree_similarity` (a grid
    /// dispatch with `skip_small` counts the workgroups of the pairs it skips too).
    pub small_workgroups: u64,
    /// Workgroups dispatched of `tree_similarity`.
    pub large_workgroups: u64,
    /// Dispatches of the two kernels.
    pub small_dispatches: u64,
    /// Dispatches of `tree_similarity`.
    pub large_dispatches: u64,
    /// The most global scratch one dispatch of `tree_similarity` used (bytes).
    pub scratch_bytes: u64,
}

/// Executor of the fine stage (forest similarity of query and reference pairs) on the device,
/// the map's forests kept resident between batches.
pub struct FineMatcherGpu {
    ctx: Arc<GpuContext>,
    map: Resident,
    /// The map last planned: its key, chunks, largest forest and tree counts.
    planned: Option<(SourceKey, ChunkedForests)>,
    params: Option<wgpu::Buffer>,
    lookup: Reused,
    q_trees: Reused,
    q_app: Reused,
    scratch: Reused,
    out: Reused,
    passes: PassBuffer<FinePass>,
    topk_passes: PassBuffer<PassParams>,
    topk: TopK,
    counters: FineCounters,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Kernel {
    /// `tree_similarity_small`
    Small,
    /// `tree_similarity`
    Large,
}

/// One dispatch: the map chunk, the kernel, its parameters, and the top-K pass recorded after
/// it (whole-map passes: after the pass's last dispatch).
struct Dispatch {
    chunk: usize,
    kernel: Kernel,
    fp: FinePass,
    topk: Option<PassParams>,
}

/// What one query chunk runs: its queries and its dispatches.
struct Work {
    queries: std::ops::Range<usize>,
    /// Listed pairs (query in chunk, reference in map chunk).
    list: Vec<[u32; 2]>,
    dispatches: Vec<Dispatch>,
    out_len: usize,
    /// Pairs each kernel scores.
    small_pairs: u64,
    large_pairs: u64,
}

/// The most trees a reference forest may have for a pair with a query forest of `nq` trees to
/// [`fits_small`] (`None`: no pair with this query fits).
fn small_partner(nq: usize) -> Option<usize> {
    match nq {
        0 => Some(SMALL_TREES),
        n if n <= SMALL_TREES => Some((SMALL_CELLS / n).min(SMALL_TREES - n)),
        _ => None,
    }
}

impl FineMatcherGpu {
    /// An executor on `ctx`; nothing is uploaded until a batch meets a map.
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        let (passes, topk_passes) = (PassBuffer::new(&ctx), PassBuffer::new(&ctx));
        FineMatcherGpu {
            ctx,
            map: Resident::default(),
            planned: None,
            params: None,
            lookup: Reused::default(),
            q_trees: Reused::default(),
            q_app: Reused::default(),
            scratch: Reused::default(),
            out: Reused::default(),
            passes,
            topk_passes,
            topk: TopK::default(),
            counters: FineCounters::default(),
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

    /// What the dispatches did so far.
    pub fn counters(&self) -> FineCounters {
        self.counters
    }

    /// Forgets the resident forests: the next batch uploads them again.
    pub fn forget_map(&mut self) {
        self.map.forget(&self.ctx);
        self.planned = None;
    }

    /// Checks the batch, makes the map's forests ready and returns the largest forest of both
    /// and every reference's tree count.
    fn prepare(&mut self, p: &TreeSimParams, queries: &DescriptorSet, refs: &dyn RefSource) -> Result<(usize, Arc<[u16]>), GpuError> {
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
            _ => (key, plan_chunks(&ctx, refs, ctx.binding_limit())?),
        };
        let (_, chunks) = self.planned.insert(planned);
        let qmax = (0..queries.len()).map(|i| queries.forest(i).len()).max().unwrap_or(0);
        let max_trees = qmax.max(chunks.max_trees).max(1);
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
        let plans = &chunks.plans;
        self.map.prepare(&ctx, key, || plans.clone(), &data, &bind)?;
        Ok((max_trees, chunks.sizes.clone()))
    }

    /// Global scratch of one pair of `tree_similarity`: its two matrices.
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

    /// Pairs per dispatch of `tree_similarity`: as many as the scratch binding holds, within
    /// the dispatch grid.
    fn large_per_dispatch(&self, max_trees: usize) -> usize {
        let g = self.ctx.max_workgroups() as u64;
        ((self.ctx.binding_limit() / Self::per_pair(max_trees)).min(g * g) as usize).max(1)
    }

    /// Pairs per dispatch of `tree_similarity_small`: [`PAIRS_PER_GROUP`] per workgroup of the
    /// dispatch grid.
    fn small_per_dispatch(&self) -> usize {
        let g = self.ctx.max_workgroups() as usize;
        (g * g).saturating_mul(PAIRS_PER_GROUP).min(u32::MAX as usize / 2)
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
        let (max_trees, sizes) = self.prepare(p, queries, refs)?;
        let caps = [self.small_per_dispatch(), self.large_per_dispatch(max_trees)];
        let mut by_query = vec![Vec::new(); queries.len()];
        for (i, &(q, r)) in pairs.iter().enumerate() {
            by_query[q as usize].push((r as usize, i));
        }
        let plans = self.map.plans().to_vec();
        let chunk_of = |r: usize| plans.partition_point(|c| c.first <= r) - 1;
        let mut scores = vec![0.0f32; pairs.len()];
        for qs in self.query_chunks(queries, usize::MAX, &|q| by_query[q].len())? {
            // the chunk's pairs by map chunk, then kernel (consecutive pairs of a query stay
            // together: `tree_similarity_small` loads a query's forest once for them)
            let mut listed: Vec<(usize, bool, [u32; 2], usize)> = qs
                .clone()
                .flat_map(|q| by_query[q].iter().map(move |&(r, i)| (q, r, i)))
                .map(|(q, r, i)| {
                    let c = chunk_of(r);
                    let large = !fits_small(queries.forest(q).len(), sizes[r] as usize);
                    (c, large, [(q - qs.start) as u32, (r - plans[c].first) as u32], i)
                })
                .collect();
            listed.sort_by_key(|e| (e.0, e.1));
            let mut dispatches = Vec::new();
            let mut at = 0;
            while at < listed.len() {
                let (c, large) = (listed[at].0, listed[at].1);
                let cap = caps[large as usize];
                let end = (at..listed.len()).find(|&j| (listed[j].0, listed[j].1) != (c, large) || j - at == cap).unwrap_or(listed.len());
                let fp = FinePass { pairs: (end - at) as u32, list_first: at as u32, out_first: at as u32, ..Default::default() };
                dispatches.push(Dispatch { chunk: c, kernel: if large { Kernel::Large } else { Kernel::Small }, fp, topk: None });
                at = end;
            }
            let large_pairs = listed.iter().filter(|e| e.1).count() as u64;
            let work = Work {
                queries: qs,
                list: listed.iter().map(|e| e.2).collect(),
                dispatches,
                out_len: listed.len(),
                small_pairs: listed.len() as u64 - large_pairs,
                large_pairs,
            };
            let got = self.run(p, queries, refs, max_trees, &work, None)?;
            for (e, s) in listed.iter().zip(got) {
                scores[e.3] = s;
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
        let (max_trees, sizes) = self.prepare(p, queries, refs)?;
        let (lim, g) = (self.ctx.binding_limit(), self.ctx.max_workgroups() as usize);
        let (small_cap, large_cap) = (self.small_per_dispatch(), self.large_per_dispatch(max_trees));
        let [part, top] = bytes_per_query(k, SEG);
        let cap = g.min((lim / top.max(part)) as usize).min((lim / (4 * SEG as u64)).max(1) as usize).max(1);
        let plans = self.map.plans().to_vec();
        let mut lists = Vec::with_capacity(queries.len());
        for qs in self.query_chunks(queries, cap, &|_| 0)? {
            let nq = qs.len();
            let run = MAX_PASS_REFS
                .min(g * SEG)
                .min((lim / (4 * nq as u64)) as usize)
                .min((lim / (nq as u64 * part)) as usize * SEG)
                .min(small_cap / nq)
                .max(1);
            // per query, the largest reference forest its pairs may have to be small; references
            // above the smallest of these are the only ones that can make a large pair
            let partner: Vec<Option<usize>> = qs.clone().map(|q| small_partner(queries.forest(q).len())).collect();
            let floor = partner.iter().map(|t| t.map_or(-1, |v| v as i64)).min().unwrap_or(-1);
            // listed large pairs: what one lookup binding holds beside the queries' spans
            let room = ((lim / 8) as usize).saturating_sub(nq);
            let (mut list, mut dispatches, mut parity) = (Vec::new(), Vec::new(), 0);
            let (mut small_pairs, mut large_pairs) = (0u64, 0u64);
            for (c, plan) in plans.iter().enumerate() {
                for start in (0..plan.len).step_by(run) {
                    let refs_n = run.min(plan.len - start);
                    let pairs = nq * refs_n;
                    let grid = FinePass { grid: 1, pairs: pairs as u32, refs: refs_n as u32, ref_first: start as u32, ..Default::default() };
                    dispatches.push(Dispatch { chunk: c, kernel: Kernel::Small, fp: grid, topk: None });
                    // the run's large pairs
                    let big: Vec<(u32, usize)> =
                        (start..start + refs_n).map(|r| (r as u32, sizes[plan.first + r] as usize)).filter(|&(_, n)| n as i64 > floor).collect();
                    let partner = &partner;
                    let large_of = |qi: usize| big.iter().filter(move |&&(_, n)| partner[qi].is_none_or(|t| n > t)).map(|&(r, _)| r);
                    let large: usize = (0..nq).map(|qi| if partner[qi].is_none() { refs_n } else { large_of(qi).count() }).sum();
                    (small_pairs, large_pairs) = (small_pairs + (pairs - large) as u64, large_pairs + large as u64);
                    if large > 0 && large <= pairs / 4 && list.len() + large <= room {
                        // few: listed, each scored where its grid pair's score goes
                        let first = list.len();
                        for qi in 0..nq {
                            match partner[qi] {
                                None => list.extend((start..start + refs_n).map(|r| [qi as u32, r as u32])),
                                Some(_) => list.extend(large_of(qi).map(|r| [qi as u32, r])),
                            }
                        }
                        for at in (first..list.len()).step_by(large_cap) {
                            let n = large_cap.min(list.len() - at);
                            let fp = FinePass { grid: 2, pairs: n as u32, list_first: at as u32, ..grid };
                            dispatches.push(Dispatch { chunk: c, kernel: Kernel::Large, fp, topk: None });
                        }
                    } else if large > 0 {
                        // many: the grid again, `tree_similarity` skipping the small pairs
                        for at in (0..pairs).step_by(large_cap) {
                            let n = large_cap.min(pairs - at);
                            let fp = FinePass { pairs: n as u32, pair_first: at as u32, skip_small: 1, ..grid };
                            dispatches.push(Dispatch { chunk: c, kernel: Kernel::Large, fp, topk: None });
                        }
                    }
                    let ps = PassParams {
                        queries: nq as u32,
                        refs: refs_n as u32,
                        ref_index: (plan.first + start) as u32,
                        k: k as u32,
                        segs: refs_n.div_ceil(SEG) as u32,
                        parity,
                        fresh: dispatches.iter().all(|d| d.topk.is_none()) as u32,
                        ..Default::default()
                    };
                    dispatches.last_mut().expect("a dispatch per pass").topk = Some(ps);
                    parity ^= 1;
                }
            }
            let work = Work { queries: qs, list, dispatches, out_len: nq * run, small_pairs, large_pairs };
            self.run(p, queries, refs, max_trees, &work, Some(k))?;
            lists.extend(self.topk.read(&self.ctx, nq, k, parity)?);
        }
        Ok(lists)
    }

    /// Runs one query chunk's dispatches; returns `out` read back (listed pairs), or nothing
    /// when `topk` is given (the scores went through the top-K kernels).
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
            w.dispatches.iter().map(|d| FinePass { dim: dim as u32, max_trees: max_trees as u32, queries: nq, row, ..d.fp }).collect();
        let tps: Vec<PassParams> = w.dispatches.iter().filter_map(|d| d.topk).collect();
        let most_large = w.dispatches.iter().filter(|d| d.kernel == Kernel::Large).map(|d| d.fp.pairs as u64).max().unwrap_or(0);
        let scratch_bytes = most_large * Self::per_pair(max_trees);
        let data = ForestChunks { refs, params: *p };
        let bind = |b: &[&wgpu::Buffer]| ctx.kernels.tree_similarity.bind_group(&ctx.device, 1, b);
        let mut counters = self.counters;
        (counters.small_pairs, counters.large_pairs) = (counters.small_pairs + w.small_pairs, counters.large_pairs + w.large_pairs);
        counters.scratch_bytes = counters.scratch_bytes.max(scratch_bytes);
        let got = ctx.scoped("fine matching", || -> Result<Vec<f32>, GpuError> {
            let mut look: Vec<[u32; 2]> = q.spans.clone();
            look.extend_from_slice(&w.list);
            let params = match self.params.take() {
                Some(b) => {
                    ctx.write(&b, 0, bytemuck::bytes_of(p));
                    b
                }
                None => ctx.uniform("tree sim params", p),
            };
            let params: &wgpu::Buffer = self.params.insert(params);
            let lookup = self.lookup.upload(&ctx, "queries' spans and pairs", bytemuck::cast_slice(&look));
            let qt = self.q_trees.upload(&ctx, "query trees", bytemuck::cast_slice(&q.trees));
            let qa = self.q_app.upload(&ctx, "query appearance", bytemuck::cast_slice(&q.app));
            let scratch = self.scratch.get(&ctx, "pair matrices", scratch_bytes);
            let out = self.out.get(&ctx, "pair scores", (w.out_len * 4) as u64);
            let pbuf = self.passes.write(&ctx, &fps);
            let group = ctx.kernels.tree_similarity.bind(&ctx.device, &[params, pbuf, lookup, qt, qa, scratch, out]);
            let g_topk = match topk {
                Some(k) => {
                    let tbuf = self.topk_passes.write(&ctx, &tps);
                    Some(self.topk.begin(&ctx, nq as usize, k, w.out_len / nq.max(1) as usize, tbuf, out))
                }
                None => None,
            };
            let (mut i, mut ti) = (0, 0);
            for c in 0..self.map.chunk_count() {
                if w.dispatches[i..].first().is_none_or(|d| d.chunk != c) {
                    continue;
                }
                let chunk = self.map.chunk(&ctx, c, &data, &bind)?;
                let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("fine chunk") });
                {
                    let mut pass = ctx.begin_pass(&mut enc, "fine chunk")?;
                    while i < w.dispatches.len() && w.dispatches[i].chunk == c {
                        let d = &w.dispatches[i];
                        let (kernel, groups) = match d.kernel {
                            Kernel::Small => {
                                let n = fps[i].pairs.div_ceil(PAIRS_PER_GROUP as u32);
                                (counters.small_workgroups, counters.small_dispatches) =
                                    (counters.small_workgroups + n as u64, counters.small_dispatches + 1);
                                (&ctx.kernels.tree_similarity_small, n)
                            }
                            Kernel::Large => {
                                let n = fps[i].pairs;
                                (counters.large_workgroups, counters.large_dispatches) =
                                    (counters.large_workgroups + n as u64, counters.large_dispatches + 1);
                                (&ctx.kernels.tree_similarity, n)
                            }
                        };
                        pass.set_pipeline(&kernel.pipeline);
                        pass.set_bind_group(0, Some(&group), &[self.passes.offset(i)]);
                        pass.set_bind_group(1, Some(&chunk), &[]);
                        pass.dispatch_workgroups(groups.min(row), groups.div_ceil(row), 1);
                        if let (Some(g), Some(ps)) = (&g_topk, &d.topk) {
                            TopK::record(&ctx, &mut pass, g, self.topk_passes.offset(ti), ps);
                            ti += 1;
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
        })?;
        self.counters = counters;
        got
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `small_partner(n)` is the largest m with `fits_small(n, m)`, or `None` when none fits.
    #[test]
    fn small_partner_is_the_largest_forest_that_fits() {
        for n in 0..300 {
            let largest = (0..300).filter(|&m| fits_small(n, m)).max();
            assert_eq!(small_partner(n), largest, "query of {n} trees");
            if let Some(m) = largest {
                assert!((0..=m).all(|k| fits_small(n, k)), "every smaller forest fits too ({n})");
            }
        }
    }
}
