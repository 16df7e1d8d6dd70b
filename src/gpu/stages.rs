//! The GPU executors of an engine ([`GpuStages`]): the coarse, fine and verification stages of
//! matching on the device ([`crate::matching::Stages`]), and the encoding executors the engine's
//! GPU path drives (global descriptors, the keypoint network, VLAD).

use super::{
    appearance::NetworkSlot, coarse::CoarseMatcherGpu, embedding::EmbeddingSlot, encode::GlobalEncoderGpu, fine::FineMatcherGpu, verify::MnnGpu,
    vlad::VladGpu, GpuContext,
};
use crate::descriptors::source::{GlobalSource, RefSource};
use crate::descriptors::DescriptorSet;
use crate::error::Result;
use crate::matching::{CpuStages, Stages};
use crate::networks::lighterglue::GlueGpu;
use crate::verify::{Verified, VerifyParams};
use rayon::prelude::*;
use semlook_kernels::abi::{SsimParams, TreeSimParams};
use std::sync::Arc;

/// The GPU executors of an engine; pipelines live in the context, buffers in the executors.
pub struct GpuStages {
    /// The GPU context every executor runs in.
    pub ctx: Arc<GpuContext>,
    /// Stage calls and encode batches run here (what `Engine::gpu_calls` counts from).
    pub(crate) work: u64,
    pub(crate) encoder: GlobalEncoderGpu,
    coarse: Option<(SsimParams, CoarseMatcherGpu)>,
    fine: FineMatcherGpu,
    pub(crate) vlad: VladGpu,
    mnn: MnnGpu,
    /// The learned matcher on the device, made with the first pair it verifies.
    glue: Option<GlueGpu>,
    /// The keypoint network (native XFeat) on the device.
    pub(crate) network: NetworkSlot,
    /// The embedding network (run natively from its checkpoint) on the device.
    pub(crate) embedding: EmbeddingSlot,
    /// Most frames held decoded at once by an encoding call so far.
    pub(crate) decoded_peak: usize,
}

impl GpuStages {
    /// Executors in `ctx`, with nothing on the device yet.
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        GpuStages {
            encoder: GlobalEncoderGpu::new(ctx.clone()),
            fine: FineMatcherGpu::new(ctx.clone()),
            vlad: VladGpu::new(ctx.clone()),
            mnn: MnnGpu::new(ctx.clone()),
            glue: None,
            network: NetworkSlot::default(),
            embedding: EmbeddingSlot::default(),
            decoded_peak: 0,
            coarse: None,
            ctx,
            work: 0,
        }
    }

    /// Forgets the maps kept on the device (call after editing a map's vectors in place: the
    /// resident copy is keyed by the map's identity and sampled content, see `SourceKey`).
    pub fn forget_map(&mut self) {
        if let Some((_, c)) = &mut self.coarse {
            c.forget_map();
        }
        self.fine.forget_map();
    }

    /// Whether the last coarse map was kept resident (false: streamed, or none yet).
    pub fn coarse_map_is_resident(&self) -> bool {
        self.coarse.as_ref().is_some_and(|c| c.1.map_is_resident())
    }

    /// Whether the last fine-stage map's forests were kept resident (false: streamed).
    pub fn fine_map_is_resident(&self) -> bool {
        self.fine.map_is_resident()
    }

    /// What the fine stage's dispatches did so far (pairs and workgroups of each kernel).
    pub fn fine_counters(&self) -> super::FineCounters {
        self.fine.counters()
    }

    /// Bytes of the last maps on the device: (coarse descriptors and statistics, fine packed
    /// forests).
    pub fn map_bytes(&self) -> (u64, u64) {
        (self.coarse.as_ref().map_or(0, |c| c.1.map_bytes()), self.fine.map_bytes())
    }

    /// Most frames an encoding call has held decoded at once (at most [`crate::engine::STREAM_FRAMES`]). A test
    /// hook (the bounded-memory tests read it), not the API.
    #[doc(hidden)]
    pub fn decoded_peak(&self) -> usize {
        self.decoded_peak
    }

    /// Uploads `refs` as the coarse stage's map for SSIM parameters `p` ahead of a batch (the
    /// first batch against a map would otherwise upload it); true if it is kept resident, false
    /// if it is beyond the budget and will be streamed with every batch.
    pub fn upload_coarse_map(&mut self, refs: &dyn GlobalSource, p: &SsimParams) -> Result<bool> {
        Ok(self.coarse_for(p)?.upload_map(refs)?)
    }

    /// Frames whose keypoint network ran on the device (native XFeat) in the current executor.
    pub fn network_frames(&self) -> u64 {
        self.network.frames()
    }

    /// Frames whose embedding network ran on the device (run natively from its checkpoint) in the
    /// current executor.
    pub fn embedding_frames(&self) -> u64 {
        self.embedding.frames()
    }

    /// Kernel time since the last call, from timestamp queries (`None` without them).
    pub fn take_kernel_seconds(&self) -> Result<Option<f64>> {
        Ok(self.ctx.take_kernel_seconds()?)
    }

    fn coarse_for(&mut self, p: &SsimParams) -> Result<&mut CoarseMatcherGpu> {
        let matcher = match self.coarse.take() {
            Some(c) if c.0 == *p => c,
            _ => (*p, CoarseMatcherGpu::new(self.ctx.clone(), *p)?),
        };
        Ok(&mut self.coarse.insert(matcher).1)
    }
}

impl Stages for GpuStages {
    /// On the device the map stays resident and passes are sized by the device's limits, so
    /// `tile` (the CPU path's scratch bound) does not apply.
    fn coarse(&mut self, refs: &dyn GlobalSource, queries: &DescriptorSet, p: &SsimParams, k: usize, _tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
        self.work += 1;
        Ok(self.coarse_for(p)?.topk(queries, refs, k)?)
    }
    fn fine_pairs(&mut self, p: &TreeSimParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<f32>> {
        self.work += 1;
        Ok(self.fine.score_pairs(p, queries, refs, pairs)?)
    }
    fn fine_topk(
        &mut self,
        p: &TreeSimParams,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        k: usize,
        _tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>> {
        self.work += 1;
        Ok(self.fine.topk_all(p, queries, refs, k)?)
    }
    /// On the CPU (the whole-image appearance vectors are not on the device).
    fn fused_coarse(
        &mut self,
        refs: &dyn RefSource,
        queries: &DescriptorSet,
        p: &SsimParams,
        w: crate::matching::FusedWeights,
        k: usize,
        tile: usize,
    ) -> Result<Vec<Vec<(f32, u32)>>> {
        CpuStages.fused_coarse(refs, queries, p, w, k, tile)
    }
    /// Mutual nearest neighbours (`mnn_match`) or LighterGlue (`lighterglue.wgsl`) on the GPU,
    /// RANSAC on the CPU.
    fn verify_pairs(&mut self, p: &VerifyParams, refs: &dyn RefSource, queries: &DescriptorSet, pairs: &[(u32, u32)]) -> Result<Vec<Verified>> {
        self.work += 1;
        if p.matcher == crate::config::Matcher::Lighterglue {
            if self.glue.is_none() {
                self.glue = Some(GlueGpu::new(self.ctx.clone(), &*crate::verify::shared_lighterglue()?)?);
            }
            let glue = self.glue.as_mut().expect("made above");
            let kp: Vec<_> = pairs.iter().map(|&(q, r)| (queries.keypoints(q as usize), refs.keypoints(r as usize))).collect();
            let matches = glue.match_pairs(&p.glue, &kp)?;
            return Ok(kp.par_iter().zip(matches.par_iter()).map(|(&(q, r), m)| crate::verify::verify_from_glue(p, q, r, m)).collect());
        }
        let best = self.mnn.best_columns(queries, refs, pairs)?;
        Ok(pairs
            .par_iter()
            .zip(best.par_iter())
            .map(|(&(q, r), b)| crate::verify::verify_from_best(p, queries.keypoints(q as usize), refs.keypoints(r as usize), b))
            .collect())
    }
}
