//! A map kept on the device between query batches, in chunks (each buffer of a chunk within the
//! binding limit, one bind group per chunk made when the chunk is uploaded).
//!
//! - Resident: when the whole map fits the context's budget, every chunk is uploaded once and
//!   kept; the next batch against a map with the same [`SourceKey`] uploads nothing of it. A
//!   different key (another map, or a changed one) replaces it.
//! - Streamed: a map beyond the budget (or one the device fails to allocate) goes through two
//!   chunk slots: chunk c is written into slot c % 2 just before its passes are submitted, so the
//!   host's copy of chunk c + 1 overlaps the device's work on chunk c (the queue orders each
//!   write after the passes that read the slot before).

use crate::descriptors::source::SourceKey;
use crate::device::buffers::Reused;
use crate::device::context::{GpuContext, GpuError};

/// What a chunk holds: references `first..first + len` of the map in buffers of these sizes.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct ChunkPlan {
    pub first: usize,
    pub len: usize,
    pub bytes: Vec<u64>,
}

/// The data of a map's chunks, written on demand.
pub(crate) trait ChunkData {
    /// Writes the data of the chunk `plan` into `buffers` (sized as the plan says) through
    /// `ctx.write`.
    fn write(&self, ctx: &GpuContext, plan: &ChunkPlan, buffers: &[&wgpu::Buffer]) -> Result<(), GpuError>;
}

struct Slot {
    buffers: Vec<Reused>,
    group: Option<wgpu::BindGroup>,
}

/// The device side of one map: resident chunks, or two streaming slots.
#[derive(Default)]
pub(crate) struct Resident {
    key: Option<SourceKey>,
    plans: Vec<ChunkPlan>,
    chunks: Vec<(Vec<wgpu::Buffer>, wgpu::BindGroup)>,
    /// Budget bytes held by the resident chunks.
    held: u64,
    slots: Vec<Slot>,
}

impl Resident {
    /// Whether the map with `key` is resident now.
    pub fn holds(&self, key: &SourceKey) -> bool {
        self.key.as_ref() == Some(key)
    }

    pub fn is_streaming(&self) -> bool {
        self.key.is_none() && !self.plans.is_empty()
    }

    /// Bytes of the map being served (all its chunks' buffers).
    pub fn bytes(&self) -> u64 {
        self.plans.iter().flat_map(|p| &p.bytes).sum()
    }

    /// The chunks of the map being served.
    pub fn plans(&self) -> &[ChunkPlan] {
        &self.plans
    }

    /// Makes `key`'s map ready: nothing to do if it is resident; else plans its chunks (`plan`),
    /// uploads every chunk when the map fits the budget and the device allocates it, and
    /// otherwise prepares streaming. `data` gives the chunks' contents; `bind` makes a chunk's
    /// bind group from its buffers. The key must name everything the chunks hold.
    pub fn prepare(
        &mut self,
        ctx: &GpuContext,
        key: SourceKey,
        plan: impl FnOnce() -> Vec<ChunkPlan>,
        data: &dyn ChunkData,
        bind: &dyn Fn(&[&wgpu::Buffer]) -> wgpu::BindGroup,
    ) -> Result<(), GpuError> {
        if self.holds(&key) {
            return Ok(());
        }
        self.drop_resident(ctx);
        let plans = plan();
        let total: u64 = plans.iter().flat_map(|p| &p.bytes).sum();
        self.plans = plans;
        if ctx.reserve(total) {
            match self.upload_all(ctx, data, bind) {
                Ok(chunks) => {
                    (self.chunks, self.held, self.key) = (chunks, total, Some(key));
                    return Ok(());
                }
                Err(GpuError::OutOfMemory(what)) => {
                    ctx.release(total);
                    log::warn!("{}: out of memory keeping the map resident ({what}); streaming it instead", ctx.describe());
                }
                Err(e) => {
                    ctx.release(total);
                    return Err(e);
                }
            }
        }
        Ok(())
    }

    fn upload_all(
        &self,
        ctx: &GpuContext,
        data: &dyn ChunkData,
        bind: &dyn Fn(&[&wgpu::Buffer]) -> wgpu::BindGroup,
    ) -> Result<Vec<(Vec<wgpu::Buffer>, wgpu::BindGroup)>, GpuError> {
        let mut chunks = Vec::with_capacity(self.plans.len());
        for plan in &self.plans {
            let chunk = ctx.scoped("uploading a resident map chunk", || -> Result<_, GpuError> {
                let buffers: Vec<wgpu::Buffer> = plan.bytes.iter().map(|&b| ctx.storage("resident map chunk", b)).collect();
                let refs: Vec<&wgpu::Buffer> = buffers.iter().collect();
                data.write(ctx, plan, &refs)?;
                let group = bind(&refs);
                Ok((buffers, group))
            })??;
            chunks.push(chunk);
        }
        Ok(chunks)
    }

    fn drop_resident(&mut self, ctx: &GpuContext) {
        ctx.release(std::mem::take(&mut self.held));
        self.chunks.clear();
        self.key = None;
    }

    /// Forgets the resident map (its next batch uploads it again) and frees its memory.
    pub fn forget(&mut self, ctx: &GpuContext) {
        self.drop_resident(ctx);
        self.plans.clear();
    }

    pub fn chunk_count(&self) -> usize {
        self.plans.len()
    }

    /// The bind group of chunk `c`, ready for its passes: the resident chunk's, or slot c % 2's
    /// with chunk c written into it.
    pub fn chunk(
        &mut self,
        ctx: &GpuContext,
        c: usize,
        data: &dyn ChunkData,
        bind: &dyn Fn(&[&wgpu::Buffer]) -> wgpu::BindGroup,
    ) -> Result<wgpu::BindGroup, GpuError> {
        if let Some((_, group)) = self.chunks.get(c) {
            return Ok(group.clone());
        }
        let n = self.plans[c].bytes.len();
        while self.slots.len() < 2 {
            self.slots.push(Slot { buffers: (0..n).map(|_| Reused::default()).collect(), group: None });
        }
        // every slot buffer as large as the largest chunk's, so slots are allocated once
        let sizes: Vec<u64> = (0..n).map(|i| self.plans.iter().map(|p| p.bytes[i]).max().unwrap_or(4)).collect();
        let slot = &mut self.slots[c % 2];
        let before: Vec<Option<wgpu::Buffer>> = slot.buffers.iter().map(|r| r.current().cloned()).collect();
        let buffers: Vec<wgpu::Buffer> = slot.buffers.iter_mut().zip(&sizes).map(|(r, &s)| r.get(ctx, "streamed map chunk", s).clone()).collect();
        let regrown = before.iter().zip(&buffers).any(|(b, n)| b.as_ref() != Some(n));
        let refs: Vec<&wgpu::Buffer> = buffers.iter().collect();
        let group = match slot.group.take() {
            Some(g) if !regrown => g,
            _ => bind(&refs),
        };
        let group = slot.group.insert(group).clone();
        data.write(ctx, &self.plans[c], &refs)?;
        Ok(group)
    }
}
