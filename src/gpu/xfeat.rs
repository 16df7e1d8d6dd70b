//! GPU executor of the XFeat network (`shaders/xfeat.wgsl`): the whole forward pass of
//! [`XFeat::forward_with`] as one submission of dispatches, with no host round trip between
//! layers; only the grey frame goes up and only the outputs come back.
//!
//! Residency: the weights are packed (`kernels::xfeat::pack_conv`) and uploaded once, when the
//! executor is made. For a frame size, the activation buffers, the one uniform buffer holding
//! every pass's parameters (at dynamic offsets), the bind groups and the read-back buffer are
//! made once and kept until a frame of another size comes; a repeated size creates no buffer and
//! writes only the frame ([`XFeatGpu::counters`]). A frame whose activations exceed the device's
//! storage binding or whose grid exceeds its workgroups per dimension is a typed
//! [`GpuError::LimitsTooSmall`], never a silent CPU run.
//!
//! The plan of passes (which kernel, its parameters, which buffers) is data (`Plan`); the same
//! plan runs on the CPU twins in [`forward_on_twins`], the reference the device is held to.

use super::context::{GpuContext, GpuError};
use super::kernels::Kernel;
use crate::appearance::nn::{Chw, NetOutputs};
use crate::appearance::xfeat::{Layer, XFeat};
use crate::appearance::{network_input, AppearanceModel, Features};
use crate::error::Error;
use crate::kernels::abi::{ConvParams, MapParams, NormParams};
use crate::kernels::xfeat::{self as twin, pack_conv};
use image::RgbImage;
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

/// The buffers a plan reads and writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Buf {
    Grey,
    X,
    Partials,
    Stats,
    Pool,
    Skip,
    A,
    B,
    X3,
    X4,
    X5,
    Desc,
    Heat,
    Logits,
    /// Bound where a kernel reads nothing (`conv2d`'s added tensor when it adds none).
    Unused,
    /// Every layer's packed weights (resident).
    Weights,
}

const BUFS: usize = 16;
const ALL: [Buf; BUFS] = [
    Buf::Grey,
    Buf::X,
    Buf::Partials,
    Buf::Stats,
    Buf::Pool,
    Buf::Skip,
    Buf::A,
    Buf::B,
    Buf::X3,
    Buf::X4,
    Buf::X5,
    Buf::Desc,
    Buf::Heat,
    Buf::Logits,
    Buf::Unused,
    Buf::Weights,
];

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Entry {
    Partials,
    Stats,
    Apply,
    AvgPool,
    SpaceToDepth,
    BilinearAdd,
    Conv,
}

#[derive(Debug, Clone, Copy)]
enum Params {
    Conv(ConvParams),
    Map(MapParams),
    Norm(NormParams),
}

impl Params {
    fn bytes(&self) -> &[u8] {
        match self {
            Params::Conv(p) => bytemuck::bytes_of(p),
            Params::Map(p) => bytemuck::bytes_of(p),
            Params::Norm(p) => bytemuck::bytes_of(p),
        }
    }
}

/// One dispatch: the kernel, its uniform, its storage bindings in binding order, its grid, and
/// whether only the keypoint and reliability heads need it.
#[derive(Debug, Clone)]
struct Pass {
    entry: Entry,
    params: Params,
    bufs: Vec<Buf>,
    grid: [u32; 3],
    head: bool,
}

/// A layer packed into the weights buffer.
#[derive(Debug, Clone, Copy)]
struct Packed {
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    act: u32,
    weight_at: u32,
    sub_at: u32,
    mul_at: u32,
}

/// The network's layers packed, in the graph's blocks, and the packed values.
#[derive(Debug, Clone)]
struct PackedNet {
    skip1: Packed,
    blocks: [Vec<Packed>; 5],
    fusion: Vec<Packed>,
    fusion_out: Packed,
    heatmap: Vec<Packed>,
    heatmap_out: Packed,
    keypoint: Vec<Packed>,
    keypoint_out: Packed,
    weights: Vec<f32>,
}

fn pack(net: &XFeat) -> crate::Result<PackedNet> {
    let g = net.graph();
    let mut weights: Vec<f32> = Vec::new();
    let mut one = |l: &Layer| -> crate::Result<Packed> {
        let (vals, sub, mul) = pack_conv(l.weight, l.cin, l.cout, l.k, l.epilogue)
            .ok_or_else(|| Error::check(format!("a {}x{}x{}x{} layer does not pack", l.cout, l.cin, l.k, l.k)))?;
        let at = weights.len();
        weights.extend_from_slice(&vals);
        if weights.len() >= u32::MAX as usize {
            return Err(Error::check("the packed weights exceed 2^32 values"));
        }
        Ok(Packed {
            cin: l.cin,
            cout: l.cout,
            k: l.k,
            stride: l.stride,
            act: l.epilogue.act(),
            weight_at: at as u32,
            sub_at: (at + sub) as u32,
            mul_at: (at + mul) as u32,
        })
    };
    let mut many = |ls: &[Layer]| ls.iter().map(&mut one).collect::<crate::Result<Vec<_>>>();
    let blocks = [many(&g.block1)?, many(&g.block2)?, many(&g.block3)?, many(&g.block4)?, many(&g.block5)?];
    let (fusion, heatmap, keypoint) = (many(&g.fusion)?, many(&g.heatmap)?, many(&g.keypoint)?);
    Ok(PackedNet {
        skip1: one(&g.skip1)?,
        blocks,
        fusion,
        fusion_out: one(&g.fusion_out)?,
        heatmap,
        heatmap_out: one(&g.heatmap_out)?,
        keypoint,
        keypoint_out: one(&g.keypoint_out)?,
        weights,
    })
}

/// (channels, height, width) of an activation.
type Shape = (usize, usize, usize);

/// Every pass of the forward pass at one frame size, and the buffers' sizes (values).
#[derive(Debug, Clone)]
struct Plan {
    /// Workgroups per dispatch dimension the plan keeps within.
    max_wg: u32,
    sizes: [usize; BUFS],
    passes: Vec<Pass>,
    desc: Shape,
    heat: Shape,
    logits: Shape,
}

/// What does not fit a plan: (what, needed, available) for the limits, or a reason.
enum PlanError {
    Limit(String, u64, u64),
    Invalid(String),
}

impl Plan {
    fn size(&mut self, b: Buf, values: usize) {
        let s = &mut self.sizes[b as usize];
        *s = (*s).max(values);
    }

    /// Appends a convolution of `input` (of shape `x`) into `out`, adding `add` after the
    /// epilogue when given; returns the output's shape.
    fn conv(&mut self, l: &Packed, x: Shape, input: Buf, out: Buf, add: Option<(Buf, Shape)>, head: bool) -> Result<Shape, PlanError> {
        if l.cin != x.0 {
            return Err(PlanError::Invalid(format!("a layer of {} input channels receives {}", l.cin, x.0)));
        }
        let mut p = ConvParams::new(l.cin, l.cout, x.1, x.2, l.k, l.stride, l.k / 2, l.act, add.is_some()).ok_or_else(|| {
            PlanError::Invalid(format!("a {0}x{0} convolution (stride {1}) on {2}x{3} does not fit the kernel's tiles", l.k, l.stride, x.1, x.2))
        })?;
        p.weight_at = l.weight_at;
        p.sub_at = l.sub_at;
        p.mul_at = l.mul_at;
        let y = (l.cout, p.ho as usize, p.wo as usize);
        if let Some((_, s)) = add {
            if s != y {
                return Err(PlanError::Invalid(format!("adding a {s:?} tensor to a {y:?} one")));
            }
        }
        let grid = p.grid();
        if let Some(&d) = grid.iter().find(|&&d| d > self.max_wg) {
            return Err(PlanError::Limit("conv2d workgroups per dimension".into(), d as u64, self.max_wg as u64));
        }
        self.size(out, p.output_len());
        self.passes.push(Pass {
            entry: Entry::Conv,
            params: Params::Conv(p),
            bufs: vec![input, Buf::Weights, add.map_or(Buf::Unused, |a| a.0), out],
            grid,
            head,
        });
        Ok(y)
    }

    /// A chain of layers from `input`, each into the other of the scratch buffers A and B, the
    /// last into `end` when given; returns the output's shape and buffer.
    fn chain(&mut self, ls: &[Packed], mut x: Shape, mut input: Buf, end: Option<Buf>, head: bool) -> Result<(Shape, Buf), PlanError> {
        for (i, l) in ls.iter().enumerate() {
            let out = match end {
                Some(e) if i + 1 == ls.len() => e,
                _ if input == Buf::A => Buf::B,
                _ => Buf::A,
            };
            x = self.conv(l, x, input, out, None, head)?;
            input = out;
        }
        Ok((x, input))
    }

    fn elementwise(&mut self, entry: Entry, p: Params, bufs: Vec<Buf>, grid: [u32; 3], head: bool) -> Result<(), PlanError> {
        if grid[1] > self.max_wg {
            return Err(PlanError::Limit(format!("{entry:?} workgroups per dimension"), grid[1] as u64, self.max_wg as u64));
        }
        self.passes.push(Pass { entry, params: p, bufs, grid, head });
        Ok(())
    }

    /// The plan for a 1 x h x w frame (h, w multiples of 32) under `max_wg` workgroups per
    /// dimension.
    fn new(net: &PackedNet, h: usize, w: usize, max_wg: u32) -> Result<Plan, PlanError> {
        let mw = max_wg as usize;
        let mut p = Plan { max_wg, sizes: [0; BUFS], passes: vec![], desc: (0, 0, 0), heat: (0, 0, 0), logits: (0, 0, 0) };
        let n = h * w;
        let np = NormParams::new(n, mw);
        p.size(Buf::Grey, n);
        p.size(Buf::X, n);
        p.size(Buf::Partials, 3 * np.chunks as usize);
        p.size(Buf::Stats, 4);
        p.size(Buf::Unused, 4);
        p.elementwise(Entry::Partials, Params::Norm(np), vec![Buf::Grey, Buf::Partials], np.partials_grid(), false)?;
        p.elementwise(Entry::Stats, Params::Norm(np), vec![Buf::Partials, Buf::Stats], [1, 1, 1], false)?;
        p.elementwise(Entry::Apply, Params::Norm(np), vec![Buf::Grey, Buf::Stats, Buf::X], np.apply_grid(), false)?;
        // skip1 on the 4x4 average pool
        let pool = MapParams::avg_pool(1, h, w, 4, mw);
        p.size(Buf::Pool, pool.n as usize);
        p.elementwise(Entry::AvgPool, Params::Map(pool), vec![Buf::X, Buf::Pool], pool.grid(), false)?;
        let skip = p.conv(&net.skip1, (1, pool.ho as usize, pool.wo as usize), Buf::Pool, Buf::Skip, None, false)?;
        // block1, its last layer adding the skip
        let [b1, b2, b3, b4, b5] = &net.blocks;
        if [b1, b3, b4, b5].iter().any(|b| b.is_empty()) {
            return Err(PlanError::Invalid("blocks 1, 3, 4 and 5 need a layer each".into()));
        }
        let (last, first) = b1.split_last().expect("checked above");
        let (x, at) = p.chain(first, (1, h, w), Buf::X, None, false)?;
        let out1 = if at == Buf::A { Buf::B } else { Buf::A };
        let x1 = p.conv(last, x, at, out1, Some((Buf::Skip, skip)), false)?;
        // block2; block3 ends in x3, block4 in x4, block5 in x5
        let (x2, at2) = p.chain(b2, x1, out1, None, false)?;
        let (x3, _) = p.chain(b3, x2, at2, Some(Buf::X3), false)?;
        let (x4, _) = p.chain(b4, x3, Buf::X3, Some(Buf::X4), false)?;
        let (x5, _) = p.chain(b5, x4, Buf::X4, Some(Buf::X5), false)?;
        if x4.0 != x3.0 || x5.0 != x3.0 {
            return Err(PlanError::Invalid(format!("blocks 3, 4 and 5 end in {}, {} and {} channels", x3.0, x4.0, x5.0)));
        }
        // x3 + x4 and x5 resized to x3, then the fusion block
        let fuse = MapParams::bilinear_add(x3.0, x3.1, x3.2, (x4.1, x4.2), (x5.1, x5.2), mw);
        p.size(Buf::A, fuse.n as usize);
        p.elementwise(Entry::BilinearAdd, Params::Map(fuse), vec![Buf::X3, Buf::X4, Buf::X5, Buf::A], fuse.grid(), false)?;
        let (xf, atf) = p.chain(&net.fusion, x3, Buf::A, None, false)?;
        p.desc = p.conv(&net.fusion_out, xf, atf, Buf::Desc, None, false)?;
        // the heads
        let (xh, ath) = p.chain(&net.heatmap, p.desc, Buf::Desc, None, true)?;
        p.heat = p.conv(&net.heatmap_out, xh, ath, Buf::Heat, None, true)?;
        let s2d = MapParams::space_to_depth8(h, w, mw);
        p.size(Buf::A, s2d.n as usize);
        p.elementwise(Entry::SpaceToDepth, Params::Map(s2d), vec![Buf::X, Buf::A], s2d.grid(), true)?;
        let xs = (64, s2d.ho as usize, s2d.wo as usize);
        let (xk, atk) = p.chain(&net.keypoint, xs, Buf::A, None, true)?;
        p.logits = p.conv(&net.keypoint_out, xk, atk, Buf::Logits, None, true)?;
        if p.heat.0 != 1 || p.logits.0 != 65 || (p.heat.1, p.heat.2) != (p.desc.1, p.desc.2) || (p.logits.1, p.logits.2) != (p.desc.1, p.desc.2) {
            return Err(PlanError::Invalid(format!("heads of {:?} and {:?} beside descriptors of {:?}", p.heat, p.logits, p.desc)));
        }
        Ok(p)
    }
}

/// What the executor did since it was made: bytes written to the device (weights, parameters,
/// frames), bytes read back, buffers created (every kind, the read-back buffer included), frames
/// run.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct XFeatCounters {
    /// Bytes written to the device: weights, parameters and frames.
    pub bytes_uploaded: u64,
    /// Bytes read back from the device.
    pub bytes_read_back: u64,
    /// Device buffers created, the read-back buffer included.
    pub buffers_created: u64,
    /// Frames run.
    pub frames: u64,
}

#[derive(Default)]
struct Counters {
    uploaded: AtomicU64,
    read_back: AtomicU64,
    created: AtomicU64,
    frames: AtomicU64,
}

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
        counters.created.fetch_add(2, Ordering::Relaxed);
        counters.uploaded.fetch_add(bytes, Ordering::Relaxed);
        Ok(XFeatGpu { ctx, net: packed, weights, unused, sized: Mutex::new(None), counters })
    }

    /// What the executor did since it was made.
    pub fn counters(&self) -> XFeatCounters {
        let c = &self.counters;
        XFeatCounters {
            bytes_uploaded: c.uploaded.load(Ordering::Relaxed),
            bytes_read_back: c.read_back.load(Ordering::Relaxed),
            buffers_created: c.created.load(Ordering::Relaxed),
            frames: c.frames.load(Ordering::Relaxed),
        }
    }

    /// The context it runs on.
    pub fn context(&self) -> &Arc<GpuContext> {
        &self.ctx
    }

    /// [`XFeat::forward_with`] on the device: the same outputs (descriptors; with `heads`, the
    /// keypoint logits and the reliability, else empty logits and no reliability).
    pub fn forward_with(&self, grey: &Chw, heads: bool) -> Result<NetOutputs, GpuError> {
        if grey.c != 1 || grey.h % 32 != 0 || grey.w % 32 != 0 || grey.h == 0 || grey.w == 0 || !grey.is_consistent() {
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
            self.counters.uploaded.fetch_add((grey.data.len() * 4) as u64, Ordering::Relaxed);
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
            ctx.queue.submit([enc.finish()]);
            let slice = s.staging.slice(..at);
            let (tx, rx) = std::sync::mpsc::channel();
            slice.map_async(wgpu::MapMode::Read, move |r| {
                let _ = tx.send(r);
            });
            ctx.device.poll(wgpu::PollType::wait_indefinitely()).map_err(|e| GpuError::DeviceLost(format!("waiting for the queue: {e}")))?;
            rx.recv().map_err(|_| bad("map callback dropped"))?.map_err(|e| bad(e.to_string()))?;
            let data: Vec<f32> = bytemuck::pod_collect_to_vec(&slice.get_mapped_range().map_err(|e| bad(e.to_string()))?);
            s.staging.unmap();
            self.counters.read_back.fetch_add(at, Ordering::Relaxed);
            Ok(data)
        })??;
        self.counters.frames.fetch_add(1, Ordering::Relaxed);
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
        let stride = (twin_uniform_max() as u64).next_multiple_of(ctx.uniform_offset_alignment() as u64);
        let mut params = vec![0u8; plan.passes.len() * stride as usize];
        for (i, p) in plan.passes.iter().enumerate() {
            let b = p.params.bytes();
            params[i * stride as usize..][..b.len()].copy_from_slice(b);
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
            ctx.count_buffer();
            let pbuf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("xfeat pass parameters"),
                size: params.len() as u64,
                usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            ctx.write(&pbuf, 0, &params);
            ctx.count_buffer();
            let staging = ctx.device.create_buffer(&wgpu::BufferDescriptor {
                label: Some("xfeat read-back"),
                size: out_bytes,
                usage: wgpu::BufferUsages::MAP_READ | wgpu::BufferUsages::COPY_DST,
                mapped_at_creation: false,
            });
            self.counters.created.fetch_add(created + 2, Ordering::Relaxed);
            self.counters.uploaded.fetch_add(params.len() as u64, Ordering::Relaxed);
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

/// The largest of the kernels' uniforms (the stride of the parameter buffer before alignment).
fn twin_uniform_max() -> usize {
    std::mem::size_of::<ConvParams>().max(std::mem::size_of::<MapParams>()).max(std::mem::size_of::<NormParams>())
}

fn kernel(k: &super::kernels::Kernels, e: Entry) -> &Kernel {
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

/// The network's outputs from the values read back (descriptors, then reliability and logits).
fn outputs(plan: &Plan, data: Vec<f32>, heads: bool) -> NetOutputs {
    let (c, h, w) = plan.desc;
    let n = c * h * w;
    let mut data = data;
    let rest = data.split_off(n);
    let descriptors = Chw { c, h, w, data };
    if !heads {
        return NetOutputs { logits: Chw::zeros(0, h, w), descriptors, reliability: None };
    }
    let hn = h * w;
    let reliability = Chw { c: 1, h, w, data: rest[..hn].to_vec() };
    let logits = Chw { c: plan.logits.0, h, w, data: rest[hn..].to_vec() };
    NetOutputs { descriptors, logits, reliability: Some(reliability) }
}

/// The executor's plan run on the CPU twins (`kernels::xfeat`), pass by pass, buffer by buffer:
/// what the device is held to. Slow (the twins are written for equivalence); for tests. What
/// does not fit is an [`Error::Check`].
#[doc(hidden)]
pub fn forward_on_twins(net: &XFeat, grey: &Chw, heads: bool) -> crate::Result<NetOutputs> {
    if grey.c != 1 || grey.h % 32 != 0 || grey.w % 32 != 0 || grey.h == 0 || grey.w == 0 || !grey.is_consistent() {
        return Err(Error::check(format!("input is {}x{}x{}; it must be 1 x (32k) x (32k)", grey.c, grey.h, grey.w)));
    }
    let packed = pack(net)?;
    let plan = Plan::new(&packed, grey.h, grey.w, 65_535).map_err(|e| match e {
        PlanError::Limit(what, n, a) => Error::check(format!("{what}: {n} > {a}")),
        PlanError::Invalid(r) => Error::check(r),
    })?;
    let mut bufs: Vec<Vec<f32>> = plan.sizes.iter().map(|&n| vec![0.0; n]).collect();
    bufs[Buf::Grey as usize].copy_from_slice(&grey.data);
    bufs[Buf::Weights as usize] = packed.weights.clone();
    for p in plan.passes.iter().filter(|p| heads || !p.head) {
        let (ins, out) = p.bufs.split_at(p.bufs.len() - 1);
        let mut o = std::mem::take(&mut bufs[out[0] as usize]);
        let i = |k: usize| bufs[ins[k] as usize].as_slice();
        match (p.entry, &p.params) {
            (Entry::Partials, Params::Norm(np)) => twin::instance_norm_partials(np, i(0), &mut o),
            (Entry::Stats, Params::Norm(np)) => twin::instance_norm_stats(np, i(0), &mut o),
            (Entry::Apply, Params::Norm(np)) => twin::instance_norm_apply(np, i(0), i(1), &mut o),
            (Entry::AvgPool, Params::Map(mp)) => twin::avg_pool(mp, i(0), &mut o),
            (Entry::SpaceToDepth, Params::Map(mp)) => twin::space_to_depth8(mp, i(0), &mut o),
            (Entry::BilinearAdd, Params::Map(mp)) => twin::bilinear_add(mp, i(0), i(1), i(2), &mut o),
            (Entry::Conv, Params::Conv(cp)) => twin::conv2d(cp, i(0), i(1), i(2), &mut o),
            (e, _) => return Err(Error::check(format!("{e:?} planned with another kernel's parameters"))),
        }
        bufs[out[0] as usize] = o;
    }
    let mut data = bufs[Buf::Desc as usize][..plan.desc.0 * plan.desc.1 * plan.desc.2].to_vec();
    if heads {
        data.extend_from_slice(&bufs[Buf::Heat as usize][..plan.desc.1 * plan.desc.2]);
        data.extend_from_slice(&bufs[Buf::Logits as usize][..plan.logits.0 * plan.desc.1 * plan.desc.2]);
    }
    Ok(outputs(&plan, data, heads))
}

/// One `xfeat.wgsl` kernel alone on the device: `entry` (its name) with the uniform `params`
/// and `inputs` bound in binding order, the output (`out_len` values, zeros before the kernel
/// runs) read back. The device side of the twins' tests.
#[doc(hidden)]
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
    if let Some(&d) = grid.iter().find(|&&d| d > ctx.max_workgroups()) {
        return Err(GpuError::LimitsTooSmall {
            adapter: ctx.describe(),
            what: format!("{entry} workgroups"),
            needed: d as u64,
            available: ctx.max_workgroups() as u64,
        });
    }
    ctx.scoped(&format!("running {entry}"), || -> Result<Vec<f32>, GpuError> {
        let mut p = params.to_vec();
        p.resize(twin_uniform_max().next_multiple_of(16), 0);
        ctx.count_buffer();
        let pbuf = ctx.device.create_buffer(&wgpu::BufferDescriptor {
            label: Some("kernel parameters"),
            size: p.len() as u64,
            usage: wgpu::BufferUsages::UNIFORM | wgpu::BufferUsages::COPY_DST,
            mapped_at_creation: false,
        });
        ctx.write(&pbuf, 0, &p);
        let bufs: Vec<wgpu::Buffer> = inputs
            .iter()
            .map(|d| {
                let b = ctx.storage("kernel input", (d.len() * 4) as u64);
                ctx.write(&b, 0, bytemuck::cast_slice(d));
                b
            })
            .collect();
        let out = ctx.storage("kernel output", (out_len * 4) as u64);
        let mut bound: Vec<&wgpu::Buffer> = vec![&pbuf];
        bound.extend(bufs.iter());
        bound.push(&out);
        let k = kernel(&ctx.kernels, e);
        let g = k.bind(&ctx.device, &bound);
        let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some(entry) });
        {
            let mut pass = ctx.begin_pass(&mut enc, entry)?;
            pass.set_pipeline(&k.pipeline);
            pass.set_bind_group(0, Some(&g), &[0]);
            pass.dispatch_workgroups(grid[0], grid[1], grid[2]);
        }
        ctx.queue.submit([enc.finish()]);
        ctx.read_back_values(&out, out_len)
    })?
}

/// The encoder's keypoint network on the device, kept between batches (made again when the
/// weights change): the hook of the GPU encoding path.
#[derive(Default)]
pub struct NetworkSlot(Option<(String, XFeatGpu)>);

impl NetworkSlot {
    /// Frames the device's network has run (0 before the first).
    pub fn frames(&self) -> u64 {
        self.0.as_ref().map_or(0, |x| x.1.counters().frames)
    }

    /// The keypoint network's features of each frame (RGB at the working size), run on the device
    /// when `model` is the native XFeat. `None` for a frame whose features the CPU path is to
    /// compute: every frame when the model is not XFeat (ONNX models run on the CPU) or there is
    /// none, a frame without RGB, or one whose input or decoding fails (the CPU path then reports
    /// why). A device failure fails the batch.
    pub fn features(
        &mut self,
        ctx: &Arc<GpuContext>,
        model: Option<&AppearanceModel>,
        rgbs: &[Option<&RgbImage>],
    ) -> Result<Vec<Option<Features>>, GpuError> {
        let Some((model, net)) = model.and_then(|m| m.xfeat().map(|x| (m, x))) else { return Ok(vec![None; rgbs.len()]) };
        if self.0.as_ref().is_none_or(|(sha, _)| *sha != model.sha256) {
            self.0 = None;
            self.0 = Some((model.sha256.clone(), XFeatGpu::new(ctx.clone(), net)?));
        }
        let x = &self.0.as_ref().expect("made above").1;
        let mut out = Vec::with_capacity(rgbs.len());
        for rgb in rgbs {
            let Some(Ok((grey, sx, sy))) = rgb.map(network_input) else {
                out.push(None);
                continue;
            };
            let t = std::time::Instant::now();
            let net_out = x.forward_with(&grey, model.needs_heads())?;
            out.push(model.decode(&net_out, sx, sy, crate::util::ms_since(t)).ok());
        }
        Ok(out)
    }
}
