// Exact Euclidean distance transform, Meijster, Roerdink & Hesselink (ISMM 2000).
// CPU twin: kernels/src/edt.rs (`edt_columns`, `edt_rows`). 32-bit integer arithmetic only, so the
// squared distances equal the CPU's bit for bit.

//#include abi.wgsl

@group(0) @binding(0) var<uniform> dims: Dims;
@group(0) @binding(1) var<storage, read> edges: array<u32>;
@group(0) @binding(2) var<storage, read_write> g: array<i32>;
@group(0) @binding(3) var<storage, read_write> s: array<i32>;
@group(0) @binding(4) var<storage, read_write> t: array<i32>;
@group(0) @binding(5) var<storage, read_write> d2: array<u32>;

// Phase 1: one invocation per column x (gid.x) of frame gid.y.
@compute @workgroup_size(64, 1, 1)
fn edt_columns(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x = gid.x;
    if (x >= dims.width || gid.y >= dims.frames) {
        return;
    }
    let w = dims.width;
    let h = dims.height;
    let base = gid.y * w * h;
    let inf = i32(w + h);
    if (edges[base + x] != 0u) { g[base + x] = 0; } else { g[base + x] = inf; }
    for (var y = 1u; y < h; y++) {
        let i = base + y * w + x;
        if (edges[i] != 0u) { g[i] = 0; } else { g[i] = min(g[i - w] + 1, inf); }
    }
    if (h > 1u) {
        for (var y = i32(h) - 2; y >= 0; y--) {
            let i = base + u32(y) * w + x;
            if (g[i + w] < g[i]) {
                g[i] = g[i + w] + 1;
            }
        }
    }
}

// Floor division for a positive divisor (WGSL's `/` truncates toward zero).
fn floor_div(a: i32, b: i32) -> i32 {
    let q = a / b;
    if (a % b != 0 && a < 0) {
        return q - 1;
    }
    return q;
}

var<private> row: u32;

fn gi(i: i32) -> i32 {
    return g[row + u32(i)];
}

fn f(x: i32, i: i32) -> i32 {
    return (x - i) * (x - i) + gi(i) * gi(i);
}

fn sep(i: i32, u: i32) -> i32 {
    return floor_div(u * u - i * i + gi(u) * gi(u) - gi(i) * gi(i), 2 * (u - i));
}

// Phase 2: one invocation per row y (gid.x) of frame gid.y; s and t are this row's scratch.
@compute @workgroup_size(64, 1, 1)
fn edt_rows(@builtin(global_invocation_id) gid: vec3<u32>) {
    if (gid.x >= dims.height || gid.y >= dims.frames) {
        return;
    }
    row = gid.y * dims.width * dims.height + gid.x * dims.width;
    let w = i32(dims.width);
    var q: i32 = 0;
    s[row] = 0;
    t[row] = 0;
    for (var u = 1; u < w; u++) {
        loop {
            if (q < 0) { break; }
            let tq = t[row + u32(q)];
            if (f(tq, s[row + u32(q)]) <= f(tq, u)) { break; }
            q -= 1;
        }
        if (q < 0) {
            q = 0;
            s[row] = u;
        } else {
            let wsep = 1 + sep(s[row + u32(q)], u);
            if (wsep < w) {
                q += 1;
                s[row + u32(q)] = u;
                t[row + u32(q)] = wsep;
            }
        }
    }
    for (var u = w - 1; u >= 0; u--) {
        d2[row + u32(u)] = u32(f(u, s[row + u32(q)]));
        if (u == t[row + u32(q)]) {
            q -= 1;
        }
    }
}
