//! GPU executor of the learned matcher LighterGlue (`shaders/lighterglue.wgsl`): a batch of
//! (query, reference) keypoint pairs through the network at once, every point of every pair one
//! row, the kernels' partner tables keeping the pairs apart; the assignment's best partners come
//! back, mutual matches above the threshold are kept on the host, RANSAC follows on the CPU
//! (`verify`), as with the MNN kernel.
//!
//! The forward pass is written once ([`forward`]) over a [`Backend`]: the device ([`GlueGpu`])
//! or the CPU twins (`semlook_kernels::lighterglue`, [`forward_on_twins`]), which is what the device is
//! held to. It follows `networks::lighterglue::LighterGlue::forward` pass for pass: per layer a
//! self- and a cross-attention block; after each layer but the last, where asked, early exit
//! (depth confidence, per pair) and point pruning (width confidence): the heads' logits come back
//! (one read of one or two values a row), the host decides, and `lg_gather` moves the kept rows
//! together. Without pruning and early exit, a batch is one submission and one read-back.
//!
//! Residency: the packed weights are uploaded once, when the executor is made; the activation
//! buffers and the pass parameters are kept between batches and regrown only when a batch needs
//! more. A batch whose largest buffer exceeds the device's storage binding is split into smaller
//! batches (pairs are independent); one pair too large for the binding is a typed
//! [`GpuError::LimitsTooSmall`].

use crate::descriptors::keypoints::KeypointsRef;
use crate::device::buffers::{PassBuffer, Reused};
use crate::device::context::{GpuContext, GpuError};
use crate::device::kernels::Kernel;
use crate::networks::lighterglue::{confidence_threshold, network_inputs, GlueMatch, GlueParams, LighterGlue, PackedFfn, PackedGlue, PackedLinear};
use crate::nn::dense::sigmoid;
use semlook_kernels::abi::LgParams;
use semlook_kernels::lighterglue::{self as twin, grid, FLAG_ACCUMULATE, FLAG_GELU, LANES, LN_ROWS, NO_PARTNER, TILE};
use std::sync::Arc;

/// The buffers of a batch.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Buf {
    /// The input descriptors (rows of input_dim).
    Desc,
    /// The points' states (rows of d).
    X,
    /// The buffer pruning gathers the states into (X and X2 swap).
    X2,
    /// The rotary encodings (rows of d).
    Enc,
    /// The buffer pruning gathers the encodings into.
    Enc2,
    /// Wqkv's output (rows of 3d).
    T3,
    /// Queries, keys and values in three planes of rows x d.
    Qkv,
    /// Attention's output.
    Ctx,
    /// The message (attention's output projected).
    Msg,
    /// The feed-forward's hidden rows (2d).
    H,
    /// The heads' logits: matchability, then token confidence (a plane each).
    Heads,
    /// The assignment's projected descriptors.
    Md,
    /// The assignment's matchability logits.
    Z,
    /// Each row's assignment bias.
    Bias,
    /// Each row's best score.
    Val,
    /// Self-attention's partner table (u32 (first row, count) a row).
    TSelf,
    /// Cross-attention's and the assignment's partner table.
    TCross,
    /// The rows pruning keeps (u32).
    Index,
    /// Each row's best partner (u32).
    Best,
    /// The packed weights (resident).
    Weights,
    /// Bound where a kernel reads nothing.
    Unused,
}

const BUFS: usize = 21;

/// The kernels of `lighterglue.wgsl`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Entry {
    /// `lg_linear`.
    Linear,
    /// `lg_layer_norm`.
    LayerNorm,
    /// `lg_rotary`.
    Rotary,
    /// `lg_attention`.
    Attention,
    /// `lg_row_lse`.
    RowLse,
    /// `lg_assignment_best`.
    AssignmentBest,
    /// `lg_gather`.
    Gather,
}

impl Entry {
    /// The entry point's name (its twin's).
    pub fn name(self) -> &'static str {
        match self {
            Entry::Linear => "lg_linear",
            Entry::LayerNorm => "lg_layer_norm",
            Entry::Rotary => "lg_rotary",
            Entry::Attention => "lg_attention",
            Entry::RowLse => "lg_row_lse",
            Entry::AssignmentBest => "lg_assignment_best",
            Entry::Gather => "lg_gather",
        }
    }
}

/// One dispatch: the kernel, its parameters and what is bound to its `a`, `b`, `out`, `table`
/// and `best` (each kernel uses some of them; the weights are always the packed weights).
#[derive(Debug, Clone, Copy)]
pub struct Pass {
    /// The kernel.
    pub entry: Entry,
    /// Its uniform.
    pub p: LgParams,
    /// Binding 1.
    pub a: Buf,
    /// Binding 2.
    pub b: Buf,
    /// Binding 4.
    pub out: Buf,
    /// Binding 5.
    pub table: Buf,
    /// Binding 6.
    pub best: Buf,
}

/// Where the forward pass runs.
pub trait Backend {
    /// Makes every buffer at least as long as asked (values; contents unspecified).
    fn alloc(&mut self, sizes: &[(Buf, usize)]) -> Result<(), GpuError>;
    /// Writes f32 values at the start of a buffer.
    fn upload(&mut self, buf: Buf, data: &[f32]) -> Result<(), GpuError>;
    /// Writes u32 values at the start of a buffer.
    fn upload_u32(&mut self, buf: Buf, data: &[u32]) -> Result<(), GpuError>;
    /// Runs (or records) one dispatch.
    fn run(&mut self, pass: Pass) -> Result<(), GpuError>;
    /// The first `len` f32 values of a buffer, after every dispatch run so far.
    fn read(&mut self, buf: Buf, len: usize) -> Result<Vec<f32>, GpuError>;
    /// The first `len` u32 values of a buffer.
    fn read_u32(&mut self, buf: Buf, len: usize) -> Result<Vec<u32>, GpuError>;
}

/// One pair's rows in the batch: side 0 at `start`, side 1 right after it.
struct PairRows {
    /// The pair's place in the caller's list.
    k: usize,
    start: usize,
    /// Each row's keypoint index, side 0 then side 1.
    index0: Vec<u32>,
    index1: Vec<u32>,
    /// Points of both sides before any pruning.
    orig: usize,
}

impl PairRows {
    fn m(&self) -> usize {
        self.index0.len()
    }
    fn n(&self) -> usize {
        self.index1.len()
    }
}

fn p0() -> LgParams {
    LgParams { scale: 1.0, ..LgParams::default() }
}

/// `y (+)= (x W^T + b) scale` over `rows` rows; `b_in` holds x's columns past `split` (or is unused).
#[allow(clippy::too_many_arguments)]
fn linear(
    be: &mut dyn Backend,
    l: &PackedLinear,
    rows: usize,
    a: Buf,
    b_in: Option<(Buf, u32)>,
    out: Buf,
    o_off: usize,
    scale: f32,
    acc: bool,
) -> Result<(), GpuError> {
    let (b, split) = b_in.unwrap_or((Buf::Unused, l.n_in));
    be.run(Pass {
        entry: Entry::Linear,
        p: LgParams {
            rows: rows as u32,
            n_in: l.n_in,
            n_out: l.n_out,
            split,
            w_off: l.w_off,
            b_off: l.b_off,
            flags: if acc { FLAG_ACCUMULATE } else { 0 },
            scale,
            o_off: o_off as u32,
            ..p0()
        },
        a,
        b,
        out,
        table: Buf::Unused,
        best: Buf::Unused,
    })
}

/// `x += l2(gelu(norm(l1([x, msg]))))`.
fn ffn(be: &mut dyn Backend, f: &PackedFfn, rows: usize, x: Buf, d: usize) -> Result<(), GpuError> {
    linear(be, &f.l1, rows, x, Some((Buf::Msg, d as u32)), Buf::H, 0, 1.0, false)?;
    be.run(Pass {
        entry: Entry::LayerNorm,
        p: LgParams { rows: rows as u32, n_in: f.l1.n_out, g_off: f.ln_g, b_off: f.ln_b, flags: FLAG_GELU, ..p0() },
        a: Buf::Unused,
        b: Buf::Unused,
        out: Buf::H,
        table: Buf::Unused,
        best: Buf::Unused,
    })?;
    linear(be, &f.l2, rows, Buf::H, None, x, 0, 1.0, true)
}

#[allow(clippy::too_many_arguments)]
fn attention(be: &mut dyn Backend, rows: usize, d: usize, table: Buf, q_off: usize, k_off: usize, v_off: usize, scale: f32) -> Result<(), GpuError> {
    be.run(Pass {
        entry: Entry::Attention,
        p: LgParams { rows: rows as u32, n_in: d as u32, q_off: q_off as u32, k_off: k_off as u32, v_off: v_off as u32, scale, ..p0() },
        a: Buf::Qkv,
        b: Buf::Unused,
        out: Buf::Ctx,
        table,
        best: Buf::Unused,
    })
}

/// Where the current states and encodings are (they swap with pruning).
#[derive(Clone, Copy)]
struct Live {
    x: Buf,
    enc: Buf,
    rows: usize,
}

fn layer(be: &mut dyn Backend, net: &PackedGlue, i: usize, s: Live) -> Result<(), GpuError> {
    let (d, rows, l) = (net.d, s.rows, &net.layers[i]);
    // self-attention
    linear(be, &l.wqkv, rows, s.x, None, Buf::T3, 0, 1.0, false)?;
    be.run(Pass {
        entry: Entry::Rotary,
        p: LgParams { rows: rows as u32, n_in: d as u32, q_off: 0, k_off: (rows * d) as u32, v_off: (2 * rows * d) as u32, ..p0() },
        a: Buf::T3,
        b: s.enc,
        out: Buf::Qkv,
        table: Buf::Unused,
        best: Buf::Unused,
    })?;
    attention(be, rows, d, Buf::TSelf, 0, rows * d, 2 * rows * d, 1.0 / (d as f32).sqrt())?;
    linear(be, &l.self_out, rows, Buf::Ctx, None, Buf::Msg, 0, 1.0, false)?;
    ffn(be, &l.self_ffn, rows, s.x, d)?;
    // cross-attention: queries and keys share a projection, scaled by d^-1/4 each
    let root = (1.0 / (d as f32).sqrt()).sqrt();
    linear(be, &l.to_qk, rows, s.x, None, Buf::Qkv, 0, root, false)?;
    linear(be, &l.to_v, rows, s.x, None, Buf::Qkv, 2 * rows * d, 1.0, false)?;
    attention(be, rows, d, Buf::TCross, 0, 0, 2 * rows * d, 1.0)?;
    linear(be, &l.cross_out, rows, Buf::Ctx, None, Buf::Msg, 0, 1.0, false)?;
    ffn(be, &l.cross_ffn, rows, s.x, d)
}

/// The assignment of layer `i`'s head: each row's best partner and its log assignment.
fn assignment(be: &mut dyn Backend, net: &PackedGlue, i: usize, s: Live) -> Result<(Vec<f32>, Vec<u32>), GpuError> {
    let (d, rows, l) = (net.d, s.rows, &net.layers[i]);
    linear(be, &l.final_proj, rows, s.x, None, Buf::Md, 0, 1.0 / (d as f32).powf(0.25), false)?;
    linear(be, &l.matchability, rows, s.x, None, Buf::Z, 0, 1.0, false)?;
    let p = LgParams { rows: rows as u32, n_in: d as u32, ..p0() };
    be.run(Pass { entry: Entry::RowLse, p, a: Buf::Md, b: Buf::Z, out: Buf::Bias, table: Buf::TCross, best: Buf::Unused })?;
    be.run(Pass {
        entry: Entry::AssignmentBest,
        p: LgParams { scale: 2.0, ..p },
        a: Buf::Md,
        b: Buf::Bias,
        out: Buf::Val,
        table: Buf::TCross,
        best: Buf::Best,
    })?;
    Ok((be.read(Buf::Val, rows)?, be.read_u32(Buf::Best, rows)?))
}

/// Mutual best partners above the threshold of one pair, by the first image's keypoints.
fn matches_of(pr: &PairRows, val: &[f32], best: &[u32], th: f32) -> Vec<GlueMatch> {
    let (s0, s1) = (pr.start, pr.start + pr.m());
    let mut out = Vec::new();
    for i in 0..pr.m() {
        let j = best[s0 + i];
        if j == NO_PARTNER || j as usize >= pr.n() || best[s1 + j as usize] != i as u32 {
            continue;
        }
        let p = val[s0 + i].exp();
        if p > th {
            out.push((pr.index0[i], pr.index1[j as usize], p));
        }
    }
    out
}

/// Partner tables of the pairs' current rows: (self-attention, cross-attention).
fn tables(pairs: &[PairRows], rows: usize) -> (Vec<u32>, Vec<u32>) {
    let (mut ts, mut tc) = (Vec::with_capacity(2 * rows), Vec::with_capacity(2 * rows));
    for pr in pairs {
        let (s0, s1, m, n) = (pr.start as u32, (pr.start + pr.m()) as u32, pr.m() as u32, pr.n() as u32);
        for _ in 0..m {
            ts.extend([s0, m]);
            tc.extend([s1, n]);
        }
        for _ in 0..n {
            ts.extend([s1, n]);
            tc.extend([s0, m]);
        }
    }
    (ts, tc)
}

/// The values a batch of `rows` rows needs of each buffer.
fn sizes(rows: usize, d: usize, input_dim: usize) -> [(Buf, usize); 19] {
    use Buf::*;
    [
        (Desc, rows * input_dim),
        (X, rows * d),
        (X2, rows * d),
        (Enc, rows * d),
        (Enc2, rows * d),
        (T3, rows * 3 * d),
        (Qkv, rows * 3 * d),
        (Ctx, rows * d),
        (Msg, rows * d),
        (H, rows * 2 * d),
        (Heads, rows * 2),
        (Md, rows * d),
        (Z, rows),
        (Bias, rows),
        (Val, rows),
        (TSelf, rows * 2),
        (TCross, rows * 2),
        (Index, rows),
        (Best, rows),
    ]
}

/// LighterGlue's matches of every pair, as `LighterGlue::match_keypoints` gives them (pairs with
/// a side without keypoints, or of another descriptor length, have none), run on `be`.
pub fn forward(
    be: &mut dyn Backend,
    packed: &PackedGlue,
    p: &GlueParams,
    pairs: &[(KeypointsRef, KeypointsRef)],
) -> Result<Vec<Vec<GlueMatch>>, GpuError> {
    let (d, n_layers) = (packed.d, packed.layers.len());
    let mut out = vec![Vec::new(); pairs.len()];
    let mut live: Vec<PairRows> = Vec::new();
    let (mut desc, mut enc) = (Vec::new(), Vec::new());
    let mut rows = 0;
    for (k, (a, b)) in pairs.iter().enumerate() {
        if a.is_empty() || b.is_empty() || a.dim != packed.input_dim || b.dim != packed.input_dim {
            continue;
        }
        let ((ka, da), (kb, db)) = (network_inputs(*a), network_inputs(*b));
        let (m, n) = (ka.len() / 2, kb.len() / 2);
        desc.extend(da);
        desc.extend(db);
        enc.extend(packed.rotary(&ka));
        enc.extend(packed.rotary(&kb));
        live.push(PairRows { k, start: rows, index0: (0..m as u32).collect(), index1: (0..n as u32).collect(), orig: m + n });
        rows += m + n;
    }
    if live.is_empty() {
        return Ok(out);
    }
    be.alloc(&sizes(rows, d, packed.input_dim))?;
    be.upload(Buf::Desc, &desc)?;
    be.upload(Buf::Enc, &enc)?;
    let mut s = Live { x: Buf::X, enc: Buf::Enc, rows };
    linear(be, &packed.input_proj, rows, Buf::Desc, None, s.x, 0, 1.0, false)?;
    let (ts, tc) = tables(&live, rows);
    be.upload_u32(Buf::TSelf, &ts)?;
    be.upload_u32(Buf::TCross, &tc)?;
    let (depth, width) = (p.depth_confidence > 0.0, p.width_confidence > 0.0);
    for i in 0..n_layers {
        layer(be, packed, i, s)?;
        if i == n_layers - 1 || (!depth && !width) {
            continue;
        }
        let l = &packed.layers[i];
        linear(be, &l.matchability, s.rows, s.x, None, Buf::Heads, 0, 1.0, false)?;
        if depth {
            let token = l.token.expect("every layer but the last has a token head");
            linear(be, &token, s.rows, s.x, None, Buf::Heads, s.rows, 1.0, false)?;
        }
        let heads = be.read(Buf::Heads, if depth { 2 * s.rows } else { s.rows })?;
        let th = confidence_threshold(i, n_layers);
        let token = |r: usize| if depth { Some(sigmoid(heads[s.rows + r])) } else { None };
        let (mut exiting, mut kept, mut index) = (Vec::new(), Vec::new(), Vec::new());
        for pr in live {
            let own = pr.start..pr.start + pr.m() + pr.n();
            if depth {
                let unconfident = own.clone().filter(|&r| token(r).is_some_and(|c| c < th)).count();
                if 1.0 - unconfident as f32 / pr.orig as f32 > p.depth_confidence {
                    exiting.push(pr);
                    continue;
                }
            }
            let keep = |r: usize| !width || sigmoid(heads[r]) > 1.0 - p.width_confidence || token(r).is_some_and(|c| c <= th);
            let k0: Vec<usize> = (0..pr.m()).filter(|&i| keep(pr.start + i)).collect();
            let k1: Vec<usize> = (0..pr.n()).filter(|&j| keep(pr.start + pr.m() + j)).collect();
            if k0.is_empty() || k1.is_empty() {
                continue; // every point of a side pruned: nothing can match
            }
            let start = index.len();
            index.extend(k0.iter().map(|&i| (pr.start + i) as u32));
            index.extend(k1.iter().map(|&j| (pr.start + pr.m() + j) as u32));
            kept.push(PairRows {
                k: pr.k,
                start,
                index0: k0.iter().map(|&i| pr.index0[i]).collect(),
                index1: k1.iter().map(|&j| pr.index1[j]).collect(),
                orig: pr.orig,
            });
        }
        if !exiting.is_empty() {
            let (val, best) = assignment(be, packed, i, s)?;
            for pr in &exiting {
                out[pr.k] = matches_of(pr, &val, &best, p.filter_threshold);
            }
        }
        live = kept;
        if live.is_empty() {
            return Ok(out);
        }
        if index.len() != s.rows || !exiting.is_empty() {
            be.upload_u32(Buf::Index, &index)?;
            let (x2, enc2) = if s.x == Buf::X { (Buf::X2, Buf::Enc2) } else { (Buf::X, Buf::Enc) };
            for (from, to) in [(s.x, x2), (s.enc, enc2)] {
                be.run(Pass {
                    entry: Entry::Gather,
                    p: LgParams { rows: index.len() as u32, n_in: d as u32, ..p0() },
                    a: from,
                    b: Buf::Unused,
                    out: to,
                    table: Buf::Index,
                    best: Buf::Unused,
                })?;
            }
            s = Live { x: x2, enc: enc2, rows: index.len() };
            let (ts, tc) = tables(&live, s.rows);
            be.upload_u32(Buf::TSelf, &ts)?;
            be.upload_u32(Buf::TCross, &tc)?;
        }
    }
    let (val, best) = assignment(be, packed, n_layers - 1, s)?;
    for pr in &live {
        out[pr.k] = matches_of(pr, &val, &best, p.filter_threshold);
    }
    Ok(out)
}

/// The CPU twins as a `Backend`: every buffer a vector, every pass its twin.
pub struct Twins {
    f: Vec<Vec<f32>>,
    u: Vec<Vec<u32>>,
}

impl Twins {
    /// Buffers for `weights` (the packed weights).
    pub fn new(weights: &[f32]) -> Twins {
        let mut f = vec![Vec::new(); BUFS];
        f[Buf::Weights as usize] = weights.to_vec();
        Twins { f, u: vec![Vec::new(); BUFS] }
    }
}

fn is_u32(b: Buf) -> bool {
    matches!(b, Buf::TSelf | Buf::TCross | Buf::Index | Buf::Best)
}

impl Backend for Twins {
    fn alloc(&mut self, sizes: &[(Buf, usize)]) -> Result<(), GpuError> {
        for &(b, n) in sizes {
            if is_u32(b) {
                let v = &mut self.u[b as usize];
                v.resize(n.max(v.len()), 0);
            } else {
                let v = &mut self.f[b as usize];
                v.resize(n.max(v.len()), 0.0);
            }
        }
        Ok(())
    }
    fn upload(&mut self, buf: Buf, data: &[f32]) -> Result<(), GpuError> {
        self.f[buf as usize][..data.len()].copy_from_slice(data);
        Ok(())
    }
    fn upload_u32(&mut self, buf: Buf, data: &[u32]) -> Result<(), GpuError> {
        self.u[buf as usize][..data.len()].copy_from_slice(data);
        Ok(())
    }
    fn run(&mut self, s: Pass) -> Result<(), GpuError> {
        let mut o = std::mem::take(&mut self.f[s.out as usize]);
        let (f, u, p) = (&self.f, &self.u, &s.p);
        let (a, b, w, t) = (&f[s.a as usize], &f[s.b as usize], &f[Buf::Weights as usize], &u[s.table as usize]);
        match s.entry {
            Entry::Linear => twin::lg_linear(p, a, b, w, &mut o),
            Entry::LayerNorm => twin::lg_layer_norm(p, w, &mut o),
            Entry::Rotary => twin::lg_rotary(p, a, b, &mut o),
            Entry::Attention => twin::lg_attention(p, a, &mut o, t),
            Entry::RowLse => twin::lg_row_lse(p, a, b, &mut o, t),
            Entry::AssignmentBest => {
                let mut best = std::mem::take(&mut self.u[s.best as usize]);
                twin::lg_assignment_best(p, a, b, &mut o, &self.u[s.table as usize], &mut best);
                self.u[s.best as usize] = best;
            }
            Entry::Gather => twin::lg_gather(p, a, &mut o, t),
        }
        self.f[s.out as usize] = o;
        Ok(())
    }
    fn read(&mut self, buf: Buf, len: usize) -> Result<Vec<f32>, GpuError> {
        Ok(self.f[buf as usize][..len].to_vec())
    }
    fn read_u32(&mut self, buf: Buf, len: usize) -> Result<Vec<u32>, GpuError> {
        Ok(self.u[buf as usize][..len].to_vec())
    }
}

/// LighterGlue's matches of every pair run on the CPU twins: what the device is held to. Slow
/// (the twins are written for equivalence): the reference a device
/// or a port is checked against.
pub fn forward_on_twins(net: &LighterGlue, p: &GlueParams, pairs: &[(KeypointsRef, KeypointsRef)]) -> Vec<Vec<GlueMatch>> {
    let packed = net.pack();
    let mut be = Twins::new(&packed.weights);
    forward(&mut be, &packed, p, pairs).expect("the twins do not fail")
}

/// The LighterGlue network resident on a device.
pub struct GlueGpu {
    ctx: Arc<GpuContext>,
    packed: Arc<PackedGlue>,
    weights: wgpu::Buffer,
    unused: wgpu::Buffer,
    bufs: Vec<Reused>,
    params: Option<PassBuffer<LgParams>>,
    pending: Vec<Pass>,
    /// Rows of the largest batch the storage binding allows.
    max_rows: usize,
}

impl GlueGpu {
    /// Packs `net`'s weights and uploads them (once).
    pub fn new(ctx: Arc<GpuContext>, net: &LighterGlue) -> Result<GlueGpu, GpuError> {
        let packed = Arc::new(net.pack());
        if packed.d > LANES || !packed.d.is_multiple_of(2) {
            return Err(GpuError::Failed {
                what: "LighterGlue on the device".into(),
                reason: format!("the kernels take an even descriptor dimension up to {LANES}; the network's is {}", packed.d),
            });
        }
        let max_rows = Self::max_rows(&ctx, &packed);
        Self::resident(ctx, packed, max_rows)
    }

    /// The executor of `packed` with its weights uploaded (once) and no buffers yet.
    fn resident(ctx: Arc<GpuContext>, packed: Arc<PackedGlue>, max_rows: usize) -> Result<GlueGpu, GpuError> {
        let bytes = (packed.weights.len().max(1) * 4) as u64;
        ctx.check_binding("the packed LighterGlue weights", bytes)?;
        let (weights, unused) = ctx.scoped("uploading the LighterGlue weights", || {
            let w = ctx.storage("lighterglue weights", bytes);
            ctx.write(&w, 0, bytemuck::cast_slice(&packed.weights));
            (w, ctx.storage("lighterglue unused binding", 16))
        })?;
        let bufs = (0..BUFS).map(|_| Reused::default()).collect();
        Ok(GlueGpu { ctx, packed, weights, unused, bufs, params: None, pending: Vec::new(), max_rows })
    }

    /// Rows of the largest batch: its widest buffer (3d values a row) within the storage binding,
    /// all its buffers within the context's resident budget, `lg_linear`'s and `lg_layer_norm`'s
    /// grids within the workgroups of one dimension, and its offsets within u32.
    fn max_rows(ctx: &GpuContext, packed: &PackedGlue) -> usize {
        let widest = 3 * packed.d.max(packed.input_dim) as u64 * 4;
        let per_row: u64 = sizes(1, packed.d, packed.input_dim).iter().map(|s| s.1 as u64 * 4).sum();
        let wg = ctx.max_workgroups() as u64;
        let rows = (ctx.binding_limit() / widest).min(ctx.resident_budget() / per_row).min(wg * TILE as u64).min(wg * LN_ROWS as u64);
        rows.min(u32::MAX as u64 / widest) as usize
    }

    /// LighterGlue's matches of every (query, reference) pair, as the CPU's
    /// `LighterGlue::match_keypoints` (within the tolerances `tests/gpu/lighterglue.rs` states),
    /// in batches the device's storage binding allows.
    pub fn match_pairs(&mut self, p: &GlueParams, pairs: &[(KeypointsRef, KeypointsRef)]) -> Result<Vec<Vec<GlueMatch>>, GpuError> {
        let mut out = Vec::with_capacity(pairs.len());
        let mut at = 0;
        while at < pairs.len() {
            let (mut end, mut rows) = (at, 0);
            while end < pairs.len() {
                // the rows `forward` gives the pair (none where it has no matches to find)
                let (a, b) = pairs[end];
                let runs = !a.is_empty() && !b.is_empty() && a.dim == self.packed.input_dim && b.dim == self.packed.input_dim;
                let r = if runs { a.len() + b.len() } else { 0 };
                if end > at && rows + r > self.max_rows {
                    break;
                }
                rows += r;
                end += 1;
            }
            if rows > self.max_rows {
                return Err(GpuError::LimitsTooSmall {
                    adapter: self.ctx.describe(),
                    what: "rows of a LighterGlue batch (one pair's keypoints; the storage binding, the resident budget and the grid bound them)"
                        .into(),
                    needed: rows as u64,
                    available: self.max_rows as u64,
                });
            }
            let packed = self.packed.clone();
            let r = forward(self, &packed, p, &pairs[at..end]);
            self.pending.clear();
            out.extend(r?);
            at = end;
        }
        Ok(out)
    }

    fn buffer(&self, b: Buf) -> &wgpu::Buffer {
        match b {
            Buf::Weights => &self.weights,
            Buf::Unused => &self.unused,
            _ => self.bufs[b as usize].current().expect("allocated before use"),
        }
    }

    /// Records the pending passes into one submission.
    fn flush(&mut self) -> Result<(), GpuError> {
        if self.pending.is_empty() {
            return Ok(());
        }
        let ctx = self.ctx.clone();
        let pending = std::mem::take(&mut self.pending);
        let params: Vec<LgParams> = pending.iter().map(|s| s.p).collect();
        ctx.scoped("running LighterGlue on the device", || -> Result<(), GpuError> {
            let pb = self.params.get_or_insert_with(|| PassBuffer::new(&ctx));
            let pbuf = pb.write(&ctx, &params).clone();
            let offsets: Vec<u32> = (0..pending.len()).map(|i| pb.offset(i)).collect();
            let k = &ctx.kernels;
            let groups: Vec<wgpu::BindGroup> = pending
                .iter()
                .map(|s| {
                    let (a, b, o, t, best) = (self.buffer(s.a), self.buffer(s.b), self.buffer(s.out), self.buffer(s.table), self.buffer(s.best));
                    let w = &self.weights;
                    let bound: Vec<&wgpu::Buffer> = match s.entry {
                        Entry::Linear => vec![&pbuf, a, b, w, o],
                        Entry::LayerNorm => vec![&pbuf, w, o],
                        Entry::Rotary => vec![&pbuf, a, b, o],
                        Entry::Gather => vec![&pbuf, a, o, t],
                        Entry::Attention | Entry::RowLse => vec![&pbuf, a, b, o, t],
                        Entry::AssignmentBest => vec![&pbuf, a, b, o, t, best],
                    };
                    kernel(k, s.entry).bind(&ctx.device, &bound)
                })
                .collect();
            let mut enc = ctx.device.create_command_encoder(&wgpu::CommandEncoderDescriptor { label: Some("lighterglue") });
            {
                let mut pass = ctx.begin_pass(&mut enc, "lighterglue")?;
                for ((s, g), off) in pending.iter().zip(&groups).zip(&offsets) {
                    let [x, y, z] = grid(s.entry.name(), &s.p, ctx.max_workgroups());
                    if x == 0 || y == 0 || s.p.rows == 0 {
                        continue;
                    }
                    pass.set_pipeline(&kernel(k, s.entry).pipeline);
                    pass.set_bind_group(0, Some(g), &[*off]);
                    pass.dispatch_workgroups(x, y, z);
                }
            }
            ctx.queue.submit([enc.finish()]);
            Ok(())
        })?
    }
}

impl Backend for GlueGpu {
    fn alloc(&mut self, sizes: &[(Buf, usize)]) -> Result<(), GpuError> {
        self.flush()?;
        let ctx = self.ctx.clone();
        for &(b, n) in sizes.iter().filter(|s| !matches!(s.0, Buf::Weights | Buf::Unused)) {
            ctx.check_binding(&format!("LighterGlue's {b:?} buffer"), (n * 4) as u64)?;
            self.bufs[b as usize].get(&ctx, "lighterglue", (n * 4) as u64);
        }
        Ok(())
    }
    fn upload(&mut self, buf: Buf, data: &[f32]) -> Result<(), GpuError> {
        self.flush()?;
        self.ctx.write(self.buffer(buf), 0, bytemuck::cast_slice(data));
        Ok(())
    }
    fn upload_u32(&mut self, buf: Buf, data: &[u32]) -> Result<(), GpuError> {
        self.flush()?;
        self.ctx.write(self.buffer(buf), 0, bytemuck::cast_slice(data));
        Ok(())
    }
    fn run(&mut self, pass: Pass) -> Result<(), GpuError> {
        self.pending.push(pass);
        Ok(())
    }
    fn read(&mut self, buf: Buf, len: usize) -> Result<Vec<f32>, GpuError> {
        self.read_values(buf, len)
    }
    fn read_u32(&mut self, buf: Buf, len: usize) -> Result<Vec<u32>, GpuError> {
        self.read_values(buf, len)
    }
}

impl GlueGpu {
    /// The first `len` 32-bit values of a buffer, after the pending passes.
    fn read_values<T: bytemuck::Pod>(&mut self, buf: Buf, len: usize) -> Result<Vec<T>, GpuError> {
        self.flush()?;
        if len == 0 {
            return Ok(Vec::new());
        }
        self.ctx.read_back_values(self.buffer(buf), len)
    }
}

fn kernel(k: &crate::device::kernels::Kernels, e: Entry) -> &Kernel {
    match e {
        Entry::Linear => &k.lg_linear,
        Entry::LayerNorm => &k.lg_layer_norm,
        Entry::Rotary => &k.lg_rotary,
        Entry::Attention => &k.lg_attention,
        Entry::RowLse => &k.lg_row_lse,
        Entry::AssignmentBest => &k.lg_assignment_best,
        Entry::Gather => &k.lg_gather,
    }
}

/// One pass alone on `be`: `inputs` (f32 values by buffer) and `tables` (u32) uploaded, its output
/// buffer holding `out` before it runs; the output and, for `lg_assignment_best`, the best partners
/// read back. What the kernel tests run on the device ([`run_kernel`]) and on the twins.
pub fn run_pass(
    be: &mut dyn Backend,
    pass: Pass,
    inputs: &[(Buf, &[f32])],
    tables: &[(Buf, &[u32])],
    out: &[f32],
) -> Result<(Vec<f32>, Vec<u32>), GpuError> {
    let rows = pass.p.rows as usize;
    let mut sizes: Vec<(Buf, usize)> = inputs.iter().map(|(b, d)| (*b, d.len())).collect();
    sizes.extend(tables.iter().map(|(b, d)| (*b, d.len())));
    sizes.extend([(pass.out, out.len()), (pass.best, rows)]);
    be.alloc(&sizes)?;
    for (b, d) in inputs {
        be.upload(*b, d)?;
    }
    for (b, d) in tables {
        be.upload_u32(*b, d)?;
    }
    be.upload(pass.out, out)?;
    be.run(pass)?;
    let o = be.read(pass.out, out.len())?;
    let best = if pass.entry == Entry::AssignmentBest { be.read_u32(pass.best, rows)? } else { Vec::new() };
    Ok((o, best))
}

/// One `lighterglue.wgsl` kernel alone on the device ([`run_pass`]), the weights `weights`. The
/// device side of the twins' tests.
pub fn run_kernel(
    ctx: &Arc<GpuContext>,
    weights: &[f32],
    pass: Pass,
    inputs: &[(Buf, &[f32])],
    tables: &[(Buf, &[u32])],
    out: &[f32],
) -> Result<(Vec<f32>, Vec<u32>), GpuError> {
    let z = PackedLinear { w_off: 0, b_off: 0, n_in: 0, n_out: 0 };
    let packed = PackedGlue { weights: weights.to_vec(), input_proj: z, layers: Vec::new(), d: 0, input_dim: 0, wr: Vec::new() };
    run_pass(&mut GlueGpu::resident(ctx.clone(), Arc::new(packed), 0)?, pass, inputs, tables, out)
}
