//! Kernel timing by timestamp queries: every compute pass the executors record writes a timestamp
//! when it begins and when it ends; the differences, summed, are the kernels' time (without the
//! host's recording, uploads and read-backs). Used where the adapter has `TIMESTAMP_QUERY`.

use crate::error::GpuError;

/// Reads `bytes` of a buffer back to the host (the context's read-back).
pub type ReadBack<'a> = &'a dyn Fn(&wgpu::Buffer, u64) -> Result<Vec<u8>, GpuError>;

/// Queries per set (two per pass). When they run out, the set is resolved and read back (one
/// wait for the queue) and reused; 512 keeps that to one wait per 256 passes.
const QUERIES: u32 = 512;

pub(crate) struct Timer {
    set: wgpu::QuerySet,
    resolve: wgpu::Buffer,
    /// Queries written since the last read-back.
    used: u32,
    period_ns: f64,
    total_ns: f64,
}

impl Timer {
    pub fn new(device: &wgpu::Device, queue: &wgpu::Queue) -> Timer {
        Timer {
            set: device.create_query_set(&wgpu::QuerySetDescriptor {
                label: Some("kernel timestamps"),
                ty: wgpu::QueryType::Timestamp,
                count: QUERIES,
            }),
            resolve: device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("resolved timestamps"),
                size: QUERIES as u64 * 8,
                usage: wgpu::BufferUsages::QUERY_RESOLVE | wgpu::BufferUsages::COPY_SRC,
                mapped_at_creation: false,
            }),
            used: 0,
            period_ns: queue.get_timestamp_period() as f64,
            total_ns: 0.0,
        }
    }

    /// The query set and the index of the next pass's first timestamp (its end goes to the next
    /// index). Call once per command encoder, before its one timed pass: a full set is read back
    /// first, and that only sees passes already submitted.
    pub fn next_writes(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, read: ReadBack) -> Result<(&wgpu::QuerySet, u32), GpuError> {
        if self.used + 2 > QUERIES {
            self.flush(device, queue, read)?;
        }
        let i = self.used;
        self.used += 2;
        Ok((&self.set, i))
    }

    /// Resolves the queries written so far, reads them back and adds their passes' durations.
    fn flush(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, read: ReadBack) -> Result<(), GpuError> {
        if self.used == 0 {
            return Ok(());
        }
        let mut enc = device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("resolve timestamps") });
        enc.resolve_query_set(&self.set, 0..self.used, &self.resolve, 0);
        queue.submit([enc.finish()]);
        let raw = read(&self.resolve, self.used as u64 * 8)?;
        let ticks: Vec<u64> = bytemuck::pod_collect_to_vec(&raw[..self.used as usize * 8]);
        self.total_ns += ticks.chunks_exact(2).map(|p| p[1].saturating_sub(p[0]) as f64).sum::<f64>() * self.period_ns;
        self.used = 0;
        Ok(())
    }

    /// Seconds of kernel time since the last call.
    pub fn take_seconds(&mut self, device: &wgpu::Device, queue: &wgpu::Queue, read: ReadBack) -> Result<f64, GpuError> {
        self.flush(device, queue, read)?;
        Ok(std::mem::take(&mut self.total_ns) * 1e-9)
    }
}
