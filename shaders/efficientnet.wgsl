// EfficientNet-Lite + GeM (the whole-image embedding, issue 61) on the device: the layers of the
// native forward pass (src/networks/embedding/efficientnet.rs) as dispatches. CPU twins:
// kernels/src/efficientnet.rs (same names, bindings and loop shapes).
//
// conv_direct: a full (the stem) or depthwise convolution with TensorFlow's SAME padding given as
//   pad_top / pad_left (reads outside the input are zeros; the odd row or column of SAME falls
//   outside the output), in-bounds inputs read as x * scale + shift, then bias and an optional
//   ReLU6. One invocation per output value; the kernel's taps in row order.
// pointwise: a 1x1 convolution, out[co, p] = bias[co] + sum over ci of w[co, ci] x in[ci, p],
//   then an optional ReLU6 and an optional residual added last. 16 x 16 output tiles (pixels x
//   channels), the input and the weights through workgroup memory 16 input channels at a time;
//   each invocation sums its channels in order.
// gem_pool: per channel (mean over the pixels of max(x, 1e-6)^3)^(1/3). One invocation per channel.

const LANES: u32 = 256u;
const TILE: u32 = 16u;
const GEM_FLOOR: f32 = 1e-6;

struct EffConvParams {
    cin: u32,
    cout: u32,
    h: u32,
    w: u32,
    ho: u32,
    wo: u32,
    k: u32,
    stride: u32,
    pad_top: u32,
    pad_left: u32,
    depthwise: u32,
    relu6: u32,
    scale: f32,
    shift: f32,
    row: u32,
    n: u32,
}

struct EffPointParams {
    cin: u32,
    cout: u32,
    hw: u32,
    relu6: u32,
    residual: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

struct GemParams {
    c: u32,
    hw: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> cp: EffConvParams;
@group(0) @binding(1) var<storage, read> conv_in: array<f32>;
@group(0) @binding(2) var<storage, read> conv_w: array<f32>;
@group(0) @binding(3) var<storage, read> conv_b: array<f32>;
@group(0) @binding(4) var<storage, read_write> conv_out: array<f32>;

@compute @workgroup_size(256, 1, 1)
fn conv_direct(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let i = (wg.x + wg.y * cp.row) * LANES + lane;
    if (i >= cp.n) {
        return;
    }
    let plane = cp.ho * cp.wo;
    let co = i / plane;
    let oy = (i % plane) / cp.wo;
    let ox = i % cp.wo;
    var c0 = 0u;
    var c1 = cp.cin;
    if (cp.depthwise == 1u) {
        c0 = co;
        c1 = co + 1u;
    }
    var s = conv_b[co];
    for (var ci = c0; ci < c1; ci++) {
        let wbase = (co * (c1 - c0) + (ci - c0)) * cp.k * cp.k;
        for (var ky = 0u; ky < cp.k; ky++) {
            let iy = i32(oy * cp.stride + ky) - i32(cp.pad_top);
            if (iy < 0 || iy >= i32(cp.h)) {
                continue;
            }
            for (var kx = 0u; kx < cp.k; kx++) {
                let ix = i32(ox * cp.stride + kx) - i32(cp.pad_left);
                if (ix < 0 || ix >= i32(cp.w)) {
                    continue;
                }
                let v = conv_in[(ci * cp.h + u32(iy)) * cp.w + u32(ix)] * cp.scale + cp.shift;
                s += conv_w[wbase + ky * cp.k + kx] * v;
            }
        }
    }
    if (cp.relu6 == 1u) {
        s = clamp(s, 0.0, 6.0);
    }
    conv_out[i] = s;
}

@group(0) @binding(5) var<uniform> pp: EffPointParams;
@group(0) @binding(6) var<storage, read> pw_in: array<f32>;
@group(0) @binding(7) var<storage, read> pw_w: array<f32>;
@group(0) @binding(8) var<storage, read> pw_b: array<f32>;
@group(0) @binding(9) var<storage, read> pw_res: array<f32>;
@group(0) @binding(10) var<storage, read_write> pw_out: array<f32>;

var<workgroup> tile_in: array<f32, 256>;
var<workgroup> tile_w: array<f32, 256>;

@compute @workgroup_size(16, 16, 1)
fn pointwise(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) lid: vec3<u32>) {
    // invocation (lid.x, lid.y): pixel wg.x * TILE + lid.x of output channel wg.y * TILE + lid.y
    let p = wg.x * TILE + lid.x;
    let co = wg.y * TILE + lid.y;
    var s = 0.0;
    for (var c0 = 0u; c0 < pp.cin; c0 += TILE) {
        // tile_in[ci][px] = in[c0 + ci, wg.x * TILE + px]; tile_w[co][ci] = w[wg.y * TILE + co, c0 + ci]
        let ci_in = c0 + lid.y;
        let p_in = wg.x * TILE + lid.x;
        var a = 0.0;
        if (ci_in < pp.cin && p_in < pp.hw) {
            a = pw_in[ci_in * pp.hw + p_in];
        }
        tile_in[lid.y * TILE + lid.x] = a;
        let co_w = wg.y * TILE + lid.y;
        let ci_w = c0 + lid.x;
        var b = 0.0;
        if (co_w < pp.cout && ci_w < pp.cin) {
            b = pw_w[co_w * pp.cin + ci_w];
        }
        tile_w[lid.y * TILE + lid.x] = b;
        workgroupBarrier();
        let n = min(TILE, pp.cin - c0);
        for (var ci = 0u; ci < n; ci++) {
            s += tile_w[lid.y * TILE + ci] * tile_in[ci * TILE + lid.x];
        }
        workgroupBarrier();
    }
    if (p < pp.hw && co < pp.cout) {
        var v = s + pw_b[co];
        if (pp.relu6 == 1u) {
            v = clamp(v, 0.0, 6.0);
        }
        if (pp.residual == 1u) {
            v += pw_res[co * pp.hw + p];
        }
        pw_out[co * pp.hw + p] = v;
    }
}

@group(0) @binding(11) var<uniform> gp: GemParams;
@group(0) @binding(12) var<storage, read> gem_in: array<f32>;
@group(0) @binding(13) var<storage, read_write> gem_out: array<f32>;

@compute @workgroup_size(256, 1, 1)
fn gem_pool(@builtin(global_invocation_id) gid: vec3<u32>) {
    let c = gid.x;
    if (c >= gp.c) {
        return;
    }
    var s = 0.0;
    for (var i = 0u; i < gp.hw; i++) {
        let v = max(gem_in[c * gp.hw + i], GEM_FLOOR);
        s += v * v * v;
    }
    gem_out[c] = pow(s / f32(gp.hw), 1.0 / 3.0);
}
