//! GPU executor of the embedding network (`shaders/efficientnet.wgsl`): the whole forward pass of
//! [`EfficientNetLite::forward`] as one submission of dispatches (the stem and the depthwise
//! convolutions by `conv_direct`, the 1x1 ones by `pointwise`, the pooling by `gem_pool`), with no
//! host round trip between layers; only the frame goes up and only the pooled values come back,
//! normalised on the host.
//!
//! Residency (the XFeat executor's pattern): each convolution's weights and bias (BatchNorm
//! folded, as the CPU pass folds them) are uploaded once, when the executor is made. For a frame
//! size, the frame buffer, the three activation buffers, the pooled values, the one uniform
//! buffer holding every pass's parameters (at dynamic offsets), the bind groups and the read-back
//! buffer are made once and kept until a frame of another size comes; a repeated size creates no
//! buffer and writes only the frame ([`EmbedderGpu::counters`]). A frame whose activations exceed
//! the device's storage binding or whose grid exceeds its workgroups per dimension is a typed
//! [`GpuError::LimitsTooSmall`], never a silent CPU run.
//!
//! The plan of passes is data (`super::plan::Plan`); the same plan runs on the CPU twins in
//! [`super::forward_on_twins`], the reference the device is held to.

use super::efficientnet::EfficientNetLite;
use super::plan::{convs, uniform_max, Buf, Entry, Plan, PlanError, ACTS};
use crate::device::context::{GpuContext, GpuError};
use crate::device::executor::{pass_parameters, staging, submit_and_read, Counters, ExecutorCounters};
use crate::device::kernels::{Kernel, Kernels};
use crate::nn::conv::Chw;
use std::sync::{Arc, Mutex};

/// What is kept for one frame size.
struct Sized {
    h: usize,
    w: usize,
    plan: Plan,
    input: wgpu::Buffer,
    _acts: Vec<wgpu::Buffer>,
    pooled: wgpu::Buffer,
    /// Every pass's parameters at `stride` apart (kept with the bind groups that bind it).
    _params: wgpu::Buffer,
    stride: u64,
    groups: Vec<wgpu::BindGroup>,
    staging: wgpu::Buffer,
}

/// The embedding network resident on a device.
pub struct EmbedderGpu {
    ctx: Arc<GpuContext>,
    /// The network's layout (weights dropped: they are on the device), what plans are made from.
    layout: EfficientNetLite,
    /// Each convolution's (weights, bias), in plan order.
    weights: Vec<(wgpu::Buffer, wgpu::Buffer)>,
    unused: wgpu::Buffer,
    sized: Mutex<Option<Sized>>,
    counters: Counters,
}

fn bad(reason: impl Into<String>) -> GpuError {
    GpuError::Failed { what: "running the embedding network on the device".into(), reason: reason.into() }
}

/// GeM values read back, L2-normalised in f64 (as the CPU pass normalises its own); `None` where
/// they have no length (zero, NaN or infinite).
pub(super) fn normalise_pooled(g: &[f32]) -> Option<Vec<f32>> {
    let norm = g.iter().map(|&v| v as f64 * v as f64).sum::<f64>().sqrt();
    (norm.is_finite() && norm > 0.0).then(|| g.iter().map(|&v| (v as f64 / norm) as f32).collect())
}

impl EmbedderGpu {
    /// Uploads `net`'s weights to `ctx`'s device (once).
    pub fn new(ctx: Arc<GpuContext>, net: &EfficientNetLite) -> Result<EmbedderGpu, GpuError> {
        let counters = Counters::default();
        let convs = convs(net);
        for (i, c) in convs.iter().enumerate() {
            ctx.check_binding(&format!("the embedding network's convolution {i}"), (c.weight.len() * 4) as u64)?;
        }
        let (weights, unused) = ctx.scoped("uploading the embedding network's weights", || {
            let up = |label: &str, v: &[f32]| {
                let b = ctx.storage(label, (v.len() * 4) as u64);
                if !v.is_empty() {
                    ctx.write(&b, 0, bytemuck::cast_slice(v));
                }
                counters.uploaded((v.len() * 4) as u64);
                b
            };
            let weights: Vec<_> = convs.iter().map(|c| (up("embedding weights", &c.weight), up("embedding bias", &c.bias))).collect();
            (weights, ctx.storage("embedding unused binding", 4))
        })?;
        counters.created(2 * weights.len() as u64 + 1);
        Ok(EmbedderGpu { ctx, layout: net.layout(), weights, unused, sized: Mutex::new(None), counters })
    }

    /// What the executor did since it was made.
    pub fn counters(&self) -> ExecutorCounters {
        self.counters.get()
    }

    /// Values of an embedding.
    pub fn dim(&self) -> usize {
        self.layout.dim()
    }

    /// [`EfficientNetLite::forward`] on the device: the embedding of an RGB image [3, H, W] with
    /// values 0..255 (GeM of the head's feature map, L2-normalised in f64 on the host). An
    /// embedding with no length (zero, NaN or infinite) is an error.
    pub fn forward(&self, rgb: &Chw) -> Result<Vec<f32>, GpuError> {
        let pooled = self.pooled(rgb)?;
        normalise_pooled(&pooled).ok_or_else(|| bad("the embedding is zero, NaN or infinite"))
    }

    /// The GeM values of `rgb` as the device computes them, before the normalisation (what a
    /// caller that finishes them itself takes: the GPU engine, through `Embedder::finish`).
    pub fn pooled(&self, rgb: &Chw) -> Result<Vec<f32>, GpuError> {
        super::efficientnet::check_rgb(rgb).map_err(bad)?;
        let ctx = self.ctx.clone();
        let mut guard = self.sized.lock().unwrap_or_else(|p| p.into_inner());
        if guard.as_ref().is_none_or(|s| (s.h, s.w) != (rgb.h, rgb.w)) {
            *guard = None;
            *guard = Some(self.make_sized(rgb.h, rgb.w)?);
        }
        let s = guard.as_ref().expect("made above");
        let pooled: Vec<f32> = ctx.scoped("running the embedding network on the device", || -> Result<Vec<f32>, GpuError> {
            ctx.write(&s.input, 0, bytemuck::cast_slice(&rgb.data));
            self.counters.uploaded((rgb.data.len() * 4) as u64);
            let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("embedding") });
            {
                let mut pass = ctx.begin_pass(&mut enc, "embedding")?;
                for (i, p) in s.plan.passes.iter().enumerate() {
                    if p.grid.contains(&0) {
                        continue;
                    }
                    pass.set_pipeline(&kernel(&ctx.kernels, p.entry).pipeline);
                    pass.set_bind_group(0, Some(&s.groups[i]), &[(i as u64 * s.stride) as u32]);
                    pass.dispatch_workgroups(p.grid[0], p.grid[1], p.grid[2]);
                }
            }
            let bytes = (s.plan.dim * 4) as u64;
            enc.copy_buffer_to_buffer(&s.pooled, 0, &s.staging, 0, bytes.max(4));
            let data = submit_and_read(&ctx, enc, &s.staging, bytes)?;
            self.counters.read_back(bytes);
            Ok(data)
        })??;
        self.counters.frame();
        Ok(pooled)
    }

    /// Buffers, parameters, bind groups and the read-back buffer for h x w frames.
    fn make_sized(&self, h: usize, w: usize) -> Result<Sized, GpuError> {
        let ctx = &self.ctx;
        let plan = Plan::new(&self.layout, h, w, ctx.max_workgroups()).map_err(|e| match e {
            PlanError::Limit(what, needed, available) => GpuError::LimitsTooSmall { adapter: ctx.describe(), what, needed, available },
            PlanError::Invalid(r) => bad(r),
        })?;
        ctx.check_binding(&format!("the embedding network's frame at {w}x{h}"), plan.input_len as u64 * 4)?;
        ctx.check_binding(&format!("the embedding network's activations at {w}x{h}"), plan.act_len as u64 * 4)?;
        ctx.scoped("making the embedding network's buffers", || {
            let input = ctx.storage("embedding frame", plan.input_len as u64 * 4);
            let acts: Vec<wgpu::Buffer> = (0..ACTS).map(|_| ctx.storage("embedding activations", plan.act_len as u64 * 4)).collect();
            let pooled = ctx.storage("embedding pooled", plan.dim as u64 * 4);
            let (params, stride, param_bytes) =
                pass_parameters(ctx, "embedding pass parameters", plan.passes.iter().map(|p| p.params.bytes()), uniform_max());
            let staging = staging(ctx, "embedding read-back", plan.dim as u64 * 4);
            self.counters.created(ACTS as u64 + 4);
            self.counters.uploaded(param_bytes);
            let get = |b: Buf| match b {
                Buf::Input => &input,
                Buf::Act(i) => &acts[i],
                Buf::Pooled => &pooled,
                Buf::Weight(i) => &self.weights[i].0,
                Buf::Bias(i) => &self.weights[i].1,
                Buf::Unused => &self.unused,
            };
            let groups = plan
                .passes
                .iter()
                .map(|p| {
                    let mut bound: Vec<&wgpu::Buffer> = vec![&params];
                    bound.extend(p.bufs.iter().map(|&b| get(b)));
                    kernel(&ctx.kernels, p.entry).bind(&ctx.device, &bound)
                })
                .collect();
            Sized { h, w, plan: plan.clone(), input, _acts: acts, pooled, _params: params, stride, groups, staging }
        })
    }
}

fn kernel(k: &Kernels, e: Entry) -> &Kernel {
    match e {
        Entry::Direct => &k.conv_direct,
        Entry::Pointwise => &k.pointwise,
        Entry::Gem => &k.gem_pool,
    }
}

/// One `efficientnet.wgsl` kernel alone on the device: `entry` (its name) with the uniform
/// `params` and `inputs` bound in binding order, the output (`out_len` values, zeros before the
/// kernel runs) read back. The device side of the twins' tests.
pub fn run_kernel(ctx: &GpuContext, entry: &str, params: &[u8], grid: [u32; 3], inputs: &[&[f32]], out_len: usize) -> Result<Vec<f32>, GpuError> {
    let e = match entry {
        "conv_direct" => Entry::Direct,
        "pointwise" => Entry::Pointwise,
        "gem_pool" => Entry::Gem,
        other => return Err(bad(format!("no kernel {other:?} in efficientnet.wgsl"))),
    };
    crate::device::executor::run_one(ctx, entry, kernel(&ctx.kernels, e), params, uniform_max(), grid, inputs, out_len)
}
