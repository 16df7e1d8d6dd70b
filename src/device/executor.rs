//! What the networks' device executors (XFeat's, the embedding's) share: their counters, the one
//! uniform buffer holding every pass's parameters at dynamic offsets, and the submission that
//! records a plan's passes and reads its outputs back through the executor's own staging buffer.

use super::context::{GpuContext, GpuError};
use std::sync::atomic::{AtomicU64, Ordering};

/// What a network's device executor did since it was made: bytes written to the device (weights,
/// parameters, frames), bytes read back, buffers created (every kind, the read-back buffer
/// included), frames run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ExecutorCounters {
    /// Bytes written to the device: weights, parameters and frames.
    pub bytes_uploaded: u64,
    /// Bytes read back from the device.
    pub bytes_read_back: u64,
    /// Device buffers created, the read-back buffer included.
    pub buffers_created: u64,
    /// Frames run.
    pub frames: u64,
}

/// [`ExecutorCounters`] as an executor shared between threads keeps them.
#[derive(Default)]
pub(crate) struct Counters {
    uploaded: AtomicU64,
    read_back: AtomicU64,
    created: AtomicU64,
    frames: AtomicU64,
}

impl Counters {
    pub(crate) fn uploaded(&self, bytes: u64) {
        self.uploaded.fetch_add(bytes, Ordering::Relaxed);
    }
    pub(crate) fn read_back(&self, bytes: u64) {
        self.read_back.fetch_add(bytes, Ordering::Relaxed);
    }
    pub(crate) fn created(&self, buffers: u64) {
        self.created.fetch_add(buffers, Ordering::Relaxed);
    }
    pub(crate) fn frame(&self) {
        self.frames.fetch_add(1, Ordering::Relaxed);
    }
    pub(crate) fn get(&self) -> ExecutorCounters {
        ExecutorCounters {
            bytes_uploaded: self.uploaded.load(Ordering::Relaxed),
            bytes_read_back: self.read_back.load(Ordering::Relaxed),
            buffers_created: self.created.load(Ordering::Relaxed),
            frames: self.frames.load(Ordering::Relaxed),
        }
    }
}

/// Every pass's parameters in one uniform buffer, `stride` bytes apart (the largest uniform of
/// the plan's shader, `max_len`, rounded up to the device's offset alignment): pass i binds at
/// offset i x stride. Returns the buffer, its stride and its bytes (written).
pub(crate) fn pass_parameters<'a>(
    ctx: &GpuContext,
    label: &str,
    params: impl ExactSizeIterator<Item = &'a [u8]>,
    max_len: usize,
) -> (wgpu::Buffer, u64, u64) {
    let stride = (max_len as u64).next_multiple_of(ctx.uniform_offset_alignment() as u64);
    let mut bytes = vec![0u8; params.len().max(1) * stride as usize];
    for (i, p) in params.enumerate() {
        bytes[i * stride as usize..][..p.len()].copy_from_slice(p);
    }
    let buf = ctx.uniform_buffer(label, bytes.len() as u64);
    ctx.write(&buf, 0, &bytes);
    (buf, stride, bytes.len() as u64)
}

/// A buffer the host maps to read an executor's outputs (`bytes`, at least 4).
pub(crate) fn staging(ctx: &GpuContext, label: &str, bytes: u64) -> wgpu::Buffer {
    ctx.count_buffer();
    ctx.device.create_buffer(&wgpu::BufferDescriptor {
        label: Some(label),
        size: bytes.max(4).next_multiple_of(4),
        usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
        mapped_at_creation: false,
    })
}

/// Submits `enc` (whose last commands copy the outputs into `staging`), waits, and reads the
/// first `bytes` of `staging` as 32-bit values.
pub(crate) fn submit_and_read<T: bytemuck::Pod>(
    ctx: &GpuContext,
    enc: wgpu::CommandEncoder,
    staging: &wgpu::Buffer,
    bytes: u64,
) -> Result<Vec<T>, GpuError> {
    let fail = |reason: String| GpuError::Failed { what: "reading a network's outputs back".into(), reason };
    ctx.queue.submit([enc.finish()]);
    let slice = staging.slice(..bytes.max(4));
    let (tx, rx) = std::sync::mpsc::channel();
    slice.map_async(wgpu::MapMode::Read, move |r| {
        let _ = tx.send(r);
    });
    ctx.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError::DeviceLost(format!("waiting for the queue: {e}")))?;
    rx.recv().map_err(|_| fail("map callback dropped".into()))?.map_err(|e| fail(e.to_string()))?;
    let data: Vec<T> = bytemuck::pod_collect_to_vec(&slice.get_mapped_range().map_err(|e| fail(e.to_string()))?[..bytes as usize]);
    staging.unmap();
    ctx.check_lost()?;
    Ok(data)
}

/// One kernel of a network's shader run alone on host data, the device side of the kernels'
/// tests against their twins: `params` (at most `uniform_max` bytes) bound at offset 0, `inputs`
/// uploaded in binding order after it, an output of `out_len` values last, `grid` workgroups
/// (none dispatched where a dimension is 0: the empty cases), the output read back.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run_one(
    ctx: &GpuContext,
    entry: &str,
    k: &super::kernels::Kernel,
    params: &[u8],
    uniform_max: usize,
    grid: [u32; 3],
    inputs: &[&[f32]],
    out_len: usize,
) -> Result<Vec<f32>, GpuError> {
    if params.len() > uniform_max {
        return Err(GpuError::Failed {
            what: format!("running {entry}"),
            reason: format!("{} bytes of parameters, {uniform_max} at most", params.len()),
        });
    }
    if let Some(&d) = grid.iter().find(|&&d| d > ctx.max_workgroups()) {
        return Err(GpuError::LimitsTooSmall {
            adapter: ctx.describe(),
            what: format!("{entry} workgroups"),
            needed: d as u64,
            available: ctx.max_workgroups() as u64,
        });
    }
    ctx.scoped(&format!("running {entry}"), || -> Result<Vec<f32>, GpuError> {
        let (pbuf, _, _) = pass_parameters(ctx, "kernel parameters", std::iter::once(params), uniform_max);
        let bufs: Vec<wgpu::Buffer> = inputs
            .iter()
            .map(|d| {
                let b = ctx.storage("kernel input", (d.len() * 4) as u64);
                if !d.is_empty() {
                    ctx.write(&b, 0, bytemuck::cast_slice(d));
                }
                b
            })
            .collect();
        let out = ctx.storage("kernel output", (out_len * 4) as u64);
        let mut bound: Vec<&wgpu::Buffer> = vec![&pbuf];
        bound.extend(bufs.iter());
        bound.push(&out);
        let g = k.bind(&ctx.device, &bound);
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(entry) });
        if !grid.contains(&0) {
            let mut pass = ctx.begin_pass(&mut enc, entry)?;
            pass.set_pipeline(&k.pipeline);
            pass.set_bind_group(0, Some(&g), &[0]);
            pass.dispatch_workgroups(grid[0], grid[1], grid[2]);
        }
        ctx.queue.submit([enc.finish()]);
        ctx.read_back_values(&out, out_len)
    })?
}
