//! Building, dropping and searching a map's approximate index ([`crate::index`]); its files and
//! their checks are [`super::index_files`]. Every change is one commit under the store's protocol.

use super::files::{write_atomic, WriteLock};
use super::index_files::{codes_for_segment, codes_name, delete_unreferenced, index_files, write_segment_codes, MapIndex};
use super::manifest::{self, FileEntry, IndexEntry, Manifest};
use super::segment::Layout;
use super::{layout_of, Map};
use crate::classes::ClassTable;
use crate::error::{Error, Result};
use crate::index::thumb::{ThumbScorer, ThumbSpec};
use crate::index::{auto_shortlist, CodeRows, IndexParams, IndexQuery, Model, Probe, Shortlist};
use crate::util::sha256_hex;
use rayon::prelude::*;
use std::collections::HashSet;
use std::ops::Range;
use std::path::Path;
use std::time::Instant;

/// References of the pool whose thumbnails one task scores.
const POOL_CHUNK: usize = 512;
/// Queries drawn from the map to measure the recall of a new index.
const RECALL_QUERIES: usize = 100;
/// The ranking depth the recall is measured at.
pub const RECALL_AT: usize = 30;

impl Map {
    /// The map's index, when it has one.
    pub fn index(&self) -> Option<&MapIndex> {
        self.index.as_ref()
    }

    /// The index's shortlist for one query: the `q.shortlist` references (0: [`auto_shortlist`],
    /// never fewer than `q.at_least`) of `range` (map indices) with the best approximate scores
    /// among the `q.probe` lists nearest to its appearance vector, best first. The approximate score is the inner product of the codes;
    /// where the index keeps thumbnails, the `q.pool` best by it are re-ranked by it plus
    /// `q.w_global` x the thumbnails' SSIM (the fused score's approximation). An error where the
    /// map has no index or a file it reads is damaged.
    pub fn index_shortlist(&self, q: &IndexQuery, range: Range<usize>) -> Result<Vec<(f32, u32)>> {
        let ix = self.index.as_ref().ok_or_else(|| Error::invalid(format!("map {}", self.path.display()), "has no index (`semlook map index`)"))?;
        if q.appearance.len() != ix.model.width {
            return Err(Error::invalid(
                "index query",
                format!("{} appearance values, the map's index reduces {}", q.appearance.len(), ix.model.width),
            ));
        }
        // the pool is re-ranked by the fused score's other terms where it has any here: the
        // thumbnails' SSIM, the embeddings' cosine
        let thumbs = !ix.thumb.is_empty() && q.w_global != 0.0;
        let reranked = thumbs || q.w_embedding != 0.0;
        let shortlist = shortlist_len(ix, q.shortlist, q.at_least, q.w_global, q.w_embedding);
        let fused = reranked && q.pool > shortlist;
        if fused && thumbs && q.global.len() != ix.thumb.width * ix.thumb.height {
            return Err(Error::invalid(
                "index query",
                format!("{} global values, the map's index keeps thumbnails of {}", q.global.len(), ix.thumb.width * ix.thumb.height),
            ));
        }
        let p = Probe::new(&ix.model, q.appearance, q.probe);
        let probed: Vec<usize> = (0..p.lists.len()).filter(|&l| p.lists[l]).collect();
        let cap = if fused { q.pool } else { shortlist };
        // each segment's probed lists scanned in parallel, their shortlists merged (the same
        // best with ties to the lower reference whatever the order)
        let parts = ix
            .codes
            .par_iter()
            .enumerate()
            .filter(|&(s, _)| self.starts[s + 1] > range.start && self.starts[s] < range.end)
            .map(|(s, codes)| {
                codes.check().map_err(Error::in_index)?;
                let mut out = Shortlist::new(cap);
                pulp::Arch::new().dispatch(ScanLists { map: self, s, codes, probe: &p, probed: &probed, range: range.clone(), out: &mut out });
                Ok(out)
            })
            .collect::<Vec<Result<Shortlist>>>()
            .into_iter()
            .collect::<Result<Vec<_>>>()?; // the first damaged segment in manifest order
        let mut out = Shortlist::new(cap);
        for part in parts {
            for (x, r) in part.into_sorted() {
                out.offer(x, r);
            }
        }
        if !fused {
            return Ok(out.into_sorted());
        }
        // the pool's thumbnails scored by the coarse stage's SSIM, in parallel chunks (none
        // without thumbnails)
        let pooled = out.into_sorted();
        let ssim: Vec<f32> = if !thumbs {
            vec![0.0; pooled.len()]
        } else {
            pooled
                .par_chunks(POOL_CHUNK)
                .map_init(
                    || {
                        let mut scorer = ThumbScorer::new(&ix.thumb, q.ssim);
                        scorer.set_query(q.global);
                        scorer
                    },
                    |scorer, chunk| {
                        scorer
                            .score(chunk.iter().map(|&(_, r)| {
                                let (s, j) = self.locate(r as usize);
                                ix.codes[s].thumb(j)
                            }))
                            .to_vec()
                    },
                )
                .flatten()
                .collect()
        };
        // the embedding term of the fused score, exact (a dot product per pooled reference)
        let emb = |r: u32| -> f32 {
            match q.w_embedding {
                0.0 => 0.0,
                w => w * crate::values::Values::F32(q.embedding).dot(&crate::descriptors::source::RefSource::image_embedding(self, r as usize)),
            }
        };
        let scored = pooled.iter().zip(&ssim).map(|(&(a, r), &s)| (a + q.w_global * s + emb(r), r));
        let mut best = Shortlist::new(shortlist);
        for (x, r) in scored {
            best.offer(x, r);
        }
        Ok(best.into_sorted())
    }
}

/// What one search of a map's index scans ([`Map::index_plan`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct IndexPlan {
    /// Lists probed (never more than the index has).
    pub probed: usize,
    /// Lists of the index.
    pub lists: usize,
    /// References shortlisted for the exact score.
    pub shortlist: usize,
}

impl Map {
    /// What a search of the index with these fields of an [`IndexQuery`] scans, without running
    /// one (for reports): `probe` lists of the index's, and the shortlist [`Map::index_shortlist`]
    /// rescores (`shortlist` 0: [`auto_shortlist`], never fewer than `at_least`). `None` without
    /// an index.
    pub fn index_plan(&self, probe: usize, shortlist: usize, at_least: usize, w_global: f32, w_embedding: f32) -> Option<IndexPlan> {
        let ix = self.index.as_ref()?;
        let lists = ix.model.lists();
        Some(IndexPlan { probed: probe.max(1).min(lists), lists, shortlist: shortlist_len(ix, shortlist, at_least, w_global, w_embedding) })
    }
}

/// The shortlist a query of `ix` rescores: `shortlist`, or for 0 [`auto_shortlist`] of whether
/// the pool is re-ranked (by thumbnails the index keeps, or an embedding term), at least `at_least`.
fn shortlist_len(ix: &MapIndex, shortlist: usize, at_least: usize, w_global: f32, w_embedding: f32) -> usize {
    let reranked = (!ix.thumb.is_empty() && w_global != 0.0) || w_embedding != 0.0;
    match shortlist {
        0 => auto_shortlist(reranked),
        s => s,
    }
    .max(at_least)
}

/// One segment's probed lists offered to a shortlist (compiled for the best vector instructions,
/// for [`crate::index::code_dot`]): each list's rows, live ones only, as map indices in `range`.
struct ScanLists<'a> {
    map: &'a Map,
    s: usize,
    codes: &'a crate::index::MappedCodes,
    probe: &'a Probe,
    probed: &'a [usize],
    range: Range<usize>,
    out: &'a mut Shortlist,
}

impl pulp::WithSimd for ScanLists<'_> {
    type Output = ();
    #[inline(always)]
    fn with_simd<S: pulp::Simd>(self, _simd: S) {
        let (first, inv, live) = (self.map.starts[self.s], self.codes.inverted(), self.map.live[self.s].as_deref());
        for &l in self.probed {
            for &j in inv.rows(l) {
                // the row's place among the segment's live rows (removed rows are not offered)
                let k = match live {
                    None => j as usize,
                    Some(rows) => match rows.binary_search(&j) {
                        Ok(k) => k,
                        Err(_) => continue,
                    },
                };
                let r = first + k;
                if self.range.contains(&r) {
                    let j = j as usize;
                    self.out.offer(crate::index::code_dot(self.codes.code(j), self.codes.scale(j), &self.probe.reduced), r as u32);
                }
            }
        }
    }
}

/// What [`build`] did.
#[derive(Debug, Clone)]
pub struct IndexReport {
    /// The index's manifest entry.
    pub entry: IndexEntry,
    /// Segments whose codes were written.
    pub segments: usize,
}

/// Live images evenly spread over `0..len`, `k` of them (all when `k >= len`), skipping `skip`.
fn spread(len: usize, k: usize, offset: usize) -> Vec<usize> {
    if k >= len {
        return (0..len).collect();
    }
    (0..k).map(|i| ((i * len) / k + offset) % len).collect()
}

/// Builds (or rebuilds) the index of the map in `dir` with `params` and commits it: the model
/// trained on a sample of the live images' appearance vectors, every segment's codes, the recall
/// measured (`RECALL_QUERIES` of the map's own images as queries, each left out of its ranking,
/// `probe` lists and a shortlist of `shortlist` against the exact appearance ranking), then one
/// commit under the lock (segments committed meanwhile by another writer get their codes there).
/// Files of an index the new one replaces are deleted after the commit. A kill at any point
/// leaves the map as one of the two generations.
pub fn build(dir: &Path, params: &IndexParams, probe: usize, shortlist: usize) -> Result<IndexReport> {
    let t0 = Instant::now();
    // the recall is the codes' own (against the exact appearance ranking): their shortlist
    let shortlist = if shortlist == 0 { auto_shortlist(false) } else { shortlist };
    let map = Map::open(dir)?;
    // thumbnails too small for one window are not kept, and the manifest says so
    let thumb = ThumbSpec::new(&map.manifest.config.global, params.thumbnail);
    let params = &IndexParams { thumbnail: if thumb.is_empty() { 0 } else { params.thumbnail }, ..*params };
    let what = || format!("map {}", dir.display());
    if map.manifest.appearance_dim == 0 {
        return Err(Error::invalid(what(), "holds no appearance vectors to index (built without the keypoint network)"));
    }
    let n = map.len();
    if n == 0 {
        return Err(Error::invalid(what(), "holds no images to index"));
    }
    map.check_all()?;
    let width = map.manifest.appearance_dim;
    let vector_of = |i: usize, dst: &mut [f32]| crate::descriptors::source::RefSource::image_appearance(&map, i).write_to(dst);
    let sample_ix = spread(n, params.sample.max(1), 0);
    let mut sample = vec![0.0f32; sample_ix.len() * width];
    for (&i, dst) in sample_ix.iter().zip(sample.chunks_mut(width)) {
        vector_of(i, dst);
    }
    let model = Model::train(&sample, sample_ix.len(), width, params)?;
    drop(sample);
    let model_bytes = model.file_bytes()?;
    let model_sha = sha256_hex(&model_bytes);
    let model_file = format!("index-model-{}.safetensors", &model_sha[..16]);
    // the files written before the commit are staged in a folder of this build's own, outside
    // what compaction, removal or a writer's cleaning of leftovers see, and moved into the map
    // under the lock by the commit (an interrupted build's folder is a leftover once its
    // process is gone: `files::leftovers`)
    let staging = Staging::new(dir)?;
    write_atomic(&staging.path, &model_file, &model_bytes)?;
    let entry0 = IndexEntry {
        model: FileEntry { file: model_file, bytes: model_bytes.len() as u64, sha256: model_sha.clone() },
        params: *params,
        dims: model.dims,
        lists: model.lists(),
        trained_on: n,
        recall_hits: 0,
        recall_of: 0,
        recall_probe: probe,
        recall_shortlist: shortlist,
        build_ms: 0,
    };
    // the recall queries and their exact rankings, folded segment by segment with the codes
    let queries: Vec<usize> = spread(n, RECALL_QUERIES, n / (2 * RECALL_QUERIES).max(1) + 1);
    let mut qv = vec![0.0f32; queries.len() * width];
    for (&i, dst) in queries.iter().zip(qv.chunks_mut(width)) {
        vector_of(i, dst);
    }
    let mut exact: Vec<Shortlist> = queries.iter().map(|_| Shortlist::new(RECALL_AT + 1)).collect();
    let layout = map.layout();
    let mut written: Vec<(String, FileEntry)> = Vec::new();
    let probes: Vec<Probe> = qv.chunks(width).map(|q| Probe::new(&model, q, probe)).collect();
    let mut approx_lists: Vec<Shortlist> = queries.iter().map(|_| Shortlist::new(shortlist)).collect();
    for (s, seg) in map.segments().iter().enumerate() {
        let codes = codes_for_segment(&model, &thumb, seg);
        // exact inner products of the live rows against the recall queries
        let rows: Vec<(usize, u32)> = map.live_rows(s).enumerate().map(|(k, j)| (j, (map.starts[s] + k) as u32)).collect();
        let mut buf = vec![0.0f32; rows.len() * width];
        for (&(j, _), dst) in rows.iter().zip(buf.chunks_mut(width)) {
            seg.image_appearance(j).write_to(dst);
        }
        let mut sims = vec![0.0f32; queries.len() * rows.len()];
        crate::index::model::matmul_bt(&qv, queries.len(), width, &buf, rows.len(), &mut sims);
        for (q, l) in exact.iter_mut().enumerate() {
            for (k, &(_, i)) in rows.iter().enumerate() {
                if i as usize != queries[q] {
                    l.offer(sims[q * rows.len() + k], i);
                }
            }
        }
        for (q, p) in probes.iter().enumerate() {
            let own = queries[q] as u32;
            p.scan(&codes, rows.iter().copied().filter(|r| r.1 != own), &mut approx_lists[q]);
        }
        let bytes = codes.to_bytes(&map.manifest.segments[s].sha256, &model_sha)?;
        let name = codes_name(&map.manifest.segments[s].file, &model_sha, params.thumbnail);
        write_atomic(&staging.path, &name, &bytes)?;
        written.push((map.manifest.segments[s].file.clone(), FileEntry { file: name, bytes: bytes.len() as u64, sha256: sha256_hex(&bytes) }));
    }
    let mut hits = 0usize;
    let mut total = 0usize;
    for (ex, approx) in exact.into_iter().zip(approx_lists) {
        let truth: Vec<u32> = ex.into_sorted().into_iter().take(RECALL_AT).map(|x| x.1).collect();
        let got: HashSet<u32> = approx.into_sorted().into_iter().map(|x| x.1).collect();
        hits += truth.iter().filter(|i| got.contains(i)).count();
        total += truth.len();
    }
    drop(map);
    staged_hook();
    // the commit: segments committed since get their codes under the lock
    let _lock = WriteLock::take(dir)?;
    let mut m = manifest::read_existing(dir)?;
    let layout_now: Layout = layout_of(&m, ClassTable::from_config(&m.config.classes)?.len());
    debug_assert_eq!(layout_now, layout);
    let entry = IndexEntry { recall_hits: hits as u64, recall_of: total as u64, build_ms: t0.elapsed().as_millis() as u64, ..entry0 };
    let old_files = index_files(&m);
    let mut cache = Some((model_sha.clone(), model));
    let m_for_codes = Manifest { index: Some(entry.clone()), ..m.clone() };
    let mut count = 0;
    staging.adopt(dir, &entry.model.file)?;
    for s in 0..m.segments.len() {
        // codes staged for a segment still listed move in; a segment committed (or rewritten by
        // a compaction) since gets its codes here
        let file = match written.iter().find(|(seg, _)| *seg == m.segments[s].file) {
            Some((_, f)) => {
                staging.adopt(dir, &f.file)?;
                f.clone()
            }
            None => write_segment_codes(dir, &m_for_codes, &entry, &m.segments[s], layout_now, &mut cache)?,
        };
        m.segments[s].index = Some(file);
        count += 1;
    }
    super::files::sync_dir(dir);
    m.index = Some(entry.clone());
    m.generation += 1;
    manifest::write(dir, &m)?;
    delete_unreferenced(dir, &m, &old_files);
    Ok(IndexReport { entry, segments: count })
}

/// The folder an index build writes its files into before its commit (`.index-staging-PID-...`
/// in the map folder), removed when the build ends, committed or not.
struct Staging {
    path: std::path::PathBuf,
}

impl Staging {
    fn new(dir: &Path) -> Result<Staging> {
        let path = dir.join(format!("{}{}", super::files::INDEX_STAGING, super::files::unique_suffix()));
        std::fs::create_dir(&path).map_err(|e| Error::io(&path, e))?;
        Ok(Staging { path })
    }
    /// Moves staged file `name` into the map folder `dir` (under the lock).
    fn adopt(&self, dir: &Path, name: &str) -> Result<()> {
        let (from, to) = (self.path.join(name), dir.join(name));
        std::fs::rename(&from, &to).map_err(|e| Error::io(&to, e))
    }
}

impl Drop for Staging {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.path);
    }
}

/// A function [`build`] calls once its files are staged, before it takes the lock to commit
/// them (a test holds it there while other writers run).
type StagedHook = Box<dyn Fn() + Send + Sync>;
static STAGED_HOOK: std::sync::Mutex<Option<StagedHook>> = std::sync::Mutex::new(None);

/// Test hook: `hook` runs in every [`build`] of this process between staging its files and
/// taking the write lock for the commit (`None` removes it): a test holds a build there, runs a
/// compaction, a removal or an add, then lets it commit, with no timing involved.
#[doc(hidden)]
pub fn set_staged_hook(hook: Option<StagedHook>) {
    *STAGED_HOOK.lock().unwrap_or_else(|e| e.into_inner()) = hook;
}

fn staged_hook() {
    if let Some(h) = STAGED_HOOK.lock().unwrap_or_else(|e| e.into_inner()).as_ref() {
        h();
    }
}

/// Drops the map's index (one commit), deleting its files after.
pub fn drop_index(dir: &Path) -> Result<bool> {
    let _lock = WriteLock::take(dir)?;
    let mut m = manifest::read_existing(dir)?;
    if m.index.is_none() {
        return Ok(false);
    }
    let old = index_files(&m);
    m.index = None;
    m.segments.iter_mut().for_each(|s| s.index = None);
    m.generation += 1;
    manifest::write(dir, &m)?;
    delete_unreferenced(dir, &m, &old);
    Ok(true)
}
