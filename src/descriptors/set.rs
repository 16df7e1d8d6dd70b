//! Columnar storage of many encoded images: the in-memory form of a map, of a map segment being
//! written, and of a batch of queries; and [`EncodedImage`], what the encoder makes of one frame.
//! Forests are concatenated, with `forest_offsets[i]..[i + 1]` the trees of image i; neighbour
//! indices stay local to their forest.

use crate::descriptors::keypoints::{ImageKeypoints, KeypointsRef};
use crate::descriptors::pose::PlacePose;
use crate::error::{Error, Result};
use crate::local::Forest;
use crate::values::Values;
use semlook_kernels::abi::SsimParams;
use semlook_kernels::tree_similarity::ForestRef;

/// Everything stored for one image.
#[derive(Debug, Clone, PartialEq)]
pub struct EncodedImage {
    /// Frame id.
    pub id: String,
    /// Size of the source image (descriptors are computed at the working size).
    pub width: u32,
    /// Height of the source image, in pixels.
    pub height: u32,
    /// Global descriptor, `global.height` x `global.width`, values in [0, 1].
    pub global: Vec<f32>,
    /// SSIM window means then variances of `global`.
    pub global_stats: Vec<f32>,
    /// The local descriptor: one tree per semantic object.
    pub forest: Forest,
    /// VLAD of all the image's appearance descriptors (the `appearance` baseline); empty without
    /// appearance.
    pub appearance: Vec<f32>,
    /// VPR-Bench HOG (the `hog` baseline); empty unless the encoder computes it.
    pub hog: Vec<f32>,
    /// The whole-image embedding ([`crate::networks::embedding`], L2-normalised); empty unless the encoder
    /// computes it.
    pub embedding: Vec<f32>,
    /// The compact HOG of the whole image ([`crate::global::hog::compact_hog`], L2-normalised); empty
    /// unless the encoder computes it (maps of small frames).
    pub compact_hog: Vec<f32>,
    /// The verification keypoints (empty when the encoder stores none).
    pub keypoints: ImageKeypoints,
    /// Where the image was taken, when its source gives a pose (a dataset's poses, a pose list):
    /// not encoded from pixels, but attached to the image so a map stores it with the place.
    pub pose: Option<PlacePose>,
}

/// Many encoded images, one column per field (see the module header).
#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorSet {
    /// Frame id of each image.
    pub ids: Vec<String>,
    /// (width, height) of each source image.
    pub sizes: Vec<[u32; 2]>,
    /// Values per global descriptor.
    pub global_len: usize,
    /// SSIM statistics values per image (0: the set keeps none).
    pub stats_len: usize,
    /// `global_len` values per image.
    pub globals: Vec<f32>,
    /// `stats_len` values per image: SSIM window means then variances of its global descriptor.
    pub global_stats: Vec<f32>,
    /// `forest_offsets[i]..[i + 1]` are image i's trees (one more entry than images).
    pub forest_offsets: Vec<u32>,
    /// Semantic class of each tree.
    pub tree_classes: Vec<u8>,
    /// Area of each tree's object, as a fraction of the image.
    pub tree_areas: Vec<f32>,
    /// (x, y) per tree, in image diagonals.
    pub tree_centroids: Vec<f32>,
    /// Neighbour slots per tree.
    pub neighbour_slots: usize,
    /// `neighbour_slots` entries per tree: indices into the tree's own forest, or `local::NO_NEIGHBOUR`.
    pub tree_neighbours: Vec<i32>,
    /// Values per appearance vector (0: no appearance).
    pub appearance_dim: usize,
    /// `appearance_dim` values per tree (zeros where `tree_has_appearance` is 0).
    pub tree_appearance: Vec<f32>,
    /// 1 where a tree has an appearance vector, else 0.
    pub tree_has_appearance: Vec<u8>,
    /// Appearance descriptors each tree's VLAD was aggregated from.
    pub tree_descriptors: Vec<u32>,
    /// Per image, the VLAD of all its descriptors (`appearance_dim` values; zeros without
    /// appearance): the whole-image `appearance` baseline.
    pub image_appearance: Vec<f32>,
    /// Per image, the VPR-Bench HOG descriptor (`hog_dim` values; 0 when not computed).
    pub hog_dim: usize,
    /// `hog_dim` values per image (zeros for an image without HOG).
    pub image_hog: Vec<f32>,
    /// Values per whole-image embedding ([`crate::networks::embedding`]; 0: the set holds none).
    pub embedding_dim: usize,
    /// `embedding_dim` values per image (zeros for an image without one).
    pub image_embedding: Vec<f32>,
    /// What made the embeddings (the encoder's network; none for a set without embeddings or a
    /// storage buffer): sets of two networks never join.
    pub embedding: Option<crate::descriptors::EmbeddingRecord>,
    /// Values per compact HOG ([`crate::global::hog::COMPACT_HOG_DIM`]; 0: the set holds none).
    pub compact_hog_dim: usize,
    /// `compact_hog_dim` values per image (zeros for an image without one).
    pub image_compact_hog: Vec<f32>,
    /// Values per verification keypoint descriptor (0: the set holds no keypoints).
    pub keypoint_dim: usize,
    /// `keypoint_offsets[i]..[i + 1]` are image i's keypoints.
    pub keypoint_offsets: Vec<u32>,
    /// `keypoint_dim` int8 values per keypoint.
    pub keypoint_descriptors: Vec<i8>,
    /// (x, y) per keypoint, fractions of the long side x `verify::keypoints::COORD_SCALE`.
    pub keypoint_xy: Vec<u16>,
    /// The semantic class under each keypoint.
    pub keypoint_classes: Vec<u8>,
    /// Per image, its pose where its source gave one ([`PlacePose`]).
    pub poses: Vec<Option<PlacePose>>,
    /// SHA-256 of the VLAD codebook the appearance vectors were aggregated with (`Codebook::sha256`;
    /// none without appearance): sets of two codebooks never join, nor enter a map of another.
    pub codebook: Option<String>,
}

impl DescriptorSet {
    /// An empty set of global descriptors and statistics sized by `ssim`, with no keypoints and no codebook.
    pub fn new(ssim: &SsimParams, neighbour_slots: usize, appearance_dim: usize, hog_dim: usize) -> Self {
        DescriptorSet {
            ids: vec![],
            sizes: vec![],
            global_len: ssim.len(),
            stats_len: ssim.stats_len(),
            globals: vec![],
            global_stats: vec![],
            forest_offsets: vec![0],
            tree_classes: vec![],
            tree_areas: vec![],
            tree_centroids: vec![],
            neighbour_slots,
            tree_neighbours: vec![],
            appearance_dim,
            tree_appearance: vec![],
            tree_has_appearance: vec![],
            tree_descriptors: vec![],
            image_appearance: vec![],
            hog_dim,
            image_hog: vec![],
            embedding_dim: 0,
            image_embedding: vec![],
            embedding: None,
            compact_hog_dim: 0,
            image_compact_hog: vec![],
            keypoint_dim: 0,
            keypoint_offsets: vec![0],
            keypoint_descriptors: vec![],
            keypoint_xy: vec![],
            keypoint_classes: vec![],
            poses: vec![],
            codebook: None,
        }
    }

    /// The same empty set, its appearance aggregated with the codebook of SHA-256 `codebook`.
    pub fn with_codebook(mut self, codebook: Option<String>) -> Self {
        self.codebook = codebook;
        self
    }

    /// The same empty set holding whole-image embeddings of `dim` values each.
    pub fn with_embedding_dim(mut self, dim: usize) -> Self {
        self.embedding_dim = dim;
        self
    }

    /// The same empty set holding the whole-image embeddings of the network `rec` records (none:
    /// no embeddings).
    pub fn with_embedding(mut self, rec: Option<crate::descriptors::EmbeddingRecord>) -> Self {
        self.embedding_dim = rec.as_ref().map_or(0, |r| r.dim);
        self.embedding = rec;
        self
    }

    /// The same empty set holding compact HOGs of `dim` values each (0: none).
    pub fn with_compact_hog_dim(mut self, dim: usize) -> Self {
        self.compact_hog_dim = dim;
        self
    }

    /// The same empty set with `rec` as what made its embeddings, its width unchanged.
    fn with_embedding_record(mut self, rec: Option<crate::descriptors::EmbeddingRecord>) -> Self {
        self.embedding = rec;
        self
    }

    /// The same empty set holding verification keypoints of `dim` values each.
    pub fn with_keypoint_dim(mut self, dim: usize) -> Self {
        self.keypoint_dim = dim;
        self
    }

    /// An empty set that keeps no SSIM statistics (`stats_len` 0): the buffer of a map segment
    /// being written, since maps recompute statistics as they are read. Not a matching source.
    pub fn for_storage(global_len: usize, neighbour_slots: usize, appearance_dim: usize, hog_dim: usize) -> Self {
        DescriptorSet { global_len, stats_len: 0, ..DescriptorSet::new(&bytemuck::Zeroable::zeroed(), neighbour_slots, appearance_dim, hog_dim) }
    }

    /// Number of images.
    pub fn len(&self) -> usize {
        self.ids.len()
    }
    /// Whether the set holds no images.
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    /// Trees of all images.
    pub fn n_trees(&self) -> usize {
        self.tree_classes.len()
    }
    /// Verification keypoints of all images.
    pub fn n_keypoints(&self) -> usize {
        self.keypoint_classes.len()
    }

    /// Appends one image. Its global size, neighbour slots and appearance dimension must match
    /// the set's (an image without appearance gets zero vectors flagged absent; without HOG,
    /// zeros), else the set is unchanged and the mismatch is returned (an [`Error::Check`] naming
    /// the image). A set without statistics ([`DescriptorSet::for_storage`]) ignores the image's.
    pub fn push(&mut self, img: &EncodedImage) -> Result<()> {
        let f = &img.forest;
        let stats_ok = self.stats_len == 0 || img.global_stats.len() == self.stats_len;
        if img.global.len() != self.global_len || !stats_ok || f.neighbour_slots != self.neighbour_slots {
            return Err(Error::check(format!("image {:?} has another global descriptor size or neighbour count than the set", img.id)));
        }
        if (f.dim != self.appearance_dim && f.dim != 0) || (!img.appearance.is_empty() && img.appearance.len() != self.appearance_dim) {
            return Err(Error::check(format!("image {:?} has appearance of dimension {}, the set {}", img.id, f.dim, self.appearance_dim)));
        }
        if !img.hog.is_empty() && img.hog.len() != self.hog_dim {
            return Err(Error::check(format!("image {:?} has a HOG descriptor of {} values, the set {}", img.id, img.hog.len(), self.hog_dim)));
        }
        if !img.embedding.is_empty() && img.embedding.len() != self.embedding_dim {
            return Err(Error::check(format!(
                "image {:?} has an embedding of {} values, the set {}",
                img.id,
                img.embedding.len(),
                self.embedding_dim
            )));
        }
        if !img.compact_hog.is_empty() && img.compact_hog.len() != self.compact_hog_dim {
            return Err(Error::check(format!(
                "image {:?} has a compact HOG of {} values, the set {}",
                img.id,
                img.compact_hog.len(),
                self.compact_hog_dim
            )));
        }
        let k = &img.keypoints;
        if !k.is_empty() && (k.dim != self.keypoint_dim || k.descriptors.len() != k.len() * k.dim || k.xy.len() != 2 * k.len()) {
            return Err(Error::check(format!(
                "image {:?} has {} keypoints of dimension {} ({} values), the set takes dimension {}",
                img.id,
                k.len(),
                k.dim,
                k.descriptors.len(),
                self.keypoint_dim
            )));
        }
        self.ids.push(img.id.clone());
        self.sizes.push([img.width, img.height]);
        self.poses.push(img.pose);
        self.globals.extend_from_slice(&img.global);
        if self.stats_len > 0 {
            self.global_stats.extend_from_slice(&img.global_stats);
        }
        self.tree_classes.extend_from_slice(&f.classes);
        self.tree_areas.extend_from_slice(&f.areas);
        self.tree_centroids.extend_from_slice(&f.centroids);
        self.tree_neighbours.extend_from_slice(&f.neighbours);
        if f.dim == self.appearance_dim {
            self.tree_appearance.extend_from_slice(&f.appearance);
            self.tree_has_appearance.extend_from_slice(&f.has_appearance);
        } else {
            self.tree_appearance.resize(self.tree_appearance.len() + f.len() * self.appearance_dim, 0.0);
            self.tree_has_appearance.resize(self.tree_has_appearance.len() + f.len(), 0);
        }
        self.tree_descriptors.extend_from_slice(&f.descriptors);
        self.tree_descriptors.resize(self.tree_classes.len(), 0);
        let fill = |dst: &mut Vec<f32>, src: &[f32], dim: usize| {
            if src.len() == dim {
                dst.extend_from_slice(src);
            } else {
                dst.resize(dst.len() + dim, 0.0);
            }
        };
        fill(&mut self.image_appearance, &img.appearance, self.appearance_dim);
        fill(&mut self.image_hog, &img.hog, self.hog_dim);
        fill(&mut self.image_embedding, &img.embedding, self.embedding_dim);
        fill(&mut self.image_compact_hog, &img.compact_hog, self.compact_hog_dim);
        self.forest_offsets.push(self.tree_classes.len() as u32);
        self.keypoint_descriptors.extend_from_slice(&k.descriptors);
        self.keypoint_xy.extend_from_slice(&k.xy);
        self.keypoint_classes.extend_from_slice(&k.classes);
        self.keypoint_offsets.push(self.keypoint_classes.len() as u32);
        Ok(())
    }

    /// Appends all images of `other`; fails, leaving the set unchanged, when the layouts differ.
    pub fn append(&mut self, other: &DescriptorSet) -> Result<()> {
        self.append_range(other, 0, other.len())
    }

    /// Appends images `start..end` of `other` (a set without statistics takes none); fails,
    /// leaving the set unchanged, when the layouts differ or the range is not in `other`.
    pub fn append_range(&mut self, other: &DescriptorSet, start: usize, end: usize) -> Result<()> {
        let sizes =
            |s: &DescriptorSet| (s.global_len, s.neighbour_slots, s.appearance_dim, s.hog_dim, s.keypoint_dim, s.embedding_dim, s.compact_hog_dim);
        if self.appearance_dim > 0 && self.codebook != other.codebook {
            return Err(Error::check(format!(
                "images aggregated with another VLAD codebook (sha256 {}) do not join a set of sha256 {}",
                other.codebook.as_deref().unwrap_or("none"),
                self.codebook.as_deref().unwrap_or("none")
            )));
        }
        if let (Some(a), Some(b)) = (&self.embedding, &other.embedding) {
            if !a.same_network(b) {
                return Err(Error::check(format!(
                    "images embedded by another network ({}, sha256 {}) do not join a set of {} (sha256 {})",
                    b.network, b.sha256, a.network, a.sha256
                )));
            }
        }
        if sizes(self) != sizes(other) || (self.stats_len != 0 && self.stats_len != other.stats_len) {
            return Err(Error::check(format!(
                "images with (global values, neighbour slots, appearance dim, HOG dim, keypoint dim, embedding dim, compact HOG dim, statistics) {:?} / {} do not join a set of {:?} / {}",
                sizes(other),
                other.stats_len,
                sizes(self),
                self.stats_len
            )));
        }
        if start > end || end > other.len() {
            return Err(Error::check(format!("images {start}..{end} of a set of {}", other.len())));
        }
        self.extend_from(other, start, end);
        Ok(())
    }

    /// [`DescriptorSet::append_range`] where the caller knows the layouts agree and the range lies
    /// in `other` (sets of one writer or one encoder).
    pub(crate) fn extend_from(&mut self, other: &DescriptorSet, start: usize, end: usize) {
        let (a, b) = (other.forest_offsets[start] as usize, other.forest_offsets[end] as usize);
        let (n, d, h, g, sl) = (self.neighbour_slots, self.appearance_dim, self.hog_dim, self.global_len, self.stats_len);
        let base = self.n_trees() as u32;
        self.ids.extend_from_slice(&other.ids[start..end]);
        self.sizes.extend_from_slice(&other.sizes[start..end]);
        self.poses.extend_from_slice(&other.poses[start..end]);
        self.globals.extend_from_slice(&other.globals[start * g..end * g]);
        self.global_stats.extend_from_slice(&other.global_stats[start * sl..end * sl]);
        self.forest_offsets.extend(other.forest_offsets[start + 1..=end].iter().map(|o| o - a as u32 + base));
        self.tree_classes.extend_from_slice(&other.tree_classes[a..b]);
        self.tree_areas.extend_from_slice(&other.tree_areas[a..b]);
        self.tree_centroids.extend_from_slice(&other.tree_centroids[2 * a..2 * b]);
        self.tree_neighbours.extend_from_slice(&other.tree_neighbours[n * a..n * b]);
        self.tree_appearance.extend_from_slice(&other.tree_appearance[d * a..d * b]);
        self.tree_has_appearance.extend_from_slice(&other.tree_has_appearance[a..b]);
        self.tree_descriptors.extend_from_slice(&other.tree_descriptors[a..b]);
        self.image_appearance.extend_from_slice(&other.image_appearance[start * d..end * d]);
        self.image_hog.extend_from_slice(&other.image_hog[start * h..end * h]);
        let e = self.embedding_dim;
        self.image_embedding.extend_from_slice(&other.image_embedding[start * e..end * e]);
        let c = self.compact_hog_dim;
        self.image_compact_hog.extend_from_slice(&other.image_compact_hog[start * c..end * c]);
        let (ka, kb, kd) = (other.keypoint_offsets[start] as usize, other.keypoint_offsets[end] as usize, self.keypoint_dim);
        let kbase = self.n_keypoints() as u32;
        self.keypoint_offsets.extend(other.keypoint_offsets[start + 1..=end].iter().map(|o| o - ka as u32 + kbase));
        self.keypoint_descriptors.extend_from_slice(&other.keypoint_descriptors[kd * ka..kd * kb]);
        self.keypoint_xy.extend_from_slice(&other.keypoint_xy[2 * ka..2 * kb]);
        self.keypoint_classes.extend_from_slice(&other.keypoint_classes[ka..kb]);
    }

    /// Images `start..end` as a set of their own. Panics, as slice indexing does, when the range
    /// is not within the set.
    pub fn slice(&self, start: usize, end: usize) -> DescriptorSet {
        let mut out = self.empty_like();
        out.extend_from(self, start, end);
        out
    }

    /// An empty set of the same layout.
    pub fn empty_like(&self) -> DescriptorSet {
        DescriptorSet {
            global_len: self.global_len,
            stats_len: self.stats_len,
            ..DescriptorSet::new(&bytemuck::Zeroable::zeroed(), self.neighbour_slots, self.appearance_dim, self.hog_dim)
        }
        .with_keypoint_dim(self.keypoint_dim)
        .with_embedding_dim(self.embedding_dim)
        .with_embedding_record(self.embedding.clone())
        .with_compact_hog_dim(self.compact_hog_dim)
        .with_codebook(self.codebook.clone())
    }

    /// The global descriptor of image i.
    pub fn global(&self, i: usize) -> &[f32] {
        &self.globals[i * self.global_len..(i + 1) * self.global_len]
    }
    /// The SSIM statistics of image i (empty when the set keeps none).
    pub fn stats(&self, i: usize) -> &[f32] {
        &self.global_stats[i * self.stats_len..(i + 1) * self.stats_len]
    }
    /// The whole-image appearance vector of image i (empty without appearance).
    pub fn image_appearance(&self, i: usize) -> &[f32] {
        &self.image_appearance[i * self.appearance_dim..(i + 1) * self.appearance_dim]
    }
    /// The HOG descriptor of image i (empty when the set holds none).
    pub fn image_hog(&self, i: usize) -> &[f32] {
        &self.image_hog[i * self.hog_dim..(i + 1) * self.hog_dim]
    }
    /// The whole-image embedding of image i (empty when the set holds none).
    pub fn image_embedding(&self, i: usize) -> &[f32] {
        &self.image_embedding[i * self.embedding_dim..(i + 1) * self.embedding_dim]
    }
    /// The compact HOG of image i (empty when the set holds none).
    pub fn image_compact_hog(&self, i: usize) -> &[f32] {
        &self.image_compact_hog[i * self.compact_hog_dim..(i + 1) * self.compact_hog_dim]
    }
    /// The verification keypoints of image i.
    pub fn keypoints(&self, i: usize) -> KeypointsRef<'_> {
        let (a, b) = (self.keypoint_offsets[i] as usize, self.keypoint_offsets[i + 1] as usize);
        let d = self.keypoint_dim;
        KeypointsRef {
            descriptors: &self.keypoint_descriptors[d * a..d * b],
            xy: &self.keypoint_xy[2 * a..2 * b],
            classes: &self.keypoint_classes[a..b],
            dim: d,
        }
    }
    /// The forest of image i.
    pub fn forest(&self, i: usize) -> ForestRef<'_> {
        let (a, b) = (self.forest_offsets[i] as usize, self.forest_offsets[i + 1] as usize);
        let (n, d) = (self.neighbour_slots, self.appearance_dim);
        ForestRef {
            classes: &self.tree_classes[a..b],
            areas: &self.tree_areas[a..b],
            centroids: &self.tree_centroids[2 * a..2 * b],
            neighbours: &self.tree_neighbours[n * a..n * b],
            neighbour_slots: n,
            appearance: Values::F32(&self.tree_appearance[d * a..d * b]),
            has_appearance: &self.tree_has_appearance[a..b],
            descriptors: &self.tree_descriptors[a..b],
            dim: d,
        }
    }

    /// Checks that every column holds as many values as the ids, sizes and forest offsets say
    /// (a set assembled from outside, e.g. numpy arrays); the message names the first column that
    /// does not. Values are checked per image by [`DescriptorSet::check_image`].
    pub fn check_layout(&self) -> Result<()> {
        let (n, o) = (self.ids.len(), &self.forest_offsets);
        if o.len() != n + 1 || o[0] != 0 || o.windows(2).any(|w| w[0] > w[1]) {
            return Err(Error::check(format!("forest_offsets: {} offsets for {n} images, from 0 and ascending", o.len())));
        }
        let t = o[n] as usize;
        let ko = &self.keypoint_offsets;
        if ko.len() != n + 1 || ko[0] != 0 || ko.windows(2).any(|w| w[0] > w[1]) {
            return Err(Error::check(format!("keypoint_offsets: {} offsets for {n} images, from 0 and ascending", ko.len())));
        }
        let p = ko[n] as usize;
        let (s, d) = (self.neighbour_slots, self.appearance_dim);
        let columns: [(&str, usize, usize); 19] = [
            ("sizes", self.sizes.len(), n),
            ("poses", self.poses.len(), n),
            ("globals", self.globals.len(), n * self.global_len),
            ("global_stats", self.global_stats.len(), n * self.stats_len),
            ("tree_classes", self.tree_classes.len(), t),
            ("tree_areas", self.tree_areas.len(), t),
            ("tree_centroids", self.tree_centroids.len(), 2 * t),
            ("tree_neighbours", self.tree_neighbours.len(), s * t),
            ("tree_appearance", self.tree_appearance.len(), d * t),
            ("tree_has_appearance", self.tree_has_appearance.len(), t),
            ("tree_descriptors", self.tree_descriptors.len(), t),
            ("image_appearance", self.image_appearance.len(), d * n),
            ("image_hog", self.image_hog.len(), self.hog_dim * n),
            ("image_embedding", self.image_embedding.len(), self.embedding_dim * n),
            ("image_compact_hog", self.image_compact_hog.len(), self.compact_hog_dim * n),
            ("keypoint_descriptors", self.keypoint_descriptors.len(), self.keypoint_dim * p),
            ("keypoint_xy", self.keypoint_xy.len(), 2 * p),
            ("keypoint_classes", self.keypoint_classes.len(), p),
            ("global_len", self.global_len.min(1), 1),
        ];
        if let Some(r) = self.embedding.as_ref().filter(|r| r.dim != self.embedding_dim) {
            return Err(Error::check(format!("embedding_dim {} but the embedding network {} gives {} values", self.embedding_dim, r.network, r.dim)));
        }
        match columns.iter().find(|(_, got, want)| got != want) {
            Some((name, got, want)) => Err(Error::check(format!("{name}: {got} values, the layout needs {want}"))),
            None => Ok(()),
        }
    }

    /// Checks image `i` with [`crate::descriptors::validate::image`].
    pub fn check_image(&self, i: usize, n_classes: usize, store: crate::values::ValueType) -> Result<()> {
        let g = Values::F32(self.global(i));
        crate::descriptors::validate::image(
            &self.ids[i],
            self.sizes[i],
            g,
            self.forest(i),
            Values::F32(self.image_appearance(i)),
            self.image_hog(i),
            n_classes,
            store,
        )?;
        crate::descriptors::validate::embedding(Values::F32(self.image_embedding(i)))?;
        crate::descriptors::validate::compact_hog(Values::F32(self.image_compact_hog(i)))?;
        crate::descriptors::validate::keypoints(self.keypoints(i), n_classes)?;
        self.poses.get(i).copied().flatten().map_or(Ok(()), |p| crate::descriptors::validate::pose_row(&p.to_row()))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn set(n: usize, global_len: usize, hog_dim: usize) -> DescriptorSet {
        let mut s = DescriptorSet::for_storage(global_len, 1, 0, hog_dim);
        for i in 0..n {
            let forest = crate::local::Forest { neighbour_slots: 1, ..Default::default() };
            let img = EncodedImage {
                id: format!("i{i}"),
                width: 1,
                height: 1,
                global: vec![0.5; global_len],
                global_stats: vec![],
                forest,
                appearance: vec![],
                hog: vec![1.0; hog_dim],
                embedding: vec![],
                compact_hog: vec![],
                keypoints: Default::default(),
                pose: None,
            };
            s.push(&img).unwrap();
        }
        s
    }

    #[test]
    fn appending_another_layout_or_a_range_outside_fails_and_changes_nothing() {
        let mut a = set(2, 4, 0);
        let before = a.clone();
        assert!(a.append(&set(1, 5, 0)).unwrap_err().to_string().contains("do not join"));
        assert!(a.append(&set(1, 4, 3)).is_err());
        assert!(a.append_range(&set(2, 4, 0), 1, 3).unwrap_err().to_string().contains("1..3 of a set of 2"));
        assert!(a.append_range(&set(2, 4, 0), 2, 1).is_err());
        assert_eq!(a, before);
        a.append_range(&set(3, 4, 0), 1, 3).unwrap();
        assert_eq!(a.ids, ["i0", "i1", "i1", "i2"]);
        assert_eq!(a.forest_offsets.len(), 5);
    }
}
