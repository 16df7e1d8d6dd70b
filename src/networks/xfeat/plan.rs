//! The XFeat executor's plan: the network's layers packed into one weights buffer, and every pass
//! of the forward pass at a frame size (which kernel, its parameters, which buffers, its grid) as
//! data, which the device executor (`super`) and the twin runner (`super::twins`) both run.

use crate::error::Error;
use crate::networks::xfeat::{Layer, XFeat};
use crate::networks::NetOutputs;
use crate::nn::conv::Chw;
use semlook_kernels::abi::{ConvParams, MapParams, NormParams};
use semlook_kernels::xfeat::pack_conv;

/// The buffers a plan reads and writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(super) enum Buf {
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

pub(super) const BUFS: usize = 16;
pub(super) const ALL: [Buf; BUFS] = [
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
pub(super) enum Entry {
    Partials,
    Stats,
    Apply,
    AvgPool,
    SpaceToDepth,
    BilinearAdd,
    Conv,
}

#[derive(Debug, Clone, Copy)]
pub(super) enum Params {
    Conv(ConvParams),
    Map(MapParams),
    Norm(NormParams),
}

impl Params {
    pub(super) fn bytes(&self) -> &[u8] {
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
pub(super) struct Pass {
    pub(super) entry: Entry,
    pub(super) params: Params,
    pub(super) bufs: Vec<Buf>,
    pub(super) grid: [u32; 3],
    pub(super) head: bool,
}

/// A layer packed into the weights buffer.
#[derive(Debug, Clone, Copy)]
pub(super) struct Packed {
    pub(super) cin: usize,
    pub(super) cout: usize,
    pub(super) k: usize,
    pub(super) stride: usize,
    pub(super) act: u32,
    pub(super) weight_at: u32,
    pub(super) sub_at: u32,
    pub(super) mul_at: u32,
}

/// The network's layers packed, in the graph's blocks, and the packed values.
#[derive(Debug, Clone)]
pub(super) struct PackedNet {
    pub(super) skip1: Packed,
    pub(super) blocks: [Vec<Packed>; 5],
    pub(super) fusion: Vec<Packed>,
    pub(super) fusion_out: Packed,
    pub(super) heatmap: Vec<Packed>,
    pub(super) heatmap_out: Packed,
    pub(super) keypoint: Vec<Packed>,
    pub(super) keypoint_out: Packed,
    pub(super) weights: Vec<f32>,
}

pub(super) fn pack(net: &XFeat) -> crate::Result<PackedNet> {
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
pub(super) type Shape = (usize, usize, usize);

/// Every pass of the forward pass at one frame size, and the buffers' sizes (values).
#[derive(Debug, Clone)]
pub(super) struct Plan {
    /// Workgroups per dispatch dimension the plan keeps within.
    pub(super) max_wg: u32,
    pub(super) sizes: [usize; BUFS],
    pub(super) passes: Vec<Pass>,
    pub(super) desc: Shape,
    pub(super) heat: Shape,
    pub(super) logits: Shape,
}

/// What does not fit a plan: (what, needed, available) for the limits, or a reason.
pub(super) enum PlanError {
    Limit(String, u64, u64),
    Invalid(String),
}

impl Plan {
    pub(super) fn size(&mut self, b: Buf, values: usize) {
        let s = &mut self.sizes[b as usize];
        *s = (*s).max(values);
    }

    /// Appends a convolution of `input` (of shape `x`) into `out`, adding `add` after the
    /// epilogue when given; returns the output's shape.
    pub(super) fn conv(&mut self, l: &Packed, x: Shape, input: Buf, out: Buf, add: Option<(Buf, Shape)>, head: bool) -> Result<Shape, PlanError> {
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
    pub(super) fn chain(&mut self, ls: &[Packed], mut x: Shape, mut input: Buf, end: Option<Buf>, head: bool) -> Result<(Shape, Buf), PlanError> {
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

    pub(super) fn elementwise(&mut self, entry: Entry, p: Params, bufs: Vec<Buf>, grid: [u32; 3], head: bool) -> Result<(), PlanError> {
        if grid[1] > self.max_wg {
            return Err(PlanError::Limit(format!("{entry:?} workgroups per dimension"), grid[1] as u64, self.max_wg as u64));
        }
        self.passes.push(Pass { entry, params: p, bufs, grid, head });
        Ok(())
    }

    /// The plan for a 1 x h x w frame (h, w multiples of 32) under `max_wg` workgroups per
    /// dimension.
    pub(super) fn new(net: &PackedNet, h: usize, w: usize, max_wg: u32) -> Result<Plan, PlanError> {
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

/// The largest of the kernels' uniforms (the stride of the parameter buffer before alignment).
pub(super) fn twin_uniform_max() -> usize {
    std::mem::size_of::<ConvParams>().max(std::mem::size_of::<MapParams>()).max(std::mem::size_of::<NormParams>())
}

/// The network's outputs from the values read back (descriptors, then reliability and logits).
pub(super) fn outputs(plan: &Plan, data: Vec<f32>, heads: bool) -> NetOutputs {
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
