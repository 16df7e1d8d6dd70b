//! The executor's plan run on the CPU twins (`semlook_kernels::efficientnet`) instead of the
//! device: the reference the device is held to.

use super::efficientnet::EfficientNetLite;
use super::plan::{convs, Buf, Entry, Params, Plan, PlanError, ACTS};
use crate::error::Error;
use crate::nn::conv::Chw;
use semlook_kernels::efficientnet as twin;

/// The embedding of an RGB image [3, H, W] with values 0..255 by the device executor's plan run
/// on the CPU twins (`semlook_kernels::efficientnet`), pass by pass, buffer by buffer, normalised
/// as [`super::EmbedderGpu::forward`] normalises what it reads back: what the device is held to.
/// Slow (the twins are written for equivalence). What does not fit is an [`Error::Check`].
pub fn forward_on_twins(net: &EfficientNetLite, rgb: &Chw) -> crate::Result<Vec<f32>> {
    super::efficientnet::check_rgb(rgb).map_err(Error::check)?;
    let plan = Plan::new(net, rgb.h, rgb.w, 65_535).map_err(|e| match e {
        PlanError::Limit(what, n, a) => Error::check(format!("{what}: {n} > {a}")),
        PlanError::Invalid(r) => Error::check(r),
    })?;
    let convs = convs(net);
    let mut acts: Vec<Vec<f32>> = (0..ACTS).map(|_| vec![0.0; plan.act_len]).collect();
    let mut pooled = vec![0.0f32; plan.dim];
    for p in &plan.passes {
        let (ins, out) = p.bufs.split_at(p.bufs.len() - 1);
        let mut o = match out[0] {
            Buf::Act(i) => std::mem::take(&mut acts[i]),
            Buf::Pooled => std::mem::take(&mut pooled),
            b => return Err(Error::check(format!("{b:?} planned as an output"))),
        };
        let get = |b: Buf| -> &[f32] {
            match b {
                Buf::Input => &rgb.data,
                Buf::Act(i) => &acts[i],
                Buf::Pooled => &pooled,
                Buf::Weight(i) => &convs[i].weight,
                Buf::Bias(i) => &convs[i].bias,
                Buf::Unused => &[],
            }
        };
        let i = |k: usize| get(ins[k]);
        match (p.entry, &p.params) {
            (Entry::Direct, Params::Direct(cp)) => twin::conv_direct(cp, i(0), i(1), i(2), &mut o),
            (Entry::Pointwise, Params::Point(pp)) => twin::pointwise(pp, i(0), i(1), i(2), i(3), &mut o),
            (Entry::Gem, Params::Gem(gp)) => twin::gem_pool(gp, i(0), &mut o),
            (e, _) => return Err(Error::check(format!("{e:?} planned with another kernel's parameters"))),
        }
        match out[0] {
            Buf::Act(i) => acts[i] = o,
            _ => pooled = o,
        }
    }
    super::device::normalise_pooled(&pooled).ok_or_else(|| Error::check("the embedding is zero, NaN or infinite"))
}
