// Parallel top-K over a pass's scores (queries x refs, query-major), in two steps.
// CPU twin: kernels/src/topk_select.rs (`topk_partial`, `topk_merge_lists`).
//
// Order: a candidate ranks before another if its score is higher, or equal with a lower reference
// index (the streaming top-K's rule: ties go to the lower index). NaN scores, and scores not above
// EMPTY_SCORE, are never candidates.
// topk_partial: one workgroup per (segment of SEG references, query) selects the segment's K best,
//   best first, by K rounds of a parallel arg-max: each lane takes the best of its strided
//   candidates that rank after the previous round's winner, then the lanes reduce (subgroup
//   operations where the adapter has them, else a tree in workgroup memory). Selection is exact,
//   so both reductions give the same lists.
// topk_merge_lists: one invocation per query merges its running list with the pass's partial
//   lists (all sorted in that order) into the other running-list buffer (ping-pong by `parity`).

//#include abi.wgsl

// One list entry: a score and the map index of its reference (EMPTY_INDEX: an empty slot).
struct Entry {
    score: f32,
    index: u32,
}

@group(0) @binding(0) var<uniform> ps: PassParams;
@group(0) @binding(1) var<storage, read> scores: array<f32>;
// queries x segs x k
@group(0) @binding(2) var<storage, read_write> partial: array<Entry>;
// queries x k each; the input is top_a when parity is 0, else top_b
@group(0) @binding(3) var<storage, read_write> top_a: array<Entry>;
@group(0) @binding(4) var<storage, read_write> top_b: array<Entry>;

const LANES: u32 = 64u;
// references per segment: one workgroup's share of a pass
const SEG: u32 = 1024u;
// lists one merge takes: the running list and up to MAX_LISTS - 1 segments
const MAX_LISTS: u32 = 64u;
const NONE: u32 = 0xffffffffu;

var<workgroup> seg_scores: array<f32, SEG>;
var<workgroup> red_s: array<f32, LANES>;
var<workgroup> red_i: array<u32, LANES>;
var<workgroup> win_i: u32;

// NaN by its bits (`s != s` may be folded away by compilers that assume finite floats)
fn is_nan(s: f32) -> bool {
    return (bitcast<u32>(s) & 0x7fffffffu) > 0x7f800000u;
}

fn is_candidate(s: f32) -> bool {
    return !is_nan(s) && s > EMPTY_SCORE;
}

// (s, i) ranks before (t, j); NONE ranks after everything
fn before(s: f32, i: u32, t: f32, j: u32) -> bool {
    if (i == NONE) {
        return false;
    }
    return j == NONE || s > t || (s == t && i < j);
}

@compute @workgroup_size(64, 1, 1)
fn topk_partial(
    @builtin(workgroup_id) wg: vec3<u32>,
    @builtin(local_invocation_index) lane: u32,
//#if SUBGROUPS
    @builtin(subgroup_invocation_id) sg_lane: u32,
    @builtin(subgroup_id) sg_id: u32,
    @builtin(num_subgroups) sg_count: u32,
//#endif
) {
    let seg = wg.x;
    let q = wg.y;
    let base = seg * SEG;
    let count = min(SEG, ps.refs - base);
    for (var j = lane; j < count; j += LANES) {
        seg_scores[j] = scores[q * ps.refs + base + j];
    }
    workgroupBarrier();
    let out = (q * ps.segs + seg) * ps.k;
    var prev_s = 0.0;
    var prev_i = NONE;
    var t = 0u;
    for (; t < ps.k; t++) {
        // this lane's best candidate ranking after the previous winner
        var bs = 0.0;
        var bi = NONE;
        for (var j = lane; j < count; j += LANES) {
            let s = seg_scores[j];
            if (is_candidate(s) && (prev_i == NONE || before(prev_s, prev_i, s, j)) && before(s, j, bs, bi)) {
                bs = s;
                bi = j;
            }
        }
//#if SUBGROUPS
        let none = bi == NONE;
        let m = subgroupMax(select(bs, -3.4e38, none));
        let mi = subgroupMin(select(NONE, bi, !none && bs == m));
        if (sg_lane == 0u) {
            red_i[sg_id] = mi;
        }
        workgroupBarrier();
        if (lane == 0u) {
            var wi = NONE;
            for (var g = 0u; g < sg_count; g++) {
                let gi = red_i[g];
                if (gi != NONE && (wi == NONE || before(seg_scores[gi], gi, seg_scores[wi], wi))) {
                    wi = gi;
                }
            }
            win_i = wi;
        }
//#else
        red_s[lane] = bs;
        red_i[lane] = bi;
        workgroupBarrier();
        for (var h = LANES / 2u; h > 0u; h >>= 1u) {
            if (lane < h && before(red_s[lane + h], red_i[lane + h], red_s[lane], red_i[lane])) {
                red_s[lane] = red_s[lane + h];
                red_i[lane] = red_i[lane + h];
            }
            workgroupBarrier();
        }
        if (lane == 0u) {
            win_i = red_i[0];
        }
//#endif
        let wi = workgroupUniformLoad(&win_i);
        if (wi == NONE) {
            break;
        }
        prev_s = seg_scores[wi];
        prev_i = wi;
        if (lane == 0u) {
            partial[out + t] = Entry(prev_s, ps.ref_index + base + wi);
        }
    }
    for (var j = t + lane; j < ps.k; j += LANES) {
        partial[out + j] = Entry(EMPTY_SCORE, EMPTY_INDEX);
    }
}

fn running(q: u32, h: u32) -> Entry {
    if (ps.parity == 0u) {
        return top_a[q * ps.k + h];
    }
    return top_b[q * ps.k + h];
}

fn list_entry(q: u32, l: u32, h: u32) -> Entry {
    if (l == 0u) {
        return running(q, h);
    }
    return partial[(q * ps.segs + l - 1u) * ps.k + h];
}

@compute @workgroup_size(64, 1, 1)
fn topk_merge_lists(@builtin(global_invocation_id) gid: vec3<u32>) {
    let q = gid.x;
    if (q >= ps.queries) {
        return;
    }
    // next unread entry of each list
    var heads: array<u32, MAX_LISTS>;
    let lists = ps.segs + 1u;
    for (var t = 0u; t < ps.k; t++) {
        var best = NONE;
        var e = Entry(EMPTY_SCORE, EMPTY_INDEX);
        // a chunk's first pass has no running list to read
        for (var l = select(0u, 1u, ps.fresh != 0u); l < lists; l++) {
            if (heads[l] < ps.k) {
                let c = list_entry(q, l, heads[l]);
                if (c.index != EMPTY_INDEX && (best == NONE || before(c.score, c.index, e.score, e.index))) {
                    best = l;
                    e = c;
                }
            }
        }
        if (best != NONE) {
            heads[best] += 1u;
        }
        if (ps.parity == 0u) {
            top_b[q * ps.k + t] = e;
        } else {
            top_a[q * ps.k + t] = e;
        }
    }
}
