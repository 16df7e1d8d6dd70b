//! Stage 4a (beyond the paper): an approximate index for the coarse stage of large maps. Every
//! query of an exact coarse stage reads the whole map; this index reads a few percent of a small
//! summary of it and hands the exact fused score a shortlist.
//!
//! Method: an inverted file (IVF; Jégou, Douze & Schmid, "Product quantization for nearest
//! neighbor search", TPAMI 2011, the coarse quantizer of faiss' `IndexIVFFlat`) over the
//! whole-image appearance vectors reduced by an uncentred PCA (the top `index.dims` directions
//! of the map's own vectors, found by subspace iteration: Halko, Martinsson & Tropp, SIAM Review
//! 2011; a VLAD's inner products live mostly in a few hundred directions, Jégou & Chum, ECCV
//! 2012). Each reference keeps, beside its segment, its list (the nearest of `index.lists`
//! centroids, spherical k-means on a sample of the map) and its reduced vector as int8 with one
//! scale (`code`, [`Codes`]). A query is reduced the same way, its `index.probe` nearest lists
//! are scanned by the approximate inner product, and the best `index.shortlist` of them are
//! scored exactly by the fused coarse score (appearance cosine + `w_global` x SSIM), which picks
//! the top-K as the exact stage would among them.
//!
//! Why an IVF and not a graph (HNSW): the lists and codes of a reference depend on the model
//! and the reference alone, so each segment's codes are written beside it under the store's
//! commit protocol (a map add writes the new segments' codes in the same commit, a removal needs
//! nothing, a compaction recomputes the new segments'), the model is content-named, and a kill at
//! any point leaves the manifest's generation whole; a graph over all references is one mutable
//! structure across every segment. Measured side by side (docs/approximate-index.md) on the same vectors.
//!
//! The shortlist follows the fused score, not the appearance alone: the scan's best `index.pool`
//! by the codes are re-ranked by the codes plus `w_global` x the SSIM of 8-bit thumbnails of the
//! global descriptors ([`thumb`], kept beside the codes), and the best `index.shortlist` of those
//! go to the exact score. At a million references with repeated scenes the appearance codes alone
//! left out references that the SSIM lifts into the exact top-30 (docs/approximate-index.md).
//!
//! What it costs: `dims` + 6 bytes per reference (262 at the defaults) and the thumbnail
//! (768 at the default pooling of a 64 x 48 descriptor by 2), and the model (`dims` x the
//! appearance width + `lists` x `dims` floats).

pub mod codes;
pub mod model;
pub mod thumb;

pub use codes::{Codes, Inverted, MappedCodes};
pub use model::{IndexParams, Model};

use std::cmp::Ordering;
use std::collections::BinaryHeap;

/// One (approximate score, reference) in a bounded heap: the lowest score on top, ties to the
/// higher reference, so that what stays is the best with ties to the lower reference.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Entry(f32, u32);
impl Eq for Entry {}
impl Ord for Entry {
    fn cmp(&self, o: &Self) -> Ordering {
        o.0.total_cmp(&self.0).then(self.1.cmp(&o.1))
    }
}
impl PartialOrd for Entry {
    fn partial_cmp(&self, o: &Self) -> Option<Ordering> {
        Some(self.cmp(o))
    }
}

/// The `m` best of a stream of (score, reference), best first (ties to the lower reference).
#[derive(Debug, Default)]
pub struct Shortlist {
    m: usize,
    heap: BinaryHeap<Entry>,
}

impl Shortlist {
    /// An empty list keeping at most `m`.
    pub fn new(m: usize) -> Shortlist {
        Shortlist { m, heap: BinaryHeap::with_capacity(m.min(4096) + 1) }
    }
    /// Offers one reference.
    pub fn offer(&mut self, score: f32, reference: u32) {
        if self.m == 0 || !score.is_finite() {
            return;
        }
        let e = Entry(score, reference);
        if self.heap.len() < self.m {
            self.heap.push(e);
        } else if self.heap.peek().is_some_and(|w| e < *w) {
            self.heap.pop();
            self.heap.push(e);
        }
    }
    /// The kept references, best first.
    pub fn into_sorted(self) -> Vec<(f32, u32)> {
        let mut v: Vec<(f32, u32)> = self.heap.into_iter().map(|e| (e.0, e.1)).collect();
        v.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        v
    }
}

/// The approximate inner product of a reduced query `y` with a stored code: `scale` x
/// sum(code_i x y_i).
#[inline(always)]
pub fn code_dot(code: &[i8], scale: f32, y: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = code.len() / 8;
    for c in 0..chunks {
        for l in 0..8 {
            acc[l] += code[c * 8 + l] as f32 * y[c * 8 + l];
        }
    }
    let mut s: f32 = acc.iter().sum();
    for i in chunks * 8..code.len() {
        s += code[i] as f32 * y[i];
    }
    s * scale
}

/// What one query's scan needs: its reduced vector and which lists to read.
#[derive(Debug, Clone)]
pub struct Probe {
    /// The query's reduced vector (`dims` values).
    pub reduced: Vec<f32>,
    /// Per list, whether the scan reads it.
    pub lists: Vec<bool>,
}

impl Probe {
    /// The probe of a query's appearance vector: its reduction and its `probe` best lists.
    pub fn new(model: &Model, appearance: &[f32], probe: usize) -> Probe {
        let reduced = model.reduce(appearance);
        let mut order: Vec<(f32, usize)> = (0..model.lists()).map(|l| (model.centroid_dot(l, &reduced), l)).collect();
        order.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        let mut lists = vec![false; model.lists()];
        for &(_, l) in order.iter().take(probe.max(1)) {
            lists[l] = true;
        }
        Probe { reduced, lists }
    }

    /// Offers rows `rows` of `codes` (each with its reference index from `index`) to `out`:
    /// those in a probed list, scored by [`code_dot`].
    pub fn scan(&self, codes: &dyn CodeRows, rows: impl Iterator<Item = (usize, u32)>, out: &mut Shortlist) {
        for (row, reference) in rows {
            let l = codes.list(row) as usize;
            if self.lists.get(l).copied().unwrap_or(false) {
                out.offer(code_dot(codes.code(row), codes.scale(row), &self.reduced), reference);
            }
        }
    }
}

/// Rows of codes, in memory ([`Codes`]) or mapped from a file ([`MappedCodes`]).
pub trait CodeRows {
    /// The list of row `j`.
    fn list(&self, j: usize) -> u16;
    /// The code of row `j`.
    fn code(&self, j: usize) -> &[i8];
    /// The scale of row `j`.
    fn scale(&self, j: usize) -> f32;
    /// The thumbnail of row `j` (empty where the index keeps none).
    fn thumb(&self, j: usize) -> &[u8];
}

/// The shortlist of `index.shortlist = 0` (the default): 150 where the pool is re-ranked with
/// thumbnails (sweep 11b), 1,000 where the codes alone choose it (an index without thumbnails, or
/// `w_global` = 0: the shortlist of before thumbnails, sweep 11).
pub fn auto_shortlist(reranked: bool) -> usize {
    if reranked {
        150
    } else {
        1000
    }
}

/// One query of the index ([`crate::descriptors::source::RefSource::index_shortlist_in`]).
#[derive(Debug, Clone, Copy)]
pub struct IndexQuery<'a> {
    /// The query's whole-image appearance vector.
    pub appearance: &'a [f32],
    /// Its global descriptor (for the thumbnails' SSIM).
    pub global: &'a [f32],
    /// Lists scanned.
    pub probe: usize,
    /// The best of the scan by the appearance codes re-ranked by the codes plus `w_global` x the
    /// thumbnails' SSIM (where the index keeps thumbnails and `pool` > `shortlist`).
    pub pool: usize,
    /// References handed to the exact fused score (0: [`auto_shortlist`]).
    pub shortlist: usize,
    /// The caller keeps this many: the shortlist is never shorter.
    pub at_least: usize,
    /// The fused score's weight of the SSIM.
    pub w_global: f32,
    /// The coarse stage's SSIM constants.
    pub ssim: &'a crate::config::GlobalConfig,
    /// The query's whole-image embedding (empty without one).
    pub embedding: &'a [f32],
    /// The fused score's weight of the embeddings' cosine (0: no embedding term).
    pub w_embedding: f32,
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_shortlist_keeps_the_best_with_ties_to_the_lower_reference() {
        let mut s = Shortlist::new(3);
        for (x, r) in [(0.5, 9), (0.9, 4), (0.5, 2), (0.1, 1), (0.9, 3), (f32::NAN, 0)] {
            s.offer(x, r);
        }
        assert_eq!(s.into_sorted(), vec![(0.9, 3), (0.9, 4), (0.5, 2)]);
        let mut empty = Shortlist::new(0);
        empty.offer(1.0, 1);
        assert!(empty.into_sorted().is_empty());
    }

    #[test]
    fn code_dot_is_the_scaled_inner_product() {
        let code: Vec<i8> = (0..19).map(|i| (i * 7 % 255) as i8 - 100).collect();
        let y: Vec<f32> = (0..19).map(|i| (i as f32 * 0.37).sin()).collect();
        let want: f64 = code.iter().zip(&y).map(|(&c, &v)| c as f64 * v as f64).sum::<f64>() * 0.5;
        assert!((code_dot(&code, 0.5, &y) as f64 - want).abs() < 1e-4);
        assert_eq!(code_dot(&[], 1.0, &[]), 0.0);
    }
}
