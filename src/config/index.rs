//! The `[index]` section: the approximate index of the coarse stage over large maps.

use serde::{Deserialize, Serialize};

/// When the fused coarse stage searches a map through its approximate index ([`crate::index`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum IndexSearch {
    /// Where the map has an index and the search covers at least `index.min_places` references.
    Auto,
    /// Never: every reference is scored exactly.
    Exact,
    /// Wherever the map has an index, whatever its size.
    Approximate,
}

/// The `[index]` section: the approximate index of the coarse stage over large maps (beyond the
/// paper; [`crate::index`]): how `map build --index` and `map index` build it (recorded in the
/// map), and when and how matching uses it (a matching section: it may change at query time).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct IndexConfig {
    /// When the fused coarse stage (`fused`, `verified`, and the coarse stage of `semlook` and
    /// `global-forest`) uses the map's index. \[R\] auto.
    pub search: IndexSearch,
    /// `auto` uses the index from this many references searched. \[R\] 20,000 (sweep 11: at
    /// 20,000 one query's exact scan took 368 ms and the index's 18 ms on the 2-core machine;
    /// smaller maps keep the exact scan, which costs little there and assumes nothing).
    pub min_places: usize,
    /// Lists scanned per query. \[R\] 112 (sweep 11b: with `shortlist` and `pool`, the best
    /// recall@30 against the exact fused top-30 at 1M references under 20 ms a query: 0.969 at
    /// 16.5 ms; sweep 11 had chosen 96 with a shortlist of 1,000 and no pool).
    pub probe: usize,
    /// References rescored exactly by the fused score (the best of the pool by its approximation);
    /// 0: 150 where the pool is re-ranked with thumbnails, 1,000 where the codes alone choose
    /// (an index without thumbnails). \[R\] 0 (sweep 11b: 150/200/300 with the pool; sweep 11:
    /// 1,000 without it).
    pub shortlist: usize,
    /// The scan's best references by the appearance codes that are re-ranked by the codes plus
    /// `matching.w_global` x the SSIM of the index's thumbnails before the `shortlist` best go to
    /// the exact score (an index without thumbnails, or `pool` <= `shortlist`: the codes alone
    /// choose the shortlist). \[R\] 6,000 (sweep 11b: 4,000/6,000).
    pub pool: usize,
    /// Build: reduced dimensions. \[R\] 256 (faiss's 1M-image example reduces 4,096-d image
    /// descriptors to 256 the same way; 262 bytes a reference with its list and scale).
    pub dims: usize,
    /// Build: lists; 0 chooses 4 x sqrt(images) rounded to a power of two, 16 to 4,096.
    /// \[R\] 0 (faiss's guideline: 4 to 16 x sqrt(N)).
    pub lists: usize,
    /// Build: images sampled to train on. \[R\] 32,768.
    pub sample: usize,
    /// Build: subspace and k-means iterations. \[R\] 8.
    pub iterations: usize,
    /// Build: seed. \[R\] 7.
    pub seed: u64,
    /// Build: the global descriptors' thumbnails kept beside the codes, pooled by this factor
    /// (8-bit, 768 bytes a reference at 2 for a 64 x 48 descriptor); 0: none. \[R\] 2 (on the
    /// real dev sets the SSIM of thumbnails pooled by 2 follows the exact SSIM at r = 0.990, by 4
    /// at 0.951: docs/approximate-index.md).
    pub thumbnail: usize,
}

impl Default for IndexConfig {
    fn default() -> Self {
        IndexConfig {
            search: IndexSearch::Auto,
            min_places: 20_000,
            probe: 112,
            shortlist: 0,
            pool: 6000,
            dims: 256,
            lists: 0,
            sample: 32_768,
            iterations: 8,
            seed: 7,
            thumbnail: 2,
        }
    }
}

impl IndexConfig {
    /// Checks that every value of `[index]` is in its range (numbers finite); the error names
    /// the field ([`super::Config::validate`] checks what spans sections).
    pub(super) fn validate(&self, v: &super::Check) -> crate::error::Result<()> {
        v.int("index.min_places", self.min_places, 0, usize::MAX)?;
        v.int("index.probe", self.probe, 1, 65536)?;
        v.int("index.shortlist", self.shortlist, 0, 1 << 20)?;
        v.int("index.pool", self.pool, 0, 1 << 22)?;
        v.int("index.thumbnail", self.thumbnail, 0, 64)?;
        v.int("index.dims", self.dims, 1, 4096)?;
        v.int("index.lists", self.lists, 0, 65536)?;
        v.int("index.sample", self.sample, 1, 1 << 24)?;
        v.int("index.iterations", self.iterations, 1, 100)?;
        Ok(())
    }
}
