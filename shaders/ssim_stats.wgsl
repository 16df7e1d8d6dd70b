// SSIM window statistics of a batch of pooled global descriptors, on the device so that a
// descriptor's stats never cross to the host to be computed. CPU twin: kernels/src/ssim_stats.rs
// (`stats_row_sums`, `stats_windows`), whose values equal `kernels::ssim::ssim_stats`'s bit for
// bit: the same separable window sums, in the same order.
//
// stats_row_sums: one invocation per (row, window column) of frame dims.first + gid.y: the sums of
//   x and x*x over the row's `win` values from that column, into `rows` ([x sums | x*x sums] per
//   frame of the run, from 0).
// stats_windows: one invocation per window of frame dims.first + gid.y: the sums of `win` row sums
//   down the column, then the window's mean and (sample) variance into `stats` ([means |
//   variances] per frame).

//#include abi.wgsl

@group(0) @binding(0) var<uniform> p: SsimParams;
@group(0) @binding(1) var<uniform> dims: Dims;
@group(0) @binding(2) var<storage, read> desc: array<f32>;
@group(0) @binding(3) var<storage, read_write> rows: array<f32>;
@group(0) @binding(4) var<storage, read_write> stats: array<f32>;

@compute @workgroup_size(64, 1, 1)
fn stats_row_sums(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = p.gh * p.nw;
    if (gid.x >= n || gid.y >= dims.frames) {
        return;
    }
    let r = gid.x / p.nw;
    let c = gid.x % p.nw;
    let src = (dims.first + gid.y) * p.gw * p.gh + r * p.gw + c;
    var s = 0.0;
    var s2 = 0.0;
    for (var k = 0u; k < p.win; k++) {
        let v = desc[src + k];
        s += v;
        s2 += v * v;
    }
    rows[2u * gid.y * n + gid.x] = s;
    rows[(2u * gid.y + 1u) * n + gid.x] = s2;
}

@compute @workgroup_size(64, 1, 1)
fn stats_windows(@builtin(global_invocation_id) gid: vec3<u32>) {
    let n = p.nh * p.nw;
    if (gid.x >= n || gid.y >= dims.frames) {
        return;
    }
    let rn = p.gh * p.nw;
    let r = gid.x / p.nw;
    let c = gid.x % p.nw;
    var s = 0.0;
    var s2 = 0.0;
    for (var k = 0u; k < p.win; k++) {
        s += rows[2u * gid.y * rn + (r + k) * p.nw + c];
        s2 += rows[(2u * gid.y + 1u) * rn + (r + k) * p.nw + c];
    }
    let inv = 1.0 / f32(p.win * p.win);
    let m = s * inv;
    let f = dims.first + gid.y;
    stats[2u * f * n + gid.x] = m;
    stats[2u * f * n + n + gid.x] = (s2 * inv - m * m) * p.cov_norm;
}
