//! The fast CPU path of mutual-nearest-neighbour matching (the twin is
//! [`semlook_kernels::mnn_match`]): the dot products of a pair as one f32 matrix product, then the
//! first maximum of every row and column; the twin's result bit for bit (tested below).

use semlook_kernels::mnn_match::NO_MATCH;

/// Best columns of one pair: per query keypoint (index into the reference's, dot product) and per
/// reference keypoint (index into the query's).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BestColumns {
    /// Per query keypoint, its best reference keypoint, or `NO_MATCH` when the reference has none.
    pub query_best: Vec<u32>,
    /// Per query keypoint, the dot product with its best reference keypoint (`i32::MIN` without one).
    pub query_dot: Vec<i32>,
    /// Per reference keypoint, its best query keypoint, or `NO_MATCH` when the query has none.
    pub ref_best: Vec<u32>,
}

/// The fast CPU path for one pair: the dot products as one f32 matrix product (int8 products and
/// their sums stay below 2^24, so every value is exact), then the first maximum of every row and
/// every column; the twin's result exactly.
pub fn best_columns(q: &[i8], r: &[i8], dim: usize, scratch: &mut Vec<f32>) -> BestColumns {
    let (nq, nr) = (q.len() / dim.max(1), r.len() / dim.max(1));
    let mut out = BestColumns { query_best: vec![NO_MATCH; nq], query_dot: vec![i32::MIN; nq], ref_best: vec![NO_MATCH; nr] };
    if nq == 0 || nr == 0 || dim == 0 {
        return out;
    }
    let qf: Vec<f32> = q.iter().map(|&v| v as f32).collect();
    let rf: Vec<f32> = r.iter().map(|&v| v as f32).collect();
    scratch.clear();
    scratch.resize(nq * nr, 0.0);
    // S = Q (nq x dim) * R^T (dim x nr)
    // SAFETY: qf is nq x dim (row stride dim), rf read as dim x nr (row stride 1, column stride
    // dim) is R^T, scratch is nq x nr (row stride nr); all three live for the call, and scratch,
    // the only one written, aliases neither input.
    unsafe {
        matrixmultiply::sgemm(
            nq,
            dim,
            nr,
            1.0,
            qf.as_ptr(),
            dim as isize,
            1,
            rf.as_ptr(),
            1,
            dim as isize,
            0.0,
            scratch.as_mut_ptr(),
            nr as isize,
            1,
        );
    }
    let mut col_best = vec![f32::NEG_INFINITY; nr];
    for i in 0..nq {
        let row = &scratch[i * nr..(i + 1) * nr];
        let (mut bd, mut bj) = (f32::NEG_INFINITY, 0usize);
        for (j, &d) in row.iter().enumerate() {
            if d > bd {
                bd = d;
                bj = j;
            }
            if d > col_best[j] {
                col_best[j] = d;
                out.ref_best[j] = i as u32;
            }
        }
        out.query_best[i] = bj as u32;
        out.query_dot[i] = bd as i32;
    }
    out
}

/// Mutual nearest neighbours whose dot product reaches `min_dot`: (query keypoint, reference
/// keypoint) pairs in query order.
pub fn mutual(b: &BestColumns, min_dot: i32) -> Vec<(u32, u32)> {
    b.query_best
        .iter()
        .zip(&b.query_dot)
        .enumerate()
        .filter(|&(i, (&j, &d))| j != NO_MATCH && d >= min_dot && b.ref_best.get(j as usize) == Some(&(i as u32)))
        .map(|(i, (&j, _))| (i as u32, j))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;
    use semlook_kernels::abi::{MnnPair, MnnParams};
    use semlook_kernels::mnn_match::{mnn_match, pack};

    fn random(n: usize, dim: usize, rng: &mut SplitMix64) -> Vec<i8> {
        (0..n * dim).map(|_| (rng.below(255) as i32 - 127) as i8).collect()
    }

    #[test]
    fn the_fast_path_equals_the_twin_bit_for_bit() {
        let mut rng = SplitMix64::new(5);
        let dim = 16;
        for (nq, nr) in [(7, 5), (1, 9), (12, 12), (0, 4), (3, 0)] {
            let (q, r) = (random(nq, dim, &mut rng), random(nr, dim, &mut rng));
            // ties: a repeated reference row
            let r = if nr > 2 { [r.clone(), r[..dim].to_vec()].concat() } else { r };
            let nr = r.len() / dim;
            let max = nq.max(nr).max(1);
            let params = MnnParams { pairs: 1, words: (dim / 4) as u32, max_keypoints: max as u32, _pad: 0 };
            let pair = MnnPair { query_start: 0, query_len: nq as u32, ref_start: 0, ref_len: nr as u32 };
            let mut best = vec![NO_MATCH; 2 * max];
            let mut dot = vec![i32::MIN; 2 * max];
            mnn_match(&params, &[pair], &pack(&q), &pack(&r), &mut best, &mut dot);
            let fast = best_columns(&q, &r, dim, &mut vec![]);
            assert_eq!(fast.query_best, best[..nq]);
            assert_eq!(fast.query_dot, dot[..nq]);
            assert_eq!(fast.ref_best, best[max..max + nr]);
        }
    }

    #[test]
    fn mutual_matches_need_both_directions_and_the_threshold() {
        // q0 ~ r1, q1 ~ r0, q2's best is r1 but r1 prefers q0
        let q: Vec<i8> = vec![100, 0, 0, 0, 0, 100, 0, 0, 90, 10, 0, 0];
        let r: Vec<i8> = vec![0, 100, 0, 0, 100, 0, 0, 0];
        let b = best_columns(&q, &r, 4, &mut vec![]);
        assert_eq!(mutual(&b, 0), vec![(0, 1), (1, 0)]);
        assert_eq!(mutual(&b, 10_001), vec![]);
        assert_eq!(mutual(&best_columns(&[], &r, 4, &mut vec![]), 0), vec![]);
    }
}
