//! The CPU twins of `shaders/xfeat.wgsl` (the XFeat network on the device): the same entry
//! points under the same names, the same bindings (arguments, in binding order) and the same loop
//! shape: an outer loop over the dispatch's workgroups, then the shader's phases (between its
//! barriers) each as a loop over the workgroup's invocations. The CPU path runs the fast ops of
//! `nn::conv` (im2col + sgemm, ...), which the tests hold to these twins; the device is
//! held to them too (`tests/gpu/xfeat.rs`).
//!
//! Also here, host-side and shared by the twins, the executor (`semlook::networks::xfeat::XFeatGpu`) and the
//! tests: the uniform structs (`#[repr(C)]`, checked against naga's reflection of the WGSL by this
//! crate's `layout_tests`), the shader's constants, and the packing of a layer's weights.

use super::abi::{ConvParams, MapParams, NormParams};
/// Lanes of the reduction and element-wise kernels' workgroups.
pub const LANES: usize = 256;
/// Values of the grey input per `instance_norm_partials` workgroup.
pub const CHUNK: usize = 4096;
/// Output pixels per `conv2d` workgroup: TILE_W x TILE_H.
pub const TILE_W: usize = 32;
/// Output rows per `conv2d` workgroup.
pub const TILE_H: usize = 8;
/// Output channels per `conv2d` workgroup (weights are packed in groups of this many).
pub const CO_GROUP: usize = 8;
/// Floats of `conv2d`'s workgroup input tile and weight tile.
pub const IN_CAP: usize = 2560;
/// Floats of `conv2d`'s workgroup weight tile.
pub const W_CAP: usize = 576;
/// Invocations of a `conv2d` workgroup (8 x 8).
pub const THREADS: usize = 64;
/// `conv2d` activations.
pub const ACT_NONE: u32 = 0;
/// `conv2d` activation: ReLU.
pub const ACT_RELU: u32 = 1;
/// `conv2d` activation: the logistic sigmoid.
pub const ACT_SIGMOID: u32 = 2;

impl ConvParams {
    /// A `cout` x `cin` x `k` x `k` convolution of a `h` x `w` input with stride `stride` and
    /// zero padding `pad`; `None` when the kernel does not fit the input or the workgroup's tiles.
    #[allow(clippy::too_many_arguments)]
    pub fn new(cin: usize, cout: usize, h: usize, w: usize, k: usize, stride: usize, pad: usize, act: u32, has_add: bool) -> Option<ConvParams> {
        if k == 0 || stride == 0 || cin == 0 || cout == 0 || h + 2 * pad < k || w + 2 * pad < k {
            return None;
        }
        let (ho, wo) = ((h + 2 * pad - k) / stride + 1, (w + 2 * pad - k) / stride + 1);
        let (rows, cols) = ((TILE_H - 1) * stride + k, (TILE_W - 1) * stride + k);
        let pitch = cols + (40 - cols % 32) % 32;
        let chunk = cin.min(IN_CAP / (rows * pitch)).min(W_CAP / (k * k * CO_GROUP));
        if chunk == 0 {
            return None;
        }
        let u = |v: usize| v as u32;
        Some(ConvParams {
            cin: u(cin),
            cout: u(cout),
            h: u(h),
            w: u(w),
            ho: u(ho),
            wo: u(wo),
            k: u(k),
            stride: u(stride),
            pad: u(pad),
            chunk: u(chunk),
            rows: u(rows),
            cols: u(cols),
            pitch: u(pitch),
            act,
            has_add: has_add as u32,
            ..Default::default()
        })
    }

    /// Channel groups of CO_GROUP the output is computed in.
    pub fn groups(&self) -> usize {
        (self.cout as usize).div_ceil(CO_GROUP)
    }

    /// The dispatch: workgroups in x (output columns), y (output rows), z (channel groups).
    pub fn grid(&self) -> [u32; 3] {
        [(self.wo as usize).div_ceil(TILE_W) as u32, (self.ho as usize).div_ceil(TILE_H) as u32, self.groups() as u32]
    }

    /// Values of the output (cout x ho x wo).
    pub fn output_len(&self) -> usize {
        (self.cout * self.ho * self.wo) as usize
    }
}

/// What follows a convolution.
#[derive(Debug, Clone, Copy)]
pub enum Epilogue<'a> {
    /// Inference-mode BatchNorm2d(affine = False, eps 1e-5), then ReLU.
    BatchNormRelu {
        /// Running mean per output channel.
        mean: &'a [f32],
        /// Running variance per output channel.
        var: &'a [f32],
    },
    /// A bias.
    Bias(&'a [f32]),
    /// A bias, then the logistic sigmoid.
    BiasSigmoid(&'a [f32]),
}

impl Epilogue<'_> {
    /// The `conv2d` activation code that ends this epilogue (`ACT_*`).
    pub fn act(&self) -> u32 {
        match self {
            Epilogue::BatchNormRelu { .. } => ACT_RELU,
            Epilogue::Bias(_) => ACT_NONE,
            Epilogue::BiasSigmoid(_) => ACT_SIGMOID,
        }
    }
}

/// A layer's weights as `conv2d` reads them: `weight` ([cout, cin, k, k], PyTorch's layout)
/// regrouped to `[group][cin][k * k][CO_GROUP]` (output channels past `cout` zero), then per output
/// channel (padded to whole groups) the epilogue's subtrahend and factor: y = (acc - sub) * mul,
/// i.e. (mean, 1 / sqrt(var + 1e-5)) for batch norm and (-bias, 1) for a bias. Returns the packed
/// values and the offsets of the subtrahends and factors in them; `None` when the sizes disagree.
pub fn pack_conv(weight: &[f32], cin: usize, cout: usize, k: usize, epi: Epilogue) -> Option<(Vec<f32>, usize, usize)> {
    let kk = k * k;
    if weight.len() != cout * cin * kk {
        return None;
    }
    let groups = cout.div_ceil(CO_GROUP);
    let padded = groups * CO_GROUP;
    let mut out = vec![0.0f32; groups * cin * kk * CO_GROUP + 2 * padded];
    for co in 0..cout {
        let (g, j) = (co / CO_GROUP, co % CO_GROUP);
        for ci in 0..cin {
            for t in 0..kk {
                out[((g * cin + ci) * kk + t) * CO_GROUP + j] = weight[(co * cin + ci) * kk + t];
            }
        }
    }
    let (sub_at, mul_at) = (groups * cin * kk * CO_GROUP, groups * cin * kk * CO_GROUP + padded);
    for co in 0..padded {
        let (sub, mul) = match epi {
            _ if co >= cout => (0.0, 1.0),
            Epilogue::BatchNormRelu { mean, var } => (*mean.get(co)?, 1.0 / (var.get(co)? + 1e-5).sqrt()),
            Epilogue::Bias(b) | Epilogue::BiasSigmoid(b) => (-b.get(co)?, 1.0),
        };
        out[sub_at + co] = sub;
        out[mul_at + co] = mul;
    }
    Some((out, sub_at, mul_at))
}

/// A grid of `items` workgroups at most `max` wide: (row, [x, y, 1]).
pub fn grid_of(items: usize, max: usize) -> (u32, [u32; 3]) {
    let row = items.clamp(1, max.max(1));
    (row as u32, [row as u32, items.div_ceil(row) as u32, 1])
}

impl MapParams {
    /// The grid of the element-wise kernels for these parameters (row and n set).
    pub fn grid(&self) -> [u32; 3] {
        grid_of((self.n as usize).div_ceil(LANES), self.row as usize).1
    }

    /// `n` outputs in grid rows of at most `max_row` workgroups.
    fn with_n(self, n: usize, max_row: usize) -> MapParams {
        MapParams { n: n as u32, row: grid_of(n.div_ceil(LANES), max_row).0, ..self }
    }

    /// `avg_pool` of c planes of h x w by k.
    pub fn avg_pool(c: usize, h: usize, w: usize, k: usize, max_row: usize) -> MapParams {
        let (ho, wo) = (h / k.max(1), w / k.max(1));
        let u = |v: usize| v as u32;
        MapParams { c: u(c), h: u(h), w: u(w), ho: u(ho), wo: u(wo), k: u(k), inv: 1.0 / (k * k) as f32, ..Default::default() }
            .with_n(c * ho * wo, max_row)
    }

    /// `space_to_depth8` of one plane of h x w.
    pub fn space_to_depth8(h: usize, w: usize, max_row: usize) -> MapParams {
        let (ho, wo) = (h / 8, w / 8);
        let u = |v: usize| v as u32;
        MapParams { c: 64, h: u(h), w: u(w), ho: u(ho), wo: u(wo), k: 8, ..Default::default() }.with_n(64 * ho * wo, max_row)
    }

    /// `bilinear_add` of c planes of ho x wo and two maps of (h1, w1) and (h2, w2) resized to it.
    pub fn bilinear_add(c: usize, ho: usize, wo: usize, b: (usize, usize), cc: (usize, usize), max_row: usize) -> MapParams {
        let u = |v: usize| v as u32;
        let scale = |src: usize, out: usize| src as f32 / out as f32;
        MapParams {
            c: u(c),
            h: u(ho),
            w: u(wo),
            ho: u(ho),
            wo: u(wo),
            h1: u(b.0),
            w1: u(b.1),
            h2: u(cc.0),
            w2: u(cc.1),
            sy1: scale(b.0, ho),
            sx1: scale(b.1, wo),
            sy2: scale(cc.0, ho),
            sx2: scale(cc.1, wo),
            ..Default::default()
        }
        .with_n(c * ho * wo, max_row)
    }
}

impl NormParams {
    /// `n` grey values, `row` workgroups per grid row at most.
    pub fn new(n: usize, max_row: usize) -> NormParams {
        let chunks = n.div_ceil(CHUNK);
        NormParams { n: n as u32, chunks: chunks as u32, row: grid_of(n.div_ceil(LANES), max_row).0, chunk_row: grid_of(chunks, max_row).0 }
    }
    /// The grid of `instance_norm_partials` (one workgroup per chunk).
    pub fn partials_grid(&self) -> [u32; 3] {
        grid_of(self.chunks as usize, self.chunk_row as usize).1
    }
    /// The grid of `instance_norm_apply` (one invocation per value).
    pub fn apply_grid(&self) -> [u32; 3] {
        grid_of((self.n as usize).div_ceil(LANES), self.row as usize).1
    }
}

/// Every invocation index of an element-wise grid, in dispatch order (workgroup y, x, lane).
fn invocations(row: u32, grid: [u32; 3]) -> impl Iterator<Item = usize> {
    (0..grid[1] as usize)
        .flat_map(move |y| (0..grid[0] as usize).flat_map(move |x| (0..LANES).map(move |lane| (x + y * row as usize) * LANES + lane)))
}

/// Sum of per-lane values by the shader's tree (`lane_sum`).
fn lane_sum(mut red: [f32; LANES]) -> f32 {
    let mut h = LANES / 2;
    while h > 0 {
        for lane in 0..h {
            red[lane] += red[lane + h];
        }
        h /= 2;
    }
    red[0]
}

/// Bindings: `np`, `grey`, `partials` (out: count, mean, M2 per chunk). One workgroup per chunk
/// of CHUNK values; lane l sums values l, l + LANES, ... of it, twice (the mean, then the squared
/// deviations from it), each reduced by the tree.
pub fn instance_norm_partials(np: &NormParams, grey: &[f32], partials: &mut [f32]) {
    let [gx, gy, _] = np.partials_grid();
    let n = np.n as usize;
    for y in 0..gy as usize {
        for x in 0..gx as usize {
            let chunk = x + y * np.chunk_row as usize;
            let valid = chunk < np.chunks as usize;
            let start = chunk * CHUNK;
            let mut red = [0.0f32; LANES];
            for (lane, r) in red.iter_mut().enumerate().filter(|_| valid) {
                for i in 0..CHUNK / LANES {
                    let j = start + i * LANES + lane;
                    if j < n {
                        *r += grey[j];
                    }
                }
            }
            let total = lane_sum(red);
            let count = if valid { CHUNK.min(n - start) } else { 1 };
            let mean = total / count as f32;
            let mut red = [0.0f32; LANES];
            for (lane, r) in red.iter_mut().enumerate().filter(|_| valid) {
                for i in 0..CHUNK / LANES {
                    let j = start + i * LANES + lane;
                    if j < n {
                        let d = grey[j] - mean;
                        *r += d * d;
                    }
                }
            }
            let m2 = lane_sum(red);
            if valid {
                partials[chunk * 3..chunk * 3 + 3].copy_from_slice(&[count as f32, mean, m2]);
            }
        }
    }
}

/// The shader's `chan`: (count, mean, M2) of two parts to that of their union.
fn chan(a: [f32; 3], b: [f32; 3]) -> [f32; 3] {
    if b[0] == 0.0 {
        return a;
    }
    if a[0] == 0.0 {
        return b;
    }
    let n = a[0] + b[0];
    let d = b[1] - a[1];
    [n, a[1] + d * (b[0] / n), a[2] + b[2] + d * d * (a[0] * b[0] / n)]
}

/// Bindings: `np`, `partials_in`, `stats` (out: mean, 1 / sqrt(var + 1e-5)). One workgroup: lane
/// l folds chunks l, l + LANES, ..., then a tree over the lanes.
pub fn instance_norm_stats(np: &NormParams, partials_in: &[f32], stats: &mut [f32]) {
    let mut red3 = [[0.0f32; 3]; LANES];
    for (lane, r) in red3.iter_mut().enumerate() {
        let mut acc = [0.0f32; 3];
        let mut c = lane;
        while c < np.chunks as usize {
            acc = chan(acc, [partials_in[c * 3], partials_in[c * 3 + 1], partials_in[c * 3 + 2]]);
            c += LANES;
        }
        *r = acc;
    }
    let mut h = LANES / 2;
    while h > 0 {
        for lane in 0..h {
            red3[lane] = chan(red3[lane], red3[lane + h]);
        }
        h /= 2;
    }
    let t = red3[0];
    let var = t[2] / t[0].max(1.0);
    stats[0] = t[1];
    stats[1] = 1.0 / (var + 1e-5).sqrt();
}

/// Bindings: `np`, `grey`, `stats_in`, `normed` (out). One invocation per value.
pub fn instance_norm_apply(np: &NormParams, grey: &[f32], stats_in: &[f32], normed: &mut [f32]) {
    for i in invocations(np.row, np.apply_grid()) {
        if i < np.n as usize {
            normed[i] = (grey[i] - stats_in[0]) * stats_in[1];
        }
    }
}

/// Bindings: `mp`, `src_a` (c x h x w), `dst` (out, c x ho x wo). AvgPool2d(k, stride k); one
/// invocation per output value.
pub fn avg_pool(mp: &MapParams, src_a: &[f32], dst: &mut [f32]) {
    let (h, w, ho, wo, k) = (mp.h as usize, mp.w as usize, mp.ho as usize, mp.wo as usize, mp.k as usize);
    for i in invocations(mp.row, mp.grid()) {
        if i >= mp.n as usize {
            continue;
        }
        let (ox, oy, c) = (i % wo, (i / wo) % ho, i / (wo * ho));
        let mut s = 0.0f32;
        for dy in 0..k {
            for dx in 0..k {
                s += src_a[(c * h + oy * k + dy) * w + ox * k + dx];
            }
        }
        dst[i] = s * mp.inv;
    }
}

/// Bindings: `mp`, `src_a` (1 x h x w), `dst` (out, 64 x ho x wo, plane ky * 8 + kx). One
/// invocation per output value.
pub fn space_to_depth8(mp: &MapParams, src_a: &[f32], dst: &mut [f32]) {
    let (w, ho, wo) = (mp.w as usize, mp.ho as usize, mp.wo as usize);
    for i in invocations(mp.row, mp.grid()) {
        if i >= mp.n as usize {
            continue;
        }
        let (ox, oy, c) = (i % wo, (i / wo) % ho, i / (wo * ho));
        dst[i] = src_a[(oy * 8 + c / 8) * w + ox * 8 + c % 8];
    }
}

/// The shader's `source_index`: (i0, i1, weight of i1).
fn source_index(o: usize, len: usize, scale: f32) -> (usize, usize, f32) {
    let s = (scale * (o as f32 + 0.5) - 0.5).max(0.0);
    let i0 = (s.floor() as usize).min(len - 1);
    let i1 = (i0 + 1).min(len - 1);
    (i0, i1, s - i0 as f32)
}

/// The shader's `upsample`: a bilinear sample of plane c of `src` (h x w, axis scales sy, sx).
#[allow(clippy::too_many_arguments)]
fn upsample(src: &[f32], h: usize, w: usize, sy: f32, sx: f32, c: usize, oy: usize, ox: usize) -> f32 {
    let (y0, y1, ly) = source_index(oy, h, sy);
    let (x0, x1, lx) = source_index(ox, w, sx);
    let base = c * h * w;
    let (r0, r1) = (base + y0 * w, base + y1 * w);
    let t = src[r0 + x0] * (1.0 - lx) + src[r0 + x1] * lx;
    let b = src[r1 + x0] * (1.0 - lx) + src[r1 + x1] * lx;
    t * (1.0 - ly) + b * ly
}

/// Bindings: `mp`, `src_a` (c x ho x wo), `src_b` (c x h1 x w1), `src_c` (c x h2 x w2), `dst`
/// (out, c x ho x wo): a + resize(b) + resize(c), bilinear as PyTorch's align_corners = False.
/// One invocation per output value.
pub fn bilinear_add(mp: &MapParams, src_a: &[f32], src_b: &[f32], src_c: &[f32], dst: &mut [f32]) {
    let (ho, wo) = (mp.ho as usize, mp.wo as usize);
    for i in invocations(mp.row, mp.grid()) {
        if i >= mp.n as usize {
            continue;
        }
        let (ox, oy, c) = (i % wo, (i / wo) % ho, i / (wo * ho));
        let b = upsample(src_b, mp.h1 as usize, mp.w1 as usize, mp.sy1, mp.sx1, c, oy, ox);
        let cc = upsample(src_c, mp.h2 as usize, mp.w2 as usize, mp.sy2, mp.sx2, c, oy, ox);
        dst[i] = (src_a[i] + b) + cc;
    }
}

/// Bindings: `cp`, `conv_in` (cin x h x w), `weights` (every layer's, packed by [`pack_conv`];
/// this layer's at cp.weight_at, sub_at, mul_at), `conv_add` (cout x ho x wo, read when
/// cp.has_add), `conv_out` (out, cout x ho x wo).
///
/// Per workgroup (TILE_W x TILE_H output pixels x CO_GROUP channels), per chunk of input
/// channels: every invocation loads part of the zero-padded input tile and the chunk's weights
/// (barrier); then invocation (tx, ty) accumulates its pixels (tx + 8p, ty), p < 4, for its 8
/// channels, input channel by channel, tap by tap (barrier). The epilogue: (acc - sub) * mul,
/// the activation, then the added tensor.
pub fn conv2d(cp: &ConvParams, conv_in: &[f32], weights: &[f32], conv_add: &[f32], conv_out: &mut [f32]) {
    let [gx, gy, gz] = cp.grid();
    let (k, s, pad) = (cp.k as usize, cp.stride as usize, cp.pad as usize);
    let (cin, h, w, ho, wo, cout) = (cp.cin as usize, cp.h as usize, cp.w as usize, cp.ho as usize, cp.wo as usize, cp.cout as usize);
    let (kk, pitch, cols) = (k * k, cp.pitch as usize, cp.cols as usize);
    let plane = cp.rows as usize * pitch;
    let chunk = cp.chunk as usize;
    let mut tile = vec![0.0f32; IN_CAP];
    let mut wtile = vec![[0.0f32; 4]; W_CAP / 4];
    for g in 0..gz as usize {
        for wy in 0..gy as usize {
            for wx in 0..gx as usize {
                let (ox0, oy0) = (wx * TILE_W, wy * TILE_H);
                // per invocation: acc[p] channels 0..3 of pixel p, acc[4 + p] channels 4..7
                let mut acc = [[[0.0f32; 4]; 8]; THREADS];
                let mut c0 = 0;
                while c0 < cin {
                    let cn = chunk.min(cin - c0);
                    for li in 0..THREADS {
                        let mut i = li;
                        while i < cn * plane {
                            let (c, r, col) = (i / plane, (i % plane) / pitch, i % pitch);
                            let iy = (oy0 * s + r) as isize - pad as isize;
                            let ix = (ox0 * s + col) as isize - pad as isize;
                            let inside = col < cols && iy >= 0 && ix >= 0 && (iy as usize) < h && (ix as usize) < w;
                            tile[i] = if inside { conv_in[((c0 + c) * h + iy as usize) * w + ix as usize] } else { 0.0 };
                            i += THREADS;
                        }
                    }
                    let wbase = cp.weight_at as usize + (g * cin + c0) * kk * CO_GROUP;
                    for li in 0..THREADS {
                        let mut i = li;
                        while i < cn * kk * 2 {
                            let b = wbase + i * 4;
                            wtile[i] = [weights[b], weights[b + 1], weights[b + 2], weights[b + 3]];
                            i += THREADS;
                        }
                    }
                    // barrier
                    for (li, a) in acc.iter_mut().enumerate() {
                        let (tx, ty) = (li % 8, li / 8);
                        for c in 0..cn {
                            for ky in 0..k {
                                for kx in 0..k {
                                    let t = (c * kk + ky * k + kx) * 2;
                                    let (w0, w1) = (wtile[t], wtile[t + 1]);
                                    let base = c * plane + (ty * s + ky) * pitch + tx * s + kx;
                                    for p in 0..4 {
                                        let v = tile[base + p * 8 * s];
                                        for j in 0..4 {
                                            a[p][j] += v * w0[j];
                                            a[4 + p][j] += v * w1[j];
                                        }
                                    }
                                }
                            }
                        }
                    }
                    // barrier
                    c0 += chunk;
                }
                for (li, a) in acc.iter().enumerate() {
                    let (tx, ty) = (li % 8, li / 8);
                    let oy = oy0 + ty;
                    for p in 0..4 {
                        let ox = ox0 + tx + p * 8;
                        if oy >= ho || ox >= wo {
                            continue;
                        }
                        for j in 0..CO_GROUP {
                            let co = g * CO_GROUP + j;
                            if co >= cout {
                                continue;
                            }
                            let mut y = (a[(j / 4) * 4 + p][j % 4] - weights[cp.sub_at as usize + co]) * weights[cp.mul_at as usize + co];
                            if cp.act == ACT_RELU {
                                y = y.max(0.0);
                            } else if cp.act == ACT_SIGMOID {
                                y = 1.0 / (1.0 + (-y).exp());
                            }
                            let o = (co * ho + oy) * wo + ox;
                            if cp.has_add != 0 {
                                y += conv_add[o];
                            }
                            conv_out[o] = y;
                        }
                    }
                }
            }
        }
    }
}
