// Mutual nearest neighbours between the keypoints of (query, reference) pairs: for every row of one
// side, the column of the other side with the largest dot product (the lowest index among equals)
// and that dot product. CPU twin: kernels/src/mnn_match.rs (`mnn_match`), which gives the same
// indices and dot products bit for bit (integer arithmetic).
//
// Descriptors are int8, four to a u32 word. One workgroup scores 64 rows of one side of one pair
// (workgroup id x: the block of rows, y: the pair, z: the direction, 0 = query rows against the
// reference's keypoints, 1 = the reverse). The other side's descriptors are read a tile of 64 at a
// time into workgroup memory, every row of the block scoring the whole tile.

struct MnnParams {
    pairs: u32,
    words: u32,
    max_keypoints: u32,
    _pad: u32,
}

struct MnnPair {
    query_start: u32,
    query_len: u32,
    ref_start: u32,
    ref_len: u32,
}

@group(0) @binding(0) var<uniform> p: MnnParams;
@group(0) @binding(1) var<storage, read> pairs: array<MnnPair>;
@group(0) @binding(2) var<storage, read> queries: array<u32>;
@group(0) @binding(3) var<storage, read> refs: array<u32>;
@group(0) @binding(4) var<storage, read_write> best: array<u32>;
@group(0) @binding(5) var<storage, read_write> best_dot: array<i32>;

// rows per workgroup, columns per tile
const ROWS: u32 = 64u;
const TILE: u32 = 64u;
// longest descriptor in words (256 int8 values, SuperPoint's width)
const MAX_WORDS: u32 = 64u;
const NO_MATCH: u32 = 0xffffffffu;

// 16 KiB, WebGPU's guaranteed workgroup storage, and nothing else
var<workgroup> tile: array<u32, 4096>; // TILE * MAX_WORDS

// Dot product of the four signed bytes of two words (extractBits sign-extends signed values).
fn dot4(x: u32, y: u32) -> i32 {
    let a = bitcast<i32>(x);
    let b = bitcast<i32>(y);
    return extractBits(a, 0u, 8u) * extractBits(b, 0u, 8u) + extractBits(a, 8u, 8u) * extractBits(b, 8u, 8u)
        + extractBits(a, 16u, 8u) * extractBits(b, 16u, 8u) + extractBits(a, 24u, 8u) * extractBits(b, 24u, 8u);
}

@compute @workgroup_size(64, 1, 1)
fn mnn_match(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let pair = pairs[wg.y];
    let dir = wg.z;
    var row_start = pair.query_start;
    var row_len = pair.query_len;
    var col_start = pair.ref_start;
    if (dir == 1u) {
        row_start = pair.ref_start;
        row_len = pair.ref_len;
        col_start = pair.query_start;
    }
    let w = p.words;
    let i = wg.x * ROWS + lane;
    let has_row = i < row_len;
    var row: array<u32, 64>;
    if (has_row) {
        for (var k = 0u; k < w; k++) {
            let at = (row_start + i) * w + k;
            if (dir == 0u) {
                row[k] = queries[at];
            } else {
                row[k] = refs[at];
            }
        }
    }
    // the column count, uniform across the workgroup (every lane loops and meets the barriers):
    // read from a read-only binding at the workgroup's pair, as a `let`
    let n = select(pair.ref_len, pair.query_len, dir == 1u);
    var bd = bitcast<i32>(0x80000000u);
    var bj = NO_MATCH;
    for (var t0 = 0u; t0 < n; t0 += TILE) {
        let tl = min(TILE, n - t0);
        for (var k = lane; k < tl * w; k += ROWS) {
            let at = (col_start + t0) * w + k;
            if (dir == 0u) {
                tile[k] = refs[at];
            } else {
                tile[k] = queries[at];
            }
        }
        workgroupBarrier();
        if (has_row) {
            for (var jj = 0u; jj < tl; jj++) {
                var d = 0i;
                for (var k = 0u; k < w; k++) {
                    d += dot4(row[k], tile[jj * w + k]);
                }
                if (d > bd) {
                    bd = d;
                    bj = t0 + jj;
                }
            }
        }
        workgroupBarrier();
    }
    if (has_row) {
        let at = (wg.y * 2u + dir) * p.max_keypoints + i;
        best[at] = bj;
        best_dot[at] = bd;
    }
}
