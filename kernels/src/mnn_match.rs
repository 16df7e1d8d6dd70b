//! Mutual nearest neighbours between the keypoints of (query, reference) pairs: CPU twin of
//! `shaders/mnn_match.wgsl` (same name, bindings and loop shape). The fast CPU path the engine
//! runs is `verify::best_columns` (a matrix product; the twin's indices and dot products, bit
//! for bit).
//!
//! Descriptors are int8 (`semlook::descriptors::keypoints::DESCRIPTOR_SCALE` times the unit vector), four to a
//! `u32` word. Dot products are exact integers, so the twin, the fast path and the GPU kernel agree
//! exactly: for every row of one side, the column of the other side with the largest dot product
//! (the lowest index among equals) and that dot product. A query keypoint i and a reference
//! keypoint j match when each is the other's best and their dot product reaches the threshold
//! (XFeat's matcher: mutual nearest neighbours above a cosine, Potje et al. 2024).

use super::abi::{MnnPair, MnnParams};

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
/// Columns per tile of the kernel.
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

/// int8 descriptors packed four to a word (little-endian lanes), as the kernel reads them.
pub fn pack(desc: &[i8]) -> Vec<u32> {
    desc.chunks(4).map(|c| c.iter().enumerate().fold(0u32, |w, (l, &v)| w | ((v as u8 as u32) << (8 * l)))).collect()
}
