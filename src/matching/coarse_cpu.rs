//! The CPU coarse stage at hardware speed: SSIM of a query batch against a map tile by blocked,
//! vectorised, parallel evaluation of [`ssim_lanes_fast`] (one reference per vector lane; scores
//! equal to the twin `ssim_topk::ssim_tile`'s bit for bit), folded by the same streaming top-K.
//!
//! Algorithm (cache-blocked batched SSIM, one pair per vector lane):
//! - terms: each query's lane terms ([`query_lane_terms`]) are prepared once per batch
//!   ([`CoarseCpu::prepare`]); a task interleaves its references' descriptors and stats records
//!   ([`interleave`], [`ref_lane_terms`]) once per query pass, into that worker's scratch (no tile-sized buffer);
//! - blocking: a task scores [`REFS_PER_BLOCK`] references against up to [`QUERIES_PER_PASS`]
//!   queries, so the interleaved references are read from memory once per pass and then reused
//!   from cache by every query of the pass;
//! - parallelism: rayon over the blocks of a tile, each worker with its own scratch from the
//!   executor's pool (no allocation per tile or pair);
//! - SIMD: the block loop is generic over `pulp`'s vector types and compiled once per instruction
//!   set; `pulp::Arch` picks one at run time (AVX2 on x86-64-v3 processors; AVX-512, 16 pairs a
//!   vector, was measured 10% slower per pair on the Zen 4 development machine and is not built). Every instantiation evaluates the
//!   same IEEE operations in the same order, so they give the same bits. Where pulp finds no
//!   vector instruction set, blocks run the twin's `ssim_pair` instead ([`Simd::Twin`]).
//!
//! Scores are written reference-major (`scores[r * queries + q]`) so that each block owns one
//! contiguous slice; `ssim_topk::topk_merge_ref_major` folds them into the K-lists.

use crate::global::ssim_fast::{
    interleave, query_lane_terms, query_lane_terms_len, ref_lane_terms, ref_lane_terms_len, ssim_lanes_fast, LaneScratch,
};
use rayon::prelude::*;
use semlook_kernels::abi::{self, SsimParams};
use semlook_kernels::ssim::{ssim_pair, SsimScratch};
use semlook_kernels::ssim_topk;
use std::sync::{Mutex, PoisonError};

/// References per task: one group of 8 vector lanes with AVX2 (two with NEON). A group's
/// descriptors and stats, interleaved, take ~250 KiB at the default 64x48 size: they stay in
/// L2 while the pass's queries stream past; a 4096-reference tile still makes 512 tasks.
pub const REFS_PER_BLOCK: usize = 8;

/// Queries per pass over a tile. Their descriptors and terms (~6.3 MiB at the default size)
/// stay in a shared L3 while every block reads them; larger batches take several passes, each
/// re-reading the tile's references from memory once.
pub const QUERIES_PER_PASS: usize = 128;

/// The kernel and instruction set the block loop runs with.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Simd {
    /// `ssim_lanes_fast`, one lane at a time (pulp's scalar fallback): any processor.
    Scalar,
    /// The twin's `ssim_pair` per pair (the same bits): what `Best` falls back to where pulp finds
    /// no vector instruction set, since the twin's loops, auto-vectorised for the build's
    /// baseline (SSE2), beat one-lane code.
    Twin,
    /// `ssim_lanes_fast` with the best `pulp` finds at run time: AVX2+FMA ("x86-64-v3") on x86-64,
    /// NEON on aarch64; else `Twin`.
    Best,
}

/// Scratch of one worker thread.
#[derive(Default)]
struct Worker {
    /// One lane group's descriptors (interleaved) and lane terms.
    ref_lanes: Vec<f32>,
    ref_terms: Vec<f32>,
    lanes: LaneScratch,
    twin: SsimScratch,
}

/// Executor of the fast coarse stage: owns the query batch's terms and one scratch per worker.
pub struct CoarseCpu {
    p: SsimParams,
    simd: Simd,
    arch: pulp::Arch,
    nq: usize,
    /// The batch's lane terms ([`query_lane_terms`]).
    query_terms: Vec<f32>,
    /// The batch's stats records (kept for `Simd::Twin` only).
    query_stats: Vec<f32>,
    workers: Vec<Mutex<Worker>>,
}

impl CoarseCpu {
    /// An executor with the best instruction set this processor has.
    pub fn new(p: &SsimParams) -> Self {
        Self::with_simd(p, Simd::Best)
    }

    /// An executor restricted to `simd`.
    pub fn with_simd(p: &SsimParams, simd: Simd) -> Self {
        let (simd, arch) = match (simd, pulp::Arch::new()) {
            (Simd::Best, pulp::Arch::Scalar) | (Simd::Twin, _) => (Simd::Twin, pulp::Arch::Scalar),
            (Simd::Best, a) => (Simd::Best, a),
            (Simd::Scalar, _) => (Simd::Scalar, pulp::Arch::Scalar),
        };
        CoarseCpu { p: *p, simd, arch, nq: 0, query_terms: Vec::new(), query_stats: Vec::new(), workers: Vec::new() }
    }

    /// The kernel in use: pulp's name of the instruction set (`V3` is AVX2), "scalar" or "twin".
    pub fn describe_simd(&self) -> String {
        match self.simd {
            Simd::Scalar => "scalar".into(),
            Simd::Twin => "twin (no vector instruction set found)".into(),
            Simd::Best => format!("{:?}", self.arch).split('(').next().unwrap_or("?").to_string(),
        }
    }

    /// Prepares a batch of `nq` queries from their stats records (once per batch).
    pub fn prepare(&mut self, query_stats: &[f32], nq: usize) {
        let (p, tl, sl) = (self.p, query_lane_terms_len(&self.p), self.p.stats_len());
        if self.simd == Simd::Twin {
            self.query_stats.clear();
            self.query_stats.extend_from_slice(&query_stats[..nq * sl]);
        } else {
            self.query_terms.resize(nq * tl, 0.0);
            self.query_terms.par_chunks_mut(tl).zip(query_stats[..nq * sl].par_chunks(sl)).for_each(|(t, s)| query_lane_terms(&p, s, t));
        }
        self.nq = nq;
        while self.workers.len() < rayon::current_num_threads() {
            self.workers.push(Mutex::new(Worker::default()));
        }
    }

    /// SSIM of every prepared query (descriptors `queries`) against every reference of a tile
    /// (descriptors `refs`, stats `ref_stats`), into `scores[r * queries + q]`.
    pub fn score_tile(&self, queries: &[f32], refs: &[f32], ref_stats: &[f32], scores: &mut [f32]) {
        let (nq, len) = (self.nq, self.p.len());
        let t = refs.len() / len;
        if nq == 0 || t == 0 || self.workers.is_empty() {
            return;
        }
        for q0 in (0..nq).step_by(QUERIES_PER_PASS) {
            let qs = q0..(q0 + QUERIES_PER_PASS).min(nq);
            scores[..t * nq].par_chunks_mut(REFS_PER_BLOCK * nq).enumerate().for_each(|(b, out)| {
                let slot = rayon::current_thread_index().unwrap_or(0) % self.workers.len();
                let mut w = self.workers[slot].lock().unwrap_or_else(PoisonError::into_inner);
                let rs = b * REFS_PER_BLOCK..(b * REFS_PER_BLOCK + REFS_PER_BLOCK).min(t);
                let block = Block {
                    x: self,
                    queries,
                    qs: qs.clone(),
                    refs: &refs[rs.start * len..rs.end * len],
                    ref_stats: &ref_stats[rs.start * self.p.stats_len()..rs.end * self.p.stats_len()],
                    w: &mut w,
                    out,
                };
                match self.simd {
                    Simd::Twin => block.twin(),
                    _ => self.arch.dispatch(block),
                }
            });
        }
    }
}

/// One task: the queries `qs` against one block of references, with a worker's scratch.
struct Block<'a> {
    x: &'a CoarseCpu,
    queries: &'a [f32],
    qs: std::ops::Range<usize>,
    refs: &'a [f32],
    ref_stats: &'a [f32],
    w: &'a mut Worker,
    /// The block's scores, reference-major over the whole batch.
    out: &'a mut [f32],
}

impl Block<'_> {
    /// The block through the twin's `ssim_pair`.
    fn twin(self) {
        let CoarseCpu { p, nq, query_stats, .. } = self.x;
        let (len, sl) = (p.len(), p.stats_len());
        for q in self.qs {
            let (x, xs) = (&self.queries[q * len..(q + 1) * len], &query_stats[q * sl..(q + 1) * sl]);
            for (r, (y, ys)) in self.refs.chunks_exact(len).zip(self.ref_stats.chunks_exact(sl)).enumerate() {
                self.out[r * nq + q] = ssim_pair(p, x, xs, y, ys, &mut self.w.twin);
            }
        }
    }
}

impl pulp::WithSimd for Block<'_> {
    type Output = ();

    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, simd: S) {
        let CoarseCpu { p, nq, query_terms, .. } = self.x;
        let (len, sl, tl, lanes) = (p.len(), p.stats_len(), query_lane_terms_len(p), S::F32_LANES);
        let nr = self.refs.len() / len;
        let w = self.w;
        let groups = nr.div_ceil(lanes);
        let (gl, gt) = (len * lanes, ref_lane_terms_len(p, lanes));
        w.ref_lanes.resize(groups * gl, 0.0);
        w.ref_terms.resize(groups * gt, 0.0);
        // each group of `lanes` references interleaved once; then every query of the pass against
        // the groups in turn (its values still in cache for the second)
        for (g, (yl, yt)) in w.ref_lanes.chunks_exact_mut(gl).zip(w.ref_terms.chunks_exact_mut(gt)).take(groups).enumerate() {
            let (r0, m) = (g * lanes, lanes.min(nr - g * lanes));
            interleave(&self.refs[r0 * len..(r0 + m) * len], len, m, lanes, yl);
            ref_lane_terms(p, &self.ref_stats[r0 * sl..(r0 + m) * sl], m, lanes, yt);
        }
        let mut scores = [0.0f32; 64];
        for q in self.qs.clone() {
            let (x, xt) = (&self.queries[q * len..(q + 1) * len], &query_terms[q * tl..(q + 1) * tl]);
            for (g, (yl, yt)) in w.ref_lanes.chunks_exact(gl).zip(w.ref_terms.chunks_exact(gt)).take(groups).enumerate() {
                let (r0, m) = (g * lanes, lanes.min(nr - g * lanes));
                ssim_lanes_fast(simd, p, x, xt, yl, yt, &mut w.lanes, &mut scores);
                for (i, s) in scores[..m].iter().enumerate() {
                    self.out[(r0 + i) * nq + q] = *s;
                }
            }
        }
    }
}

/// A function folding one tile's scores into the K-lists (`topk_merge` or its reference-major form).
type Merge = fn(&abi::TileParams, &[f32], &mut [f32], &mut [u32]);

/// The CPU streaming top-K over a map of `n` references: per tile of at most `tile` references,
/// `score` fills the queries x tile scores, which `merge` folds into each query's K-list.
pub(crate) fn stream_topk(
    nq: usize,
    n: usize,
    k: usize,
    tile: usize,
    merge: Merge,
    mut score: impl FnMut(&abi::TileParams, &mut [f32]),
) -> Vec<Vec<(f32, u32)>> {
    let tile = tile.max(1).min(n.max(1));
    let mut scores = vec![0.0f32; nq * tile];
    let mut top_s = vec![abi::EMPTY_SCORE; nq * k];
    let mut top_i = vec![abi::EMPTY_INDEX; nq * k];
    let mut start = 0;
    while start < n {
        let end = (start + tile).min(n);
        let tp = abi::TileParams { queries: nq as u32, tile_len: (end - start) as u32, tile_start: start as u32, k: k as u32 };
        score(&tp, &mut scores[..nq * (end - start)]);
        merge(&tp, &scores[..nq * (end - start)], &mut top_s, &mut top_i);
        start = end;
    }
    ssim_topk::topk_lists(k, &top_s, &top_i)
}

#[cfg(test)]
#[path = "coarse_cpu_tests.rs"]
mod tests;
