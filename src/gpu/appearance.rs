//! The appearance stage's keypoint network on the device: the native XFeat run by its device
//! executor ([`crate::networks::xfeat::XFeatGpu`]), its outputs decoded by the stage
//! ([`AppearanceModel::decode`]), as the CPU path decodes its own run.

use crate::appearance::{AppearanceModel, Features};
use crate::device::context::{GpuContext, GpuError};
use crate::networks::network_input;
use crate::networks::xfeat::XFeatGpu;
use image::RgbImage;
use std::sync::Arc;

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
