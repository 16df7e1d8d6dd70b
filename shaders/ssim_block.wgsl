// Block-tiled batched SSIM: the coarse stage's scores. CPU twin: kernels/src/ssim_block.rs
// (`ssim_block`), whose scores equal `kernels::ssim::ssim_pair`'s bit for bit.
//
// Algorithm: one workgroup scores a block of `rb` references x `qb` queries (the block shape is
// chosen on the host so that the workgroup arrays below hold it). The image is streamed row by
// row, every row once per block:
//   1. the products x*y of the row, for every pair of the block, into `prod`;
//   2. the direct `win`-tap horizontal window sums of those products (in the twin's pair order,
//      `pair_lo`/`pair_own`) into a ring of `win` rows (`ring`, slot row % win);
//   3. once `win` rows are in the ring, the direct vertical sums (pair order) of the window row that ends here,
//      the SSIM window formula with both descriptors' window means and variances, and the
//      accumulation of window w into lane slot w % 64 of the pair (`acc`);
// then, per pair, a tree over the 64 lane slots gives the mean. That is the twin `ssim_pair`'s
// arithmetic in its order, so a shader compiler that neither fuses nor reorders gives its bits.
// Direct sums, not running sums: running sums round differently, and the covariance
// E[xy] - mx*my amplifies that by up to 2 / C2 in near-flat windows (a test in the twin shows one
// input where they miss the twin by more than 1e-5).
// Each reference is read once per block of `qb` queries; the dispatch puts query blocks on x, so
// consecutive workgroups share their references through the cache.

//#include abi.wgsl

@group(0) @binding(0) var<uniform> p: SsimParams;
@group(0) @binding(1) var<uniform> ps: PassParams;
@group(0) @binding(2) var<storage, read> queries: array<f32>;
@group(0) @binding(3) var<storage, read> query_stats: array<f32>;
@group(0) @binding(4) var<storage, read_write> scores: array<f32>;
@group(1) @binding(0) var<storage, read> refs: array<f32>;
@group(1) @binding(1) var<storage, read> ref_stats: array<f32>;

const LANES: u32 = 64u;
// rb * qb
const PAIR_CAP: u32 = 8u;
// rb * qb * gw
const PROD_CAP: u32 = 512u;
// rb * qb * win * nw
const RING_CAP: u32 = 2560u;

// 14 KiB in all, within the 16 KiB every adapter has
var<workgroup> prod: array<f32, PROD_CAP>;
var<workgroup> ring: array<f32, RING_CAP>;
var<workgroup> acc: array<f32, 512>;

// f: the factors (1 / win², 2 cov_norm) (`window_factors`)
fn ssim_window(f: vec2<f32>, sum_xy: f32, mx: f32, my: f32, vx: f32, vy: f32) -> f32 {
    // the twin's grouping (kernels/src/ssim.rs, ssim_window_terms)
    let a = mx * my;
    let num = (2.0 * a + p.c1) * ((sum_xy * f.x - a) * f.y + p.c2);
    let den = ((mx * mx + p.c1) + my * my) * ((vx + p.c2) + vy);
    return num / den;
}

@compute @workgroup_size(64, 1, 1)
fn ssim_block(@builtin(workgroup_id) wg: vec3<u32>, @builtin(local_invocation_index) lane: u32) {
    let rb = ps.rb;
    let np = rb * ps.qb;
    let q0 = wg.x * ps.qb;
    let r0 = wg.y * rb;
    let len = p.gw * p.gh;
    let n = p.nw * p.nh;
    // the twin's `window_factors`, once per invocation
    let f = vec2<f32>(1.0 / f32(p.win * p.win), 2.0 * p.cov_norm);
    for (var i = lane; i < np * LANES; i += LANES) {
        acc[i] = 0.0;
    }
    for (var row = 0u; row < p.gh; row++) {
        // 1. products of this row
        for (var i = lane; i < np * p.gw; i += LANES) {
            let pair = i / p.gw;
            let q = q0 + pair / rb;
            let r = r0 + pair % rb;
            var v = 0.0;
            if (q < ps.queries && r < ps.refs) {
                let o = row * p.gw + i % p.gw;
                v = queries[q * len + o] * refs[(ps.ref_first + r) * len + o];
            }
            prod[i] = v;
        }
        workgroupBarrier();
        // 2. horizontal window sums into ring slot row % win
        let slot = row % p.win;
        for (var i = lane; i < np * p.nw; i += LANES) {
            let pair = i / p.nw;
            let c = i % p.nw;
            let lo = pair * p.gw + pair_lo(c);
            var h = prod[lo];
            for (var k = 1u; k + 1u < p.win; k++) {
                h += prod[lo + k];
            }
            h += prod[pair * p.gw + pair_own(c, p.win)];
            ring[(pair * p.win + slot) * p.nw + c] = h;
        }
        workgroupBarrier();
        // 3. the window row ending at this row: vertical sums, window formula, lane slot w % 64
        //    (for one pair, columns with equal slots belong to one invocation: no races)
        if (row + 1u >= p.win) {
            let wr = row + 1u - p.win;
            for (var i = lane; i < np * p.nw; i += LANES) {
                let pair = i / p.nw;
                let c = i % p.nw;
                let q = q0 + pair / rb;
                let r = r0 + pair % rb;
                if (q < ps.queries && r < ps.refs) {
                    let lo = pair_lo(wr);
                    var v = ring[(pair * p.win + lo % p.win) * p.nw + c];
                    for (var k = 1u; k + 1u < p.win; k++) {
                        v += ring[(pair * p.win + (lo + k) % p.win) * p.nw + c];
                    }
                    v += ring[(pair * p.win + pair_own(wr, p.win) % p.win) * p.nw + c];
                    let w = wr * p.nw + c;
                    let sq = q * 2u * n;
                    let sr = (ps.ref_first + r) * 2u * n;
                    let s = ssim_window(f, v, query_stats[sq + w], ref_stats[sr + w], query_stats[sq + n + w], ref_stats[sr + n + w]);
                    acc[pair * LANES + w % LANES] += s;
                }
            }
        }
        workgroupBarrier();
    }
    // per pair, the twin's tree over the lane slots
    for (var h = LANES / 2u; h > 0u; h >>= 1u) {
        for (var i = lane; i < np * h; i += LANES) {
            let base = (i / h) * LANES + i % h;
            acc[base] += acc[base + h];
        }
        workgroupBarrier();
    }
    if (lane < np) {
        let q = q0 + lane / rb;
        let r = r0 + lane % rb;
        if (q < ps.queries && r < ps.refs) {
            scores[q * ps.refs + r] = acc[lane * LANES] / f32(n);
        }
    }
}
