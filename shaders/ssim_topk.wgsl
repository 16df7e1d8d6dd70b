// Batched SSIM of a query batch against one tile of the map, and streaming top-K.
// CPU twin: kernels/src/ssim_topk.rs (`ssim_tile`, `topk_merge`), which uses
// kernels/src/ssim.rs (`ssim_pair`) for one pair.
//
// ssim_tile: one workgroup per (reference in tile, query) pair. Lanes compute the horizontal
// window sums of x*y into workgroup memory, then the vertical sums (both in the twin's pair
// order: `pair_lo`, `pair_own`) and the per-window SSIM of windows lane, lane + 64, ..., then a
// tree reduction gives the mean.
// topk_merge: one invocation per query folds the tile's scores into its running top-K list
// (ties go to the lower reference index; NaN scores are skipped). Only the K-lists are ever
// read back.

//#include abi.wgsl

struct TileParams {
    queries: u32,
    tile_len: u32,
    tile_start: u32,
    k: u32,
}

@group(0) @binding(0) var<uniform> p: SsimParams;
@group(0) @binding(1) var<uniform> tp: TileParams;
@group(0) @binding(2) var<storage, read> queries: array<f32>;
@group(0) @binding(3) var<storage, read> query_stats: array<f32>;
@group(0) @binding(4) var<storage, read> refs: array<f32>;
@group(0) @binding(5) var<storage, read> ref_stats: array<f32>;
@group(0) @binding(6) var<storage, read_write> scores: array<f32>;
@group(0) @binding(7) var<storage, read_write> topk_scores: array<f32>;
@group(0) @binding(8) var<storage, read_write> topk_index: array<u32>;

const LANES: u32 = 64u;
// gh * nw must fit (checked on the host): 15 KiB of the 16 KiB WebGPU minimum.
const MAX_ROW_SUMS: u32 = 3840u;

var<workgroup> rows: array<f32, 3840>;
var<workgroup> partial: array<f32, 64>;

// f: the factors (1 / win², 2 cov_norm) (`window_factors`)
fn ssim_window(f: vec2<f32>, sum_xy: f32, mx: f32, my: f32, vx: f32, vy: f32) -> f32 {
    // the twin's grouping (kernels/src/ssim.rs, ssim_window_terms)
    let a = mx * my;
    let num = (2.0 * a + p.c1) * ((sum_xy * f.x - a) * f.y + p.c2);
    let den = ((mx * mx + p.c1) + my * my) * ((vx + p.c2) + vy);
    return num / den;
}

@compute @workgroup_size(64, 1, 1)
fn ssim_tile(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let r = wg.x;
    let q = wg.y;
    let len = p.gw * p.gh;
    let xq = q * len;
    let yr = r * len;
    let nrows = p.gh * p.nw;
    for (var idx = lane; idx < nrows; idx += LANES) {
        let row = idx / p.nw;
        let c = idx % p.nw;
        let lo = row * p.gw + pair_lo(c);
        var acc = queries[xq + lo] * refs[yr + lo];
        for (var k = 1u; k + 1u < p.win; k++) {
            acc += queries[xq + lo + k] * refs[yr + lo + k];
        }
        let own = row * p.gw + pair_own(c, p.win);
        acc += queries[xq + own] * refs[yr + own];
        rows[idx] = acc;
    }
    workgroupBarrier();
    let n = p.nw * p.nh;
    // the twin's `window_factors`, once per invocation
    let f = vec2<f32>(1.0 / f32(p.win * p.win), 2.0 * p.cov_norm);
    let sq = q * 2u * n;
    let sr = r * 2u * n;
    var acc = 0.0;
    for (var w = lane; w < n; w += LANES) {
        let row = w / p.nw;
        let c = w % p.nw;
        let lo = pair_lo(row);
        var v = rows[lo * p.nw + c];
        for (var k = 1u; k + 1u < p.win; k++) {
            v += rows[(lo + k) * p.nw + c];
        }
        v += rows[pair_own(row, p.win) * p.nw + c];
        acc += ssim_window(f, v, query_stats[sq + w], ref_stats[sr + w], query_stats[sq + n + w], ref_stats[sr + n + w]);
    }
    partial[lane] = acc;
    workgroupBarrier();
    for (var s = LANES / 2u; s > 0u; s >>= 1u) {
        if (lane < s) {
            partial[lane] += partial[lane + s];
        }
        workgroupBarrier();
    }
    if (lane == 0u) {
        scores[q * tp.tile_len + r] = partial[0] / f32(n);
    }
}

// NaN by its bits (exponent all ones, mantissa non-zero): `s != s` may be folded to false by
// shader compilers that assume finite floats.
fn is_nan(s: f32) -> bool {
    return (bitcast<u32>(s) & 0x7fffffffu) > 0x7f800000u;
}

@compute @workgroup_size(64, 1, 1)
fn topk_merge(@builtin(global_invocation_id) gid: vec3<u32>) {
    let q = gid.x;
    if (q >= tp.queries) {
        return;
    }
    let base = q * tp.k;
    for (var j = 0u; j < tp.tile_len; j++) {
        let s = scores[q * tp.tile_len + j];
        if (is_nan(s) || s <= topk_scores[base + tp.k - 1u]) {
            continue;
        }
        var pos = tp.k - 1u;
        loop {
            if (pos == 0u || topk_scores[base + pos - 1u] >= s) {
                break;
            }
            topk_scores[base + pos] = topk_scores[base + pos - 1u];
            topk_index[base + pos] = topk_index[base + pos - 1u];
            pos -= 1u;
        }
        topk_scores[base + pos] = s;
        topk_index[base + pos] = tp.tile_start + j;
    }
}
