//! GPU executor for per-object VLAD of a batch of frames: all frames' keypoint descriptors
//! (sorted by object) and object runs are concatenated, assigned to centres by `vlad_assign`,
//! and aggregated with normalisations by `vlad_accumulate`, one workgroup per object.

use super::buffers::Reused;
use super::context::{GpuContext, GpuError};
use crate::appearance::check_vlad_input;
use crate::appearance::vlad::{Codebook, VladNorm};
use crate::kernels::abi::VladParams;
use crate::kernels::vlad_accumulate::MAX_CENTRES;
use std::sync::Arc;

/// Buffers kept between batches.
#[derive(Default)]
struct Buffers {
    centres: Reused,
    descriptors: Reused,
    assignment: Reused,
    offsets: Reused,
    out: Reused,
}

pub struct VladGpu {
    ctx: Arc<GpuContext>,
    buffers: Buffers,
}

impl VladGpu {
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        VladGpu { ctx, buffers: Buffers::default() }
    }

    /// VLAD vectors of every run of every frame: `frames` holds (descriptors sorted by run,
    /// run offsets) per frame; returns the vectors per frame.
    pub fn run(&mut self, codebook: &Codebook, norm: VladNorm, frames: &[(&[f32], &[u32])]) -> Result<Vec<Vec<f32>>, GpuError> {
        let ctx = self.ctx.clone();
        if codebook.k > MAX_CENTRES {
            return Err(GpuError::LimitsTooSmall {
                adapter: ctx.describe(),
                what: "VLAD centres".into(),
                needed: codebook.k as u64,
                available: MAX_CENTRES as u64,
            });
        }
        let d = codebook.dim;
        let mut descs: Vec<f32> = Vec::new();
        let mut offsets: Vec<u32> = vec![0];
        let mut object_counts = Vec::with_capacity(frames.len());
        for (f, (fd, fo)) in frames.iter().enumerate() {
            check_vlad_input(fd, fo, codebook)
                .map_err(|r| GpuError::Failed { what: "VLAD aggregation".into(), reason: format!("frame {f}: {r}") })?;
            let base = (descs.len() / d) as u32;
            offsets.extend(fo[1..].iter().map(|o| o + base));
            descs.extend_from_slice(fd);
            object_counts.push(fo.len() - 1);
        }
        let (n, objects) = (descs.len() / d, offsets.len() - 1);
        let out_len = objects * codebook.k * d;
        for (what, bytes) in [("keypoint descriptors", descs.len() * 4), ("VLAD vectors", out_len * 4)] {
            ctx.check_binding(what, bytes as u64)?;
        }
        let k = &ctx.kernels;
        let b = &mut self.buffers;
        let vectors: Vec<f32> = ctx.scoped("VLAD aggregation", || -> Result<Vec<f32>, GpuError> {
            let p = VladParams::new(codebook.k, codebook.dim, n, objects, norm.power, norm.intra);
            let params = ctx.uniform("vlad params", &p);
            let centres = b.centres.upload(&ctx, "centres", bytemuck::cast_slice(&codebook.centres));
            let desc_buf = b.descriptors.upload(&ctx, "descriptors", bytemuck::cast_slice(&descs));
            let assign = b.assignment.get(&ctx, "assignment", (n * 4) as u64);
            let off = b.offsets.upload(&ctx, "object offsets", bytemuck::cast_slice(&offsets));
            let out = b.out.get(&ctx, "vlad vectors", (out_len * 4) as u64);
            let g1 = k.vlad_assign.bind(&ctx.device, &[&params, centres, desc_buf, assign]);
            let g2 = k.vlad_accumulate.bind(&ctx.device, &[&params, centres, desc_buf, assign, off, out]);
            let groups = (n as u32).div_ceil(64);
            let o = objects as u32;
            ctx.run(
                "vlad",
                &[
                    (&k.vlad_assign.pipeline, &g1, [groups.min(65_535), groups.div_ceil(65_535), 1]),
                    (&k.vlad_accumulate.pipeline, &g2, [o.min(65_535), o.div_ceil(65_535), 1]),
                ],
            )?;
            ctx.read_back_values(out, out_len)
        })??;
        let mut res = Vec::with_capacity(frames.len());
        let (mut at, per) = (0usize, codebook.k * d);
        for &count in &object_counts {
            res.push(vectors[at * per..(at + count) * per].to_vec());
            at += count;
        }
        Ok(res)
    }
}
