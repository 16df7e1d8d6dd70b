// Batched forest-to-forest similarity. CPU twin: src/kernels/tree_similarity.rs
// (`tree_similarity`: phase 1 cosines, phase 2 pair scores, phase 3 greedy assignment).
// One workgroup per (query forest, reference forest) pair; per-pair matrices live in `scratch`.
// The references' forests are resident on the device, one bind group (group 1) per map chunk;
// a pass either lists its pairs (`lookup` after the query spans) or takes every query against a
// run of the chunk's references (`grid`), which is how the whole-map top-K runs.

struct TreeSimParams {
    w_area: f32,
    w_position: f32,
    w_appearance: f32,
    w_intrinsic: f32,
    w_neighbours: f32,
    position_sigma: f32,
    neutral: f32,
    gaussian_position: u32,
    drop_missing: u32,
    use_appearance: u32,
    greedy: u32,
    neighbour_slots: u32,
    // 0 uniform, 1 area, 2 sqrt(area), 3 descriptors + 1 (computed on the host into Tree.weight)
    tree_weight: u32,
    geometric_norm: u32,
    _pad0: u32,
    _pad1: u32,
    // per class, the key trees pair by (the class or its category), four u8 to a word
    class_key: array<vec4<u32>, 16>,
}

// One pass, at a dynamic offset of one parameter buffer.
struct FinePass {
    // appearance vector length
    dim: u32,
    // pairs in this pass
    pairs: u32,
    // stride of one pair's matrices in `scratch` (max trees per forest)
    max_trees: u32,
    // 1: pair pi is (query pi / refs, reference ref_first + pi % refs); 0: listed in `lookup`
    grid: u32,
    // queries of the batch: their spans head `lookup`
    queries: u32,
    // grid passes: references per query (the row length of `out`) and the first one in the chunk
    refs: u32,
    ref_first: u32,
    // listed passes: where this pass's pairs start after the query spans
    list_first: u32,
    // workgroups per row of the dispatch grid (pair = x + y * row)
    row: u32,
    // where this pass's scores start in `out`
    out_first: u32,
    _pad0: u32,
    _pad1: u32,
}

struct Tree {
    class_id: u32,
    has_app: u32,
    area: f32,
    cx: f32,
    cy: f32,
    // the tree's weight in the image similarity (TreeSimParams::tree_weight on the host)
    weight: f32,
    nb: array<i32, MAX_SLOTS>,
}

struct Pair {
    q_start: u32,
    q_count: u32,
    r_start: u32,
    r_count: u32,
}

@group(0) @binding(0) var<uniform> p: TreeSimParams;
@group(0) @binding(1) var<uniform> fp: FinePass;
// the queries' (first tree, tree count), then the listed pairs' (query, chunk reference)
@group(0) @binding(2) var<storage, read> lookup: array<vec2<u32>>;
@group(0) @binding(3) var<storage, read> q_trees: array<Tree>;
@group(0) @binding(4) var<storage, read> q_app: array<f32>;
@group(0) @binding(5) var<storage, read_write> scratch: array<f32>;
@group(0) @binding(6) var<storage, read_write> out: array<f32>;
// the map chunk: each reference's (first tree, tree count), its trees and their appearance
@group(1) @binding(0) var<storage, read> r_spans: array<vec2<u32>>;
@group(1) @binding(1) var<storage, read> r_trees: array<Tree>;
@group(1) @binding(2) var<storage, read> r_app: array<f32>;

const LANES: u32 = 64u;
// most trees per forest (the workgroup's row and column flags)
const MAX_TREES: u32 = 256u;
// most neighbour slots of a tree record
const MAX_SLOTS: u32 = 8u;
const MISSING: f32 = -2.0;
const NOT_A_PAIR: f32 = -1.0;
const NONE: u32 = 0xffffffffu;

var<workgroup> best_val: array<f32, LANES>;
var<workgroup> best_idx: array<u32, LANES>;
var<workgroup> row_used: array<u32, MAX_TREES>;
var<workgroup> col_used: array<u32, MAX_TREES>;
var<workgroup> steps_shared: u32;
var<workgroup> total: f32;

// The pairing key of class c (the twin's `TreeSimParams::key`).
fn class_key(c: u32) -> u32 {
    let word = p.class_key[c / 16u][(c / 4u) % 4u];
    return (word >> (8u * (c % 4u))) & 0xffu;
}

fn pair_at(pi: u32) -> Pair {
    var q: u32;
    var r: u32;
    if (fp.grid != 0u) {
        q = pi / fp.refs;
        r = fp.ref_first + pi % fp.refs;
    } else {
        let e = lookup[fp.queries + fp.list_first + pi];
        q = e.x;
        r = e.y;
    }
    let qs = lookup[q];
    let rs = r_spans[r];
    return Pair(qs.x, qs.y, rs.x, rs.y);
}

fn cos_plus(c: f32) -> f32 {
    if (c == MISSING) {
        return p.neutral;
    }
    return max(c, 0.0);
}

// The dot product of query tree vector qa and reference tree vector ra (offsets into q_app and
// r_app), summed in order as the twin sums it. Unrolled by 16: besides saving loop overhead, this
// keeps long vectors (4,096 values) within lavapipe's loop limit, under which an invocation's
// loops end silently after 65,535 iterations in all (llvmpipe's LP_MAX_TGSI_LOOP_ITERATIONS).
fn app_dot(qa: u32, ra: u32) -> f32 {
    var c = 0.0;
    var k = 0u;
    for (; k + 16u <= fp.dim; k += 16u) {
        c += q_app[qa + k + 0u] * r_app[ra + k + 0u];
        c += q_app[qa + k + 1u] * r_app[ra + k + 1u];
        c += q_app[qa + k + 2u] * r_app[ra + k + 2u];
        c += q_app[qa + k + 3u] * r_app[ra + k + 3u];
        c += q_app[qa + k + 4u] * r_app[ra + k + 4u];
        c += q_app[qa + k + 5u] * r_app[ra + k + 5u];
        c += q_app[qa + k + 6u] * r_app[ra + k + 6u];
        c += q_app[qa + k + 7u] * r_app[ra + k + 7u];
        c += q_app[qa + k + 8u] * r_app[ra + k + 8u];
        c += q_app[qa + k + 9u] * r_app[ra + k + 9u];
        c += q_app[qa + k + 10u] * r_app[ra + k + 10u];
        c += q_app[qa + k + 11u] * r_app[ra + k + 11u];
        c += q_app[qa + k + 12u] * r_app[ra + k + 12u];
        c += q_app[qa + k + 13u] * r_app[ra + k + 13u];
        c += q_app[qa + k + 14u] * r_app[ra + k + 14u];
        c += q_app[qa + k + 15u] * r_app[ra + k + 15u];
    }
    for (; k < fp.dim; k++) {
        c += q_app[qa + k] * r_app[ra + k];
    }
    return c;
}

fn pair_score(pr: Pair, cos_base: u32, t: u32, u: u32) -> f32 {
    let nr = pr.r_count;
    let a = q_trees[pr.q_start + t];
    let b = r_trees[pr.r_start + u];
    var s_area = 1.0;
    if (max(a.area, b.area) > 0.0) {
        s_area = min(a.area, b.area) / max(a.area, b.area);
    }
    let dx = a.cx - b.cx;
    let dy = a.cy - b.cy;
    let d = sqrt(dx * dx + dy * dy);
    var s_pos = max(1.0 - d, 0.0);
    if (p.gaussian_position != 0u) {
        s_pos = exp(-(d * d) / (2.0 * p.position_sigma * p.position_sigma));
    }
    var num = p.w_area * s_area + p.w_position * s_pos;
    var den = p.w_area + p.w_position;
    if (p.use_appearance != 0u) {
        let c = scratch[cos_base + t * nr + u];
        if (c != MISSING || p.drop_missing == 0u) {
            num += p.w_appearance * cos_plus(c);
            den += p.w_appearance;
        }
    }
    var s_in = 0.0;
    if (den > 0.0) {
        s_in = num / den;
    }
    var used = array<bool, MAX_SLOTS>();
    var s_nb = 0.0;
    let slots = p.neighbour_slots;
    for (var sa = 0u; sa < slots; sa++) {
        let na = a.nb[sa];
        if (na < 0) {
            continue;
        }
        var best = -1.0;
        var best_slot = NONE;
        for (var sb = 0u; sb < slots; sb++) {
            let nb = b.nb[sb];
            if (nb < 0 || used[sb] || class_key(q_trees[pr.q_start + u32(na)].class_id) != class_key(r_trees[pr.r_start + u32(nb)].class_id)) {
                continue;
            }
            var v = 1.0;
            if (p.use_appearance != 0u) {
                v = cos_plus(scratch[cos_base + u32(na) * nr + u32(nb)]);
            }
            if (v > best) {
                best = v;
                best_slot = sb;
            }
        }
        if (best_slot != NONE) {
            used[best_slot] = true;
            s_nb += best;
        }
    }
    if (slots > 0u) {
        s_nb = s_nb / f32(slots);
    } else {
        s_nb = 0.0;
    }
    return p.w_intrinsic * s_in + p.w_neighbours * s_nb;
}

@compute @workgroup_size(64, 1, 1)
fn tree_similarity(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let pi = wg.x + wg.y * fp.row;
    let valid = pi < fp.pairs;
    var pr = Pair(0u, 0u, 0u, 0u);
    if (valid) {
        pr = pair_at(pi);
    }
    let nq = pr.q_count;
    let nr = pr.r_count;
    let n = nq * nr;
    let cos_base = pi * 2u * fp.max_trees * fp.max_trees;
    let sc_base = cos_base + fp.max_trees * fp.max_trees;
    // phase 1: appearance cosines
    if (p.use_appearance != 0u) {
        for (var idx = lane; idx < n; idx += LANES) {
            let t = idx / nr;
            let u = idx % nr;
            var c = MISSING;
            if (q_trees[pr.q_start + t].has_app != 0u && r_trees[pr.r_start + u].has_app != 0u) {
                c = app_dot((pr.q_start + t) * fp.dim, (pr.r_start + u) * fp.dim);
            }
            scratch[cos_base + idx] = c;
        }
    }
    storageBarrier();
    // phase 2: tree similarities of same-class pairs
    for (var idx = lane; idx < n; idx += LANES) {
        let t = idx / nr;
        let u = idx % nr;
        var s = NOT_A_PAIR;
        if (class_key(q_trees[pr.q_start + t].class_id) == class_key(r_trees[pr.r_start + u].class_id)) {
            s = pair_score(pr, cos_base, t, u);
        }
        scratch[sc_base + idx] = s;
    }
    for (var i = lane; i < MAX_TREES; i += LANES) {
        row_used[i] = 0u;
        col_used[i] = 0u;
    }
    if (lane == 0u) {
        total = 0.0;
        steps_shared = min(nq, nr);
        if (p.greedy == 0u) {
            steps_shared = 0u;
        }
    }
    storageBarrier();
    workgroupBarrier();
    // phase 3a: greedy one-to-one assignment, one accepted pair per step
    let steps = workgroupUniformLoad(&steps_shared);
    for (var step = 0u; step < steps; step++) {
        var bv = NOT_A_PAIR;
        var bi = NONE;
        for (var idx = lane; idx < n; idx += LANES) {
            let s = scratch[sc_base + idx];
            if (row_used[idx / nr] == 0u && col_used[idx % nr] == 0u && s > bv) {
                bv = s;
                bi = idx;
            }
        }
        best_val[lane] = bv;
        best_idx[lane] = bi;
        workgroupBarrier();
        for (var h = LANES / 2u; h > 0u; h >>= 1u) {
            if (lane < h) {
                let ov = best_val[lane + h];
                let oi = best_idx[lane + h];
                if (ov > best_val[lane] || (ov == best_val[lane] && oi < best_idx[lane])) {
                    best_val[lane] = ov;
                    best_idx[lane] = oi;
                }
            }
            workgroupBarrier();
        }
        if (lane == 0u && best_idx[0] != NONE) {
            let t = best_idx[0] / nr;
            let u = best_idx[0] % nr;
            row_used[t] = 1u;
            col_used[u] = 1u;
            total += best_val[0] * sqrt(q_trees[pr.q_start + t].weight * r_trees[pr.r_start + u].weight);
        }
        workgroupBarrier();
    }
    // phase 3b: best match per query tree (when not greedy)
    if (p.greedy == 0u && lane == 0u) {
        for (var t = 0u; t < nq; t++) {
            var m = 0.0;
            var mu = NONE;
            for (var u = 0u; u < nr; u++) {
                let s = scratch[sc_base + t * nr + u];
                if (s > m) {
                    m = s;
                    mu = u;
                }
            }
            if (mu != NONE) {
                total += m * sqrt(q_trees[pr.q_start + t].weight * r_trees[pr.r_start + mu].weight);
            }
        }
    }
    // normalisation by the forests' total tree weights
    if (lane == 0u && valid) {
        var sq = 0.0;
        for (var t = 0u; t < nq; t++) {
            sq += q_trees[pr.q_start + t].weight;
        }
        var sr = 0.0;
        for (var u = 0u; u < nr; u++) {
            sr += r_trees[pr.r_start + u].weight;
        }
        var norm = max(sq, sr);
        if (p.geometric_norm != 0u) {
            norm = sqrt(sq * sr);
        }
        if (n == 0u || norm <= 0.0) {
            out[fp.out_first + pi] = 0.0;
        } else {
            out[fp.out_first + pi] = total / norm;
        }
    }
}
