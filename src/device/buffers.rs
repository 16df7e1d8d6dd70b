//! Device buffers of the executors: storage and uniform buffers, buffers kept between batches
//! ([`Reused`]), the parameter buffer of a batch's passes ([`PassBuffer`], one entry per pass at
//! dynamic offsets) and typed read-backs. Every write goes through [`GpuContext::write`], which
//! counts the bytes.

use super::context::{GpuContext, GpuError};

/// A storage buffer kept by an executor between batches, regrown only when a batch needs more.
#[derive(Default)]
pub(crate) struct Reused {
    buf: Option<wgpu::Buffer>,
    /// Buffers made so far: a bind group made with generation g is stale once this moves on.
    generation: u64,
}

impl Reused {
    /// The buffer, at least `bytes` long (contents unspecified).
    pub fn get(&mut self, ctx: &GpuContext, label: &str, bytes: u64) -> &wgpu::Buffer {
        let need = bytes.max(4).next_multiple_of(4);
        if self.buf.as_ref().is_some_and(|b| b.size() < need) {
            self.buf = None;
        }
        if self.buf.is_none() {
            self.generation += 1;
        }
        self.buf.get_or_insert_with(|| ctx.storage(label, need))
    }

    /// The buffer as it is now, if any.
    pub fn current(&self) -> Option<&wgpu::Buffer> {
        self.buf.as_ref()
    }

    /// Which buffer [`Reused::get`] returned last (changes whenever it made a new one).
    pub fn generation(&self) -> u64 {
        self.generation
    }

    /// The buffer holding `data` (written through the queue).
    pub fn upload(&mut self, ctx: &GpuContext, label: &str, data: &[u8]) -> &wgpu::Buffer {
        let b = self.get(ctx, label, data.len() as u64);
        ctx.write(b, 0, data);
        b
    }
}

/// One uniform buffer holding a batch's per-pass parameters, each at a dynamic offset (the
/// device's uniform offset alignment apart): written once per batch, bound once, selected per
/// dispatch by its offset. No buffer or bind group is made per pass.
pub(crate) struct PassBuffer<T> {
    buf: Option<wgpu::Buffer>,
    stride: u64,
    _t: std::marker::PhantomData<T>,
}

impl<T: bytemuck::Pod> PassBuffer<T> {
    pub fn new(ctx: &GpuContext) -> Self {
        PassBuffer {
            buf: None,
            stride: (std::mem::size_of::<T>() as u64).next_multiple_of(ctx.uniform_offset_alignment() as u64),
            _t: std::marker::PhantomData,
        }
    }

    /// Writes `entries` (one write; the buffer regrows when a batch has more passes).
    pub fn write(&mut self, ctx: &GpuContext, entries: &[T]) -> &wgpu::Buffer {
        let need = (entries.len().max(1) as u64) * self.stride;
        if self.buf.as_ref().is_some_and(|b| b.size() < need) {
            self.buf = None;
        }
        let mut bytes = vec![0u8; entries.len() * self.stride as usize];
        for (e, dst) in entries.iter().zip(bytes.chunks_exact_mut(self.stride as usize)) {
            dst[..std::mem::size_of::<T>()].copy_from_slice(bytemuck::bytes_of(e));
        }
        let b = self.buf.get_or_insert_with(|| {
            ctx.count_buffer();
            ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("pass parameters"),
                size: need,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        });
        ctx.write(b, 0, &bytes);
        b
    }

    /// The dynamic offset of entry `i`.
    pub fn offset(&self, i: usize) -> u32 {
        (i as u64 * self.stride) as u32
    }
}

impl GpuContext {
    /// A storage buffer of `size` bytes (at least 4), copyable both ways.
    pub(crate) fn storage(&self, label: &str, size: u64) -> wgpu::Buffer {
        self.count_buffer();
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(4).next_multiple_of(4),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    pub(crate) fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        self.count_buffer();
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: (std::mem::size_of::<T>() as u64).next_multiple_of(16),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.write(&buf, 0, bytemuck::bytes_of(value));
        buf
    }

    /// A uniform buffer of `size` bytes (rounded up to 16), written by the caller.
    pub(crate) fn uniform_buffer(&self, label: &str, size: u64) -> wgpu::Buffer {
        self.count_buffer();
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.next_multiple_of(16),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        })
    }

    /// Copies `bytes` bytes of `src` back to the host (waits for the queue).
    pub(crate) fn read_back(&self, src: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, GpuError> {
        Ok(self.read_back_many(&[(src, bytes)])?.swap_remove(0))
    }

    /// Copies the first bytes of each buffer back to the host in one submission and one wait,
    /// through the context's staging buffer (kept between read-backs, regrown when one needs
    /// more); each result is its byte count rounded up to 4.
    pub(crate) fn read_back_many(&self, parts: &[(&wgpu::Buffer, u64)]) -> Result<Vec<Vec<u8>>, GpuError> {
        let sizes: Vec<u64> = parts.iter().map(|p| p.1.next_multiple_of(4).max(4)).collect();
        let total: u64 = sizes.iter().sum();
        let mut kept = self.staging.lock().unwrap_or_else(|e| e.into_inner());
        if kept.as_ref().is_some_and(|b| b.size() < total) {
            *kept = None;
        }
        let staging = kept.get_or_insert_with(|| {
            self.count_buffer();
            self.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("readback"),
                size: total,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            })
        });
        self.read_back_bytes.fetch_add(total, std::sync::atomic::Ordering::Relaxed);
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
        let mut at = 0;
        for ((src, _), &n) in parts.iter().zip(&sizes) {
            enc.copy_buffer_to_buffer(src, 0, staging, at, n);
            at += n;
        }
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, ..total, move |r| {
            let _ = tx.send(r);
        });
        self.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError::DeviceLost(format!("waiting for the queue: {e}")))?;
        rx.recv()
            .map_err(|_| GpuError::Failed { what: "reading back".into(), reason: "map callback dropped".into() })?
            .map_err(|e| GpuError::Failed { what: "reading back".into(), reason: e.to_string() })?;
        let data = staging.get_mapped_range(..total).map_err(|e| GpuError::Failed { what: "reading back".into(), reason: e.to_string() })?.to_vec();
        staging.unmap();
        self.check_lost()?;
        let mut out = Vec::with_capacity(parts.len());
        let mut at = 0;
        for n in sizes {
            out.push(data[at as usize..(at + n) as usize].to_vec());
            at += n;
        }
        Ok(out)
    }

    /// Reads back the first `n` 32-bit values (f32 or u32) of `src`.
    pub(crate) fn read_back_values<T: bytemuck::Pod>(&self, src: &wgpu::Buffer, n: usize) -> Result<Vec<T>, GpuError> {
        Ok(bytemuck::pod_collect_to_vec(&self.read_back(src, (n * 4) as u64)?[..n * 4]))
    }
}
