// VLAD per object. CPU twin: kernels/src/vlad_accumulate.rs (`vlad_assign`, `vlad_accumulate`).
// vlad_assign: one invocation per keypoint, nearest centre (ties to the lower index).
// vlad_accumulate: one workgroup per object; lane l owns dimensions l, l + 64, ... of every
// centre: residual sums, optional per-centre L2 (intra) normalisation and signed square root, and
// the final L2 normalisation, with tree reductions over the lanes.

struct VladParams {
    centres: u32,
    dim: u32,
    keypoints: u32,
    objects: u32,
    power_norm: u32,
    intra_norm: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: VladParams;
@group(0) @binding(1) var<storage, read> centres: array<f32>;
@group(0) @binding(2) var<storage, read> descriptors: array<f32>;
@group(0) @binding(3) var<storage, read_write> assignment: array<u32>;
@group(0) @binding(4) var<storage, read> object_offsets: array<u32>;
@group(0) @binding(5) var<storage, read_write> out: array<f32>;

const LANES: u32 = 64u;

@compute @workgroup_size(64, 1, 1)
fn vlad_assign(@builtin(global_invocation_id) gid: vec3<u32>) {
    let i = gid.x + gid.y * 65535u * LANES;
    if (i >= p.keypoints) {
        return;
    }
    var best = 3.0e38;
    var bj = 0u;
    for (var j = 0u; j < p.centres; j++) {
        var dist = 0.0;
        for (var d = 0u; d < p.dim; d++) {
            let diff = descriptors[i * p.dim + d] - centres[j * p.dim + d];
            dist += diff * diff;
        }
        if (dist < best) {
            best = dist;
            bj = j;
        }
    }
    assignment[i] = bj;
}

var<workgroup> partial: array<f32, 64>;

// Sum of `v` over the lanes (all lanes call it; the result is the same in every lane).
fn lane_total(lane: u32, v: f32) -> f32 {
    partial[lane] = v;
    workgroupBarrier();
    for (var h = LANES / 2u; h > 0u; h >>= 1u) {
        if (lane < h) {
            partial[lane] += partial[lane + h];
        }
        workgroupBarrier();
    }
    let total = partial[0];
    workgroupBarrier();
    return total;
}

@compute @workgroup_size(64, 1, 1)
fn vlad_accumulate(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let o = wg.x + wg.y * 65535u;
    let valid = o < p.objects;
    var a = 0u;
    var b = 0u;
    if (valid) {
        a = object_offsets[o];
        b = object_offsets[o + 1u];
    }
    let k = p.centres;
    let d = p.dim;
    let base = o * k * d;
    if (valid) {
        for (var j = 0u; j < k; j++) {
            for (var dd = lane; dd < d; dd += LANES) {
                out[base + j * d + dd] = 0.0;
            }
        }
        for (var i = a; i < b; i++) {
            let j = assignment[i];
            for (var dd = lane; dd < d; dd += LANES) {
                out[base + j * d + dd] += descriptors[i * d + dd] - centres[j * d + dd];
            }
        }
    }
    // intra-normalisation (a uniform condition: every lane takes the same path)
    for (var j = 0u; j < k * min(p.intra_norm, 1u); j++) {
        var s = 0.0;
        if (valid) {
            for (var dd = lane; dd < d; dd += LANES) {
                let v = out[base + j * d + dd];
                s += v * v;
            }
        }
        let norm = sqrt(lane_total(lane, s));
        if (valid && norm > 0.0) {
            for (var dd = lane; dd < d; dd += LANES) {
                out[base + j * d + dd] /= norm;
            }
        }
    }
    // power normalisation, then the final L2 normalisation
    var s = 0.0;
    if (valid) {
        for (var j = 0u; j < k; j++) {
            for (var dd = lane; dd < d; dd += LANES) {
                var v = out[base + j * d + dd];
                if (p.power_norm != 0u) {
                    v = sign(v) * sqrt(abs(v));
                    out[base + j * d + dd] = v;
                }
                s += v * v;
            }
        }
    }
    let norm = sqrt(lane_total(lane, s));
    if (valid && norm > 0.0) {
        for (var j = 0u; j < k; j++) {
            for (var dd = lane; dd < d; dd += LANES) {
                out[base + j * d + dd] /= norm;
            }
        }
    }
}
