//! The three heavy operations of matching as a trait ([`Stages`]), and their CPU implementation
//! ([`CpuStages`]): the coarse scan, the tree similarity of pairs or of the whole map, the fused
//! coarse scan and the verification of pairs. The GPU's is `gpu::GpuStages`.

use super::coarse::{coarse_topk, fused_topk_cpu, FusedWeights};
use super::coarse_cpu::stream_topk;
use crate::descriptors::source::{GlobalSource, RefSource};
use crate::descriptors::DescriptorSet;
use crate::error::Result;
use crate::verify::{verify_pairs_cpu, Verified, VerifyParams};
use rayon::prelude::*;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::ssim_topk;
use semlook_kernels::tree_similarity::{tree_similarity, TreeSimScratch};

/// The three heavy operations of matching, implemented by the CPU path ([`CpuStages`]) and by
/// the GPU path (`gpu::GpuStages`); [`match_with`](super::match_with) composes them the same way for both.
pub trait Stages {
    /// For each query, the `k` best references by SSIM (best first).
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
    /// Tree-set similarity of each (query, reference) pair.
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>>;
    /// For each query, the `k` best references of the whole map by tree-set similarity.
    fn fine_topk(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>>;
    /// For each query, the `k` best references by cos(appearance) + `w.embedding` x
    /// cos(embeddings) + `w.global` x SSIM.
    fn fused_coarse(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        p: &SsimParams,
        w: FusedWeights,
        k: usize,
        tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>>;
    /// Geometric verification of each (query, reference) pair.
    fn verify_pairs(&mut self, p: &VerifyParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<Verified>>;
}

/// The CPU reference path (rayon over queries or pairs).
pub struct CpuStages;

impl Stages for CpuStages {
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(coarse_topk(refs, queries, p, k, tile))
    }
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>> {
        Ok(pairs
            .par_iter()
            .map_init(TreeSimScratch::default, |s, &(q, r)| tree_similarity(p, queries.forest(q as usize), refs.forest(r as usize), s))
            .collect())
    }
    /// Tree similarities of all queries against one tile of references at a time, folded into
    /// the per-query top-K by `topk_merge`, as the GPU path does.
    fn fine_topk(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(stream_topk(queries.len(), refs.len(), k, tile, ssim_topk::topk_merge, |tp, scores| {
            let (start, t) = (tp.tile_start as usize, tp.tile_len as usize);
            scores.par_iter_mut().enumerate().for_each_init(TreeSimScratch::default, |scratch, (i, s)| {
                *s = tree_similarity(p, queries.forest(i / t), refs.forest(start + i % t), scratch);
            });
        }))
    }
    fn fused_coarse(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        p: &SsimParams,
        w: FusedWeights,
        k: usize,
        tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>> {
        Ok(fused_topk_cpu(refs, queries, p, w, k, tile))
    }
    /// Mutual nearest neighbours by the fast path (a matrix product per pair), or LighterGlue; then RANSAC.
    fn verify_pairs(&mut self, p: &VerifyParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<Verified>> {
        verify_pairs_cpu(p, &|q| queries.keypoints(q as usize), &|r| refs.keypoints(r as usize), pairs)
    }
}
