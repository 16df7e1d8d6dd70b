// Semantic edge extraction. CPU twin: kernels/src/semantic_edges.rs (`semantic_edges`).
// A pixel is an edge pixel when its class is used and a 4-neighbour has a different used class.
// One invocation per pixel; frames of a batch along z. Class ids are bytes, four to a word
// (pixel i in byte i % 4 of word i / 4): one byte per pixel crosses to the device.

//#include abi.wgsl

@group(0) @binding(0) var<uniform> dims: Dims;
@group(0) @binding(1) var<storage, read> labels: array<u32>;
@group(0) @binding(2) var<storage, read> used: array<u32, 256>;
@group(0) @binding(3) var<storage, read_write> edges: array<u32>;

fn label_at(i: u32) -> u32 {
    return (labels[i >> 2u] >> ((i & 3u) * 8u)) & 0xffu;
}

fn differs(c: u32, j: u32) -> bool {
    let n = label_at(j);
    return n != c && used[n] != 0u;
}

@compute @workgroup_size(16, 16, 1)
fn semantic_edges(@builtin(global_invocation_id) gid: vec3<u32>) {
    let x = gid.x;
    let y = gid.y;
    if (x >= dims.width || y >= dims.height || gid.z >= dims.frames) {
        return;
    }
    let w = dims.width;
    let i = gid.z * w * dims.height + y * w + x;
    let c = label_at(i);
    var edge = 0u;
    if (used[c] != 0u) {
        if ((x > 0u && differs(c, i - 1u)) || (x + 1u < w && differs(c, i + 1u))
            || (y > 0u && differs(c, i - w)) || (y + 1u < dims.height && differs(c, i + w))) {
            edge = 1u;
        }
    }
    edges[i] = edge;
}
