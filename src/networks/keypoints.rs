//! The seam between the keypoint networks and the appearance stage: the grey input every keypoint
//! network takes ([`network_input`]), the outputs it gives ([`NetOutputs`], SuperPoint's layout),
//! the trait the stage runs ([`KeypointNetwork`]) and the ONNX Runtime adapter for any exported
//! model of that layout ([`OnnxKeypoints`]). XFeat implements the trait in its own module.

use crate::error::{Error, Result};
use crate::nn::conv::Chw;
use image::RgbImage;
use std::path::{Path, PathBuf};

/// What a keypoint network gives at 1/8 resolution.
#[derive(Debug, Clone)]
pub struct NetOutputs {
    /// Dense descriptors [D, h, w].
    pub descriptors: Chw,
    /// Keypoint logits [65, h, w], SuperPoint cell layout (64 pixels + dustbin).
    pub logits: Chw,
    /// Reliability [1, h, w] in [0, 1], when the network has one (XFeat).
    pub reliability: Option<Chw>,
}

/// A keypoint network as the appearance stage sees it: a grey image in, [`NetOutputs`] out.
/// Failures are [`Error::Check`] reasons the stage names with the model's file.
pub trait KeypointNetwork: Send + Sync {
    /// Runs the network on a grey image [1, H, W] in [0, 1] (H, W multiples of
    /// [`MIN_NETWORK_SIDE`]); `heads: false` lets a network that can skip its keypoint heads do so
    /// (the logits are then empty).
    fn run(&self, grey: &Chw, heads: bool) -> Result<NetOutputs>;
}

/// Any keypoint network exported to ONNX with SuperPoint's output layout (65-channel cell
/// logits, dense descriptors, optionally a one-channel reliability map), run by ONNX Runtime.
pub struct OnnxKeypoints {
    sessions: crate::nn::onnx::SessionPool,
    logits: usize,
    reliability: Option<usize>,
    descriptors: usize,
}

impl OnnxKeypoints {
    /// Loads the model at `path` (`onnxruntime`: see [`crate::nn::onnx::library_path`]) and tells
    /// its outputs apart; fails, naming the file, when it cannot.
    pub fn load(path: &Path, onnxruntime: Option<&Path>) -> Result<OnnxKeypoints> {
        let sessions = crate::nn::onnx::SessionPool::new(path, onnxruntime)?;
        let (logits, reliability, descriptors) =
            sessions.with_shared(|s| identify_outputs(s)).map_err(|e| e.named(|reason| Error::Model { path: PathBuf::from(path), reason }))?;
        Ok(OnnxKeypoints { sessions, logits, reliability, descriptors })
    }
}

impl KeypointNetwork for OnnxKeypoints {
    /// Runs every head (an exported graph cannot skip them).
    fn run(&self, grey: &Chw, _heads: bool) -> Result<NetOutputs> {
        let (logits, reliability, descriptors) = (self.logits, self.reliability, self.descriptors);
        self.sessions.run(|s| {
            let input = ort::value::TensorRef::from_array_view(([1usize, 1, grey.h, grey.w], grey.data.as_slice()))
                .map_err(|e| Error::check(e.to_string()))?;
            let outputs = s.run(ort::inputs![input]).map_err(|e| Error::check(e.to_string()))?;
            let get = |i: usize| -> Result<Chw> {
                let value = outputs.values().nth(i).ok_or_else(|| Error::check(format!("the model returned no output {i}")))?;
                let (shape, data) = value.try_extract_tensor::<f32>().map_err(|e| Error::check(format!("output {i}: {e}")))?;
                let [1, c, h, w] = shape[..] else { return Err(Error::check(format!("output {i} has shape {shape:?}, expected [1, C, h, w]"))) };
                let dims = [c, h, w].map(|d| usize::try_from(d).ok().filter(|&d| d > 0));
                let [Some(c), Some(h), Some(w)] = dims else {
                    return Err(Error::check(format!("output {i} has shape {shape:?}, expected [1, C, h, w]")));
                };
                if c.checked_mul(h).and_then(|v| v.checked_mul(w)) != Some(data.len()) {
                    return Err(Error::check(format!("output {i} holds {} values for shape {shape:?}", data.len())));
                }
                Ok(Chw { c, h, w, data: data.to_vec() })
            };
            let out = NetOutputs { descriptors: get(descriptors)?, logits: get(logits)?, reliability: reliability.map(get).transpose()? };
            let same = |m: &Chw| (m.h, m.w) == (out.descriptors.h, out.descriptors.w);
            if out.logits.c != 65 || !same(&out.logits) || !out.reliability.as_ref().is_none_or(|r| r.c == 1 && same(r)) || out.descriptors.c == 0 {
                return Err(Error::check(format!(
                    "outputs are not SuperPoint's layout: logits {}x{}x{} (need 65 channels), descriptors {}x{}x{}, all at one resolution",
                    out.logits.c, out.logits.h, out.logits.w, out.descriptors.c, out.descriptors.h, out.descriptors.w
                )));
            }
            Ok(out)
        })
    }
}

/// Which outputs are logits (65 channels), reliability (1 channel) and descriptors (the rest),
/// from the static shapes, else from the names XFeat and SuperPoint exports use.
fn identify_outputs(session: &ort::session::Session) -> Result<(usize, Option<usize>, usize)> {
    let n = session.outputs().len();
    let (mut logits, mut rel, mut desc) = (None, None, None);
    for i in 0..n {
        let shape = crate::nn::onnx::output_shape(session, i);
        let name = session.outputs()[i].name().to_ascii_lowercase();
        match shape.get(1).copied() {
            Some(65) => logits = Some(i),
            Some(1) => rel = Some(i),
            Some(c) if c > 1 => desc = Some(i),
            _ if name.contains("semi") || name.contains("keypoint") => logits = Some(i),
            _ if name.contains("heat") || name.contains("reliab") => rel = Some(i),
            _ if name.contains("desc") || name.contains("feat") => desc = Some(i),
            _ => {}
        }
    }
    match (logits, desc) {
        (Some(l), Some(d)) => Ok((l, rel, d)),
        _ => Err(Error::check(format!("cannot tell keypoint logits (65 channels) and descriptors apart among {n} outputs"))),
    }
}

/// The smallest side a keypoint network takes: XFeat's input sides are multiples of 32.
pub const MIN_NETWORK_SIDE: usize = 32;

/// Grey network input in [0, 1] with sides rounded down to multiples of 32 (bilinear, as
/// XFeat's preprocessing), and the factors back to image pixels.
pub fn network_input(rgb: &RgbImage) -> Result<(Chw, f32, f32)> {
    let (w, h) = (rgb.width() as usize, rgb.height() as usize);
    let (w32, h32) = (w / MIN_NETWORK_SIDE * MIN_NETWORK_SIDE, h / MIN_NETWORK_SIDE * MIN_NETWORK_SIDE);
    if w32 == 0 || h32 == 0 {
        return Err(Error::invalid("image", format!("{w}x{h} is below the {MIN_NETWORK_SIDE}x{MIN_NETWORK_SIDE} a keypoint network needs")));
    }
    let data = rgb.pixels().map(|p| (p.0[0] as f32 + p.0[1] as f32 + p.0[2] as f32) / (3.0 * 255.0)).collect();
    let grey = Chw { c: 1, h, w, data };
    let grey = if (w32, h32) == (w, h) {
        grey
    } else {
        crate::nn::conv::resize_bilinear(&grey, h32, w32).map_err(|e| e.named(|r| Error::invalid("image", r)))?
    };
    Ok((grey, w as f32 / w32 as f32, h as f32 / h32 as f32))
}
