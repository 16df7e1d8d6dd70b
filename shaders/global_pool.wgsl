// Truncation and area resizing of the distance transform. CPU twin: kernels/src/global_pool.rs
// (`global_pool`). One invocation per output cell (gid.x) of frame gid.y.

struct PoolParams {
    src_width: u32,
    src_height: u32,
    dst_width: u32,
    dst_height: u32,
    tau: f32,
    frames: u32,
    _pad0: u32,
    _pad1: u32,
}

@group(0) @binding(0) var<uniform> p: PoolParams;
@group(0) @binding(1) var<storage, read> d2: array<u32>;
@group(0) @binding(2) var<storage, read_write> out: array<f32>;

@compute @workgroup_size(64, 1, 1)
fn global_pool(@builtin(global_invocation_id) gid: vec3<u32>) {
    let cells = p.dst_width * p.dst_height;
    if (gid.x >= cells || gid.y >= p.frames) {
        return;
    }
    let ox = gid.x % p.dst_width;
    let oy = gid.x / p.dst_width;
    let src = gid.y * p.src_width * p.src_height;
    let sx = f32(p.src_width) / f32(p.dst_width);
    let sy = f32(p.src_height) / f32(p.dst_height);
    let x0 = f32(ox) * sx;
    let x1 = f32(ox + 1u) * sx;
    let y0 = f32(oy) * sy;
    let y1 = f32(oy + 1u) * sy;
    let xs = u32(floor(x0));
    let xe = min(u32(ceil(x1)), p.src_width);
    let ys = u32(floor(y0));
    let ye = min(u32(ceil(y1)), p.src_height);
    var acc = 0.0;
    for (var y = ys; y < ye; y++) {
        let wy = max(min(y1, f32(y + 1u)) - max(y0, f32(y)), 0.0);
        var rowsum = 0.0;
        for (var x = xs; x < xe; x++) {
            let wx = max(min(x1, f32(x + 1u)) - max(x0, f32(x)), 0.0);
            let d = sqrt(f32(d2[src + y * p.src_width + x]));
            rowsum += wx * min(d, p.tau);
        }
        acc += wy * rowsum;
    }
    out[gid.y * cells + gid.x] = min(acc / (sx * sy * p.tau), 1.0);
}
