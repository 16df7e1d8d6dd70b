//! GPU executor for per-object VLAD of a batch of frames: all frames' keypoint descriptors
//! (sorted by object) and object runs are concatenated, assigned to centres by `vlad_assign`,
//! and aggregated with normalisations by `vlad_accumulate`, one workgroup per object.

use crate::appearance::check_vlad_input;
use crate::device::buffers::Reused;
use crate::device::context::{GpuContext, GpuError};
use crate::global::vlad::{Codebook, VladNorm};
use semlook_kernels::abi::VladParams;
use semlook_kernels::vlad_accumulate::MAX_CENTRES;
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

/// The uniform, the centres on the device and the bind groups, kept between batches: the
/// centres are uploaded when the codebook changes, the parameters when a batch's sizes do, and
/// the bind groups are made again only when a buffer was regrown.
struct Kept {
    params: wgpu::Buffer,
    written: Option<VladParams>,
    centres: Vec<f32>,
    /// (bind groups of vlad_assign and vlad_accumulate, the buffers' generations they bind)
    groups: Option<([wgpu::BindGroup; 2], [u64; 5])>,
}

/// Executor of per-object VLAD aggregation on the device.
pub struct VladGpu {
    ctx: Arc<GpuContext>,
    buffers: Buffers,
    kept: Option<Kept>,
}

impl VladGpu {
    /// An executor on `ctx`; its buffers and uniform are made with the first batch.
    pub fn new(ctx: Arc<GpuContext>) -> Self {
        VladGpu { ctx, buffers: Buffers::default(), kept: None }
    }

    /// VLAD vectors of every run of every frame: `frames` holds (descriptors sorted by run,
    /// run offsets) per frame; returns the vectors per frame. A batch uploads its descriptors
    /// and run offsets (and the codebook when it changed) and reads back its vectors.
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
        let kept = self.kept.get_or_insert_with(|| Kept {
            params: ctx.uniform_buffer("vlad params", std::mem::size_of::<VladParams>() as u64),
            written: None,
            centres: Vec::new(),
            groups: None,
        });
        let vectors: Vec<f32> = ctx.scoped("VLAD aggregation", || -> Result<Vec<f32>, GpuError> {
            let p = VladParams::new(codebook.k, codebook.dim, n, objects, norm.power, norm.intra);
            if kept.written != Some(p) {
                ctx.write(&kept.params, 0, bytemuck::bytes_of(&p));
                kept.written = Some(p);
            }
            let fresh_centres = b.centres.current().is_none() || kept.centres != codebook.centres;
            let centres_len = (codebook.centres.len() * 4) as u64;
            b.centres.get(&ctx, "centres", centres_len);
            if fresh_centres {
                ctx.write(b.centres.current().expect("made above"), 0, bytemuck::cast_slice(&codebook.centres));
                kept.centres.clone_from(&codebook.centres);
            }
            b.descriptors.upload(&ctx, "descriptors", bytemuck::cast_slice(&descs));
            b.assignment.get(&ctx, "assignment", (n * 4) as u64);
            b.offsets.upload(&ctx, "object offsets", bytemuck::cast_slice(&offsets));
            b.out.get(&ctx, "vlad vectors", (out_len * 4) as u64);
            let gens = [b.centres.generation(), b.descriptors.generation(), b.assignment.generation(), b.offsets.generation(), b.out.generation()];
            if kept.groups.as_ref().is_none_or(|g| g.1 != gens) {
                fn cur(r: &Reused) -> &wgpu::Buffer {
                    r.current().expect("made above")
                }
                let (centres, desc, assign, off, out) = (cur(&b.centres), cur(&b.descriptors), cur(&b.assignment), cur(&b.offsets), cur(&b.out));
                let g1 = k.vlad_assign.bind(&ctx.device, &[&kept.params, centres, desc, assign]);
                let g2 = k.vlad_accumulate.bind(&ctx.device, &[&kept.params, centres, desc, assign, off, out]);
                kept.groups = Some(([g1, g2], gens));
            }
            let [g1, g2] = &kept.groups.as_ref().expect("made above").0;
            let groups = (n as u32).div_ceil(64);
            let o = objects as u32;
            ctx.run(
                "vlad",
                &[
                    (&k.vlad_assign.pipeline, g1, [groups.min(65_535), groups.div_ceil(65_535), 1]),
                    (&k.vlad_accumulate.pipeline, g2, [o.min(65_535), o.div_ceil(65_535), 1]),
                ],
            )?;
            ctx.read_back_values(b.out.current().expect("made above"), out_len)
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
