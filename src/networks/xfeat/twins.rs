//! The executor's plan run on the CPU twins (`semlook_kernels::xfeat`) instead of the device: the
//! reference the device is held to.

use super::plan::{outputs, pack, Buf, Entry, Params, Plan, PlanError};
use crate::error::Error;
use crate::networks::xfeat::XFeat;
use crate::networks::NetOutputs;
use crate::nn::conv::Chw;
use semlook_kernels::xfeat as twin;

/// The executor's plan run on the CPU twins (`semlook_kernels::xfeat`), pass by pass, buffer by buffer:
/// what the device is held to. Slow (the twins are written for equivalence): the reference a device
/// or a port is checked against. What
/// does not fit is an [`Error::Check`].
pub fn forward_on_twins(net: &XFeat, grey: &Chw, heads: bool) -> crate::Result<NetOutputs> {
    if grey.c != 1 || !grey.h.is_multiple_of(32) || !grey.w.is_multiple_of(32) || grey.h == 0 || grey.w == 0 || !grey.is_consistent() {
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
