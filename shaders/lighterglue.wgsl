// LighterGlue (XFeat's LightGlue: Potje et al., CVPR 2024; Lindenberger, Sarlin and Pollefeys,
// ICCV 2023) on the device: the operations of one forward pass over a batch of keypoint pairs.
// CPU twins of the same names, bindings and loop shape: kernels/src/lighterglue.rs; the executor
// that strings them into the network: src/gpu/lighterglue.rs (the same plan runs on the twins).
//
// Every point of every pair is one row of the batch; a row's partners (its own image's points in
// self-attention, the other image's in cross-attention and the assignment) are a contiguous range
// of rows given by `table` (start, count per row), so one dispatch serves every pair.
//
// - lg_linear: y = (x W^T + b) * scale, onto the output or added to it; x may be the concatenation
//   of two row-major inputs (the feed-forward's [x, message]). 16 x 16 outputs per workgroup, the
//   input and weight tiles 16 values of k at a time; each output sums k in order.
// - lg_layer_norm: layer norm of each row (PyTorch's, biased variance), then GELU (exact form, erf by
//   Abramowitz and Stegun 7.1.26, |error| <= 1.5e-7), in place; one invocation per row.
// - lg_rotary: the rotary positional encoding applied to the self-attention's queries and keys,
//   split from the interleaved Wqkv output into three planes.
// - lg_attention: softmax(scale q k^T) v of each row over its partners, the softmax online (a
//   running maximum and sum, rescaled per chunk of 128 partners: no rows x partners matrix).
// - lg_row_lse, lg_assignment_best: the assignment head. The log assignment of (i, j) is
//   2 s_ij + bias_i + bias_j with bias = log sigmoid(matchability) - logsumexp of the row's
//   similarities; each row's best partner (ties to the lowest) and its score.
// - lg_gather: the rows a pruning step keeps, moved together.

struct LgParams {
    rows: u32,
    n_in: u32,
    n_out: u32,
    split: u32,
    w_off: u32,
    b_off: u32,
    g_off: u32,
    flags: u32,
    scale: f32,
    o_off: u32,
    q_off: u32,
    k_off: u32,
    v_off: u32,
    _pad0: u32,
    _pad1: u32,
    _pad2: u32,
}

@group(0) @binding(0) var<uniform> p: LgParams;
@group(0) @binding(1) var<storage, read> a: array<f32>;
@group(0) @binding(2) var<storage, read> b: array<f32>;
@group(0) @binding(3) var<storage, read> weights: array<f32>;
@group(0) @binding(4) var<storage, read_write> out: array<f32>;
@group(0) @binding(5) var<storage, read> table: array<u32>;
@group(0) @binding(6) var<storage, read_write> best: array<u32>;

// invocations of the row kernels' workgroups, and partners per chunk
const LANES: u32 = 128u;
// lg_linear's tile: TILE x TILE outputs, TILE values of k at a time
const TILE: u32 = 16u;
// rows per lg_layer_norm workgroup
const LN_ROWS: u32 = 64u;
// lg_linear: add to the output; lg_layer_norm: GELU after the norm
const FLAG_ACCUMULATE: u32 = 1u;
const FLAG_GELU: u32 = 1u;
// a row without partners
const NO_PARTNER: u32 = 0xffffffffu;
const LN_EPS: f32 = 1e-5;
const LOWEST: f32 = -3.402823e38;

// the row of a row kernel's workgroup (grids wider than 65,535 fold into y)
fn row_of(wg: vec3<u32>, nwg: vec3<u32>) -> u32 {
    return wg.y * nwg.x + wg.x;
}

var<workgroup> xs: array<f32, 256>; // TILE * TILE
var<workgroup> ws: array<f32, 256>;

fn lin_in(r: u32, i: u32) -> f32 {
    if (i < p.split) {
        return a[r * p.split + i];
    }
    return b[r * (p.n_in - p.split) + (i - p.split)];
}

@compute @workgroup_size(16, 16, 1)
fn lg_linear(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_id) l: vec3<u32>) {
    var acc = 0.0;
    for (var k0 = 0u; k0 < p.n_in; k0 += TILE) {
        // invocation (x, y) loads the input (row y of the tile, k0 + x) and the weight (output y)
        let kk = k0 + l.x;
        let ri = wg.y * TILE + l.y;
        let oi = wg.x * TILE + l.y;
        var xv = 0.0;
        if (ri < p.rows && kk < p.n_in) {
            xv = lin_in(ri, kk);
        }
        var wv = 0.0;
        if (oi < p.n_out && kk < p.n_in) {
            wv = weights[p.w_off + oi * p.n_in + kk];
        }
        xs[l.y * TILE + l.x] = xv;
        ws[l.y * TILE + l.x] = wv;
        workgroupBarrier();
        let n = min(TILE, p.n_in - k0);
        for (var j = 0u; j < n; j++) {
            acc += xs[l.y * TILE + j] * ws[l.x * TILE + j];
        }
        workgroupBarrier();
    }
    let r = wg.y * TILE + l.y;
    let o = wg.x * TILE + l.x;
    if (r < p.rows && o < p.n_out) {
        let y = (acc + weights[p.b_off + o]) * p.scale;
        let at = p.o_off + r * p.n_out + o;
        if ((p.flags & FLAG_ACCUMULATE) != 0u) {
            out[at] = out[at] + y;
        } else {
            out[at] = y;
        }
    }
}

fn lg_erf(x: f32) -> f32 {
    let z = abs(x);
    let t = 1.0 / (1.0 + 0.3275911 * z);
    let poly = ((((1.061405429 * t - 1.453152027) * t + 1.421413741) * t - 0.284496736) * t + 0.254829592) * t;
    let y = 1.0 - poly * exp(-z * z);
    return select(y, -y, x < 0.0);
}

@compute @workgroup_size(64, 1, 1)
fn lg_layer_norm(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let r = wg.x * LN_ROWS + lane;
    if (r >= p.rows) {
        return;
    }
    let w = p.n_in;
    let base = p.o_off + r * w;
    var s = 0.0;
    for (var i = 0u; i < w; i++) {
        s += out[base + i];
    }
    let mean = s / f32(w);
    var v = 0.0;
    for (var i = 0u; i < w; i++) {
        let c = out[base + i] - mean;
        v += c * c;
    }
    let inv = 1.0 / sqrt(v / f32(w) + LN_EPS);
    for (var i = 0u; i < w; i++) {
        var y = (out[base + i] - mean) * inv * weights[p.g_off + i] + weights[p.b_off + i];
        if ((p.flags & FLAG_GELU) != 0u) {
            y = 0.5 * y * (1.0 + lg_erf(y * 0.70710677));
        }
        out[base + i] = y;
    }
}

@compute @workgroup_size(128, 1, 1)
fn lg_rotary(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    // one invocation per (row, pair of dimensions); a: Wqkv's output (q, k, v interleaved), b: the
    // encoding (cos, sin per pair)
    let d = p.n_in;
    let h = d / 2u;
    let i = row_of(wg, nwg) * LANES + lane;
    if (i >= p.rows * h) {
        return;
    }
    let r = i / h;
    let k = i % h;
    let t = r * 3u * d + 6u * k;
    let e = r * d + 2u * k;
    let c = b[e];
    let s = b[e + 1u];
    let o = r * d + 2u * k;
    out[p.q_off + o] = a[t] * c - a[t + 3u] * s;
    out[p.q_off + o + 1u] = a[t + 3u] * c + a[t] * s;
    out[p.k_off + o] = a[t + 1u] * c - a[t + 4u] * s;
    out[p.k_off + o + 1u] = a[t + 4u] * c + a[t + 1u] * s;
    out[p.v_off + o] = a[t + 2u];
    out[p.v_off + o + 1u] = a[t + 5u];
}

var<workgroup> qs: array<f32, 128>; // the row's query (n_in <= LANES)
var<workgroup> ss: array<f32, 128>; // the chunk's scores
var<workgroup> ps: array<f32, 128>; // the chunk's exp(score - running maximum)

// The scores of chunk c0 of row r's partners into ss (scale q.k, plus `add[j]` where `with_bias`):
// invocation `lane` scores partner c0 + lane.
fn chunk_scores(r: u32, start: u32, c0: u32, n: u32, lane: u32, with_bias: bool) {
    if (lane < n) {
        let d = p.n_in;
        let kr = p.k_off + (start + c0 + lane) * d;
        var s = 0.0;
        for (var j = 0u; j < d; j++) {
            s += qs[j] * a[kr + j];
        }
        s = s * p.scale;
        if (with_bias) {
            s += b[start + c0 + lane];
        }
        ss[lane] = s;
    }
}

fn load_query(r: u32, lane: u32) {
    if (lane < p.n_in) {
        qs[lane] = a[p.q_off + r * p.n_in + lane];
    }
}

fn chunk_max(n: u32) -> f32 {
    var m = ss[0];
    for (var j = 1u; j < n; j++) {
        m = max(m, ss[j]);
    }
    return m;
}

// One chunk of the online softmax over the scores in ss: ps = exp(score - the new running
// maximum), the running maximum m and sum l updated; returns the factor earlier sums are rescaled
// by (0 for the first chunk).
fn online_step(c0: u32, n: u32, lane: u32, m: ptr<function, f32>, l: ptr<function, f32>) -> f32 {
    let cm = chunk_max(n);
    let nm = select(max(*m, cm), cm, c0 == 0u);
    let alpha = select(exp(*m - nm), 0.0, c0 == 0u);
    if (lane < n) {
        ps[lane] = exp(ss[lane] - nm);
    }
    workgroupBarrier();
    var cs = 0.0;
    for (var j = 0u; j < n; j++) {
        cs += ps[j];
    }
    *l = *l * alpha + cs;
    *m = nm;
    return alpha;
}

@compute @workgroup_size(128, 1, 1)
fn lg_attention(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let r = row_of(wg, nwg);
    if (r >= p.rows) {
        return;
    }
    let start = table[2u * r];
    let len = table[2u * r + 1u];
    let d = p.n_in;
    load_query(r, lane);
    workgroupBarrier();
    var m = 0.0;
    var l = 0.0;
    var acc = 0.0;
    for (var c0 = 0u; c0 < len; c0 += LANES) {
        let n = min(LANES, len - c0);
        chunk_scores(r, start, c0, n, lane, false);
        workgroupBarrier();
        let alpha = online_step(c0, n, lane, &m, &l);
        if (lane < d) {
            var t = 0.0;
            for (var j = 0u; j < n; j++) {
                t += ps[j] * a[p.v_off + (start + c0 + j) * d + lane];
            }
            acc = acc * alpha + t;
        }
        workgroupBarrier();
    }
    if (lane < d) {
        out[p.o_off + r * d + lane] = select(0.0, acc / l, len > 0u);
    }
}

@compute @workgroup_size(128, 1, 1)
fn lg_row_lse(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    // a: the projected descriptors (queries and keys alike), b: each row's matchability logit;
    // out: each row's bias, log sigmoid(matchability) - logsumexp of its similarities
    let r = row_of(wg, nwg);
    if (r >= p.rows) {
        return;
    }
    let start = table[2u * r];
    let len = table[2u * r + 1u];
    load_query(r, lane);
    workgroupBarrier();
    var m = 0.0;
    var l = 0.0;
    for (var c0 = 0u; c0 < len; c0 += LANES) {
        let n = min(LANES, len - c0);
        chunk_scores(r, start, c0, n, lane, false);
        workgroupBarrier();
        online_step(c0, n, lane, &m, &l);
        workgroupBarrier();
    }
    if (lane == 0u) {
        let z = b[r];
        let ls = min(z, 0.0) - log(1.0 + exp(-abs(z)));
        out[r] = select(LOWEST, ls - (log(l) + m), len > 0u);
    }
}

@compute @workgroup_size(128, 1, 1)
fn lg_assignment_best(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    // a: the projected descriptors, b: the rows' biases (lg_row_lse); scale 2. best: the index of
    // the best partner within the row's range (NO_PARTNER without any), out: the log assignment
    // of the row and that partner
    let r = row_of(wg, nwg);
    if (r >= p.rows) {
        return;
    }
    let start = table[2u * r];
    let len = table[2u * r + 1u];
    load_query(r, lane);
    workgroupBarrier();
    var bv = LOWEST;
    var bj = NO_PARTNER;
    for (var c0 = 0u; c0 < len; c0 += LANES) {
        let n = min(LANES, len - c0);
        chunk_scores(r, start, c0, n, lane, true);
        workgroupBarrier();
        for (var j = 0u; j < n; j++) {
            if (bj == NO_PARTNER || ss[j] > bv) {
                bv = ss[j];
                bj = c0 + j;
            }
        }
        workgroupBarrier();
    }
    if (lane == 0u) {
        best[r] = bj;
        out[r] = select(LOWEST, bv + b[r], len > 0u);
    }
}

@compute @workgroup_size(128, 1, 1)
fn lg_gather(@builtin(workgroup_id) wg: vec3<u32>, @builtin(num_workgroups) nwg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    // row i of out (n_in values) = row table[i] of a
    let w = p.n_in;
    let i = row_of(wg, nwg) * LANES + lane;
    if (i >= p.rows * w) {
        return;
    }
    let r = i / w;
    let c = i % w;
    out[r * w + c] = a[table[r] * w + c];
}
