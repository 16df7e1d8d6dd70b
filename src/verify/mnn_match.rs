//! Mutual nearest neighbours between the keypoints of (query, reference) pairs: CPU twin of
//! `shaders/mnn_match.wgsl` (same name, bindings and loop shape), and the fast CPU path that the
//! engine runs (a matrix product; the same indices and dot products as the twin, bit for bit).
//!
//! Descriptors are int8 ([`crate::descriptors::keypoints::DESCRIPTOR_SCALE`] times the unit vector), four to a
//! `u32` word. Dot products are exact integers, so the twin, the fast path and the GPU kernel agree
//! exactly: for every row of one side, the column of the other side with the largest dot product
//! (the lowest index among equals) and that dot product. A query keypoint i and a reference
//! keypoint j match when each is the other's best and their dot product reaches the threshold
//! (XFeat's matcher: mutual nearest neighbours above a cosine, Potje et al. 2024).

use bytemuck::{Pod, Zeroable};

/// Uniform parameters of `mnn_match`, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct MnnParams {
    /// Pairs in the batch.
    pub pairs: u32,
    /// u32 words per descriptor (dimension / 4).
    pub words: u32,
    /// Most keypoints of any image (rows of the per-pair output).
    pub max_keypoints: u32,
    pub _pad: u32,
}

/// One (query, reference) pair: the ranges of their keypoints in the packed descriptor arrays
/// (in keypoints), in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct MnnPair {
    pub query_start: u32,
    pub query_len: u32,
    pub ref_start: u32,
    pub ref_len: u32,
}

/// Marks an output row without a best column (the other side has no keypoints).
pub const NO_MATCH: u32 = u32::MAX;

/// Dot product of two packed int8 descriptors.
#[inline]
pub fn dot_packed(a: &[u32], b: &[u32]) -> i32 {
    a.iter().zip(b).map(|(&x, &y)| dot4(x, y)).sum()
}

/// Dot product of four int8 lanes packed in each word.
#[inline]
fn dot4(x: u32, y: u32) -> i32 {
    (0..4).map(|l| ((x >> (8 * l)) as u8 as i8 as i32) * ((y >> (8 * l)) as u8 as i8 as i32)).sum()
}

/// Rows per workgroup and columns per tile of the kernel.
pub const ROWS: usize = 64;
pub const TILE: usize = 64;
/// Longest descriptor the kernel holds, in words (256 int8 values, SuperPoint's width).
pub const MAX_WORDS: usize = 64;

/// The twin of the kernel: for pair `p` and direction `dir` (0: each query keypoint against the
/// reference's, 1: the reverse), row i's best column and its dot product, at
/// `((p * 2 + dir) * max_keypoints + i)` of `best` and `best_dot`. Rows past a side's count are
/// left as they are. Loops as the kernel's workgroups do: blocks of [`ROWS`] rows, columns a
/// [`TILE`] at a time.
pub fn mnn_match(params: &MnnParams, pairs: &[MnnPair], queries: &[u32], refs: &[u32], best: &mut [u32], best_dot: &mut [i32]) {
    let w = params.words as usize;
    for (p, pair) in pairs.iter().enumerate().take(params.pairs as usize) {
        for dir in 0..2usize {
            // rows of one side, columns of the other
            let (rows, rstart, rlen, cols, cstart, clen) = match dir {
                0 => (queries, pair.query_start, pair.query_len, refs, pair.ref_start, pair.ref_len),
                _ => (refs, pair.ref_start, pair.ref_len, queries, pair.query_start, pair.query_len),
            };
            let (rstart, rlen, cstart, clen) = (rstart as usize, rlen as usize, cstart as usize, clen as usize);
            for block in 0..rlen.div_ceil(ROWS) {
                for lane in 0..ROWS {
                    let i = block * ROWS + lane;
                    if i >= rlen {
                        continue;
                    }
                    let row = &rows[(rstart + i) * w..][..w];
                    let (mut bd, mut bj) = (i32::MIN, NO_MATCH);
                    for t0 in (0..clen).step_by(TILE) {
                        let tile = &cols[(cstart + t0) * w..(cstart + (t0 + TILE).min(clen)) * w];
                        for jj in 0..tile.len() / w {
                            let d = dot_packed(row, &tile[jj * w..(jj + 1) * w]);
                            if d > bd {
                                bd = d;
                                bj = (t0 + jj) as u32;
                            }
                        }
                    }
                    let at = (p * 2 + dir) * params.max_keypoints as usize + i;
                    best[at] = bj;
                    best_dot[at] = bd;
                }
            }
        }
    }
}

/// Best columns of one pair: per query keypoint (index into the reference's, dot product) and per
/// reference keypoint (index into the query's).
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct BestColumns {
    pub query_best: Vec<u32>,
    pub query_dot: Vec<i32>,
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

/// int8 descriptors packed four to a word (little-endian lanes), as the kernel reads them.
pub fn pack(desc: &[i8]) -> Vec<u32> {
    desc.chunks(4).map(|c| c.iter().enumerate().fold(0u32, |w, (l, &v)| w | ((v as u8 as u32) << (8 * l)))).collect()
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::util::SplitMix64;

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
