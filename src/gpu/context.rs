//! The GPU context: device, queue, what adapter they came from, and the effective limits the
//! executors plan with. Either created here (`GpuContext::new`) or wrapped around a host
//! application's device (`GpuContext::from_device`), so the engine can run inside someone else's
//! wgpu context. Every GPU operation runs inside error scopes, so validation errors, out-of-memory
//! and device loss come back as typed [`GpuError`]s instead of panics.

use super::kernels::Kernels;
use std::sync::{Arc, Mutex};

#[derive(Debug, thiserror::Error)]
pub enum GpuError {
    #[error("no GPU adapter found{0}")]
    NoAdapter(String),
    #[error("adapter {adapter}: cannot create a device: {reason}")]
    Device { adapter: String, reason: String },
    #[error("GPU device lost: {0}")]
    DeviceLost(String),
    #[error("GPU out of memory while {0}")]
    OutOfMemory(String),
    #[error("adapter {adapter}: {what} needs {needed} but the limit is {available}")]
    LimitsTooSmall { adapter: String, what: String, needed: u64, available: u64 },
    #[error("shader {name}: {message}")]
    Shader { name: String, message: String },
    #[error("GPU error while {what}: {reason}")]
    Failed { what: String, reason: String },
}

/// A storage buffer kept by an executor between batches, regrown only when a batch needs more.
#[derive(Default)]
pub(crate) struct Reused(Option<wgpu::Buffer>);

impl Reused {
    /// The buffer, at least `bytes` long (contents unspecified).
    pub fn get(&mut self, ctx: &GpuContext, label: &str, bytes: u64) -> &wgpu::Buffer {
        let need = bytes.max(4).next_multiple_of(4);
        if self.0.as_ref().is_none_or(|b| b.size() < need) {
            self.0 = Some(ctx.storage(label, need));
        }
        self.0.as_ref().unwrap()
    }

    /// The buffer holding `data` (written through the queue).
    pub fn upload(&mut self, ctx: &GpuContext, label: &str, data: &[u8]) -> &wgpu::Buffer {
        let b = self.get(ctx, label, data.len() as u64);
        if !data.is_empty() {
            ctx.queue.write_buffer(b, 0, data);
        }
        b
    }
}

/// How to pick an adapter and how much of it to use.
#[derive(Debug, Clone)]
pub struct GpuOptions {
    /// Accept software adapters (lavapipe / llvmpipe): right for tests, slow for work.
    pub allow_software: bool,
    /// Use at most this many bytes per storage binding (lower than the device's to force tiling).
    pub max_binding_size: Option<u64>,
    /// Backends to try. Default: Vulkan, Metal, DX12 (not GL: wgpu would silently fall back to
    /// llvmpipe through it).
    pub backends: wgpu::Backends,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions { allow_software: true, max_binding_size: None, backends: wgpu::Backends::PRIMARY }
    }
}

/// A device and queue with the engine's pipelines, ready for the executors.
pub struct GpuContext {
    pub device: wgpu::Device,
    pub queue: wgpu::Queue,
    pub info: wgpu::AdapterInfo,
    binding_limit: u64,
    lost: Arc<Mutex<Option<String>>>,
    pub(crate) kernels: Kernels,
}

impl std::fmt::Debug for GpuContext {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "GpuContext({})", self.describe())
    }
}

fn adapter_name(info: &wgpu::AdapterInfo) -> String {
    format!("{} ({:?}, {:?})", info.name, info.backend, info.device_type)
}

impl GpuContext {
    /// Picks an adapter (a real GPU first; a software one only if allowed), creates a device with
    /// the adapter's own limits, and builds the pipelines.
    pub fn new(opts: &GpuOptions) -> Result<GpuContext, GpuError> {
        let mut desc = wgpu::InstanceDescriptor::new_without_display_handle();
        desc.backends = opts.backends;
        let instance = wgpu::Instance::new(desc);
        let adapters = pollster::block_on(instance.enumerate_adapters(opts.backends));
        let seen: Vec<String> = adapters.iter().map(|a| adapter_name(&a.get_info())).collect();
        let rank = |t: wgpu::DeviceType| match t {
            wgpu::DeviceType::DiscreteGpu => 0,
            wgpu::DeviceType::IntegratedGpu => 1,
            wgpu::DeviceType::VirtualGpu => 2,
            wgpu::DeviceType::Other => 3,
            wgpu::DeviceType::Cpu => 4,
        };
        let adapter = adapters
            .into_iter()
            .filter(|a| opts.allow_software || a.get_info().device_type != wgpu::DeviceType::Cpu)
            .min_by_key(|a| rank(a.get_info().device_type))
            .ok_or_else(|| {
                GpuError::NoAdapter(if seen.is_empty() {
                    " (no Vulkan, Metal or DX12 driver answered; on Debian: apt-get install mesa-vulkan-drivers libvulkan1)".into()
                } else {
                    format!(" among: {} (software adapters not allowed)", seen.join(", "))
                })
            })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("semlook"),
            required_features: wgpu::Features::empty(),
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device { adapter: adapter_name(&info), reason: e.to_string() })?;
        let lost = Arc::new(Mutex::new(None));
        let sink = lost.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            let mut l = sink.lock().unwrap();
            if l.is_none() {
                *l = Some(format!("uncaptured error: {e}"));
            }
        }));
        Self::finish(device, queue, info, opts, lost)
    }

    /// Wraps a device and queue that belong to the host application. The engine adds its
    /// pipelines to that device and uses error scopes for everything it submits; it does not
    /// replace the host's uncaptured-error handler.
    pub fn from_device(device: wgpu::Device, queue: wgpu::Queue, info: wgpu::AdapterInfo, opts: &GpuOptions) -> Result<GpuContext, GpuError> {
        Self::finish(device, queue, info, opts, Arc::new(Mutex::new(None)))
    }

    fn finish(device: wgpu::Device, queue: wgpu::Queue, info: wgpu::AdapterInfo, opts: &GpuOptions, lost: Arc<Mutex<Option<String>>>) -> Result<GpuContext, GpuError> {
        let sink = lost.clone();
        device.set_device_lost_callback(move |reason, msg| {
            *sink.lock().unwrap() = Some(format!("{reason:?}: {msg}"));
        });
        let limits = device.limits();
        let binding_limit = (limits.max_storage_buffer_binding_size).min(limits.max_buffer_size).min(opts.max_binding_size.unwrap_or(u64::MAX));
        let needs = [
            ("storage buffers per shader stage", 7u64, limits.max_storage_buffers_per_shader_stage as u64),
            ("workgroup storage (bytes)", 15_616, limits.max_compute_workgroup_storage_size as u64),
            ("invocations per workgroup", 256, limits.max_compute_invocations_per_workgroup as u64),
        ];
        for (what, needed, available) in needs {
            if available < needed {
                return Err(GpuError::LimitsTooSmall { adapter: adapter_name(&info), what: what.into(), needed, available });
            }
        }
        let kernels = Kernels::new(&device)?;
        Ok(GpuContext { device, queue, info, binding_limit, lost, kernels })
    }

    /// "name (backend, device type)".
    pub fn describe(&self) -> String {
        adapter_name(&self.info)
    }

    /// Whether the adapter is a software rasteriser (lavapipe): correct, not fast.
    pub fn is_software(&self) -> bool {
        self.info.device_type == wgpu::DeviceType::Cpu
    }

    /// Largest storage binding the executors may use, in bytes.
    pub fn binding_limit(&self) -> u64 {
        self.binding_limit
    }

    pub(crate) fn check_lost(&self) -> Result<(), GpuError> {
        match self.lost.lock().unwrap().clone() {
            Some(m) => Err(GpuError::DeviceLost(m)),
            None => Ok(()),
        }
    }

    /// Runs `f` inside out-of-memory, validation and internal error scopes and maps what they
    /// caught to a typed error naming `what`.
    pub(crate) fn scoped<T>(&self, what: &str, f: impl FnOnce() -> T) -> Result<T, GpuError> {
        self.check_lost()?;
        let oom = self.device.push_error_scope(wgpu::ErrorFilter::OutOfMemory);
        let val = self.device.push_error_scope(wgpu::ErrorFilter::Validation);
        let int = self.device.push_error_scope(wgpu::ErrorFilter::Internal);
        let out = f();
        let errors = [pollster::block_on(int.pop()), pollster::block_on(val.pop()), pollster::block_on(oom.pop())];
        self.check_lost()?;
        match errors.into_iter().flatten().next() {
            Some(wgpu::Error::OutOfMemory { .. }) => Err(GpuError::OutOfMemory(what.into())),
            Some(other) => Err(GpuError::Failed { what: what.into(), reason: other.to_string() }),
            None => Ok(out),
        }
    }

    /// A storage buffer of `size` bytes (at least 4), copyable both ways.
    pub(crate) fn storage(&self, label: &str, size: u64) -> wgpu::Buffer {
        self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: size.max(4).next_multiple_of(4),
            usage: wgpu::BufferUsages::STORAGE | wgpu::BufferUsages::COPY_DST | wgpu::BufferUsages::COPY_SRC,
            mapped_at_creation: false,
        })
    }

    pub(crate) fn uniform<T: bytemuck::Pod>(&self, label: &str, value: &T) -> wgpu::Buffer {
        let buf = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some(label),
            size: (std::mem::size_of::<T>() as u64).next_multiple_of(16),
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        self.queue.write_buffer(&buf, 0, bytemuck::bytes_of(value));
        buf
    }

    /// Fails with `LimitsTooSmall` if one binding of `bytes` exceeds the binding limit.
    pub(crate) fn check_binding(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        if bytes > self.binding_limit {
            return Err(GpuError::LimitsTooSmall { adapter: self.describe(), what: what.into(), needed: bytes, available: self.binding_limit });
        }
        Ok(())
    }

    /// Copies `bytes` bytes of `src` back to the host (waits for the queue).
    pub(crate) fn read_back(&self, src: &wgpu::Buffer, bytes: u64) -> Result<Vec<u8>, GpuError> {
        let bytes = bytes.next_multiple_of(4).max(4);
        let staging = self.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("readback"),
            size: bytes,
            usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("readback") });
        enc.copy_buffer_to_buffer(src, 0, &staging, 0, bytes);
        self.queue.submit([enc.finish()]);
        let (tx, rx) = std::sync::mpsc::channel();
        staging.map_async(wgpu::MapMode::Read, .., move |r| {
            let _ = tx.send(r);
        });
        self.device
            .poll(wgpu::PollType::wait_indefinitely())
            .map_err(|e| GpuError::DeviceLost(format!("waiting for the queue: {e}")))?;
        rx.recv()
            .map_err(|_| GpuError::Failed { what: "reading back".into(), reason: "map callback dropped".into() })?
            .map_err(|e| GpuError::Failed { what: "reading back".into(), reason: e.to_string() })?;
        let data = staging
            .get_mapped_range(..)
            .map_err(|e| GpuError::Failed { what: "reading back".into(), reason: e.to_string() })?
            .to_vec();
        staging.unmap();
        self.check_lost()?;
        Ok(data)
    }

    /// Reads back the first `n` 32-bit values (f32 or u32) of `src`.
    pub(crate) fn read_back_values<T: bytemuck::Pod>(&self, src: &wgpu::Buffer, n: usize) -> Result<Vec<T>, GpuError> {
        Ok(bytemuck::pod_collect_to_vec(&self.read_back(src, (n * 4) as u64)?[..n * 4]))
    }

    /// The K-lists of `nq` queries from top-K score and index buffers.
    pub(crate) fn read_topk(&self, top_s: &wgpu::Buffer, top_i: &wgpu::Buffer, nq: usize, k: usize) -> Result<Vec<Vec<(f32, u32)>>, GpuError> {
        let s: Vec<f32> = self.read_back_values(top_s, nq * k)?;
        let i: Vec<u32> = self.read_back_values(top_i, nq * k)?;
        Ok(crate::matching::ssim_topk::topk_lists(k, &s, &i))
    }

    /// Records one compute pass with `dispatches` of (pipeline, bind group, workgroups) and submits it.
    pub(crate) fn run(&self, label: &str, dispatches: &[(&wgpu::ComputePipeline, &wgpu::BindGroup, [u32; 3])]) {
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut pass = enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(label), timestamp_writes: None });
            for (pipeline, bind, [x, y, z]) in dispatches {
                if *x == 0 || *y == 0 || *z == 0 {
                    continue;
                }
                pass.set_pipeline(pipeline);
                pass.set_bind_group(0, Some(*bind), &[]);
                pass.dispatch_workgroups(*x, *y, *z);
            }
        }
        self.queue.submit([enc.finish()]);
    }
}
