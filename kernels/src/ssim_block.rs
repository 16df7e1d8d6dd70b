//! Block-tiled batched SSIM (CPU twin of `shaders/ssim_block.wgsl`): scores of a pass's queries
//! against a run of references, one "workgroup" per block of `rb` references x `qb` queries, the
//! image streamed row by row through the shader's three workgroup arrays (products of a row, a
//! ring of `win` rows of horizontal window sums, 64 lane slots per pair). Every score equals
//! [`ssim_pair`](crate::ssim::ssim_pair)'s bit for bit: the same operations in the same
//! order (tested below).

use super::abi::PassParams;
use crate::abi::SsimParams;
use crate::ssim::{pair_order_sum, ssim_window, LANES};

/// Most pairs (rb x qb) a workgroup scores: the shader's `PAIR_CAP`.
pub const PAIR_CAP: usize = 8;
/// Floats of the shader's product row (rb x qb x gw): `PROD_CAP`.
pub const PROD_CAP: usize = 512;
/// Floats of the shader's ring of horizontal sums (rb x qb x win x nw): `RING_CAP`. With the
/// products and the lane slots, 14 KiB: within the 16 KiB of workgroup memory every adapter has.
pub const RING_CAP: usize = 2560;

/// The block shape for descriptors of `p`: the most pairs the shader's arrays hold, as many
/// queries as references or more (a reference is read once per `qb` queries); `None` if not
/// even one pair fits (descriptors too wide for the kernel).
pub fn block_shape(p: &SsimParams) -> Option<(u32, u32)> {
    let per_pair_ring = (p.win * p.nw) as usize;
    let fits = |n: usize| n <= PAIR_CAP && n * p.gw as usize <= PROD_CAP && n * per_pair_ring <= RING_CAP;
    let n = (1..=PAIR_CAP).rev().find(|&n| fits(n))?;
    // the most square split with qb >= rb
    let rb = (1..=n).filter(|r| n % r == 0 && r * r <= n).max().unwrap_or(1);
    Some((rb as u32, (n / rb) as u32))
}

/// The shader's workgroup arrays.
struct Workgroup {
    prod: Vec<f32>,
    ring: Vec<f32>,
    acc: Vec<f32>,
}

/// Bindings: `p`, `ps`, `queries`, `query_stats` (the pass's queries), `scores` (out, queries x
/// refs), `refs`, `ref_stats` (the map chunk). One workgroup per block, blocks in dispatch order
/// (query blocks on x); within a workgroup, the lanes' loops run one after another, which is
/// legal because the shader's steps are race-free between barriers.
#[allow(clippy::too_many_arguments)]
pub fn ssim_block(p: &SsimParams, ps: &PassParams, queries: &[f32], query_stats: &[f32], scores: &mut [f32], refs: &[f32], ref_stats: &[f32]) {
    let (rb, qb) = (ps.rb as usize, ps.qb as usize);
    let mut wg = Workgroup { prod: vec![0.0; PROD_CAP], ring: vec![0.0; RING_CAP], acc: vec![0.0; PAIR_CAP * LANES] };
    for y in 0..(ps.refs as usize).div_ceil(rb) {
        for x in 0..(ps.queries as usize).div_ceil(qb) {
            block(p, ps, [x, y], &mut wg, queries, query_stats, scores, refs, ref_stats);
        }
    }
}

#[allow(clippy::too_many_arguments)]
fn block(
    p: &SsimParams,
    ps: &PassParams,
    wg: [usize; 2],
    w: &mut Workgroup,
    queries: &[f32],
    query_stats: &[f32],
    scores: &mut [f32],
    refs: &[f32],
    ref_stats: &[f32],
) {
    let (rb, np) = (ps.rb as usize, (ps.rb * ps.qb) as usize);
    let (q0, r0) = (wg[0] * ps.qb as usize, wg[1] * rb);
    let (gw, gh, win, nw, nh) = (p.gw as usize, p.gh as usize, p.win as usize, p.nw as usize, p.nh as usize);
    let (len, n, first) = (gw * gh, nw * nh, ps.ref_first as usize);
    let valid = |pair: usize| {
        let (q, r) = (q0 + pair / rb, r0 + pair % rb);
        (q < ps.queries as usize && r < ps.refs as usize).then_some((q, r))
    };
    w.acc[..np * LANES].fill(0.0);
    for row in 0..gh {
        // 1. products of this row
        for i in 0..np * gw {
            let o = row * gw + i % gw;
            w.prod[i] = valid(i / gw).map_or(0.0, |(q, r)| queries[q * len + o] * refs[(first + r) * len + o]);
        }
        // 2. horizontal window sums (in `pair_order_sum`'s order) into ring slot row % win
        let slot = row % win;
        for i in 0..np * nw {
            let (pair, c) = (i / nw, i % nw);
            let prod = &w.prod[pair * gw..];
            w.ring[(pair * win + slot) * nw + c] = pair_order_sum(c, win, |i| prod[i]);
        }
        // 3. the window row ending here: vertical sums, window formula, lane slot w % 64
        if row + 1 >= win {
            let wr = row + 1 - win;
            for i in 0..np * nw {
                let (pair, c) = (i / nw, i % nw);
                let Some((q, r)) = valid(pair) else { continue };
                let ring = &w.ring;
                let v = pair_order_sum(wr, win, |i| ring[(pair * win + i % win) * nw + c]);
                let wi = wr * nw + c;
                let (sq, sr) = (q * 2 * n, (first + r) * 2 * n);
                w.acc[pair * LANES + wi % LANES] +=
                    ssim_window(p, v, query_stats[sq + wi], ref_stats[sr + wi], query_stats[sq + n + wi], ref_stats[sr + n + wi]);
            }
        }
    }
    // per pair, the tree over the lane slots
    let mut h = LANES / 2;
    while h > 0 {
        for i in 0..np * h {
            let base = (i / h) * LANES + i % h;
            w.acc[base] += w.acc[base + h];
        }
        h /= 2;
    }
    for pair in 0..np {
        if let Some((q, r)) = valid(pair) {
            scores[q * ps.refs as usize + r] = w.acc[pair * LANES] / n as f32;
        }
    }
}

#[cfg(test)]
#[path = "ssim_block_tests.rs"]
mod tests;
