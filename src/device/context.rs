//! The GPU context: device, queue, what adapter they came from, and the effective limits the
//! executors plan with. Either created here (`GpuContext::new`) or wrapped around a host
//! application's device (`GpuContext::from_device`), so the engine can run inside someone else's
//! wgpu context. Every GPU operation runs inside error scopes, so validation errors, out-of-memory
//! and device loss come back as typed [`GpuError`]s instead of panics. The context also counts
//! every byte written to the device (`bytes_uploaded`), holds the budget that resident maps share,
//! and the timestamp queries that time the kernels where the adapter has them.

use super::kernels::Kernels;
use super::timer::Timer;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// Default budget of resident map data: this fraction of the adapter's largest buffer. wgpu
/// reports no memory size, and the largest buffer is what an adapter promises to allocate at
/// once; a budget the device cannot honour shows as an out-of-memory error on upload, after
/// which the executor streams instead.
pub const RESIDENT_FRACTION: f64 = 0.5;

pub use crate::error::GpuError;

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
    /// Bytes of map data (descriptors, statistics, forests) kept on the device between batches;
    /// a map larger than this is streamed (double-buffered). Default: [`RESIDENT_FRACTION`] of
    /// the adapter's largest buffer.
    pub resident_budget: Option<u64>,
    /// Use at most this many workgroups per dispatch dimension (lower than the device's to force
    /// chunking of query batches and passes).
    pub max_workgroups: Option<u32>,
    /// Reduce through subgroup operations where the adapter has them (off: the workgroup-memory
    /// fallback everywhere).
    pub subgroups: bool,
    /// Time the kernels with timestamp queries where the adapter has them.
    pub timestamps: bool,
    /// Take the n-th adapter in order of preference (discrete GPUs first, then integrated,
    /// virtual, other, software; wgpu's enumeration order within a kind) instead of the first:
    /// one process per GPU on a machine with several. `None`: the first.
    pub adapter: Option<usize>,
}

impl Default for GpuOptions {
    fn default() -> Self {
        GpuOptions {
            allow_software: true,
            max_binding_size: None,
            backends: wgpu::Backends::PRIMARY,
            resident_budget: None,
            max_workgroups: None,
            subgroups: true,
            timestamps: true,
            adapter: None,
        }
    }
}

/// A device and queue with the engine's pipelines, ready for the executors.
pub struct GpuContext {
    /// The wgpu device the pipelines and buffers live on.
    pub device: wgpu::Device,
    /// The device's queue, which every submission and write goes through.
    pub queue: wgpu::Queue,
    /// The adapter the device was requested from.
    pub info: wgpu::AdapterInfo,
    binding_limit: u64,
    max_workgroups: u32,
    uniform_align: u32,
    budget: u64,
    /// Bytes of the budget that resident sets hold now.
    resident: AtomicU64,
    uploaded: AtomicU64,
    pub(crate) read_back_bytes: AtomicU64,
    buffers: AtomicU64,
    /// The read-back staging buffer, kept between read-backs (regrown when one needs more).
    pub(crate) staging: Mutex<Option<wgpu::Buffer>>,
    subgroups: bool,
    timer: Mutex<Option<Timer>>,
    lost: Arc<Mutex<Option<String>>>,
    pub(crate) kernels: Kernels,
}

/// Counts of a context's traffic and allocations ([`GpuContext::counters`]); differences between
/// two readings give what a call did.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct GpuCounters {
    /// Bytes written to device buffers.
    pub bytes_uploaded: u64,
    /// Bytes read back from the device.
    pub bytes_read_back: u64,
    /// Device buffers created.
    pub buffers_created: u64,
    /// Bind groups created.
    pub bind_groups_created: u64,
}

impl std::ops::Sub for GpuCounters {
    type Output = GpuCounters;
    fn sub(self, o: GpuCounters) -> GpuCounters {
        GpuCounters {
            bytes_uploaded: self.bytes_uploaded - o.bytes_uploaded,
            bytes_read_back: self.bytes_read_back - o.bytes_read_back,
            buffers_created: self.buffers_created - o.buffers_created,
            bind_groups_created: self.bind_groups_created - o.bind_groups_created,
        }
    }
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
        let mut usable: Vec<wgpu::Adapter> =
            adapters.into_iter().filter(|a| opts.allow_software || a.get_info().device_type != wgpu::DeviceType::Cpu).collect();
        // stable: wgpu's order within a kind
        usable.sort_by_key(|a| rank(a.get_info().device_type));
        let n = usable.len();
        let adapter = usable.into_iter().nth(opts.adapter.unwrap_or(0)).ok_or_else(|| {
            GpuError::NoAdapter(match (seen.is_empty(), opts.adapter) {
                (true, _) => " (no Vulkan, Metal or DX12 driver answered; on Debian: apt-get install mesa-vulkan-drivers libvulkan1)".into(),
                (false, Some(i)) if n > 0 => format!(": adapter {i} asked for, {n} usable among: {}", seen.join(", ")),
                (false, _) => format!(" among: {} (software adapters not allowed)", seen.join(", ")),
            })
        })?;
        let info = adapter.get_info();
        let limits = adapter.limits();
        let wanted = wgpu::Features::SUBGROUP | wgpu::Features::TIMESTAMP_QUERY;
        let (device, queue) = pollster::block_on(adapter.request_device(&wgpu::DeviceDescriptor {
            label: Some("semlook"),
            required_features: adapter.features() & wanted,
            required_limits: limits,
            ..Default::default()
        }))
        .map_err(|e| GpuError::Device { adapter: adapter_name(&info), reason: e.to_string() })?;
        let lost = Arc::new(Mutex::new(None));
        let sink = lost.clone();
        device.on_uncaptured_error(Arc::new(move |e: wgpu::Error| {
            // a poisoned lock still holds a whole Option<String>
            let mut l = sink.lock().unwrap_or_else(|p| p.into_inner());
            if l.is_none() {
                *l = Some(format!("uncaptured error: {e}"));
            }
        }));
        let sink = lost.clone();
        device.set_device_lost_callback(move |reason, msg| {
            *sink.lock().unwrap_or_else(|p| p.into_inner()) = Some(format!("{reason:?}: {msg}"));
        });
        Self::finish(device, queue, info, opts, lost)
    }

    /// Wraps a device and queue that belong to the host application. The engine adds its
    /// pipelines to that device and uses error scopes for everything it submits; it installs
    /// no callback (neither the uncaptured-error handler nor the device-lost callback, of which
    /// wgpu keeps one per device), so the host's stay in place. A host that wants the engine to
    /// refuse work on a lost device forwards the loss from its own callback with
    /// [`GpuContext::report_device_lost`].
    pub fn from_device(device: wgpu::Device, queue: wgpu::Queue, info: wgpu::AdapterInfo, opts: &GpuOptions) -> Result<GpuContext, GpuError> {
        Self::finish(device, queue, info, opts, Arc::new(Mutex::new(None)))
    }

    /// Marks the device lost (what the engine's own callback does for devices it created);
    /// every later call returns [`GpuError::DeviceLost`] with this message.
    pub fn report_device_lost(&self, message: impl Into<String>) {
        let mut l = self.lost.lock().unwrap_or_else(|p| p.into_inner());
        if l.is_none() {
            *l = Some(message.into());
        }
    }

    fn finish(
        device: wgpu::Device,
        queue: wgpu::Queue,
        info: wgpu::AdapterInfo,
        opts: &GpuOptions,
        lost: Arc<Mutex<Option<String>>>,
    ) -> Result<GpuContext, GpuError> {
        let limits = device.limits();
        let binding_limit = (limits.max_storage_buffer_binding_size).min(limits.max_buffer_size).min(opts.max_binding_size.unwrap_or(u64::MAX));
        let needs = [
            ("storage buffers per shader stage", 8u64, limits.max_storage_buffers_per_shader_stage as u64),
            ("dynamic uniform buffers per pipeline layout", 1, limits.max_dynamic_uniform_buffers_per_pipeline_layout as u64),
            ("workgroup storage (bytes)", semlook_kernels::abi::WORKGROUP_STORAGE, limits.max_compute_workgroup_storage_size as u64),
            ("invocations per workgroup", 256, limits.max_compute_invocations_per_workgroup as u64),
            ("bind groups", 2, limits.max_bind_groups as u64),
        ];
        for (what, needed, available) in needs {
            if available < needed {
                return Err(GpuError::LimitsTooSmall { adapter: adapter_name(&info), what: what.into(), needed, available });
            }
        }
        let features = device.features();
        let subgroups = opts.subgroups && features.contains(wgpu::Features::SUBGROUP);
        let kernels = Kernels::new(&device, subgroups)?;
        let timer = (opts.timestamps && features.contains(wgpu::Features::TIMESTAMP_QUERY)).then(|| Timer::new(&device, &queue));
        let budget = opts.resident_budget.unwrap_or((limits.max_buffer_size as f64 * RESIDENT_FRACTION) as u64);
        let max_workgroups = limits.max_compute_workgroups_per_dimension.min(opts.max_workgroups.unwrap_or(u32::MAX)).max(1);
        Ok(GpuContext {
            device,
            queue,
            info,
            binding_limit,
            max_workgroups,
            uniform_align: limits.min_uniform_buffer_offset_alignment,
            budget,
            resident: AtomicU64::new(0),
            uploaded: AtomicU64::new(0),
            read_back_bytes: AtomicU64::new(0),
            buffers: AtomicU64::new(0),
            staging: Mutex::new(None),
            subgroups,
            timer: Mutex::new(timer),
            lost,
            kernels,
        })
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

    /// Most workgroups per dispatch dimension the executors use.
    pub fn max_workgroups(&self) -> u32 {
        self.max_workgroups
    }

    /// Alignment of dynamic offsets into a uniform buffer: the stride of per-pass parameters.
    pub fn uniform_offset_alignment(&self) -> u32 {
        self.uniform_align
    }

    /// Whether the reductions run through subgroup operations.
    pub fn uses_subgroups(&self) -> bool {
        self.subgroups
    }

    /// Whether the kernels are timed (timestamp queries).
    pub fn has_timestamps(&self) -> bool {
        self.timer.lock().unwrap_or_else(|e| e.into_inner()).is_some()
    }

    /// Bytes of map data the device may keep between batches.
    pub fn resident_budget(&self) -> u64 {
        self.budget
    }

    /// Reserves `bytes` of the resident budget; false (nothing reserved) if they do not fit.
    pub(crate) fn reserve(&self, bytes: u64) -> bool {
        self.resident.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |held| (held + bytes <= self.budget).then_some(held + bytes)).is_ok()
    }

    /// Returns `bytes` reserved earlier.
    pub(crate) fn release(&self, bytes: u64) {
        let _ = self.resident.fetch_update(Ordering::SeqCst, Ordering::SeqCst, |held| Some(held.saturating_sub(bytes)));
    }

    /// Bytes written to the device through the queue since the context was made: every upload
    /// the executors do goes through `GpuContext::write`.
    pub fn bytes_uploaded(&self) -> u64 {
        self.uploaded.load(Ordering::Relaxed)
    }

    /// What the executors have done on this context so far: bytes written and read back, buffers
    /// and bind groups created. Tests hold executors to them (a repeated batch creates nothing).
    pub fn counters(&self) -> GpuCounters {
        GpuCounters {
            bytes_uploaded: self.uploaded.load(Ordering::Relaxed),
            bytes_read_back: self.read_back_bytes.load(Ordering::Relaxed),
            buffers_created: self.buffers.load(Ordering::Relaxed),
            bind_groups_created: self.kernels.bind_groups_created(),
        }
    }

    /// Counts a buffer an executor created on the device itself.
    pub(crate) fn count_buffer(&self) {
        self.buffers.fetch_add(1, Ordering::Relaxed);
    }

    /// Writes `data` into `buffer` at `offset` through the queue, counting the bytes.
    pub(crate) fn write(&self, buffer: &wgpu::Buffer, offset: u64, data: &[u8]) {
        if !data.is_empty() {
            self.uploaded.fetch_add(data.len() as u64, Ordering::Relaxed);
            self.queue.write_buffer(buffer, offset, data);
        }
    }

    /// Kernel time (s) measured by timestamp queries since the last call; `None` where the adapter
    /// has no timestamps.
    pub fn take_kernel_seconds(&self) -> Result<Option<f64>, GpuError> {
        let mut t = self.timer.lock().unwrap_or_else(|e| e.into_inner());
        match t.as_mut() {
            Some(t) => Ok(Some(t.take_seconds(&self.device, &self.queue, &|b, n| self.read_back(b, n))?)),
            None => Ok(None),
        }
    }

    /// Begins a compute pass on `enc`, timed where timestamps are on.
    pub(crate) fn begin_pass<'e>(&self, enc: &'e mut wgpu::CommandEncoder, label: &str) -> Result<wgpu::ComputePass<'e>, GpuError> {
        let mut t = self.timer.lock().unwrap_or_else(|e| e.into_inner());
        let writes = match t.as_mut() {
            Some(t) => Some(t.next_writes(&self.device, &self.queue, &|b, n| self.read_back(b, n))?),
            None => None,
        };
        let writes = writes.as_ref().map(|(set, i)| wgpu::ComputePassTimestampWrites {
            query_set: set,
            beginning_of_pass_write_index: Some(*i),
            end_of_pass_write_index: Some(*i + 1),
        });
        Ok(enc.begin_compute_pass(&wgpu::ComputePassDescriptor { label: Some(label), timestamp_writes: writes }))
    }

    pub(crate) fn check_lost(&self) -> Result<(), GpuError> {
        match self.lost.lock().unwrap_or_else(|p| p.into_inner()).clone() {
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

    /// Fails with `LimitsTooSmall` if one binding of `bytes` exceeds the binding limit.
    pub(crate) fn check_binding(&self, what: &str, bytes: u64) -> Result<(), GpuError> {
        if bytes > self.binding_limit {
            return Err(GpuError::LimitsTooSmall { adapter: self.describe(), what: what.into(), needed: bytes, available: self.binding_limit });
        }
        Ok(())
    }

    /// Records one compute pass with `dispatches` of (pipeline, bind group, workgroups) and submits it.
    pub(crate) fn run(&self, label: &str, dispatches: &[(&wgpu::ComputePipeline, &wgpu::BindGroup, [u32; 3])]) -> Result<(), GpuError> {
        let mut enc = self.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(label) });
        {
            let mut pass = self.begin_pass(&mut enc, label)?;
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
        Ok(())
    }
}
