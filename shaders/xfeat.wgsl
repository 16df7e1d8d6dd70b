// The XFeat network (Potje et al., CVPR 2024) on the device: every layer of the native forward
// pass (src/appearance/xfeat.rs) as a dispatch, with no host round trip between layers (the
// executor is src/gpu/xfeat/). CPU twins: kernels/src/xfeat.rs (same names, bindings and loop
// shapes); the CPU path runs the fast ops of src/nn/conv.rs, held to these twins by tests.
//
// instance_norm_partials: one workgroup per CHUNK values of the grey input: their count, mean
//   and sum of squared deviations (two passes over the chunk, tree reductions over the lanes).
// instance_norm_stats: one workgroup folds the chunks' statistics (Chan et al.'s pairwise
//   update, per lane then by a tree) into the mean and 1 / sqrt(var + 1e-5).
// instance_norm_apply, avg_pool, space_to_depth8, bilinear_add: one invocation per output value.
// conv2d: convolution with the layer's epilogue (batch norm + ReLU, or bias, or bias + sigmoid),
//   plus an optional tensor added after it. One workgroup per TILE_W x TILE_H output pixels x
//   CO_GROUP output channels; 8 x 8 invocations, each 4 pixels (8 apart in x) x 8 channels. Per
//   chunk of input channels the input tile (zero padded) and the weights pass through workgroup
//   memory; the tile's row pitch is cols rounded to 8 mod 32, so a warp's reads hit distinct banks.

const LANES: u32 = 256u;
const CHUNK: u32 = 4096u;
const TILE_W: u32 = 32u;
const TILE_H: u32 = 8u;
const CO_GROUP: u32 = 8u;
const IN_CAP: u32 = 2560u;
const W_CAP: u32 = 576u;
const THREADS: u32 = 64u;
const ACT_RELU: u32 = 1u;
const ACT_SIGMOID: u32 = 2u;

struct ConvParams {
    cin: u32,
    cout: u32,
    h: u32,
    w: u32,
    ho: u32,
    wo: u32,
    k: u32,
    stride: u32,
    pad: u32,
    chunk: u32,
    rows: u32,
    cols: u32,
    pitch: u32,
    weight_at: u32,
    sub_at: u32,
    mul_at: u32,
    act: u32,
    has_add: u32,
    _pad0: u32,
    _pad1: u32,
}

struct MapParams {
    c: u32,
    h: u32,
    w: u32,
    ho: u32,
    wo: u32,
    k: u32,
    row: u32,
    n: u32,
    h1: u32,
    w1: u32,
    h2: u32,
    w2: u32,
    sy1: f32,
    sx1: f32,
    sy2: f32,
    sx2: f32,
    inv: f32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct NormParams {
    n: u32,
    chunks: u32,
    row: u32,
    chunk_row: u32,
}

@group(0) @binding(0) var<uniform> cp: ConvParams;
@group(0) @binding(1) var<storage, read> conv_in: array<f32>;
@group(0) @binding(2) var<storage, read> weights: array<f32>;
@group(0) @binding(3) var<storage, read> conv_add: array<f32>;
@group(0) @binding(4) var<storage, read_write> conv_out: array<f32>;

@group(0) @binding(5) var<uniform> mp: MapParams;
@group(0) @binding(6) var<storage, read> src_a: array<f32>;
@group(0) @binding(7) var<storage, read> src_b: array<f32>;
@group(0) @binding(8) var<storage, read> src_c: array<f32>;
@group(0) @binding(9) var<storage, read_write> dst: array<f32>;

@group(0) @binding(10) var<uniform> np: NormParams;
@group(0) @binding(11) var<storage, read> grey: array<f32>;
@group(0) @binding(12) var<storage, read_write> partials: array<f32>;
@group(0) @binding(13) var<storage, read> partials_in: array<f32>;
@group(0) @binding(14) var<storage, read_write> stats: array<f32>;
@group(0) @binding(15) var<storage, read> stats_in: array<f32>;
@group(0) @binding(16) var<storage, read_write> normed: array<f32>;

var<workgroup> red: array<f32, LANES>;
var<workgroup> red3: array<vec3<f32>, LANES>;

// Sum of `v` over the lanes by a tree (every lane calls it; every lane gets the total).
fn lane_sum(lane: u32, v: f32) -> f32 {
    red[lane] = v;
    workgroupBarrier();
    for (var h = LANES / 2u; h > 0u; h >>= 1u) {
        if (lane < h) {
            red[lane] += red[lane + h];
        }
        workgroupBarrier();
    }
    let total = red[0];
    workgroupBarrier();
    return total;
}

@compute @workgroup_size(256, 1, 1)
fn instance_norm_partials(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let chunk = wg.x + wg.y * np.chunk_row;
    let valid = chunk < np.chunks;
    let start = chunk * CHUNK;
    var s = 0.0;
    if (valid) {
        for (var i = 0u; i < CHUNK / LANES; i++) {
            let j = start + i * LANES + lane;
            if (j < np.n) {
                s += grey[j];
            }
        }
    }
    let total = lane_sum(lane, s);
    var count = 1u;
    if (valid) {
        count = min(CHUNK, np.n - start);
    }
    let mean = total / f32(count);
    var q = 0.0;
    if (valid) {
        for (var i = 0u; i < CHUNK / LANES; i++) {
            let j = start + i * LANES + lane;
            if (j < np.n) {
                let d = grey[j] - mean;
                q += d * d;
            }
        }
    }
    let m2 = lane_sum(lane, q);
    if (valid && lane == 0u) {
        partials[chunk * 3u] = f32(count);
        partials[chunk * 3u + 1u] = mean;
        partials[chunk * 3u + 2u] = m2;
    }
}

// Chan et al.'s pairwise update: (count, mean, M2) of two parts to that of their union.
fn chan(a: vec3<f32>, b: vec3<f32>) -> vec3<f32> {
    if (b.x == 0.0) {
        return a;
    }
    if (a.x == 0.0) {
        return b;
    }
    let n = a.x + b.x;
    let d = b.y - a.y;
    return vec3<f32>(n, a.y + d * (b.x / n), a.z + b.z + d * d * (a.x * b.x / n));
}

@compute @workgroup_size(256, 1, 1)
fn instance_norm_stats(@builtin(local_invocation_index) lane: u32) {
    var acc = vec3<f32>(0.0, 0.0, 0.0);
    for (var c = lane; c < np.chunks; c += LANES) {
        acc = chan(acc, vec3<f32>(partials_in[c * 3u], partials_in[c * 3u + 1u], partials_in[c * 3u + 2u]));
    }
    red3[lane] = acc;
    workgroupBarrier();
    for (var h = LANES / 2u; h > 0u; h >>= 1u) {
        if (lane < h) {
            red3[lane] = chan(red3[lane], red3[lane + h]);
        }
        workgroupBarrier();
    }
    if (lane == 0u) {
        let t = red3[0];
        let var_ = t.z / max(t.x, 1.0);
        stats[0] = t.y;
        stats[1] = 1.0 / sqrt(var_ + 1e-5);
    }
}

// The index of invocation `lane` of workgroup (x, y) in a grid `row` workgroups wide.
fn flat(wg: vec3<u32>, lane: u32, row: u32) -> u32 {
    return (wg.x + wg.y * row) * LANES + lane;
}

@compute @workgroup_size(256, 1, 1)
fn instance_norm_apply(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = flat(wg, lane, np.row);
    if (i < np.n) {
        normed[i] = (grey[i] - stats_in[0]) * stats_in[1];
    }
}

// AvgPool2d(k, stride k): c planes of h x w to ho x wo.
@compute @workgroup_size(256, 1, 1)
fn avg_pool(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = flat(wg, lane, mp.row);
    if (i >= mp.n) {
        return;
    }
    let ox = i % mp.wo;
    let oy = (i / mp.wo) % mp.ho;
    let c = i / (mp.wo * mp.ho);
    var s = 0.0;
    for (var dy = 0u; dy < mp.k; dy++) {
        for (var dx = 0u; dx < mp.k; dx++) {
            s += src_a[(c * mp.h + oy * mp.k + dy) * mp.w + ox * mp.k + dx];
        }
    }
    dst[i] = s * mp.inv;
}

// XFeat's _unfold2d(x, 8): one plane of h x w to 64 planes of ho x wo, plane ky * 8 + kx.
@compute @workgroup_size(256, 1, 1)
fn space_to_depth8(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = flat(wg, lane, mp.row);
    if (i >= mp.n) {
        return;
    }
    let ox = i % mp.wo;
    let oy = (i / mp.wo) % mp.ho;
    let c = i / (mp.wo * mp.ho);
    dst[i] = src_a[(oy * 8u + c / 8u) * mp.w + ox * 8u + c % 8u];
}

// PyTorch's bilinear source index (align_corners = False) for output index `o` of an axis of
// `len` source values at scale `scale` (source / output length): (i0, i1, weight of i1).
fn source_index(o: u32, len: u32, scale: f32) -> vec3<f32> {
    let s = max(scale * (f32(o) + 0.5) - 0.5, 0.0);
    let i0 = min(u32(floor(s)), len - 1u);
    let i1 = min(i0 + 1u, len - 1u);
    return vec3<f32>(f32(i0), f32(i1), s - f32(i0));
}

// Bilinear sample of plane c of `which` (1: src_b, h1 x w1; 2: src_c, h2 x w2) at output (oy, ox).
fn upsample(which: u32, c: u32, oy: u32, ox: u32) -> f32 {
    var h = mp.h1;
    var w = mp.w1;
    var sy = mp.sy1;
    var sx = mp.sx1;
    if (which == 2u) {
        h = mp.h2;
        w = mp.w2;
        sy = mp.sy2;
        sx = mp.sx2;
    }
    let ys = source_index(oy, h, sy);
    let xs = source_index(ox, w, sx);
    let base = c * h * w;
    let y0 = base + u32(ys.x) * w;
    let y1 = base + u32(ys.y) * w;
    let x0 = u32(xs.x);
    let x1 = u32(xs.y);
    var t = 0.0;
    var b = 0.0;
    if (which == 2u) {
        t = src_c[y0 + x0] * (1.0 - xs.z) + src_c[y0 + x1] * xs.z;
        b = src_c[y1 + x0] * (1.0 - xs.z) + src_c[y1 + x1] * xs.z;
    } else {
        t = src_b[y0 + x0] * (1.0 - xs.z) + src_b[y0 + x1] * xs.z;
        b = src_b[y1 + x0] * (1.0 - xs.z) + src_b[y1 + x1] * xs.z;
    }
    return t * (1.0 - ys.z) + b * ys.z;
}

// a + resize(b) + resize(c), all of c planes of ho x wo (XFeat's pyramid fusion).
@compute @workgroup_size(256, 1, 1)
fn bilinear_add(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = flat(wg, lane, mp.row);
    if (i >= mp.n) {
        return;
    }
    let ox = i % mp.wo;
    let oy = (i / mp.wo) % mp.ho;
    let c = i / (mp.wo * mp.ho);
    dst[i] = (src_a[i] + upsample(1u, c, oy, ox)) + upsample(2u, c, oy, ox);
}

var<workgroup> tile: array<f32, IN_CAP>;
var<workgroup> wtile: array<vec4<f32>, W_CAP / 4u>;

@compute @workgroup_size(8, 8, 1)
fn conv2d(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>, @builtin(local_invocation_index) li: u32) {
    let tx = lid.x;
    let ty = lid.y;
    let g = wg.z;
    let ox0 = wg.x * TILE_W;
    let oy0 = wg.y * TILE_H;
    let k = cp.k;
    let kk = k * k;
    let s = cp.stride;
    let plane = cp.rows * cp.pitch;
    // acc[p]: channels 0..3 of pixel p, acc[4 + p]: channels 4..7
    var acc: array<vec4<f32>, 8>;
    for (var c0 = 0u; c0 < cp.cin; c0 += cp.chunk) {
        let cn = min(cp.chunk, cp.cin - c0);
        for (var i = li; i < cn * plane; i += THREADS) {
            let c = i / plane;
            let r = (i % plane) / cp.pitch;
            let col = i % cp.pitch;
            let iy = i32(oy0 * s + r) - i32(cp.pad);
            let ix = i32(ox0 * s + col) - i32(cp.pad);
            var v = 0.0;
            if (col < cp.cols && iy >= 0 && ix >= 0 && u32(iy) < cp.h && u32(ix) < cp.w) {
                v = conv_in[((c0 + c) * cp.h + u32(iy)) * cp.w + u32(ix)];
            }
            tile[i] = v;
        }
        let wbase = cp.weight_at + (g * cp.cin + c0) * kk * CO_GROUP;
        for (var i = li; i < cn * kk * 2u; i += THREADS) {
            let b = wbase + i * 4u;
            wtile[i] = vec4<f32>(weights[b], weights[b + 1u], weights[b + 2u], weights[b + 3u]);
        }
        workgroupBarrier();
        for (var c = 0u; c < cn; c++) {
            for (var ky = 0u; ky < k; ky++) {
                for (var kx = 0u; kx < k; kx++) {
                    let t = (c * kk + ky * k + kx) * 2u;
                    let w0 = wtile[t];
                    let w1 = wtile[t + 1u];
                    let base = c * plane + (ty * s + ky) * cp.pitch + tx * s + kx;
                    for (var p = 0u; p < 4u; p++) {
                        let v = tile[base + p * 8u * s];
                        acc[p] += v * w0;
                        acc[4u + p] += v * w1;
                    }
                }
            }
        }
        workgroupBarrier();
    }
    let oy = oy0 + ty;
    for (var p = 0u; p < 4u; p++) {
        let ox = ox0 + tx + p * 8u;
        if (oy < cp.ho && ox < cp.wo) {
            for (var j = 0u; j < CO_GROUP; j++) {
                let co = g * CO_GROUP + j;
                if (co < cp.cout) {
                    var y = (acc[(j / 4u) * 4u + p][j % 4u] - weights[cp.sub_at + co]) * weights[cp.mul_at + co];
                    if (cp.act == ACT_RELU) {
                        y = max(y, 0.0);
                    } else if (cp.act == ACT_SIGMOID) {
                        y = 1.0 / (1.0 + exp(-y));
                    }
                    let o = (co * cp.ho + oy) * cp.wo + ox;
                    if (cp.has_add != 0u) {
                        y += conv_add[o];
                    }
                    conv_out[o] = y;
                }
            }
        }
    }
}
