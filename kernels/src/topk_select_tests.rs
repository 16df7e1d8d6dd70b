//! Partial lists and merges keep what the streaming fold keeps, bit for bit.

use super::*;
use crate::abi::TileParams;
use crate::rng::SplitMix64;
use crate::ssim_topk::{topk_lists, topk_merge};
use proptest::prelude::*;

/// Scores with exact ties, both zeros, NaN (quiet, signalling, negative), infinities and the
/// empty score itself.
fn score(rng: &mut SplitMix64) -> f32 {
    match rng.below(12) {
        0 => f32::NAN,
        1 => f32::from_bits(0x7f80_0001),
        2 => f32::from_bits(0xffc0_0000),
        3 => f32::INFINITY,
        4 => f32::NEG_INFINITY,
        5 => EMPTY_SCORE,
        6 => -0.0,
        7 => 0.0,
        _ => rng.below(6) as f32 / 5.0 - 0.5,
    }
}

/// The executor's loop on the twins: passes of `pass` references, each scored into a
/// queries x pass block, selected per segment, merged into the running lists (ping-pong).
fn select_topk(scores: &[f32], nq: usize, n: usize, k: usize, pass: usize) -> Vec<Vec<(f32, u32)>> {
    let (mut a, mut b) = (vec![Entry::EMPTY; nq * k], vec![Entry::EMPTY; nq * k]);
    let mut parity = 0;
    let mut start = 0;
    while start < n {
        let refs = pass.min(n - start);
        let segs = refs.div_ceil(SEG);
        let block: Vec<f32> = (0..nq * refs).map(|i| scores[(i / refs) * n + start + i % refs]).collect();
        let ps = PassParams {
            queries: nq as u32,
            refs: refs as u32,
            ref_index: start as u32,
            k: k as u32,
            segs: segs as u32,
            parity,
            ..Default::default()
        };
        let mut partial = vec![Entry { score: 7.0, index: 7 }; nq * segs * k];
        topk_partial(&ps, &block, &mut partial);
        topk_merge_lists(&ps, &partial, &mut a, &mut b);
        parity ^= 1;
        start += refs;
    }
    let top = if parity == 0 { a } else { b };
    let (s, i): (Vec<f32>, Vec<u32>) = top.iter().map(|e| (e.score, e.index)).unzip();
    topk_lists(k, &s, &i)
}

fn fold_topk(scores: &[f32], nq: usize, n: usize, k: usize) -> Vec<Vec<(f32, u32)>> {
    let (mut ts, mut ti) = (vec![EMPTY_SCORE; nq * k], vec![EMPTY_INDEX; nq * k]);
    topk_merge(&TileParams { queries: nq as u32, tile_len: n as u32, tile_start: 0, k: k as u32 }, scores, &mut ts, &mut ti);
    topk_lists(k, &ts, &ti)
}

fn bits(l: &[Vec<(f32, u32)>]) -> Vec<Vec<(u32, u32)>> {
    l.iter().map(|q| q.iter().map(|&(s, i)| (s.to_bits(), i)).collect()).collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(64))]

    /// Any pass length (several segments per pass, a last short one), any K (also above the
    /// segment's candidates): the fold's lists, score bits and indices.
    #[test]
    fn partial_lists_and_merges_keep_what_the_fold_keeps(nq in 1usize..4, n in 1usize..2600, k in 1usize..40, pass in 1usize..2100, seed in any::<u64>()) {
        let mut rng = SplitMix64::new(seed);
        let scores: Vec<f32> = (0..nq * n).map(|_| score(&mut rng)).collect();
        prop_assert_eq!(bits(&select_topk(&scores, nq, n, k, pass)), bits(&fold_topk(&scores, nq, n, k)));
    }
}

/// A segment with fewer candidates than K fills its list with empty entries; a list of NaN only
/// is empty.
#[test]
fn short_segments_are_padded_with_empty_entries() {
    let scores = [0.5, f32::NAN, 0.5, f32::NAN, f32::NAN, f32::NAN];
    let ps = PassParams { queries: 2, refs: 3, ref_index: 10, k: 4, segs: 1, ..Default::default() };
    let mut partial = vec![Entry { score: 1.0, index: 1 }; 8];
    topk_partial(&ps, &scores, &mut partial);
    let e = Entry::EMPTY;
    assert_eq!(partial, vec![Entry { score: 0.5, index: 10 }, Entry { score: 0.5, index: 12 }, e, e, e, e, e, e]);
}

/// A chunk's first pass (`fresh`) merges its segment lists alone: whatever the running-list
/// buffer holds (never written for the chunk) is not read; later passes read it.
#[test]
fn a_fresh_pass_does_not_read_the_running_lists() {
    let ps = PassParams { queries: 1, refs: 2, k: 2, segs: 1, fresh: 1, ..Default::default() };
    let partial = vec![Entry { score: 0.3, index: 7 }, Entry { score: 0.1, index: 8 }];
    // stale entries better than any candidate, as a buffer from another batch could hold
    let stale = vec![Entry { score: 0.9, index: 1 }, Entry { score: 0.8, index: 2 }];
    let (mut top_a, mut top_b) = (stale.clone(), vec![Entry::EMPTY; 2]);
    topk_merge_lists(&ps, &partial, &mut top_a, &mut top_b);
    assert_eq!(top_b, partial, "a fresh pass kept entries of the running lists");
    let (mut top_a, mut top_b) = (stale.clone(), vec![Entry::EMPTY; 2]);
    topk_merge_lists(&PassParams { fresh: 0, ..ps }, &partial, &mut top_a, &mut top_b);
    assert_eq!(top_b, stale, "a later pass must merge the running lists");
}
