//! One segment file: the descriptors of up to a few thousand images as safetensors (readable from
//! Python with `safetensors.numpy.load_file`), read through a memory map without copying.
//!
//! Tensors (n images, t trees, f = f32 or f16 as the manifest says): `global` `[n, gh, gw]` f,
//! `image_size` `[n, 2]` u32, `forest_offsets` `[n + 1]` u32, `tree_class` `[t]` u8, `tree_area` `[t]` f32,
//! `tree_centroid` `[t, 2]` f32, `tree_neighbours` `[t, slots]` i32, `tree_has_appearance` `[t]` u8,
//! `tree_descriptors` `[t]` u32, the trees' and the images' appearance vectors as their non-zero
//! blocks of int8 values (`values::Blocks`; VLAD: one block per centre) in `tree_block_offsets`
//! `[t + 1]` u32, `tree_block_ids` `[bt]` u8, `tree_block_exponents` `[bt]` i8, `tree_block_values`
//! `[bt, block]` i8 and `image_block_*` likewise over the n images,
//! `image_hog` `[n, hog]` f32, the ids as UTF-8 bytes `id_bytes` `[b]` u8 with `id_offsets`
//! `[n + 1]` u32, and the verification keypoints (p of them): `keypoint_offsets` `[n + 1]` u32,
//! `keypoint_descriptors` `[p, kdim]` i8, `keypoint_xy` `[p, 2]` u16, `keypoint_class` `[p]` u8, and,
//! only in segments where some image has a pose, `place_pose` `[n, 7]` f64 (`x y z qx qy qz qw`, NaN
//! where there is none: [`PlacePose::to_row`]; segments without it, older ones among them, hold no
//! poses), only in maps with whole-image embeddings `image_embedding` `[n, emb]` f16, and only in
//! maps of small frames compact HOGs `image_compact_hog` `[n, chog]` f16. SSIM
//! statistics are not stored: readers recompute them per tile.
//!
//! Opening checks the header: every tensor's dtype, shape, and alignment (safetensors writers sort
//! tensors by element size and pad the header to 8 bytes, so each tensor starts at a multiple of
//! its element size; a file that breaks this is refused rather than copied), and the file size. The
//! SHA-256 and the values are checked on first use ([`Mapped::ensure`]).

use super::manifest::SegmentEntry;
use crate::descriptors::keypoints::KeypointsRef;
use crate::descriptors::{validate, DescriptorSet, PlacePose};
use crate::error::{Error, Result};
use crate::values::{to_f16_bits, ValueType, Values};
use memmap2::Mmap;
use safetensors::tensor::{Dtype, TensorView};
use semlook_kernels::tree_similarity::ForestRef;
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// What every segment of a map shares: sizes from the manifest.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Layout {
    /// Global descriptor width (`global.width`).
    pub gw: usize,
    /// Global descriptor height (`global.height`).
    pub gh: usize,
    /// Neighbour slots per tree.
    pub slots: usize,
    /// Values per appearance vector (0: no appearance).
    pub dim: usize,
    /// Values per image HOG descriptor (0: none stored).
    pub hog: usize,
    /// Values per verification keypoint descriptor (0: none stored).
    pub kdim: usize,
    /// Values per whole-image embedding (0: none stored).
    pub emb: usize,
    /// Values per compact HOG (0: none stored; maps of small frames store them).
    pub chog: usize,
    /// Values per stored appearance block (the keypoint network's descriptor width; 0 without
    /// appearance).
    pub block: usize,
    /// How global descriptors and appearance vectors are stored.
    pub values: ValueType,
    /// Classes of the map's class table (stored class ids lie below it).
    pub n_classes: usize,
}

impl Layout {
    /// Values per global descriptor.
    pub fn global_len(&self) -> usize {
        self.gw * self.gh
    }
    /// Bytes of one image without its trees, at most (every appearance block stored).
    pub fn image_bytes(&self) -> usize {
        self.global_len() * self.values.bytes() + self.appearance_bytes() + self.hog * 4 + self.emb * 2 + self.chog * 2 + 2 * 4 + 2 * 4 + 4
    }
    /// Bytes of one tree, at most.
    pub fn tree_bytes(&self) -> usize {
        1 + 4 + 8 + 4 * self.slots + self.appearance_bytes() + 1 + 4 + 4
    }
    /// Bytes of one appearance vector with every block stored.
    fn appearance_bytes(&self) -> usize {
        match self.block {
            0 => 0,
            b => self.dim / b * (b + 2),
        }
    }
    /// Bytes of one verification keypoint.
    pub fn keypoint_bytes(&self) -> usize {
        self.kdim + 4 + 1
    }
    /// An empty set of this layout without SSIM statistics: the buffer of a segment being written.
    pub fn storage_set(&self) -> DescriptorSet {
        DescriptorSet::for_storage(self.global_len(), self.slots, self.dim, self.hog)
            .with_keypoint_dim(self.kdim)
            .with_embedding_dim(self.emb)
            .with_compact_hog_dim(self.chog)
    }
}

/// Serialises a set (its rows must hold `layout.global_len()` global values) to segment bytes;
/// fails naming the tensor whose data does not fill its shape (a set whose columns disagree).
pub fn to_bytes(set: &DescriptorSet, layout: &Layout) -> Result<Vec<u8>> {
    let (n, t, dim) = (set.len(), set.n_trees(), layout.dim);
    let sizes: Vec<u32> = set.sizes.iter().flatten().copied().collect();
    let mut id_bytes = Vec::new();
    let mut id_offsets = vec![0u32];
    for id in &set.ids {
        id_bytes.extend_from_slice(id.as_bytes());
        id_offsets.push(id_bytes.len() as u32);
    }
    let (fdt, narrow) = match layout.values {
        ValueType::F32 => (Dtype::F32, None),
        ValueType::F16 => (Dtype::F16, Some(to_f16_bits(&set.globals))),
    };
    let g: &[u8] = match &narrow {
        None => bytemuck::cast_slice(&set.globals),
        Some(g) => bytemuck::cast_slice(g),
    };
    let b = layout.block;
    let (to, ti, te, tv) = crate::values::to_blocks(&set.tree_appearance, dim, b, 0);
    let (io, ii, ie, iv) = crate::values::to_blocks(&set.image_appearance, dim, b, 0);
    // without appearance: no vectors, but one offset per tree and image
    let (to, io) = if dim == 0 { (vec![0u32; t + 1], vec![0u32; n + 1]) } else { (to, io) };
    let p = set.n_keypoints();
    // poses only where some image has one, so maps without poses keep the bytes of before
    let poses: Vec<f64> =
        if set.poses.iter().any(Option::is_some) { set.poses.iter().flat_map(|q| q.map_or([f64::NAN; 7], |q| q.to_row())).collect() } else { vec![] };
    let mut parts: Vec<(&str, Dtype, Vec<usize>, &[u8])> = vec![
        ("global", fdt, vec![n, layout.gh, layout.gw], g),
        ("image_size", Dtype::U32, vec![n, 2], bytemuck::cast_slice(&sizes)),
        ("forest_offsets", Dtype::U32, vec![n + 1], bytemuck::cast_slice(&set.forest_offsets)),
        ("tree_class", Dtype::U8, vec![t], &set.tree_classes),
        ("tree_area", Dtype::F32, vec![t], bytemuck::cast_slice(&set.tree_areas)),
        ("tree_centroid", Dtype::F32, vec![t, 2], bytemuck::cast_slice(&set.tree_centroids)),
        ("tree_neighbours", Dtype::I32, vec![t, layout.slots], bytemuck::cast_slice(&set.tree_neighbours)),
        ("tree_has_appearance", Dtype::U8, vec![t], &set.tree_has_appearance),
        ("tree_descriptors", Dtype::U32, vec![t], bytemuck::cast_slice(&set.tree_descriptors)),
        ("tree_block_offsets", Dtype::U32, vec![t + 1], bytemuck::cast_slice(&to)),
        ("tree_block_ids", Dtype::U8, vec![ti.len()], &ti),
        ("tree_block_exponents", Dtype::I8, vec![te.len()], bytemuck::cast_slice(&te)),
        ("tree_block_values", Dtype::I8, vec![te.len(), b], bytemuck::cast_slice(&tv)),
        ("image_block_offsets", Dtype::U32, vec![n + 1], bytemuck::cast_slice(&io)),
        ("image_block_ids", Dtype::U8, vec![ii.len()], &ii),
        ("image_block_exponents", Dtype::I8, vec![ie.len()], bytemuck::cast_slice(&ie)),
        ("image_block_values", Dtype::I8, vec![ie.len(), b], bytemuck::cast_slice(&iv)),
        ("image_hog", Dtype::F32, vec![n, layout.hog], bytemuck::cast_slice(&set.image_hog)),
        ("id_bytes", Dtype::U8, vec![id_bytes.len()], &id_bytes),
        ("id_offsets", Dtype::U32, vec![n + 1], bytemuck::cast_slice(&id_offsets)),
        ("keypoint_offsets", Dtype::U32, vec![n + 1], bytemuck::cast_slice(&set.keypoint_offsets)),
        ("keypoint_descriptors", Dtype::I8, vec![p, layout.kdim], bytemuck::cast_slice(&set.keypoint_descriptors)),
        ("keypoint_xy", Dtype::U16, vec![p, 2], bytemuck::cast_slice(&set.keypoint_xy)),
        ("keypoint_class", Dtype::U8, vec![p], &set.keypoint_classes),
    ];
    if !poses.is_empty() {
        parts.push(("place_pose", Dtype::F64, vec![n, 7], bytemuck::cast_slice(&poses)));
    }
    // embeddings (f16) only in maps that have them, so maps without keep the bytes of before
    let embedding = to_f16_bits(&set.image_embedding);
    if layout.emb > 0 {
        parts.push(("image_embedding", Dtype::F16, vec![n, layout.emb], bytemuck::cast_slice(&embedding)));
    }
    // compact HOGs (f16) only in maps of small frames
    let compact_hog = to_f16_bits(&set.image_compact_hog);
    if layout.chog > 0 {
        parts.push(("image_compact_hog", Dtype::F16, vec![n, layout.chog], bytemuck::cast_slice(&compact_hog)));
    }
    let tensors = parts
        .into_iter()
        .map(|(name, dtype, shape, bytes)| {
            TensorView::new(dtype, shape, bytes).map(|v| (name, v)).map_err(|e| Error::check(format!("tensor {name:?}: {e}")))
        })
        .collect::<Result<Vec<_>>>()?;
    let meta = std::collections::HashMap::from([("format".to_string(), "semlook-map-segment 4".to_string())]);
    safetensors::serialize(tensors, Some(meta)).map_err(|e| Error::check(format!("segment does not serialise: {e}")))
}

/// A set as a segment file: its bytes and its manifest entry (named by the start of its SHA-256).
pub fn encode(set: &DescriptorSet, layout: &Layout) -> Result<(Vec<u8>, SegmentEntry)> {
    let bytes = to_bytes(set, layout)?;
    let sha = crate::util::sha256_hex(&bytes);
    let entry = SegmentEntry {
        file: format!("segment-{}.safetensors", &sha[..16]),
        images: set.len(),
        trees: set.n_trees(),
        keypoints: set.n_keypoints(),
        bytes: bytes.len() as u64,
        sha256: sha,
        removed: vec![],
        traversal: 0,
        index: None,
    };
    Ok((bytes, entry))
}

/// Absolute byte ranges of the tensors in the file.
#[derive(Debug, Clone, Default)]
struct Ranges {
    global: Range<usize>,
    image_size: Range<usize>,
    forest_offsets: Range<usize>,
    tree_class: Range<usize>,
    tree_area: Range<usize>,
    tree_centroid: Range<usize>,
    tree_neighbours: Range<usize>,
    tree_has_appearance: Range<usize>,
    tree_descriptors: Range<usize>,
    tree_blocks: BlockRanges,
    image_blocks: BlockRanges,
    image_hog: Range<usize>,
    id_bytes: Range<usize>,
    id_offsets: Range<usize>,
    keypoint_offsets: Range<usize>,
    keypoint_descriptors: Range<usize>,
    keypoint_xy: Range<usize>,
    keypoint_class: Range<usize>,
    /// Absent in segments without poses.
    place_pose: Option<Range<usize>>,
    /// Empty in maps without embeddings.
    image_embedding: Range<usize>,
    /// Empty in maps without compact HOGs.
    image_compact_hog: Range<usize>,
}

/// The four tensors of a column of appearance blocks.
#[derive(Debug, Clone, Default)]
struct BlockRanges {
    offsets: Range<usize>,
    ids: Range<usize>,
    exponents: Range<usize>,
    values: Range<usize>,
}

/// A memory-mapped segment file.
#[derive(Debug)]
pub struct Mapped {
    /// Path of the segment file.
    pub path: PathBuf,
    /// The file's manifest entry.
    pub entry: SegmentEntry,
    /// Sizes of the map's columns.
    pub layout: Layout,
    mmap: Mmap,
    n: usize,
    t: usize,
    /// Verification keypoints in the file.
    p: usize,
    r: Ranges,
    /// What [`Mapped::verify`] found wrong, once it ran (`None`: nothing).
    verified: OnceLock<Option<String>>,
}

impl Mapped {
    /// Maps `dir/entry.file` and checks its size and header against the manifest.
    pub fn open(dir: &Path, entry: &SegmentEntry, layout: Layout) -> Result<Mapped> {
        let path = dir.join(&entry.file);
        let file = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
        let meta = file.metadata().map_err(|e| Error::io(&path, e))?;
        if !meta.is_file() {
            return Err(Error::corrupt(&path, "is not a regular file (a directory or device in the segment's place)"));
        }
        let len = meta.len();
        if len != entry.bytes {
            return Err(Error::corrupt(&path, format!("file is {len} bytes, the manifest says {} (truncated or replaced)", entry.bytes)));
        }
        // SAFETY: the store never changes a segment file after renaming it into place (new
        // contents always go to new files), so the mapped bytes do not change under the map.
        let mmap = unsafe { Mmap::map(&file) }.map_err(|e| Error::io(&path, e))?;
        let r = ranges(&mmap, entry, &layout).map_err(|e| e.named(|reason| Error::corrupt(&path, reason)))?;
        Ok(Mapped { path, entry: entry.clone(), layout, mmap, n: entry.images, t: entry.trees, p: entry.keypoints, r, verified: OnceLock::new() })
    }

    /// Images stored in the file (removed ones included).
    pub fn len(&self) -> usize {
        self.n
    }
    /// Whether the file stores no images.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }
    /// Trees stored in the file.
    pub fn n_trees(&self) -> usize {
        self.t
    }
    /// Verification keypoints stored in the file.
    pub fn n_keypoints(&self) -> usize {
        self.p
    }
    /// The whole file, as mapped.
    pub fn bytes(&self) -> &[u8] {
        &self.mmap
    }

    // Ranges were checked at open to lie in the file and to be aligned to their element size,
    // so these casts cannot fail.
    fn raw(&self, r: &Range<usize>) -> &[u8] {
        &self.mmap[r.clone()]
    }
    fn u32s(&self, r: &Range<usize>) -> &[u32] {
        bytemuck::cast_slice(self.raw(r))
    }
    fn f32s(&self, r: &Range<usize>) -> &[f32] {
        bytemuck::cast_slice(self.raw(r))
    }
    fn vals(&self, r: &Range<usize>) -> Values<'_> {
        match self.layout.values {
            ValueType::F32 => Values::F32(bytemuck::cast_slice(self.raw(r))),
            ValueType::F16 => Values::F16(bytemuck::cast_slice(self.raw(r))),
        }
    }

    /// Global descriptors of rows `a..b`.
    pub fn globals(&self, a: usize, b: usize) -> Values<'_> {
        let g = self.layout.global_len();
        self.vals(&self.r.global).slice(a * g, b * g)
    }
    /// (width, height) of the source image of row `j`.
    pub fn size(&self, j: usize) -> [u32; 2] {
        let s = self.u32s(&self.r.image_size);
        [s[2 * j], s[2 * j + 1]]
    }
    /// Trees `a..b` of row `j` from an offsets table, or an empty run where the table is broken
    /// (a segment that failed its checks is never served, but reading it must not panic).
    fn span(offsets: &[u32], j: usize, limit: usize) -> (usize, usize) {
        match (offsets.get(j), offsets.get(j + 1)) {
            (Some(&a), Some(&b)) if a <= b && b as usize <= limit => (a as usize, b as usize),
            _ => (0, 0),
        }
    }
    /// The forest of row `j` (no trees where the offsets table is broken).
    pub fn forest(&self, j: usize) -> ForestRef<'_> {
        let (a, b) = Self::span(self.u32s(&self.r.forest_offsets), j, self.t);
        let (s, d) = (self.layout.slots, self.layout.dim);
        ForestRef {
            classes: &self.raw(&self.r.tree_class)[a..b],
            areas: &self.f32s(&self.r.tree_area)[a..b],
            centroids: &self.f32s(&self.r.tree_centroid)[2 * a..2 * b],
            neighbours: &bytemuck::cast_slice::<u8, i32>(self.raw(&self.r.tree_neighbours))[s * a..s * b],
            neighbour_slots: s,
            appearance: self.blocks(&self.r.tree_blocks, a, b),
            has_appearance: &self.raw(&self.r.tree_has_appearance)[a..b],
            descriptors: &self.u32s(&self.r.tree_descriptors)[a..b],
            dim: d,
        }
    }
    /// The verification keypoints of row `j` (none where the offsets table is broken).
    pub fn keypoints(&self, j: usize) -> KeypointsRef<'_> {
        let (a, b) = Self::span(self.u32s(&self.r.keypoint_offsets), j, self.p);
        let d = self.layout.kdim;
        KeypointsRef {
            descriptors: &bytemuck::cast_slice::<u8, i8>(self.raw(&self.r.keypoint_descriptors))[d * a..d * b],
            xy: &bytemuck::cast_slice::<u8, u16>(self.raw(&self.r.keypoint_xy))[2 * a..2 * b],
            classes: &self.raw(&self.r.keypoint_class)[a..b],
            dim: d,
        }
    }
    /// The id of row `j` (empty where the id table is broken).
    pub fn id(&self, j: usize) -> &str {
        let bytes = self.raw(&self.r.id_bytes);
        let (a, b) = Self::span(self.u32s(&self.r.id_offsets), j, bytes.len());
        std::str::from_utf8(&bytes[a..b]).unwrap_or("")
    }
    /// The whole-image appearance vector of row `j` (none without appearance).
    pub fn image_appearance(&self, j: usize) -> Values<'_> {
        self.blocks(&self.r.image_blocks, j, j + 1)
    }
    /// The whole-image appearance vectors of every row (removed ones included).
    pub fn image_appearances(&self) -> Values<'_> {
        self.blocks(&self.r.image_blocks, 0, self.n)
    }
    /// Bytes of the file by what they hold: (column, bytes), the safetensors header and padding
    /// last.
    pub fn column_bytes(&self) -> Vec<(&'static str, usize)> {
        let r = &self.r;
        let len = |rs: &[&Range<usize>]| rs.iter().map(|x| x.len()).sum::<usize>();
        let blocks = |b: &BlockRanges| len(&[&b.offsets, &b.ids, &b.exponents, &b.values]);
        let mut out = vec![
            ("global descriptor", len(&[&r.global])),
            ("image appearance", blocks(&r.image_blocks)),
            (
                "trees",
                len(&[
                    &r.forest_offsets,
                    &r.tree_class,
                    &r.tree_area,
                    &r.tree_centroid,
                    &r.tree_neighbours,
                    &r.tree_has_appearance,
                    &r.tree_descriptors,
                ]),
            ),
            ("tree appearance", blocks(&r.tree_blocks)),
            ("verification keypoints", len(&[&r.keypoint_offsets, &r.keypoint_descriptors, &r.keypoint_xy, &r.keypoint_class])),
            ("hog", len(&[&r.image_hog])),
            ("embedding", len(&[&r.image_embedding])),
            ("compact hog", len(&[&r.image_compact_hog])),
            ("ids and sizes", len(&[&r.id_bytes, &r.id_offsets, &r.image_size])),
        ];
        if let Some(p) = &r.place_pose {
            out.push(("poses", p.len()));
        }
        let counted: usize = out.iter().map(|c| c.1).sum();
        out.push(("header and padding", self.mmap.len() - counted.min(self.mmap.len())));
        out
    }
    /// Vectors `a..b` of a block column (none without appearance; empty where the offsets table
    /// is broken).
    fn blocks(&self, r: &BlockRanges, a: usize, b: usize) -> Values<'_> {
        let offsets = self.u32s(&r.offsets);
        if self.layout.dim == 0 || b >= offsets.len() || a > b {
            return Values::F32(&[]);
        }
        Values::Blocks(crate::values::Blocks {
            dim: self.layout.dim,
            block: self.layout.block,
            offsets: &offsets[a..=b],
            ids: self.raw(&r.ids),
            exponents: bytemuck::cast_slice(self.raw(&r.exponents)),
            values: bytemuck::cast_slice(self.raw(&r.values)),
        })
    }
    /// The pose of row `j`: none where the segment stores no poses, the row holds none, or the
    /// row is broken (which [`Mapped::verify`] reports).
    pub fn pose(&self, j: usize) -> Option<PlacePose> {
        let r = self.r.place_pose.as_ref()?;
        let rows: &[f64] = bytemuck::cast_slice(self.raw(r));
        PlacePose::from_row(rows.get(7 * j..7 * j + 7)?).ok().flatten()
    }
    /// Whether the segment stores poses (some of its images have one).
    pub fn has_poses(&self) -> bool {
        self.r.place_pose.is_some()
    }
    /// The HOG descriptor of row `j` (empty when the map stores none).
    pub fn image_hog(&self, j: usize) -> &[f32] {
        let h = self.layout.hog;
        &self.f32s(&self.r.image_hog)[j * h..(j + 1) * h]
    }
    /// The whole-image embedding of row `j`, f16 (empty when the map stores none).
    pub fn image_embedding(&self, j: usize) -> Values<'_> {
        let e = self.layout.emb;
        let all: &[u16] = bytemuck::cast_slice(self.raw(&self.r.image_embedding));
        Values::F16(&all[j * e..(j + 1) * e])
    }
    /// The compact HOG of row `j`, f16 (empty when the map stores none).
    pub fn image_compact_hog(&self, j: usize) -> Values<'_> {
        let c = self.layout.chog;
        let all: &[u16] = bytemuck::cast_slice(self.raw(&self.r.image_compact_hog));
        Values::F16(&all[j * c..(j + 1) * c])
    }

    /// Checks the SHA-256 against the manifest, then every value (offsets, ids, and each image
    /// with [`validate::image`]); a failure is an [`Error::CorruptMap`] naming the file, its
    /// reason the image where there is one.
    pub fn verify(&self) -> Result<()> {
        self.check_values().map_err(|e| e.named(|reason| Error::corrupt(&self.path, reason)))
    }

    /// [`Mapped::verify`]'s checks, before the file is named.
    fn check_values(&self) -> Result<()> {
        if crate::util::sha256_hex(&self.mmap) != self.entry.sha256 {
            return Err(Error::check("SHA-256 differs from the manifest (file altered or damaged)"));
        }
        let table_ok = |offsets: &[u32], end: usize| {
            offsets.first() == Some(&0) && offsets.windows(2).all(|w| w[0] <= w[1]) && offsets.last().map(|&l| l as usize) == Some(end)
        };
        if !table_ok(self.u32s(&self.r.forest_offsets), self.t) {
            return Err(Error::check("forest offsets do not run from 0 to the tree count"));
        }
        if !table_ok(self.u32s(&self.r.id_offsets), self.r.id_bytes.len()) {
            return Err(Error::check("id offsets do not run over the id bytes"));
        }
        if !table_ok(self.u32s(&self.r.keypoint_offsets), self.p) {
            return Err(Error::check("keypoint offsets do not run from 0 to the keypoint count"));
        }
        for (what, r, rows) in [("tree", &self.r.tree_blocks, self.t), ("image", &self.r.image_blocks, self.n)] {
            let count = r.ids.len();
            let offsets = self.u32s(&r.offsets);
            if offsets.len() != rows + 1
                || !table_ok(offsets, count)
                || r.exponents.len() != count
                || (self.layout.block > 0 && r.values.len() != count * self.layout.block)
            {
                return Err(Error::check(format!("{what} appearance block offsets do not run from 0 to the block count")));
            }
            let per_vector = self.layout.dim / self.layout.block.max(1);
            if self.raw(&r.ids).iter().any(|&id| id as usize >= per_vector) || offsets.windows(2).any(|w| w[1] - w[0] > per_vector as u32) {
                return Err(Error::check(format!("a {what} appearance block lies outside its vector of {per_vector} blocks")));
            }
        }
        let mut ids = std::collections::HashSet::with_capacity(self.n);
        for j in 0..self.n {
            let raw = &self.raw(&self.r.id_bytes)[{
                let (a, b) = Self::span(self.u32s(&self.r.id_offsets), j, self.r.id_bytes.len());
                a..b
            }];
            let id = std::str::from_utf8(raw).map_err(|_| Error::check(format!("the id of row {j} is not UTF-8")))?;
            if !ids.insert(id) {
                return Err(Error::check(format!("image id {id:?} is stored twice")));
            }
            let g = self.globals(j, j + 1);
            validate::image(
                id,
                self.size(j),
                g,
                self.forest(j),
                self.image_appearance(j),
                self.image_hog(j),
                self.layout.n_classes,
                self.layout.values,
            )
            .and_then(|()| validate::keypoints(self.keypoints(j), self.layout.n_classes))
            .and_then(|()| validate::embedding(self.image_embedding(j)))
            .and_then(|()| validate::compact_hog(self.image_compact_hog(j)))
            .map_err(|r| Error::check(format!("image {id:?}: {r}")))?;
            if let Some(r) = &self.r.place_pose {
                let rows: &[f64] = bytemuck::cast_slice(self.raw(r));
                validate::pose_row(&rows[7 * j..7 * j + 7]).map_err(|e| e.named(|r| Error::check(format!("image {id:?}: {r}"))))?;
            }
        }
        Ok(())
    }

    /// [`Mapped::verify`], once per process: later calls return the first call's result.
    pub fn ensure(&self) -> Result<()> {
        match self.verified.get_or_init(|| self.check_values().err().map(|e| e.to_string())) {
            None => Ok(()),
            Some(reason) => Err(Error::corrupt(&self.path, reason.clone())),
        }
    }
    /// Takes over `prev`'s [`Mapped::ensure`] result where `prev` maps the same file with the same
    /// checksum and size (segment files never change once in place: a later generation of the
    /// map shares them), so a reopened map does not check them again.
    pub fn inherit(&self, prev: &Mapped) {
        let same = prev.path == self.path && prev.entry.sha256 == self.entry.sha256 && prev.entry.bytes == self.entry.bytes;
        crate::util::take_over_check(&self.verified, &prev.verified, same);
    }
    /// Whether [`Mapped::ensure`] has run (here or, inherited, on an earlier generation).
    pub fn checked(&self) -> bool {
        self.verified.get().is_some()
    }
    /// The stored verification failure (its reason), if the segment was checked and failed.
    pub fn failure(&self) -> Option<&str> {
        self.verified.get().and_then(|r| r.as_deref())
    }

    /// Appends row `j` to `set` (a [`DescriptorSet::for_storage`] of the same layout), widened
    /// to f32 (an f16 value widens exactly, so writing it back as f16 gives the same bits).
    pub fn append_row(&self, j: usize, set: &mut DescriptorSet) {
        let f = self.forest(j);
        set.ids.push(self.id(j).to_string());
        set.sizes.push(self.size(j));
        set.poses.push(self.pose(j));
        self.globals(j, j + 1).extend_into(&mut set.globals);
        set.tree_classes.extend_from_slice(f.classes);
        set.tree_areas.extend_from_slice(f.areas);
        set.tree_centroids.extend_from_slice(f.centroids);
        set.tree_neighbours.extend_from_slice(f.neighbours);
        f.appearance.extend_into(&mut set.tree_appearance);
        set.tree_has_appearance.extend_from_slice(f.has_appearance);
        set.tree_descriptors.extend_from_slice(f.descriptors);
        self.image_appearance(j).extend_into(&mut set.image_appearance);
        set.image_hog.extend_from_slice(self.image_hog(j));
        self.image_embedding(j).extend_into(&mut set.image_embedding);
        self.image_compact_hog(j).extend_into(&mut set.image_compact_hog);
        set.forest_offsets.push(set.tree_classes.len() as u32);
        let k = self.keypoints(j);
        set.keypoint_descriptors.extend_from_slice(k.descriptors);
        set.keypoint_xy.extend_from_slice(k.xy);
        set.keypoint_classes.extend_from_slice(k.classes);
        set.keypoint_offsets.push(set.keypoint_classes.len() as u32);
    }
}

/// The checked byte ranges of every tensor.
fn ranges(bytes: &[u8], entry: &SegmentEntry, l: &Layout) -> Result<Ranges> {
    let (header, meta) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| Error::check(format!("not a safetensors file: {e}")))?;
    let start = 8 + header;
    let (n, t) = (entry.images, entry.trees);
    let fdt = match l.values {
        ValueType::F32 => Dtype::F32,
        ValueType::F16 => Dtype::F16,
    };
    let get = |name: &str, dtype: Dtype, shape: &[Option<usize>]| -> Result<Range<usize>> {
        let info = meta.info(name).ok_or_else(|| Error::check(format!("tensor {name:?} is missing")))?;
        let ok = info.dtype == dtype && info.shape.len() == shape.len() && info.shape.iter().zip(shape).all(|(a, b)| b.is_none_or(|b| *a == b));
        if !ok {
            return Err(Error::check(format!("tensor {name:?} is {:?} {:?}, expected {dtype:?} {shape:?}", info.dtype, info.shape)));
        }
        let (a, b) = info.data_offsets;
        let size = dtype.bitsize() / 8;
        if (start + a) % size != 0 {
            return Err(Error::check(format!(
                "tensor {name:?} starts at byte {}, not a multiple of its {size}-byte elements (written by another tool?)",
                start + a
            )));
        }
        Ok(start + a..start + b)
    };
    let block_ranges = |name: &str, rows: usize| -> Result<BlockRanges> {
        let offsets = get(&format!("{name}_block_offsets"), Dtype::U32, &[Some(rows + 1)])?;
        let ids = get(&format!("{name}_block_ids"), Dtype::U8, &[None])?;
        let exponents = get(&format!("{name}_block_exponents"), Dtype::I8, &[None])?;
        let values = get(&format!("{name}_block_values"), Dtype::I8, &[None, Some(l.block)])?;
        Ok(BlockRanges { offsets, ids, exponents, values })
    };
    Ok(Ranges {
        global: get("global", fdt, &[Some(n), Some(l.gh), Some(l.gw)])?,
        image_size: get("image_size", Dtype::U32, &[Some(n), Some(2)])?,
        forest_offsets: get("forest_offsets", Dtype::U32, &[Some(n + 1)])?,
        tree_class: get("tree_class", Dtype::U8, &[Some(t)])?,
        tree_area: get("tree_area", Dtype::F32, &[Some(t)])?,
        tree_centroid: get("tree_centroid", Dtype::F32, &[Some(t), Some(2)])?,
        tree_neighbours: get("tree_neighbours", Dtype::I32, &[Some(t), Some(l.slots)])?,
        tree_has_appearance: get("tree_has_appearance", Dtype::U8, &[Some(t)])?,
        tree_descriptors: get("tree_descriptors", Dtype::U32, &[Some(t)])?,
        tree_blocks: block_ranges("tree", t)?,
        image_blocks: block_ranges("image", n)?,
        image_hog: get("image_hog", Dtype::F32, &[Some(n), Some(l.hog)])?,
        id_bytes: get("id_bytes", Dtype::U8, &[None])?,
        id_offsets: get("id_offsets", Dtype::U32, &[Some(n + 1)])?,
        keypoint_offsets: get("keypoint_offsets", Dtype::U32, &[Some(n + 1)])?,
        keypoint_descriptors: get("keypoint_descriptors", Dtype::I8, &[Some(entry.keypoints), Some(l.kdim)])?,
        keypoint_xy: get("keypoint_xy", Dtype::U16, &[Some(entry.keypoints), Some(2)])?,
        keypoint_class: get("keypoint_class", Dtype::U8, &[Some(entry.keypoints)])?,
        place_pose: match meta.info("place_pose") {
            None => None,
            Some(_) => Some(get("place_pose", Dtype::F64, &[Some(n), Some(7)])?),
        },
        image_embedding: match l.emb {
            0 => 0..0,
            e => get("image_embedding", Dtype::F16, &[Some(n), Some(e)])?,
        },
        image_compact_hog: match l.chog {
            0 => 0..0,
            c => get("image_compact_hog", Dtype::F16, &[Some(n), Some(c)])?,
        },
    })
}
