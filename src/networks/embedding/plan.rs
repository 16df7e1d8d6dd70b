//! The embedding executor's plan: every pass of [`EfficientNetLite::forward`] at a frame size
//! (which kernel of `shaders/efficientnet.wgsl`, its parameters, which buffers, its grid) as data,
//! which the device executor (`super::device`) and the twin runner (`super::twins`) both run.
//!
//! Buffers: the frame (RGB 0..255, [3, H, W]), three activation buffers each as large as the
//! largest activation at this size (a block reads its input, the expansion and the depthwise
//! output, and writes a fourth tensor: with the residual's input kept, three suffice, each pass
//! writing one that none of its inputs is), the pooled values, and each convolution's weights and
//! bias (resident, numbered in the network's order: stem, per block expansion, depthwise,
//! projection, head).

use super::efficientnet::{Conv, EfficientNetLite, INPUT_MEAN, INPUT_STD};
use crate::nn::conv::same_padding;
use semlook_kernels::abi::{EffConvParams, EffPointParams, GemParams};
use semlook_kernels::efficientnet::{LANES, TILE};

/// Activation buffers a plan rotates through.
pub(super) const ACTS: usize = 3;

/// A buffer a pass binds.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Buf {
    /// The frame, RGB 0..255.
    Input,
    /// Activation buffer 0..ACTS.
    Act(usize),
    /// The GeM values, one per channel of the head.
    Pooled,
    /// Convolution i's weights (resident).
    Weight(usize),
    /// Convolution i's bias (resident).
    Bias(usize),
    /// Bound where a kernel reads nothing (`pointwise`'s residual when it adds none).
    Unused,
}

/// The kernels.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Entry {
    Direct,
    Pointwise,
    Gem,
}

/// A pass's uniform.
#[derive(Debug, Clone, Copy)]
pub(super) enum Params {
    Direct(EffConvParams),
    Point(EffPointParams),
    Gem(GemParams),
}

impl Params {
    pub(super) fn bytes(&self) -> &[u8] {
        match self {
            Params::Direct(p) => bytemuck::bytes_of(p),
            Params::Point(p) => bytemuck::bytes_of(p),
            Params::Gem(p) => bytemuck::bytes_of(p),
        }
    }
}

/// The largest uniform of the file (the stride a plan's parameters are laid out at is this,
/// rounded up to the device's offset alignment).
pub(super) fn uniform_max() -> usize {
    [std::mem::size_of::<EffConvParams>(), std::mem::size_of::<EffPointParams>(), std::mem::size_of::<GemParams>()].into_iter().max().unwrap_or(0)
}

/// One dispatch: the kernel, its uniform, its storage bindings in binding order (the output
/// last), its grid.
#[derive(Debug, Clone)]
pub(super) struct Pass {
    pub(super) entry: Entry,
    pub(super) params: Params,
    pub(super) bufs: Vec<Buf>,
    pub(super) grid: [u32; 3],
}

/// Every pass at one frame size, and the buffers' lengths (values).
#[derive(Debug, Clone)]
pub(super) struct Plan {
    pub(super) passes: Vec<Pass>,
    /// Values of the frame.
    pub(super) input_len: usize,
    /// Values of each activation buffer.
    pub(super) act_len: usize,
    /// Values pooled (the head's channels).
    pub(super) dim: usize,
}

/// Why a plan cannot be made: a size beyond the device's limits (what, needed, available), or an
/// input the network cannot take.
#[derive(Debug)]
pub(super) enum PlanError {
    Limit(String, u64, u64),
    Invalid(String),
}

/// The network's convolutions in plan order (stem, per block expansion, depthwise, projection,
/// head): what `Buf::Weight(i)` and `Buf::Bias(i)` name.
pub(super) fn convs(net: &EfficientNetLite) -> Vec<&Conv> {
    let mut out = vec![&net.stem];
    for b in &net.blocks {
        out.extend(b.expand.as_ref());
        out.push(&b.depthwise);
        out.push(&b.project);
    }
    out.push(&net.head);
    out
}

/// A one-dimensional grid of `n` invocations in LANES-wide workgroups, as (x, y) rows of at most
/// `max` workgroups; the row's length is the kernel's `row`.
fn flat_grid(what: &str, n: usize, max: u32) -> Result<([u32; 3], u32), PlanError> {
    let groups = n.div_ceil(LANES);
    let row = groups.clamp(1, max as usize);
    let rows = groups.div_ceil(row);
    if rows > max as usize {
        return Err(PlanError::Limit(format!("{what}: workgroup rows"), rows as u64, max as u64));
    }
    Ok(([row as u32, rows as u32, 1], row as u32))
}

impl Plan {
    /// The passes of `net` on an h x w frame, grids within `max_workgroups` a dimension.
    pub(super) fn new(net: &EfficientNetLite, h: usize, w: usize, max_workgroups: u32) -> Result<Plan, PlanError> {
        if h == 0 || w == 0 {
            return Err(PlanError::Invalid(format!("an empty frame ({w}x{h}) has no embedding")));
        }
        let mut plan = Plan { passes: vec![], input_len: 3 * h * w, act_len: 1, dim: net.head.cout };
        let mut index = 0usize;
        let mut next_conv = || {
            index += 1;
            index - 1
        };
        // the buffer a pass writes: the first activation buffer none of its inputs is
        let free = |busy: &[Buf]| -> Buf {
            let i = (0..ACTS).find(|&i| !busy.contains(&Buf::Act(i))).expect("three buffers, at most two busy");
            Buf::Act(i)
        };
        let direct =
            |plan: &mut Plan, i: usize, conv: &Conv, src: Buf, (c, h, w): (usize, usize, usize), stride: usize, depthwise: bool, busy: &[Buf]| {
                let (ho, wo) = (h.div_ceil(stride), w.div_ceil(stride));
                let n = conv.cout * ho * wo;
                let (grid, row) = flat_grid(&format!("convolution {i} at {w}x{h}"), n, max_workgroups)?;
                if depthwise && conv.cin != c {
                    return Err(PlanError::Invalid(format!("convolution {i}: a depthwise convolution of {} channels on {c}", conv.cin)));
                }
                let (scale, shift) = if src == Buf::Input { (1.0 / INPUT_STD, -INPUT_MEAN / INPUT_STD) } else { (1.0, 0.0) };
                let p = EffConvParams {
                    cin: c as u32,
                    cout: conv.cout as u32,
                    h: h as u32,
                    w: w as u32,
                    ho: ho as u32,
                    wo: wo as u32,
                    k: conv.k as u32,
                    stride: stride as u32,
                    pad_top: same_padding(h, conv.k, stride).0 as u32,
                    pad_left: same_padding(w, conv.k, stride).0 as u32,
                    depthwise: depthwise as u32,
                    relu6: 1,
                    scale,
                    shift,
                    row,
                    n: n as u32,
                };
                let out = free(busy);
                plan.act_len = plan.act_len.max(n);
                plan.passes.push(Pass { entry: Entry::Direct, params: Params::Direct(p), bufs: vec![src, Buf::Weight(i), Buf::Bias(i), out], grid });
                Ok::<_, PlanError>((out, conv.cout, ho, wo))
            };
        let pointwise = |plan: &mut Plan, i: usize, conv: &Conv, src: Buf, c: usize, hw: usize, relu6: bool, residual: Option<Buf>| {
            if conv.cin != c || conv.k != 1 {
                return Err(PlanError::Invalid(format!(
                    "convolution {i}: a {}x{} convolution of {} channels planned as 1x1 on {c}",
                    conv.k, conv.k, conv.cin
                )));
            }
            let grid = [hw.div_ceil(TILE) as u32, conv.cout.div_ceil(TILE) as u32, 1];
            if let Some(&g) = grid.iter().find(|&&g| g > max_workgroups) {
                return Err(PlanError::Limit(format!("convolution {i}: workgroups"), g as u64, max_workgroups as u64));
            }
            let p = EffPointParams {
                cin: c as u32,
                cout: conv.cout as u32,
                hw: hw as u32,
                relu6: relu6 as u32,
                residual: residual.is_some() as u32,
                _pad: [0; 3],
            };
            let busy: Vec<Buf> = [Some(src), residual].into_iter().flatten().collect();
            let out = free(&busy);
            plan.act_len = plan.act_len.max(conv.cout * hw);
            plan.passes.push(Pass {
                entry: Entry::Pointwise,
                params: Params::Point(p),
                bufs: vec![src, Buf::Weight(i), Buf::Bias(i), residual.unwrap_or(Buf::Unused), out],
                grid,
            });
            Ok::<_, PlanError>((out, conv.cout))
        };
        let (mut cur, mut c, mut h, mut w) = direct(&mut plan, next_conv(), &net.stem, Buf::Input, (3, h, w), 2, false, &[])?;
        for b in &net.blocks {
            let input = cur;
            if let Some(e) = &b.expand {
                (cur, c) = pointwise(&mut plan, next_conv(), e, cur, c, h * w, true, None)?;
            }
            (cur, c, h, w) = direct(&mut plan, next_conv(), &b.depthwise, cur, (c, h, w), b.stride, true, &[cur, input])?;
            (cur, c) = pointwise(&mut plan, next_conv(), &b.project, cur, c, h * w, false, b.residual.then_some(input))?;
        }
        (cur, c) = pointwise(&mut plan, next_conv(), &net.head, cur, c, h * w, true, None)?;
        let gp = GemParams { c: c as u32, hw: (h * w) as u32, _pad: [0; 2] };
        plan.passes.push(Pass {
            entry: Entry::Gem,
            params: Params::Gem(gp),
            bufs: vec![cur, Buf::Pooled],
            grid: [c.div_ceil(LANES).max(1) as u32, 1, 1],
        });
        Ok(plan)
    }
}
