//! GPU executor of the verification's mutual-nearest-neighbour search (`mnn_match.wgsl`): the
//! batch's query keypoints and the keypoints of every reference its pairs name are uploaded once
//! per batch (packed int8), one dispatch per run of up to 65,535 pairs scores both directions of
//! every pair, and only the best column and dot product of every row come back. RANSAC then runs
//! on the CPU (`verify::verify_from_best`): its sampling is sequential and its input small.

use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::device::buffers::Reused;
use crate::device::context::{GpuContext, GpuError};
use crate::verify::best_columns::BestColumns;
use semlook_kernels::abi::{MnnPair, MnnParams};
use semlook_kernels::mnn_match::{pack, MAX_WORDS, ROWS};
use std::collections::HashMap;
use std::sync::Arc;

/// Pairs per dispatch: the largest workgroup count of one dimension a device must support.
const PAIRS_PER_DISPATCH: usize = 65_535;

#[derive(Default)]
struct Buffers {
    pairs: Reused,
    queries: Reused,
    refs: Reused,
    best: Reused,
    best_dot: Reused,
}

/// Executor of the mutual-nearest-neighbour search between keypoints of (query, reference)
/// pairs on the device.
pub struct MnnGpu {
    ctx: Arc<GpuContext>,
    /// The parameter buffer, made with the first batch (never on a lost device).
    params: Option<wgpu::Buffer>,
    buffers: Buffers,
}

impl MnnGpu {
    /// An executor on `ctx`; its buffers are made with the first batch.
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        MnnGpu { ctx, params: None, buffers: Buffers::default() }
    }

    /// The best columns of every (query, reference) pair, as [`crate::verify::best_columns::best_columns`]
    /// gives them on the CPU (bit for bit: the arithmetic is integer).
    pub fn best_columns(&mut self, queries: &DescriptorSet, refs: &dyn RefSource, pairs: &[(u32, u32)]) -> Result<Vec<BestColumns>, GpuError> {
        let dim = queries.keypoint_dim;
        let fail = |reason: String| GpuError::Failed { what: "keypoint matching".into(), reason };
        if pairs.is_empty() || dim == 0 {
            return Ok(vec![BestColumns::default(); pairs.len()]);
        }
        if !dim.is_multiple_of(4) || dim / 4 > MAX_WORDS || refs.keypoint_dim() != dim {
            return Err(fail(format!(
                "descriptors of {dim} values (the references' {}); the kernel takes multiples of 4 up to {}",
                refs.keypoint_dim(),
                4 * MAX_WORDS
            )));
        }
        let words = dim / 4;
        let ctx = self.ctx.clone();
        // the queries' keypoints as they are laid out in the set; each named reference's once
        let query_words = pack(&queries.keypoint_descriptors);
        let mut ref_at: HashMap<u32, (u32, u32)> = HashMap::new();
        let mut ref_desc: Vec<i8> = Vec::new();
        for &(_, r) in pairs {
            ref_at.entry(r).or_insert_with(|| {
                let k = refs.keypoints(r as usize);
                let start = (ref_desc.len() / dim) as u32;
                ref_desc.extend_from_slice(k.descriptors);
                (start, k.len() as u32)
            });
        }
        let ref_words = pack(&ref_desc);
        let table: Vec<MnnPair> = pairs
            .iter()
            .map(|&(q, r)| {
                let (a, b) = (queries.keypoint_offsets[q as usize], queries.keypoint_offsets[q as usize + 1]);
                let (rs, rl) = ref_at[&r];
                MnnPair { query_start: a, query_len: b - a, ref_start: rs, ref_len: rl }
            })
            .collect();
        let max_kp = table.iter().map(|p| p.query_len.max(p.ref_len)).max().unwrap_or(0).max(1);
        for (what, bytes) in [("query keypoints", query_words.len() * 4), ("reference keypoints", ref_words.len() * 4)] {
            ctx.check_binding(what, bytes as u64)?;
        }
        let chunk = PAIRS_PER_DISPATCH.min((ctx.binding_limit() as usize / (2 * max_kp as usize * 4)).max(1));
        ctx.check_lost()?;
        let params_buf = self.params.get_or_insert_with(|| ctx.uniform("mnn params", &MnnParams { pairs: 0, words: 0, max_keypoints: 0, _pad: 0 }));
        let b = &mut self.buffers;
        let mut out = Vec::with_capacity(pairs.len());
        ctx.scoped("keypoint matching", || -> Result<(), GpuError> {
            let qb = b.queries.upload(&ctx, "query keypoints", bytemuck::cast_slice(&query_words));
            let rb = b.refs.upload(&ctx, "reference keypoints", bytemuck::cast_slice(&ref_words));
            for part in table.chunks(chunk) {
                let n = part.len();
                let params = MnnParams { pairs: n as u32, words: words as u32, max_keypoints: max_kp, _pad: 0 };
                ctx.write(params_buf, 0, bytemuck::bytes_of(&params));
                let pb = b.pairs.upload(&ctx, "keypoint pairs", bytemuck::cast_slice(part));
                let rows = n * 2 * max_kp as usize;
                let best = b.best.get(&ctx, "best columns", (rows * 4) as u64);
                let best_dot = b.best_dot.get(&ctx, "best dot products", (rows * 4) as u64);
                let group = ctx.kernels.mnn_match.bind(&ctx.device, &[params_buf, pb, qb, rb, best, best_dot]);
                ctx.run("mnn_match", &[(&ctx.kernels.mnn_match.pipeline, &group, [(max_kp as usize).div_ceil(ROWS) as u32, n as u32, 2])])?;
                let bi: Vec<u32> = ctx.read_back_values(best, rows)?;
                let bd: Vec<i32> = ctx.read_back_values(best_dot, rows)?;
                for (p, pair) in part.iter().enumerate() {
                    let (q0, r0) = ((p * 2) * max_kp as usize, (p * 2 + 1) * max_kp as usize);
                    let (nq, nr) = (pair.query_len as usize, pair.ref_len as usize);
                    // a side without keypoints leaves the other's rows at no match (as the CPU path)
                    out.push(BestColumns {
                        query_best: bi[q0..q0 + nq].to_vec(),
                        query_dot: bd[q0..q0 + nq].to_vec(),
                        ref_best: bi[r0..r0 + nr].to_vec(),
                    });
                }
            }
            Ok(())
        })??;
        Ok(out)
    }
}
