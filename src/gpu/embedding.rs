//! The whole-image embedding on the device: the network run natively from its checkpoint
//! ([`crate::networks::embedding::EfficientNetLite`]) by its device executor
//! ([`crate::networks::embedding::EmbedderGpu`]), finished as the CPU path finishes its own run
//! ([`Embedder::finish`]).

use crate::device::context::{GpuContext, GpuError};
use crate::networks::embedding::{network_input, Embedder, EmbedderGpu};
use image::RgbImage;
use std::sync::Arc;

/// The encoder's embedding network on the device, kept between batches (made again when the
/// network changes): the hook of the GPU encoding path.
#[derive(Default)]
pub struct EmbeddingSlot(Option<(String, EmbedderGpu)>);

impl EmbeddingSlot {
    /// Frames the device's network has run (0 before the first).
    pub fn frames(&self) -> u64 {
        self.0.as_ref().map_or(0, |x| x.1.counters().frames)
    }

    /// The embedding of each frame and its milliseconds, made on the device when `embedder` runs
    /// natively. `None` for a frame the CPU path is to embed: every frame when the network is an
    /// ONNX graph (ONNX Runtime runs it on the host) or there is none, a frame without RGB, or
    /// one whose input or result fails (the CPU path then reports why). A device failure fails
    /// the batch.
    pub fn embeddings(
        &mut self,
        ctx: &Arc<GpuContext>,
        embedder: Option<&Embedder>,
        rgbs: &[Option<&RgbImage>],
    ) -> Result<Vec<Option<(Vec<f32>, f64)>>, GpuError> {
        let Some((embedder, net)) = embedder.and_then(|e| e.native().map(|n| (e, n))) else { return Ok(vec![None; rgbs.len()]) };
        if self.0.as_ref().is_none_or(|(sha, _)| sha != embedder.sha256()) {
            self.0 = None;
            self.0 = Some((embedder.sha256().to_string(), EmbedderGpu::new(ctx.clone(), net)?));
        }
        let gpu = &self.0.as_ref().expect("made above").1;
        let mut out = Vec::with_capacity(rgbs.len());
        for rgb in rgbs {
            // timed as the CPU path times its own: the resize included
            let t = std::time::Instant::now();
            let Some(Ok(input)) = rgb.map(|r| network_input(r, embedder.long_side())) else {
                out.push(None);
                continue;
            };
            // a device failure fails the batch; values the checks refuse (zero, NaN) go to the CPU
            // path, which reports them for this frame alone
            let pooled = gpu.pooled(&input)?;
            out.push(embedder.finish(pooled).ok().map(|v| (v, crate::util::ms_since(t))));
        }
        Ok(out)
    }
}
