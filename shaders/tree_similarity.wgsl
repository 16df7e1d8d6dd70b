// Batched forest-to-forest similarity. CPU twin: kernels/src/tree_similarity.rs
// (phase 1 cosines, phase 2 pair scores, phase 3 greedy assignment or best match, normalisation).
// Two entry points:
// - `tree_similarity_small`: a workgroup takes PAIRS_PER_GROUP consecutive pairs and scores them
//   in rounds, as many pairs a round as the pools of workgroup memory hold (SMALL_CELLS cells of
//   cosines and of scores, SMALL_TREES trees; a query forest shared by consecutive pairs is loaded
//   once), every lane working on every pair's cells, the assignment run by LANES / 2^k lanes per
//   pair. No global scratch. A pair that does not fit a round alone (`fits_small`) is skipped.
// - `tree_similarity`: one workgroup per pair, its matrices in `scratch`; the pairs the first
//   skips (with `skip_small`, it skips the others).
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
    // 1: grid pair g = pair_first + j is (query g / refs, reference ref_first + g % refs), its
    // score at out_first + g; 0: pair j is listed in `lookup`, its score at out_first + j; 2: listed,
    // its score where its grid pair's would be (out_first + query * refs + reference - ref_first)
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
    // grid passes: the grid pair of this dispatch's pair 0 (pair j is grid pair pair_first + j)
    pair_first: u32,
    // 1: `tree_similarity` skips the pairs that `fits_small` (`tree_similarity_small` scores them)
    skip_small: u32,
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

// Pair j of this pass: its query, its reference (in the map chunk) and where its score goes.
struct PairAt {
    q: u32,
    r: u32,
    out: u32,
}

fn pair_ids(j: u32) -> PairAt {
    if (fp.grid == 1u) {
        let g = fp.pair_first + j;
        return PairAt(g / fp.refs, fp.ref_first + g % fp.refs, fp.out_first + g);
    }
    let e = lookup[fp.queries + fp.list_first + j];
    if (fp.grid == 2u) {
        return PairAt(e.x, e.y, fp.out_first + e.x * fp.refs + e.y - fp.ref_first);
    }
    return PairAt(e.x, e.y, fp.out_first + j);
}

fn pair_of(at: PairAt) -> Pair {
    let qs = lookup[at.q];
    let rs = r_spans[at.r];
    return Pair(qs.x, qs.y, rs.x, rs.y);
}

// Whether forests of nq and nr trees fit one round of `tree_similarity_small` alone (the twin's
// `fits_small`).
fn fits_small(nq: u32, nr: u32) -> bool {
    return nq * nr <= SMALL_CELLS && nq + nr <= SMALL_TREES;
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
    var valid = pi < fp.pairs;
    var pr = Pair(0u, 0u, 0u, 0u);
    var at = PairAt(0u, 0u, 0u);
    if (valid) {
        at = pair_ids(pi);
        pr = pair_of(at);
        // left to `tree_similarity_small`: nothing to do here
        if (fp.skip_small != 0u && fits_small(pr.q_count, pr.r_count)) {
            valid = false;
            pr = Pair(0u, 0u, 0u, 0u);
        }
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
            if (fp.dim > 0u && q_trees[pr.q_start + t].has_app != 0u && r_trees[pr.r_start + u].has_app != 0u) {
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
        if (n > 0u && norm > 0.0) {
            out[at.out] = total / norm;
        } else {
            out[at.out] = 0.0;
        }
    }
}

// ---- several pairs of small forests per workgroup ----

// pairs a workgroup takes, and the most in one round
const PAIRS_PER_GROUP: u32 = 8u;
// cells of a round's pairs together (each of the two matrices)
const SMALL_CELLS: u32 = 1536u;
// trees of a round's forests together
const SMALL_TREES: u32 = 128u;
// an empty neighbour slot of a packed tree
const NO_NB: u32 = 255u;

// A tree in workgroup memory: its pairing key (bits 0-7) and appearance flag (bit 8), geometry,
// and its neighbours (indices in its forest, four u8 to a word, NO_NB for none).
struct SmallTree {
    key_app: u32,
    area: f32,
    cx: f32,
    cy: f32,
    nb: vec2<u32>,
}

// A pair of the round: its output, its forests (query index for sharing, first tree, count), its
// first cell and first row flag (column flags follow the rows), its trees in the pool.
struct Slot {
    out: u32,
    q: u32,
    q_start: u32,
    nq: u32,
    r_start: u32,
    nr: u32,
    cell: u32,
    flag: u32,
    qt: u32,
    rt: u32,
}

// cosines (phases 1-2), then the row and column flags or the best-match rows (phase 3)
var<workgroup> sm_cos: array<f32, SMALL_CELLS>;
var<workgroup> sm_score: array<f32, SMALL_CELLS>;
var<workgroup> sm_trees: array<SmallTree, SMALL_TREES>;
var<workgroup> sm_slots: array<Slot, PAIRS_PER_GROUP>;
var<workgroup> sm_n: u32;
var<workgroup> sm_cells: u32;
var<workgroup> sm_flags: u32;
var<workgroup> sm_steps: u32;
var<workgroup> sm_cursor: u32;

fn small_tree(t: Tree) -> SmallTree {
    var nb = vec2<u32>(0u, 0u);
    for (var k = 0u; k < MAX_SLOTS; k++) {
        var v = NO_NB;
        if (t.nb[k] >= 0 && t.nb[k] < i32(NO_NB)) {
            v = u32(t.nb[k]);
        }
        nb[k / 4u] |= v << (8u * (k % 4u));
    }
    return SmallTree(class_key(t.class_id) | (select(0u, 1u, t.has_app != 0u) << 8u), t.area, t.cx, t.cy, nb);
}

fn small_nb(t: SmallTree, k: u32) -> u32 {
    return (t.nb[k / 4u] >> (8u * (k % 4u))) & 0xffu;
}

fn small_key(t: SmallTree) -> u32 {
    return t.key_app & 0xffu;
}

// Lane 0: fills the next round with the pairs from sm_cursor on (before `end`) while their cells,
// trees and flags fit; a pair too large for a round alone is skipped (left to `tree_similarity`).
fn fill_round(end: u32) {
    var n = 0u;
    var cells = 0u;
    var trees = 0u;
    var flags = 0u;
    var steps = 0u;
    var c = sm_cursor;
    loop {
        if (c >= end || n == PAIRS_PER_GROUP) {
            break;
        }
        let at = pair_ids(c);
        let pr = pair_of(at);
        let nq = pr.q_count;
        let nr = pr.r_count;
        if (!fits_small(nq, nr)) {
            c++;
            continue;
        }
        let same_query = n > 0u && sm_slots[n - 1u].q == at.q;
        var new_trees = nq + nr;
        var qt = trees;
        var rt = trees + nq;
        if (same_query) {
            new_trees = nr;
            qt = sm_slots[n - 1u].qt;
            rt = trees;
        }
        if (cells + nq * nr > SMALL_CELLS || trees + new_trees > SMALL_TREES || flags + nq + nr > SMALL_CELLS) {
            break;
        }
        sm_slots[n] = Slot(at.out, at.q, pr.q_start, nq, pr.r_start, nr, cells, flags, qt, rt);
        n++;
        cells += nq * nr;
        trees += new_trees;
        flags += nq + nr;
        steps = max(steps, min(nq, nr));
        c++;
    }
    sm_cursor = c;
    sm_n = n;
    sm_cells = cells;
    sm_flags = flags;
    sm_steps = select(0u, steps, p.greedy != 0u);
}

// The round's pair owning cell idx (pairs without cells are passed over).
fn slot_of(idx: u32, n: u32) -> u32 {
    var s = 0u;
    while (s + 1u < n && sm_slots[s + 1u].cell <= idx) {
        s++;
    }
    return s;
}

// `pair_score` on the pool: cosines in sm_cos at the pair's cells, trees in sm_trees.
fn small_pair_score(sl: Slot, t: u32, u: u32) -> f32 {
    let nr = sl.nr;
    let a = sm_trees[sl.qt + t];
    let b = sm_trees[sl.rt + u];
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
        let c = sm_cos[sl.cell + t * nr + u];
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
        let na = small_nb(a, sa);
        if (na == NO_NB) {
            continue;
        }
        var best = -1.0;
        var best_slot = NONE;
        for (var sb = 0u; sb < slots; sb++) {
            let nb = small_nb(b, sb);
            if (nb == NO_NB || used[sb] || small_key(sm_trees[sl.qt + na]) != small_key(sm_trees[sl.rt + nb])) {
                continue;
            }
            var v = 1.0;
            if (p.use_appearance != 0u) {
                v = cos_plus(sm_cos[sl.cell + na * nr + nb]);
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
fn tree_similarity_small(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let first = (wg.x + wg.y * fp.row) * PAIRS_PER_GROUP;
    let end = min(first + PAIRS_PER_GROUP, fp.pairs);
    if (lane == 0u) {
        sm_cursor = first;
    }
    loop {
        if (lane == 0u) {
            fill_round(end);
        }
        let n = workgroupUniformLoad(&sm_n);
        if (n == 0u) {
            break;
        }
        let cells = sm_cells;
        // the round's trees (a shared query forest once)
        for (var s = 0u; s < n; s++) {
            let sl = sm_slots[s];
            if (s == 0u || sm_slots[s - 1u].qt != sl.qt) {
                for (var t = lane; t < sl.nq; t += LANES) {
                    sm_trees[sl.qt + t] = small_tree(q_trees[sl.q_start + t]);
                }
            }
            for (var u = lane; u < sl.nr; u += LANES) {
                sm_trees[sl.rt + u] = small_tree(r_trees[sl.r_start + u]);
            }
        }
        workgroupBarrier();
        // phase 1: appearance cosines of every cell of the round
        if (p.use_appearance != 0u) {
            for (var idx = lane; idx < cells; idx += LANES) {
                let sl = sm_slots[slot_of(idx, n)];
                let t = (idx - sl.cell) / sl.nr;
                let u = (idx - sl.cell) % sl.nr;
                var c = MISSING;
                if (fp.dim > 0u && (sm_trees[sl.qt + t].key_app & 0x100u) != 0u && (sm_trees[sl.rt + u].key_app & 0x100u) != 0u) {
                    c = app_dot((sl.q_start + t) * fp.dim, (sl.r_start + u) * fp.dim);
                }
                sm_cos[idx] = c;
            }
        }
        workgroupBarrier();
        // phase 2: pair scores of every cell
        for (var idx = lane; idx < cells; idx += LANES) {
            let sl = sm_slots[slot_of(idx, n)];
            let t = (idx - sl.cell) / sl.nr;
            let u = (idx - sl.cell) % sl.nr;
            var s = NOT_A_PAIR;
            if (small_key(sm_trees[sl.qt + t]) == small_key(sm_trees[sl.rt + u])) {
                s = small_pair_score(sl, t, u);
            }
            sm_score[idx] = s;
        }
        workgroupBarrier();
        // the cosines are spent: their pool holds the row and column flags now
        let flags = sm_flags;
        for (var i = lane; i < flags; i += LANES) {
            sm_cos[i] = 0.0;
        }
        workgroupBarrier();
        // phase 3: LANES / 2^k lanes per pair (k the smallest with 2^k >= n)
        let per = LANES >> firstLeadingBit(2u * n - 1u);
        let si = lane / per;
        let sub = lane % per;
        let mine = si < n;
        var sl = sm_slots[0];
        if (mine) {
            sl = sm_slots[si];
        }
        var total = 0.0;
        // 3a: greedy, one accepted cell per pair and step
        let steps = workgroupUniformLoad(&sm_steps);
        for (var step = 0u; step < steps; step++) {
            var bv = NOT_A_PAIR;
            var bi = NONE;
            if (mine) {
                for (var idx = sub; idx < sl.nq * sl.nr; idx += per) {
                    let s = sm_score[sl.cell + idx];
                    if (sm_cos[sl.flag + idx / sl.nr] == 0.0 && sm_cos[sl.flag + sl.nq + idx % sl.nr] == 0.0 && s > bv) {
                        bv = s;
                        bi = idx;
                    }
                }
            }
            best_val[lane] = bv;
            best_idx[lane] = bi;
            workgroupBarrier();
            for (var h = per / 2u; h > 0u; h >>= 1u) {
                if (sub < h) {
                    let ov = best_val[lane + h];
                    let oi = best_idx[lane + h];
                    if (ov > best_val[lane] || (ov == best_val[lane] && oi < best_idx[lane])) {
                        best_val[lane] = ov;
                        best_idx[lane] = oi;
                    }
                }
                workgroupBarrier();
            }
            if (mine && sub == 0u && best_idx[lane] != NONE) {
                let t = best_idx[lane] / sl.nr;
                let u = best_idx[lane] % sl.nr;
                sm_cos[sl.flag + t] = 1.0;
                sm_cos[sl.flag + sl.nq + u] = 1.0;
                total += best_val[lane] * sqrt(q_trees[sl.q_start + t].weight * r_trees[sl.r_start + u].weight);
            }
            workgroupBarrier();
        }
        // 3b: best match, the pair's lanes over its rows (-1: no match)
        if (p.greedy == 0u && mine) {
            for (var t = sub; t < sl.nq; t += per) {
                var m = 0.0;
                var mu = NONE;
                for (var u = 0u; u < sl.nr; u++) {
                    let s = sm_score[sl.cell + t * sl.nr + u];
                    if (s > m) {
                        m = s;
                        mu = u;
                    }
                }
                var c = -1.0;
                if (mu != NONE) {
                    c = m * sqrt(q_trees[sl.q_start + t].weight * r_trees[sl.r_start + mu].weight);
                }
                sm_cos[sl.flag + t] = c;
            }
        }
        workgroupBarrier();
        // the pair's first lane: its total, the normalisation by the forests' tree weights
        if (mine && sub == 0u) {
            if (p.greedy == 0u) {
                for (var t = 0u; t < sl.nq; t++) {
                    let c = sm_cos[sl.flag + t];
                    if (c >= 0.0) {
                        total += c;
                    }
                }
            }
            var sq = 0.0;
            for (var t = 0u; t < sl.nq; t++) {
                sq += q_trees[sl.q_start + t].weight;
            }
            var sr = 0.0;
            for (var u = 0u; u < sl.nr; u++) {
                sr += r_trees[sl.r_start + u].weight;
            }
            var norm = max(sq, sr);
            if (p.geometric_norm != 0u) {
                norm = sqrt(sq * sr);
            }
            if (sl.nq > 0u && sl.nr > 0u && norm > 0.0) {
                out[sl.out] = total / norm;
            } else {
                out[sl.out] = 0.0;
            }
        }
        // the next round overwrites the pools
        workgroupBarrier();
    }
}
