//! GPU executor of the XFeat network (`shaders/xfeat.wgsl`): the whole forward pass of
//! [`XFeat::forward_with`] as one submission of dispatches, with no host round trip between
//! layers; only the grey frame goes up and only the outputs come back.
//!
//! Residency: the weights are packed (`semlook_kernels::xfeat::pack_conv`) and uploaded once, when the
//! executor is made. For a frame size, the activation buffers, the one uniform buffer holding
//! every pass's parameters (at dynamic offsets), the bind groups and the read-back buffer are
//! made once and kept until a frame of another size comes; a repeated size creates no buffer and
//! writes only the frame ([`XFeatGpu::counters`]). A frame whose activations exceed the device's
//! storage binding or whose grid exceeds its workgroups per dimension is a typed
//! [`GpuError::LimitsTooSmall`], never a silent CPU run.
//!
//! The plan of passes (which kernel, its parameters, which buffers) is data (`Plan`); the same
//! plan runs on the CPU twins in [`forward_on_twins`], the reference the device is held to.

use super::plan::{outputs, pack, twin_uniform_max, Buf, Entry, PackedNet, Plan, PlanError, Shape, ALL};
use super::XFeat;
use crate::device::context::{GpuContext, GpuError};
use crate::device::executor::{pass_parameters, staging, submit_and_read, Counters, ExecutorCounters};
use crate::device::kernels::Kernel;
use crate::networks::NetOutputs;
use crate::nn::conv::Chw;
use std::sync::{Arc, Mutex};

/// What is kept for one frame size.
struct Sized {
    h: usize,
    w: usize,
    plan: Plan,
    buffers: Vec<Option<wgpu::Buffer>>,
    /// Every pass's parameters at `stride` apart (not needed after creation; kept with its bind groups).
    _params: wgpu::Buffer,
    stride: u64,
    groups: Vec<wgpu::BindGroup>,
    staging: wgpu::Buffer,
}

/// The XFeat network resident on a device.
pub struct XFeatGpu {
    ctx: Arc<GpuContext>,
    net: PackedNet,
    weights: wgpu::Buffer,
    unused: wgpu::Buffer,
    sized: Mutex<Option<Sized>>,
    counters: Counters,
}

fn bad(reason: impl Into<String>) -> GpuError {
    GpuError::Failed { what: "running XFeat on the device".into(), reason: reason.into() }
}

impl XFeatGpu {
    /// Packs `net`'s weights and uploads them (once).
    pub fn new(ctx: Arc<GpuContext>, net: &XFeat) -> Result<XFeatGpu, GpuError> {
        let packed = pack(net).map_err(|e| bad(e.to_string()))?;
        let bytes = (packed.weights.len() * 4) as u64;
        ctx.check_binding("the packed XFeat weights", bytes)?;
        let counters = Counters::default();
        let (weights, unused) = ctx.scoped("uploading the XFeat weights", || {
            let w = ctx.storage("xfeat weights", bytes);
            ctx.write(&w, 0, bytemuck::cast_slice(&packed.weights));
            (w, ctx.storage("xfeat unused binding", 16))
        })?;
        counters.created(2);
        counters.uploaded(bytes);
        Ok(XFeatGpu { ctx, net: packed, weights, unused, sized: Mutex::new(None), counters })
    }

    /// What the executor did since it was made.
    pub fn counters(&self) -> ExecutorCounters {
        self.counters.get()
    }

    /// The context it runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// [`XFeat::forward_with`] on the device: the same outputs (descriptors; with `heads`, the
    /// keypoint logits and the reliability, else empty logits and no reliability).
    pub fn forward_with(&self, grey: &Chw, heads: bool) -> Result<NetOutputs, GpuError> {
        if grey.c != 1 || !grey.h.is_multiple_of(32) || !grey.w.is_multiple_of(32) || grey.h == 0 || grey.w == 0 || !grey.is_consistent() {
            return Err(bad(format!("input is {}x{}x{}; it must be 1 x (32k) x (32k)", grey.c, grey.h, grey.w)));
        }
        let ctx = self.ctx.clone();
        let mut guard = self.sized.lock().unwrap_or_else(|p| p.into_inner());
        if guard.as_ref().is_none_or(|s| (s.h, s.w) != (grey.h, grey.w)) {
            *guard = None;
            *guard = Some(self.make_sized(grey.h, grey.w)?);
        }
        let s = guard.as_ref().expect("made above");
        let out = ctx.scoped("running XFeat on the device", || -> Result<Vec<f32>, GpuError> {
            let grey_buf = s.buffers[Buf::Grey as usize].as_ref().expect("planned");
            ctx.write(grey_buf, 0, bytemuck::cast_slice(&grey.data));
            self.counters.uploaded((grey.data.len() * 4) as u64);
            let k = &ctx.kernels;
            let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("xfeat") });
            {
                let mut pass = ctx.begin_pass(&mut enc, "xfeat")?;
                for (i, p) in s.plan.passes.iter().enumerate() {
                    if p.head && !heads {
                        continue;
                    }
                    pass.set_pipeline(&kernel(k, p.entry).pipeline);
                    pass.set_bind_group(0, Some(&s.groups[i]), &[(i as u64 * s.stride) as u32]);
                    pass.dispatch_workgroups(p.grid[0], p.grid[1], p.grid[2]);
                }
            }
            let outs: &[(Buf, Shape)] =
                if heads { &[(Buf::Desc, s.plan.desc), (Buf::Heat, s.plan.heat), (Buf::Logits, s.plan.logits)] } else { &[(Buf::Desc, s.plan.desc)] };
            let mut at = 0u64;
            for &(b, (c, h, w)) in outs {
                let bytes = (c * h * w * 4) as u64;
                enc.copy_buffer_to_buffer(s.buffers[b as usize].as_ref().expect("planned"), 0, &s.staging, at, bytes);
                at += bytes;
            }
            let data = submit_and_read(&ctx, enc, &s.staging, at)?;
            self.counters.read_back(at);
            Ok(data)
        })??;
        self.counters.frame();
        Ok(outputs(&s.plan, out, heads))
    }

    /// Buffers, parameters, bind groups and the read-back buffer for h x w frames.
    fn make_sized(&self, h: usize, w: usize) -> Result<Sized, GpuError> {
        let ctx = &self.ctx;
        let plan = Plan::new(&self.net, h, w, ctx.max_workgroups()).map_err(|e| match e {
            PlanError::Limit(what, needed, available) => GpuError::LimitsTooSmall { adapter: ctx.describe(), what, needed, available },
            PlanError::Invalid(r) => bad(r),
        })?;
        for b in ALL {
            ctx.check_binding(&format!("XFeat's {b:?} activations at {w}x{h}"), plan.sizes[b as usize] as u64 * 4)?;
        }
        let out_bytes = ((plan.desc.0 + plan.heat.0 + plan.logits.0) * plan.desc.1 * plan.desc.2 * 4) as u64;
        let s = ctx.scoped("making XFeat's buffers", || {
            let mut created = 0u64;
            let buffers: Vec<Option<wgpu::Buffer>> = ALL
                .iter()
                .map(|&b| match b {
                    Buf::Weights | Buf::Unused => None,
                    _ => {
                        created += 1;
                        Some(ctx.storage(&format!("xfeat {b:?}"), plan.sizes[b as usize] as u64 * 4))
                    }
                })
                .collect();
            let (pbuf, stride, param_bytes) =
                pass_parameters(ctx, "xfeat pass parameters", plan.passes.iter().map(|p| p.params.bytes()), twin_uniform_max());
            let staging = staging(ctx, "xfeat read-back", out_bytes);
            self.counters.created(created + 2);
            self.counters.uploaded(param_bytes);
            let get = |b: Buf| match b {
                Buf::Weights => &self.weights,
                Buf::Unused => &self.unused,
                _ => buffers[b as usize].as_ref().expect("made above"),
            };
            let groups = plan
                .passes
                .iter()
                .map(|p| {
                    let mut bound: Vec<&wgpu::Buffer> = vec![&pbuf];
                    bound.extend(p.bufs.iter().map(|&b| get(b)));
                    kernel(&ctx.kernels, p.entry).bind(&ctx.device, &bound)
                })
                .collect();
            Sized { h, w, plan: plan.clone(), buffers, _params: pbuf, stride, groups, staging }
        })?;
        Ok(s)
    }
}

fn kernel(k: &crate::device::kernels::Kernels, e: Entry) -> &Kernel {
    match e {
        Entry::Partials => &k.instance_norm_partials,
        Entry::Stats => &k.instance_norm_stats,
        Entry::Apply => &k.instance_norm_apply,
        Entry::AvgPool => &k.avg_pool,
        Entry::SpaceToDepth => &k.space_to_depth8,
        Entry::BilinearAdd => &k.bilinear_add,
        Entry::Conv => &k.conv2d,
    }
}

/// One `xfeat.wgsl` kernel alone on the device: `entry` (its name) with the uniform `params`
/// and `inputs` bound in binding order, the output (`out_len` values, zeros before the kernel
/// runs) read back. The device side of the twins' tests.
pub fn run_kernel(ctx: &GpuContext, entry: &str, params: &[u8], grid: [u32; 3], inputs: &[&[f32]], out_len: usize) -> Result<Vec<f32>, GpuError> {
    let e = match entry {
        "instance_norm_partials" => Entry::Partials,
        "instance_norm_stats" => Entry::Stats,
        "instance_norm_apply" => Entry::Apply,
        "avg_pool" => Entry::AvgPool,
        "space_to_depth8" => Entry::SpaceToDepth,
        "bilinear_add" => Entry::BilinearAdd,
        "conv2d" => Entry::Conv,
        other => return Err(bad(format!("no kernel {other:?} in xfeat.wgsl"))),
    };
    crate::device::executor::run_one(ctx, entry, kernel(&ctx.kernels, e), params, twin_uniform_max(), grid, inputs, out_len)
}
