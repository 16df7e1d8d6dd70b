//! Stage 3: the map of places, stored so that it scales to millions of images and survives
//! crashes, concurrent writers and bad data. A map directory holds
//! - `manifest.json` ([`manifest`]): format version, generation, the encoding config, the storage
//!   layout, and per segment its file, image and tree counts, byte size, SHA-256 and removed rows;
//! - `segment-<hash>.safetensors` ([`segment`]): the descriptors of a run of images, named by
//!   the start of their SHA-256;
//! - `codebook.safetensors` with appearance; `.lock`, the writers' advisory lock.
//!
//! Reading: [`Map::open`] reads the manifest and maps every segment (memory-mapped, no copies),
//! checking headers, dtypes, shapes, alignment and sizes: its cost does not grow with the images
//! stored. Each segment's SHA-256 and values are checked the first time matching reads it (a
//! coarse pass reads every segment, so the first query of a process checks them all, each once);
//! `semlook map verify` checks all and names every damaged segment. Matching reads the map through
//! [`GlobalSource`] tiles (global descriptors borrowed from the mapping when f32 and contiguous, else
//! gathered and widened; SSIM statistics recomputed per tile) and [`RefSource`] look-ups (forests
//! borrowed from the mapping). Removed images are left out of the index space: reference `i` is
//! the i-th image that is not removed, so a top-K always holds K live images.
//!
//! Writing ([`writer`]): segments are written and committed one by one, each commit under the
//! directory's advisory lock (taken, manifest re-read, segment written, manifest replaced with the
//! next generation, released), so a crash loses at most the segment in progress, concurrent writers
//! both land, and readers see one whole generation or the next. Removal, compaction, verification
//! and `--force` replacement are in [`edit`].

pub mod edit;
pub mod files;
pub mod index;
pub mod index_files;
pub mod manifest;
pub mod segment;
pub mod shard;
pub mod writer;

pub use crate::descriptors::EmbeddingRecord;
pub use manifest::{Manifest, SegmentEntry, FORMAT, VERSION};
pub use writer::{ColumnDims, MapWriter, StoreOptions, TraversalPlan};

use crate::classes::ClassTable;
use crate::config::{first_difference, EncodingConfig};
use crate::descriptors::keypoints::KeypointsRef;
use crate::descriptors::source::{GlobalSource, Place, RefSource, TileBuf};
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Result};
use crate::global::vlad::Codebook;
use crate::values::Values;
use rayon::prelude::*;
use segment::{Layout, Mapped};
use semlook_kernels::abi::SsimParams;
use semlook_kernels::tree_similarity::ForestRef;
use std::path::{Path, PathBuf};

/// How often [`Map::open`] re-reads the manifest when a segment it lists has vanished: compaction
/// deletes replaced segments right after committing, so a reader that read the manifest just
/// before may find one gone, and the next manifest is complete. More than a few in a row means
/// the map is being compacted in a loop, or a file was deleted by hand.
const OPEN_ATTEMPTS: usize = 5;

/// An open map: its manifest and its memory-mapped segments.
#[derive(Debug)]
pub struct Map {
    /// The map directory.
    pub path: PathBuf,
    /// The manifest of the generation opened.
    pub manifest: Manifest,
    segments: Vec<Mapped>,
    /// Index of the first live image of each segment, then the live total.
    starts: Vec<usize>,
    /// Per segment with removed images: its live rows, ascending.
    live: Vec<Option<Vec<u32>>>,
    codebook: Option<Codebook>,
    ssim: SsimParams,
    routes: Routes,
    /// The approximate index of the coarse stage, when the map has one.
    index: Option<index_files::MapIndex>,
    /// The null of `verified`'s evidence measured at build, when the manifest keeps one.
    null: Option<std::sync::Arc<crate::descriptors::null::NullEvidence>>,
}

/// The traversals of a map's live images: each segment's first position along its traversal, and
/// per traversal its segments in order and its length.
#[derive(Debug, Default)]
struct Routes {
    first_position: Vec<u32>,
    segments: Vec<Vec<usize>>,
    lens: Vec<u32>,
}

impl Routes {
    fn of(m: &Manifest) -> Routes {
        let n = manifest::traversal_names(m).len();
        let mut r = Routes { first_position: Vec::with_capacity(m.segments.len()), segments: vec![vec![]; n], lens: vec![0; n] };
        for (s, e) in m.segments.iter().enumerate() {
            let t = e.traversal as usize;
            r.first_position.push(r.lens[t]);
            r.segments[t].push(s);
            r.lens[t] += e.live() as u32;
        }
        r
    }
}

impl Map {
    /// Opens the map in `dir`: the manifest, the codebook (small, checked in full) and a mapping
    /// of every segment with its header checked. Checksums and values are checked on first use.
    pub fn open(dir: &Path) -> Result<Map> {
        with_current_manifest(dir, |m| Map::open_generation(dir, m))
    }

    /// [`Map::open`] where `dir` holds a map's manifest; `None` where it holds none (a new
    /// folder, or a first build not yet committed).
    pub fn open_if_exists(dir: &Path) -> Result<Option<Map>> {
        match dir.join(manifest::MANIFEST).exists() {
            true => Map::open(dir).map(Some),
            false => Ok(None),
        }
    }

    pub(crate) fn open_generation(dir: &Path, manifest: Manifest) -> Result<Map> {
        let cfg = &manifest.config;
        let table = ClassTable::from_config(&cfg.classes)?;
        let codebook = match &manifest.codebook {
            Some(entry) => Some(read_codebook(dir, entry, manifest.appearance_dim)?),
            None => None,
        };
        let layout = layout_of(&manifest, table.len());
        let mut map = Map {
            path: dir.into(),
            segments: vec![],
            starts: vec![0],
            live: vec![],
            codebook,
            ssim: cfg.global.ssim_params(),
            routes: Routes::of(&manifest),
            index: index_files::MapIndex::open(dir, &manifest)?,
            null: manifest.null.as_ref().map(|n| std::sync::Arc::new(n.evidence.clone())),
            manifest: manifest.clone(),
        };
        for entry in &manifest.segments {
            map.segments.push(Mapped::open(dir, entry, layout)?);
            let live = (!entry.removed.is_empty()).then(|| (0..entry.images).filter(|&j| entry.is_live(j)).map(|j| j as u32).collect());
            map.live.push(live);
            map.starts.push(map.len() + entry.live());
        }
        Ok(map)
    }

    /// The configuration queries of this map are encoded and matched with when none is given:
    /// the map's encoding (appearance network included) and default matching parameters.
    pub fn query_config(&self) -> crate::config::Config {
        manifest::query_config(&self.manifest)
    }

    /// The VLAD codebook of the map's appearance vectors.
    pub fn codebook(&self) -> Option<&Codebook> {
        self.codebook.as_ref()
    }
    /// Images the map serves (removed ones left out).
    pub fn len(&self) -> usize {
        self.starts.last().copied().unwrap_or(0)
    }
    /// Whether the map serves no images.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Trees stored, removed images' included.
    pub fn n_trees(&self) -> usize {
        self.manifest.segments.iter().map(|s| s.trees).sum()
    }
    /// The mapped segment files, in manifest order.
    pub fn segments(&self) -> &[Mapped] {
        &self.segments
    }
    /// Sizes of the map's columns.
    pub fn layout(&self) -> Layout {
        self.segments.first().map_or_else(|| layout_of(&self.manifest, 0), |s| s.layout)
    }
    /// (segment, row in its file) of live image `i`.
    pub fn locate(&self, i: usize) -> (usize, usize) {
        let s = self.starts.partition_point(|&st| st <= i) - 1;
        let j = i - self.starts[s];
        (s, self.live[s].as_ref().map_or(j, |rows| rows[j] as usize))
    }
    /// The pose stored with live image `i` (`map build` from a dataset with poses, or with
    /// `--poses`); none where it has none or its segment failed its checks.
    pub fn pose(&self, i: usize) -> Option<crate::descriptors::PlacePose> {
        let (s, j) = self.locate(i);
        self.sound(s)?.pose(j)
    }
    /// Seconds between consecutive frames of traversal `t`, where the map was given its images'
    /// timestamps ([`manifest::Manifest::frame_intervals`]).
    pub fn frame_interval(&self, t: u32) -> Option<f64> {
        self.manifest.frame_intervals.get(&t).copied()
    }
    /// Live images with a pose, and of those with an orientation (reads every pose row of the
    /// segments that store poses; `map info`).
    pub fn pose_counts(&self) -> (usize, usize) {
        let (mut with, mut oriented) = (0, 0);
        for (s, seg) in self.segments.iter().enumerate().filter(|(_, g)| g.has_poses()) {
            for j in self.live_rows(s) {
                if let Some(p) = seg.pose(j) {
                    with += 1;
                    oriented += usize::from(p.orientation.is_some());
                }
            }
        }
        (with, oriented)
    }
    /// Rows of segment `s` that are not removed.
    pub fn live_rows(&self, s: usize) -> Box<dyn Iterator<Item = usize> + '_> {
        match &self.live[s] {
            Some(rows) => Box::new(rows.iter().map(|&r| r as usize)),
            None => Box::new(0..self.segments[s].len()),
        }
    }

    /// Checks every segment not checked yet (in parallel), each once per process; the result of
    /// every segment, in manifest order (a damaged one's an [`Error::CorruptMap`] naming its file).
    pub fn verify_all(&self) -> Vec<(&Path, Result<()>)> {
        self.segments.par_iter().map(|s| (s.path.as_path(), s.ensure())).collect()
    }
    /// [`Map::verify_all`], failing with the first damaged segment.
    pub fn check_all(&self) -> Result<()> {
        self.verify_all().into_iter().try_for_each(|(_, r)| r)
    }

    /// The map's newest generation in the same folder ([`Map::open`]) with the checks of this one
    /// taken over ([`Map::inherit_checks`]): a stream that commits to a large map every few frames
    /// moves to each new generation checking only the files the commit added.
    pub fn reopen(&self) -> Result<Map> {
        let new = Map::open(&self.path)?;
        new.inherit_checks(self);
        Ok(new)
    }

    /// Takes over the checks `prev` ran (or found failing) of the segment and index files this
    /// map shares with it: the same path, checksum and size in a generation of the same map
    /// (its uid; a rebuild makes a new one), whose files never change once in place.
    pub fn inherit_checks(&self, prev: &Map) {
        if prev.manifest.uid != self.manifest.uid || prev.path != self.path {
            return;
        }
        let old: std::collections::HashMap<&Path, &Mapped> = prev.segments.iter().map(|s| (s.path.as_path(), s)).collect();
        for seg in &self.segments {
            if let Some(p) = old.get(seg.path.as_path()) {
                seg.inherit(p);
            }
        }
        if let (Some(ix), Some(pix)) = (&self.index, &prev.index) {
            let old: std::collections::HashMap<&Path, &crate::index::MappedCodes> = pix.codes.iter().map(|c| (c.path.as_path(), c)).collect();
            for c in &ix.codes {
                if let Some(p) = old.get(c.path.as_path()) {
                    c.inherit(p);
                }
            }
        }
    }

    /// Files (segments, index codes) whose checks have not run in this process: 0 after
    /// [`Map::prepare`] with the index.
    pub fn unchecked(&self) -> usize {
        self.segments.iter().filter(|s| !s.checked()).count() + self.index.as_ref().map_or(0, |ix| ix.unchecked())
    }

    /// Runs now, in parallel, the checks a map otherwise runs where a search first reads a file:
    /// every segment's checksum and values and, with `index` (a search that will read the index:
    /// [`crate::matching::searches_index`]), the index's codes, whose rows it also groups by list;
    /// what [`Map::inherit_checks`] took over is not run again. A stream does this before its
    /// first frame, which is then answered at the stream's pace (at 100,000 places the checks
    /// took 3-6 s), and a damaged map is refused before the stream starts rather than at its first
    /// frame. Fails with the first damaged file in manifest order, segments before the index
    /// ([`Error::CorruptMap`], [`Error::DamagedIndex`]).
    pub fn prepare(&self, index: bool) -> Result<()> {
        self.check_all()?;
        match (&self.index, index) {
            (Some(ix), true) => ix.prepare(),
            _ => Ok(()),
        }
    }

    /// All live images in one set, SSIM statistics recomputed (one allocation of the whole map:
    /// for small maps, export and tests). Checks every segment first.
    pub fn to_descriptor_set(&self) -> Result<DescriptorSet> {
        self.check_all()?;
        let rows = (0..self.segments.len()).flat_map(|s| self.live_rows(s).map(move |j| (s, j)));
        Ok(self.set_of(rows))
    }

    /// The images at (segment, row) `rows` in one set, SSIM statistics recomputed; the caller
    /// has checked their segments.
    fn set_of(&self, rows: impl Iterator<Item = (usize, usize)>) -> DescriptorSet {
        let l = self.layout();
        let mut set = DescriptorSet::for_storage(l.global_len(), l.slots, l.dim, l.hog)
            .with_keypoint_dim(l.kdim)
            .with_embedding(self.manifest.embedding.clone())
            .with_compact_hog_dim(l.chog)
            .with_codebook(self.manifest.codebook.as_ref().map(|c| c.sha256.clone()));
        for (s, j) in rows {
            self.segments[s].append_row(j, &mut set);
        }
        set.stats_len = self.ssim.stats_len();
        set.global_stats = vec![0.0; set.len() * set.stats_len];
        compute_stats(&self.ssim, &set.globals, &mut set.global_stats);
        set
    }

    /// Fails naming the difference if images encoded with `model_sha256` (the keypoint network's
    /// checksum, or none without appearance) cannot be matched against this map.
    pub fn check_model(&self, model_sha256: Option<&str>) -> Result<()> {
        if self.manifest.appearance_model.as_deref() != model_sha256 {
            // in full: two hashes may share any prefix
            let show = |v: Option<&str>| v.map_or("none".to_string(), |s| format!("sha256 {s}"));
            return Err(Error::IncompatibleConfig {
                map: self.path.clone(),
                field: "appearance keypoint network".into(),
                map_value: show(self.manifest.appearance_model.as_deref()),
                given_value: show(model_sha256),
            });
        }
        Ok(())
    }

    /// Fails with the first differing field if queries encoded with `cfg` cannot be matched here.
    pub fn check_compatible(&self, cfg: &EncodingConfig) -> Result<()> {
        match first_difference(&self.manifest.config, cfg) {
            None => Ok(()),
            Some((field, map_value, given_value)) => Err(Error::IncompatibleConfig { map: self.path.clone(), field, map_value, given_value }),
        }
    }

    /// Segment `s`, or `None` when it failed its checks (then served as empty).
    fn sound(&self, s: usize) -> Option<&Mapped> {
        let seg = &self.segments[s];
        seg.ensure().is_ok().then_some(seg)
    }
}

/// The segment layout a manifest describes.
pub(crate) fn layout_of(m: &Manifest, n_classes: usize) -> Layout {
    let g = &m.config.global;
    Layout {
        gw: g.width,
        gh: g.height,
        slots: m.neighbour_slots,
        dim: m.appearance_dim,
        hog: m.hog_dim,
        kdim: m.keypoint_dim,
        emb: m.embedding.as_ref().map_or(0, |e| e.dim),
        chog: m.compact_hog_dim,
        block: m.appearance_block,
        values: m.values,
        n_classes,
    }
}

/// SSIM statistics of every descriptor in `globals` into `stats` (in parallel).
impl Map {
    /// The descriptors of references `start..end`: borrowed from the segment when they lie in one
    /// sound segment with nothing removed, else copied into `globals` (zeros for a damaged segment,
    /// which `check` reports).
    fn read_globals<'a>(&'a self, start: usize, end: usize, globals: &'a mut Vec<f32>) -> &'a [f32] {
        let (glen, n) = (self.ssim.len(), end - start);
        let (s0, j0) = self.locate(start);
        let s1 = self.locate(end - 1).0;
        let sound = (s0..=s1).all(|s| self.sound(s).is_some());
        let borrowed = match sound && s0 == s1 && self.live[s0].is_none() {
            true => self.segments[s0].globals(j0, j0 + n).as_f32(),
            false => None,
        };
        match borrowed {
            Some(g) => g,
            None => {
                globals.clear();
                globals.resize(n * glen, 0.0);
                if sound {
                    let rows: Vec<(usize, usize)> = (start..end).map(|i| self.locate(i)).collect();
                    globals.par_chunks_mut(glen).zip(rows.par_iter()).for_each(|(dst, &(s, j))| self.segments[s].globals(j, j + 1).write_to(dst));
                }
                globals
            }
        }
    }
}

fn compute_stats(p: &SsimParams, globals: &[f32], stats: &mut [f32]) {
    crate::global::ssim_fast::ssim_stats_batch(p, globals, stats);
}

/// Runs `read` on the current manifest of `dir`, again on the next one when a segment it lists
/// (or an index file it lists) was deleted meanwhile (a compaction committed between the two
/// reads); a file missing twice from the same generation is an error.
pub(crate) fn with_current_manifest<T>(dir: &Path, mut read: impl FnMut(Manifest) -> Result<T>) -> Result<T> {
    let mut last_generation = None;
    for _ in 0..OPEN_ATTEMPTS {
        let m = manifest::read_existing(dir)?;
        let generation = m.generation;
        match read(m) {
            Err(e) if e.is_missing_file() && last_generation != Some(generation) => {
                last_generation = Some(generation);
            }
            other => return other,
        }
    }
    Err(Error::corrupt(
        dir,
        format!("segments listed by the manifest kept disappearing over {OPEN_ATTEMPTS} reads (deleted by hand, or compacted without pause)"),
    ))
}

/// Reads and checks the codebook file (small: read and hashed in full at open).
fn read_codebook(dir: &Path, entry: &manifest::FileEntry, appearance_dim: usize) -> Result<Codebook> {
    let p = dir.join(&entry.file);
    let bytes = std::fs::read(&p).map_err(|e| Error::io(&p, e))?;
    if bytes.len() as u64 != entry.bytes || crate::util::sha256_hex(&bytes) != entry.sha256 {
        return Err(Error::corrupt(&p, "size or SHA-256 differs from the manifest"));
    }
    let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| Error::corrupt(&p, e.to_string()))?;
    let t = st.tensor("centres").map_err(|_| Error::corrupt(&p, "no centres tensor"))?;
    let shape = t.shape().to_vec();
    if t.dtype() != safetensors::tensor::Dtype::F32 || shape.len() != 2 || shape[0] * shape[1] != appearance_dim || shape[0] == 0 || shape[1] == 0 {
        return Err(Error::corrupt(&p, format!("centres are {:?} {shape:?}; the map's appearance vectors have {appearance_dim} values", t.dtype())));
    }
    let centres: Vec<f32> = bytemuck::pod_collect_to_vec(t.data());
    if centres.iter().any(|v| !v.is_finite()) {
        return Err(Error::corrupt(&p, "centres hold NaN or infinity"));
    }
    Ok(Codebook { k: shape[0], dim: shape[1], centres })
}

impl GlobalSource for Map {
    fn len(&self) -> usize {
        Map::len(self)
    }
    /// Global descriptors borrowed from the mapping when the tile lies in one f32 segment without
    /// removed images, else gathered (and widened from f16) into `buf`; SSIM statistics computed
    /// into `buf`. A segment that fails its first-use check gives zeros (see [`GlobalSource::check`]).
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        let TileBuf { globals, stats } = buf;
        let g = self.read_globals(start, end, globals);
        stats.resize((end - start) * self.ssim.stats_len(), 0.0);
        compute_stats(&self.ssim, g, stats);
        (g, stats)
    }
    fn stores_stats(&self) -> bool {
        false
    }
    fn globals_tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> &'a [f32] {
        self.read_globals(start, end, &mut buf.globals)
    }
    /// The map's identity (random at creation) with the generation it was opened at: an open map
    /// never changes, and any commit (add, remove, compact, a rebuild) makes a new generation or
    /// a new map, so a device cache keyed by it is exact.
    fn generation(&self) -> Option<u64> {
        use std::hash::{Hash, Hasher};
        let mut h = std::hash::DefaultHasher::new();
        (&self.manifest.uid, self.manifest.generation).hash(&mut h);
        Some(h.finish())
    }
    /// The map's identity (random at creation), whatever its generation.
    fn lineage(&self) -> Option<u64> {
        use std::hash::{Hash, Hasher};
        let mut h = std::hash::DefaultHasher::new();
        self.manifest.uid.hash(&mut h);
        Some(h.finish())
    }
    fn stored_null(&self) -> Option<std::sync::Arc<crate::descriptors::null::NullEvidence>> {
        self.null.clone()
    }
    fn check(&self) -> Result<()> {
        match self.segments.iter().find_map(|s| s.failure().map(|r| (s, r))) {
            Some((s, reason)) => Err(Error::corrupt(&s.path, reason)),
            None => Ok(()),
        }
    }
}

impl RefSource for Map {
    fn id(&self, i: usize) -> &str {
        let (s, j) = self.locate(i);
        self.sound(s).map_or("", |seg| seg.id(j))
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        let (s, j) = self.locate(i);
        match self.sound(s) {
            Some(seg) => seg.forest(j),
            None => {
                let l = self.layout();
                ForestRef {
                    classes: &[],
                    areas: &[],
                    centroids: &[],
                    neighbours: &[],
                    neighbour_slots: l.slots,
                    appearance: Values::EMPTY,
                    has_appearance: &[],
                    descriptors: &[],
                    dim: l.dim,
                }
            }
        }
    }
    fn neighbour_slots(&self) -> usize {
        self.manifest.neighbour_slots
    }
    fn appearance_dim(&self) -> usize {
        self.manifest.appearance_dim
    }
    fn image_appearance(&self, i: usize) -> Values<'_> {
        let (s, j) = self.locate(i);
        self.sound(s).map_or(Values::EMPTY, |seg| seg.image_appearance(j))
    }
    fn hog_dim(&self) -> usize {
        self.manifest.hog_dim
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        let (s, j) = self.locate(i);
        self.sound(s).map_or(&[], |seg| seg.image_hog(j))
    }
    fn keypoint_dim(&self) -> usize {
        self.manifest.keypoint_dim
    }
    fn embedding_dim(&self) -> usize {
        self.layout().emb
    }
    fn embedding_record(&self) -> Option<&crate::descriptors::EmbeddingRecord> {
        self.manifest.embedding.as_ref()
    }
    fn image_embedding(&self, i: usize) -> Values<'_> {
        let (s, j) = self.locate(i);
        self.sound(s).map_or(Values::EMPTY, |seg| seg.image_embedding(j))
    }
    fn compact_hog_dim(&self) -> usize {
        self.manifest.compact_hog_dim
    }
    fn image_compact_hog(&self, i: usize) -> Values<'_> {
        let (s, j) = self.locate(i);
        self.sound(s).map_or(Values::EMPTY, |seg| seg.image_compact_hog(j))
    }
    fn keypoints(&self, i: usize) -> KeypointsRef<'_> {
        let (s, j) = self.locate(i);
        self.sound(s).map_or(KeypointsRef::EMPTY, |seg| seg.keypoints(j))
    }
    fn labelled(&self) -> bool {
        !self.manifest.without_labels
    }
    fn place(&self, i: usize) -> Place {
        let s = self.starts.partition_point(|&st| st <= i) - 1;
        Place { traversal: self.manifest.segments[s].traversal, position: self.routes.first_position[s] + (i - self.starts[s]) as u32 }
    }
    fn at(&self, p: Place) -> Option<usize> {
        let segs = self.routes.segments.get(p.traversal as usize)?;
        let k = segs.partition_point(|&s| self.routes.first_position[s] <= p.position).checked_sub(1)?;
        let s = segs[k];
        let j = (p.position - self.routes.first_position[s]) as usize;
        (j < self.manifest.segments[s].live()).then(|| self.starts[s] + j)
    }
    fn traversal_len(&self, t: u32) -> u32 {
        self.routes.lens.get(t as usize).copied().unwrap_or(0)
    }
    fn has_index(&self) -> bool {
        self.index.is_some()
    }
    fn index_shortlist_in(&self, query: &crate::index::IndexQuery, range: std::ops::Range<usize>) -> Option<Result<Vec<(f32, u32)>>> {
        self.index.as_ref()?;
        Some(Map::index_shortlist(self, query, range))
    }
    /// Checks the segments the rows lie in first.
    fn gather(&self, rows: &[usize]) -> Result<DescriptorSet> {
        let at: Vec<(usize, usize)> = rows.iter().map(|&i| self.locate(i)).collect();
        for &(s, _) in &at {
            self.segments[s].ensure()?;
        }
        Ok(self.set_of(at.into_iter()))
    }
}
