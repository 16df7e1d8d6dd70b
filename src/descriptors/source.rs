//! Where matching reads reference descriptors from, tile by tile: a descriptor set in memory, a
//! stored (memory-mapped) map, or any other store (a synthetic map far larger than memory in the
//! benchmarks). Tiles are the unit of streaming: no stage ever needs the whole map at once.

use super::DescriptorSet;
use crate::descriptors::keypoints::KeypointsRef;
use crate::values::Values;
use semlook_kernels::tree_similarity::ForestRef;

/// Reusable storage for tiles that a source must assemble (copy or generate).
#[derive(Debug, Default)]
pub struct TileBuf {
    /// Global descriptors of an assembled tile.
    pub globals: Vec<f32>,
    /// SSIM statistics of an assembled tile.
    pub stats: Vec<f32>,
}

/// Global descriptors and SSIM statistics of a map, readable by tiles.
pub trait GlobalSource: Sync {
    /// Number of references.
    fn len(&self) -> usize;
    /// Whether the source holds no references.
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Descriptors and stats of references `start..end`, borrowed from the source or built in `buf`.
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]);
    /// Whether the source holds its references' SSIM statistics; a source that computes them for
    /// every tile (a stored map) says no, and a device computes them there instead
    /// ([`GlobalSource::globals_tile`] then the `ssim_stats` kernels).
    fn stores_stats(&self) -> bool {
        true
    }
    /// The descriptors of references `start..end` alone (no statistics computed).
    fn globals_tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> &'a [f32] {
        self.tile(start, end, buf).0
    }
    /// Whether everything read so far was sound. A stored map checks each segment's checksum and
    /// values the first time it is read; a segment that fails is served as empty (zeros, no
    /// trees) and reported here, naming its file. Matching calls this after reading.
    fn check(&self) -> crate::Result<()> {
        Ok(())
    }
    /// A number the source changes whenever its content changes, if it keeps one: with it, a
    /// device cache of the source is exact. Without it ([`None`], the default) caches go by
    /// [`SourceKey::of`]'s fingerprint. A stored map gives one for its identity and generation.
    fn generation(&self) -> Option<u64> {
        None
    }
    /// A number that stays the same while a source grows and shrinks as one lineage (a stored map
    /// across its generations: adds, removals, compactions; a rebuild is another): what may keep
    /// a statistic of the source that does not need to follow every commit (the null of
    /// `verified`, [`crate::matching::null`]). None (the default): the source's content alone.
    fn lineage(&self) -> Option<u64> {
        None
    }
    /// The null of `verified`'s evidence the source keeps (a stored map: the one measured at
    /// build, [`crate::descriptors::null::StoredNull`]), whatever config it was measured under
    /// (its `key` says). None (the default): matching measures one.
    fn stored_null(&self) -> Option<std::sync::Arc<crate::descriptors::null::NullEvidence>> {
        None
    }
}

/// References hashed into a [`SourceKey`]'s fingerprint (evenly spaced, first and last included):
/// 64 x 31.8 KB at the default size, about 2 MB, well under a millisecond per batch, against the
/// 32 GB a 1M-reference map would take to upload again.
pub const FINGERPRINT_SAMPLES: usize = 64;

/// Names the content of a source for caches on a device (a GPU executor keeps a map resident
/// while the key of the map it is given stays the same).
///
/// With a [`GlobalSource::generation`], the key is that number with the source's length and
/// sizes. Without one, it is the length and sizes, where the source's first tile lies in memory,
/// and a hash of [`FINGERPRINT_SAMPLES`] whole references (descriptor and stats bits). Another map,
/// a map grown or shrunk, a copy, or a map whose sampled references changed gets another key. An
/// edit in place of a reference that is not sampled keeps the key: code that edits a map's vectors
/// in place must call the executor's `forget_map` (or give the source a generation).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct SourceKey {
    /// Number of references.
    pub len: usize,
    /// The source's [`GlobalSource::generation`].
    pub generation: Option<u64>,
    /// Floats per descriptor and per stats record.
    pub sizes: (usize, usize),
    /// Address of the first reference's descriptor (0 for an empty source, and for a source with
    /// a generation, whose tiles may be assembled in a buffer that moves).
    pub address: usize,
    /// FNV-1a hash of the sampled references (its offset basis alone for a source with a generation).
    pub fingerprint: u64,
}

impl SourceKey {
    /// The key of `src`'s current content.
    pub fn of(src: &dyn GlobalSource) -> SourceKey {
        let n = src.len();
        let generation = src.generation();
        let mut buf = TileBuf::default();
        let (mut h, mut sizes, mut address) = (FNV_OFFSET, (0, 0), 0);
        if n > 0 {
            let (g, s) = src.tile(0, 1, &mut buf);
            sizes = (g.len(), s.len());
            if generation.is_none() {
                address = g.as_ptr() as usize;
            }
        }
        if generation.is_none() {
            let samples = FINGERPRINT_SAMPLES.min(n);
            for j in 0..samples {
                let i = if samples == 1 { 0 } else { j * (n - 1) / (samples - 1) };
                let (g, s) = src.tile(i, i + 1, &mut buf);
                h = fnv(fnv(fnv(h, &[i as u32]), bytemuck::cast_slice(g)), bytemuck::cast_slice(s));
            }
        }
        SourceKey { len: n, generation, sizes, address, fingerprint: h }
    }
}

const FNV_OFFSET: u64 = 0xcbf2_9ce4_8422_2325;

/// FNV-1a over 32-bit words.
fn fnv(mut h: u64, words: &[u32]) -> u64 {
    for &w in words {
        h = (h ^ w as u64).wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

impl GlobalSource for DescriptorSet {
    fn len(&self) -> usize {
        self.ids.len()
    }
    fn tile<'a>(&'a self, start: usize, end: usize, _buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        (&self.globals[start * self.global_len..end * self.global_len], &self.global_stats[start * self.stats_len..end * self.stats_len])
    }
}

/// Where a reference lies on the routes a map holds: its traversal (a run of frames in order:
/// one `map build`, or one `map add` of a new run) and its position along it (0, 1, ... in the
/// order the frames were added, removed images left out). Sequence matching walks positions and
/// never crosses from one traversal into another.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, serde::Serialize)]
pub struct Place {
    /// Traversal index.
    pub traversal: u32,
    /// Position along the traversal, from 0.
    pub position: u32,
}

/// Everything matching reads about references: tiles of global descriptors, and forests and ids
/// by index. Implemented by a [`DescriptorSet`] and by a stored [`crate::map::Map`]. Indices run
/// over the references a source serves (a map leaves out removed images), `0..len()`.
pub trait RefSource: GlobalSource {
    /// The frame id of reference i.
    fn id(&self, i: usize) -> &str;
    /// The forest of reference i.
    fn forest(&self, i: usize) -> ForestRef<'_>;
    /// Neighbour slots per tree.
    fn neighbour_slots(&self) -> usize;
    /// Values per appearance vector (0: no appearance).
    fn appearance_dim(&self) -> usize;
    /// The whole-image appearance vector of reference i (`appearance_dim` values).
    fn image_appearance(&self, i: usize) -> Values<'_>;
    /// Values of each reference's HOG descriptor (0: the source holds none).
    fn hog_dim(&self) -> usize;
    /// The HOG descriptor of reference i (`hog_dim` values).
    fn image_hog(&self, i: usize) -> &[f32];
    /// Values per whole-image embedding (0: the source holds none).
    fn embedding_dim(&self) -> usize {
        0
    }
    /// What made the embeddings (none: the source holds none, or does not say).
    fn embedding_record(&self) -> Option<&crate::descriptors::EmbeddingRecord> {
        None
    }
    /// The whole-image embedding of reference i (`embedding_dim` values).
    fn image_embedding(&self, _i: usize) -> Values<'_> {
        Values::EMPTY
    }
    /// Values per compact HOG (0: the source holds none; maps of small frames hold them).
    fn compact_hog_dim(&self) -> usize {
        0
    }
    /// The compact HOG of reference i (`compact_hog_dim` values).
    fn image_compact_hog(&self, _i: usize) -> Values<'_> {
        Values::EMPTY
    }
    /// Values per verification keypoint descriptor (0: the source stores no keypoints).
    fn keypoint_dim(&self) -> usize;
    /// The verification keypoints of reference i.
    fn keypoints(&self, i: usize) -> KeypointsRef<'_>;
    /// Whether the references were encoded with semantic labels. A map built from photos with
    /// neither label maps nor a segmenter says no: only the settings that need no labels
    /// ([`crate::matching::Setting::label_free`]) can be matched against it.
    fn labelled(&self) -> bool {
        true
    }
    /// Where reference `i` lies on the source's routes. A source that records no traversals (a
    /// descriptor set) is one traversal in index order.
    fn place(&self, i: usize) -> Place {
        Place { traversal: 0, position: i as u32 }
    }
    /// The reference at `p`, if the source has one there.
    fn at(&self, p: Place) -> Option<usize> {
        (p.traversal == 0 && (p.position as usize) < self.len()).then_some(p.position as usize)
    }
    /// References along traversal `t` (0 for a traversal the source does not hold).
    fn traversal_len(&self, t: u32) -> u32 {
        if t == 0 {
            self.len() as u32
        } else {
            0
        }
    }
    /// Whether the source has an approximate index of its appearance vectors
    /// ([`crate::index`]: a stored map built or extended with one).
    fn has_index(&self) -> bool {
        false
    }
    /// The index's shortlist for one query's whole-image appearance vector among the references
    /// of `range`: the `m` with the best approximate inner products among the `probe` lists
    /// nearest to it, best first; `None` where the source has no index.
    fn index_shortlist_in(&self, _query: &crate::index::IndexQuery, _range: std::ops::Range<usize>) -> Option<crate::Result<Vec<(f32, u32)>>> {
        None
    }
    /// [`RefSource::index_shortlist_in`] over every reference.
    fn index_shortlist(&self, query: &crate::index::IndexQuery) -> Option<crate::Result<Vec<(f32, u32)>>> {
        self.index_shortlist_in(query, 0..self.len())
    }
    /// References `rows` as a descriptor set of their own, to be matched as queries (the null of
    /// `verified`, [`crate::matching::null`]); a source that cannot says so.
    fn gather(&self, _rows: &[usize]) -> crate::Result<DescriptorSet> {
        Err(crate::Error::invalid("references", "this source cannot serve its references as queries"))
    }
}

impl RefSource for DescriptorSet {
    fn id(&self, i: usize) -> &str {
        &self.ids[i]
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        DescriptorSet::forest(self, i)
    }
    fn neighbour_slots(&self) -> usize {
        self.neighbour_slots
    }
    fn appearance_dim(&self) -> usize {
        self.appearance_dim
    }
    fn image_appearance(&self, i: usize) -> Values<'_> {
        Values::F32(DescriptorSet::image_appearance(self, i))
    }
    fn hog_dim(&self) -> usize {
        self.hog_dim
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        DescriptorSet::image_hog(self, i)
    }
    fn embedding_dim(&self) -> usize {
        self.embedding_dim
    }
    fn embedding_record(&self) -> Option<&crate::descriptors::EmbeddingRecord> {
        self.embedding.as_ref()
    }
    fn image_embedding(&self, i: usize) -> Values<'_> {
        Values::F32(DescriptorSet::image_embedding(self, i))
    }
    fn compact_hog_dim(&self) -> usize {
        self.compact_hog_dim
    }
    fn image_compact_hog(&self, i: usize) -> Values<'_> {
        Values::F32(DescriptorSet::image_compact_hog(self, i))
    }
    fn keypoint_dim(&self) -> usize {
        self.keypoint_dim
    }
    fn keypoints(&self, i: usize) -> KeypointsRef<'_> {
        DescriptorSet::keypoints(self, i)
    }
    fn gather(&self, rows: &[usize]) -> crate::Result<DescriptorSet> {
        let mut out = self.empty_like();
        for &r in rows {
            out.append_range(self, r, r + 1)?;
        }
        Ok(out)
    }
}

/// The references `start..start + len` of another source, as a source of their own (index `i`
/// here is `start + i` there): what a stream searches while it tracks a place, or in loop-closure
/// mode where the newest frames are left out. Places are the inner source's.
pub struct Window<'a> {
    inner: &'a dyn RefSource,
    start: usize,
    len: usize,
}

impl<'a> Window<'a> {
    /// The window `range` of `inner` (clipped to it).
    pub fn new(inner: &'a dyn RefSource, range: std::ops::Range<usize>) -> Window<'a> {
        let end = range.end.min(inner.len());
        let start = range.start.min(end);
        Window { inner, start, len: end - start }
    }
    /// Index in the inner source of reference `i` of the window.
    pub fn inner_index(&self, i: usize) -> usize {
        self.start + i
    }
}

impl GlobalSource for Window<'_> {
    fn len(&self) -> usize {
        self.len
    }
    fn tile<'b>(&'b self, start: usize, end: usize, buf: &'b mut TileBuf) -> (&'b [f32], &'b [f32]) {
        self.inner.tile(self.start + start, self.start + end, buf)
    }
    fn stores_stats(&self) -> bool {
        self.inner.stores_stats()
    }
    fn globals_tile<'b>(&'b self, start: usize, end: usize, buf: &'b mut TileBuf) -> &'b [f32] {
        self.inner.globals_tile(self.start + start, self.start + end, buf)
    }
    fn check(&self) -> crate::Result<()> {
        self.inner.check()
    }
    fn lineage(&self) -> Option<u64> {
        self.inner.lineage()
    }
    fn stored_null(&self) -> Option<std::sync::Arc<crate::descriptors::null::NullEvidence>> {
        self.inner.stored_null()
    }
    fn generation(&self) -> Option<u64> {
        let g = self.inner.generation()?;
        Some(fnv(g ^ FNV_OFFSET, &[self.start as u32, (self.start >> 32) as u32, self.len as u32, (self.len >> 32) as u32]))
    }
}

impl RefSource for Window<'_> {
    fn id(&self, i: usize) -> &str {
        self.inner.id(self.start + i)
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        self.inner.forest(self.start + i)
    }
    fn neighbour_slots(&self) -> usize {
        self.inner.neighbour_slots()
    }
    fn appearance_dim(&self) -> usize {
        self.inner.appearance_dim()
    }
    fn image_appearance(&self, i: usize) -> Values<'_> {
        self.inner.image_appearance(self.start + i)
    }
    fn hog_dim(&self) -> usize {
        self.inner.hog_dim()
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        self.inner.image_hog(self.start + i)
    }
    fn embedding_dim(&self) -> usize {
        self.inner.embedding_dim()
    }
    fn embedding_record(&self) -> Option<&crate::descriptors::EmbeddingRecord> {
        self.inner.embedding_record()
    }
    fn image_embedding(&self, i: usize) -> Values<'_> {
        self.inner.image_embedding(self.start + i)
    }
    fn compact_hog_dim(&self) -> usize {
        self.inner.compact_hog_dim()
    }
    fn image_compact_hog(&self, i: usize) -> Values<'_> {
        self.inner.image_compact_hog(self.start + i)
    }
    fn keypoint_dim(&self) -> usize {
        self.inner.keypoint_dim()
    }
    fn keypoints(&self, i: usize) -> KeypointsRef<'_> {
        self.inner.keypoints(self.start + i)
    }
    fn labelled(&self) -> bool {
        self.inner.labelled()
    }
    fn place(&self, i: usize) -> Place {
        self.inner.place(self.start + i)
    }
    fn at(&self, p: Place) -> Option<usize> {
        self.inner.at(p).filter(|i| (self.start..self.start + self.len).contains(i)).map(|i| i - self.start)
    }
    fn traversal_len(&self, t: u32) -> u32 {
        self.inner.traversal_len(t)
    }
    fn has_index(&self) -> bool {
        self.inner.has_index()
    }
    fn index_shortlist_in(&self, query: &crate::index::IndexQuery, range: std::ops::Range<usize>) -> Option<crate::Result<Vec<(f32, u32)>>> {
        let (a, b) = (self.start + range.start.min(self.len), self.start + range.end.min(self.len));
        let inner = self.inner.index_shortlist_in(query, a..b)?;
        Some(inner.map(|l| l.into_iter().map(|(s, i)| (s, i - self.start as u32)).collect()))
    }
    fn gather(&self, rows: &[usize]) -> crate::Result<DescriptorSet> {
        self.inner.gather(&rows.iter().map(|&r| self.start + r).collect::<Vec<_>>())
    }
}
