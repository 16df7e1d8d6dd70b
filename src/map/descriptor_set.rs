//! Columnar storage of many encoded images: the in-memory form of a map, of a map segment file,
//! and of a batch of queries. Forests are concatenated, with `forest_offsets[i]..[i + 1]` the trees
//! of image i; neighbour indices stay local to their forest.

use crate::encode::EncodedImage;
use crate::global::ssim::SsimParams;
use crate::local::ForestRef;

#[derive(Debug, Clone, PartialEq)]
pub struct DescriptorSet {
    pub ids: Vec<String>,
    /// (width, height) of each source image.
    pub sizes: Vec<[u32; 2]>,
    pub global_len: usize,
    pub stats_len: usize,
    pub globals: Vec<f32>,
    pub global_stats: Vec<f32>,
    pub forest_offsets: Vec<u32>,
    pub tree_classes: Vec<u8>,
    pub tree_areas: Vec<f32>,
    pub tree_centroids: Vec<f32>,
    pub neighbour_slots: usize,
    pub tree_neighbours: Vec<i32>,
    pub appearance_dim: usize,
    pub tree_appearance: Vec<f32>,
    pub tree_has_appearance: Vec<u8>,
    /// Appearance descriptors each tree's VLAD was aggregated from.
    pub tree_descriptors: Vec<u32>,
    /// Per image, the VLAD of all its descriptors (`appearance_dim` values; zeros without
    /// appearance): the whole-image `appearance` baseline.
    pub image_appearance: Vec<f32>,
    /// Per image, the VPR-Bench HOG descriptor (`hog_dim` values; 0 when not computed).
    pub hog_dim: usize,
    pub image_hog: Vec<f32>,
}

impl DescriptorSet {
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
        }
    }

    pub fn len(&self) -> usize {
        self.ids.len()
    }
    pub fn is_empty(&self) -> bool {
        self.ids.is_empty()
    }
    pub fn n_trees(&self) -> usize {
        self.tree_classes.len()
    }

    /// Appends one image. Its global size, neighbour slots and appearance dimension must match
    /// the set's (an image without appearance gets zero vectors flagged absent; without HOG,
    /// zeros), else the set is unchanged and the mismatch is returned.
    pub fn push(&mut self, img: &EncodedImage) -> Result<(), String> {
        let f = &img.forest;
        if img.global.len() != self.global_len || img.global_stats.len() != self.stats_len || f.neighbour_slots != self.neighbour_slots {
            return Err(format!("image {:?} has another global descriptor size or neighbour count than the set", img.id));
        }
        if (f.dim != self.appearance_dim && f.dim != 0) || (!img.appearance.is_empty() && img.appearance.len() != self.appearance_dim) {
            return Err(format!("image {:?} has appearance of dimension {}, the set {}", img.id, f.dim, self.appearance_dim));
        }
        if !img.hog.is_empty() && img.hog.len() != self.hog_dim {
            return Err(format!("image {:?} has a HOG descriptor of {} values, the set {}", img.id, img.hog.len(), self.hog_dim));
        }
        self.ids.push(img.id.clone());
        self.sizes.push([img.width, img.height]);
        self.globals.extend_from_slice(&img.global);
        self.global_stats.extend_from_slice(&img.global_stats);
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
        self.forest_offsets.push(self.tree_classes.len() as u32);
        Ok(())
    }

    /// Appends all images of `other` (same layout).
    pub fn append(&mut self, other: &DescriptorSet) {
        assert_eq!((self.global_len, self.stats_len, self.neighbour_slots), (other.global_len, other.stats_len, other.neighbour_slots));
        assert_eq!((self.appearance_dim, self.hog_dim), (other.appearance_dim, other.hog_dim));
        let base = self.n_trees() as u32;
        self.ids.extend_from_slice(&other.ids);
        self.sizes.extend_from_slice(&other.sizes);
        self.globals.extend_from_slice(&other.globals);
        self.global_stats.extend_from_slice(&other.global_stats);
        self.forest_offsets.extend(other.forest_offsets[1..].iter().map(|o| o + base));
        self.tree_classes.extend_from_slice(&other.tree_classes);
        self.tree_areas.extend_from_slice(&other.tree_areas);
        self.tree_centroids.extend_from_slice(&other.tree_centroids);
        self.tree_neighbours.extend_from_slice(&other.tree_neighbours);
        self.tree_appearance.extend_from_slice(&other.tree_appearance);
        self.tree_has_appearance.extend_from_slice(&other.tree_has_appearance);
        self.tree_descriptors.extend_from_slice(&other.tree_descriptors);
        self.image_appearance.extend_from_slice(&other.image_appearance);
        self.image_hog.extend_from_slice(&other.image_hog);
    }

    /// Images `start..end` as a set of their own.
    pub fn slice(&self, start: usize, end: usize) -> DescriptorSet {
        let (a, b) = (self.forest_offsets[start] as usize, self.forest_offsets[end] as usize);
        let (n, d) = (self.neighbour_slots, self.appearance_dim);
        DescriptorSet {
            ids: self.ids[start..end].to_vec(),
            sizes: self.sizes[start..end].to_vec(),
            global_len: self.global_len,
            stats_len: self.stats_len,
            globals: self.globals[start * self.global_len..end * self.global_len].to_vec(),
            global_stats: self.global_stats[start * self.stats_len..end * self.stats_len].to_vec(),
            forest_offsets: self.forest_offsets[start..=end].iter().map(|o| o - a as u32).collect(),
            tree_classes: self.tree_classes[a..b].to_vec(),
            tree_areas: self.tree_areas[a..b].to_vec(),
            tree_centroids: self.tree_centroids[2 * a..2 * b].to_vec(),
            neighbour_slots: n,
            tree_neighbours: self.tree_neighbours[n * a..n * b].to_vec(),
            appearance_dim: d,
            tree_appearance: self.tree_appearance[d * a..d * b].to_vec(),
            tree_has_appearance: self.tree_has_appearance[a..b].to_vec(),
            tree_descriptors: self.tree_descriptors[a..b].to_vec(),
            image_appearance: self.image_appearance[start * d..end * d].to_vec(),
            hog_dim: self.hog_dim,
            image_hog: self.image_hog[start * self.hog_dim..end * self.hog_dim].to_vec(),
        }
    }

    pub fn global(&self, i: usize) -> &[f32] {
        &self.globals[i * self.global_len..(i + 1) * self.global_len]
    }
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
    pub fn forest(&self, i: usize) -> ForestRef<'_> {
        let (a, b) = (self.forest_offsets[i] as usize, self.forest_offsets[i + 1] as usize);
        let (n, d) = (self.neighbour_slots, self.appearance_dim);
        ForestRef {
            classes: &self.tree_classes[a..b],
            areas: &self.tree_areas[a..b],
            centroids: &self.tree_centroids[2 * a..2 * b],
            neighbours: &self.tree_neighbours[n * a..n * b],
            neighbour_slots: n,
            appearance: &self.tree_appearance[d * a..d * b],
            has_appearance: &self.tree_has_appearance[a..b],
            descriptors: &self.tree_descriptors[a..b],
            dim: d,
        }
    }

    /// Checks internal consistency (lengths, offsets, neighbour indices, classes below
    /// `n_classes`, finite values); the error says what is wrong. Used on every loaded file.
    pub fn validate(&self, n_classes: usize) -> Result<(), String> {
        let n = self.len();
        let t = self.n_trees();
        let check = |ok: bool, what: &str| if ok { Ok(()) } else { Err(what.to_string()) };
        check(self.sizes.len() == n, "image size count differs from id count")?;
        check(self.globals.len() == n * self.global_len, "global descriptor array has the wrong length")?;
        check(self.global_stats.len() == n * self.stats_len, "global stats array has the wrong length")?;
        check(self.forest_offsets.len() == n + 1 && self.forest_offsets[0] == 0, "forest offsets have the wrong length")?;
        check(self.forest_offsets.windows(2).all(|w| w[0] <= w[1]), "forest offsets decrease")?;
        check(*self.forest_offsets.last().unwrap() as usize == t, "forest offsets do not end at the tree count")?;
        check(self.tree_areas.len() == t && self.tree_centroids.len() == 2 * t, "tree arrays have different lengths")?;
        check(self.tree_neighbours.len() == t * self.neighbour_slots, "neighbour array has the wrong length")?;
        check(self.tree_appearance.len() == t * self.appearance_dim && self.tree_has_appearance.len() == t && self.tree_descriptors.len() == t, "appearance arrays have the wrong length")?;
        check(self.image_appearance.len() == n * self.appearance_dim && self.image_hog.len() == n * self.hog_dim, "image appearance or HOG arrays have the wrong length")?;
        check(self.sizes.iter().all(|s| s[0] > 0 && s[1] > 0), "an image size is zero")?;
        check(self.tree_classes.iter().all(|&c| (c as usize) < n_classes), "a tree has a class outside the class table")?;
        let finite = |v: &[f32]| v.iter().all(|x| x.is_finite());
        check(finite(&self.globals) && finite(&self.global_stats), "global descriptors hold NaN or infinity")?;
        check(finite(&self.tree_areas) && finite(&self.tree_centroids) && finite(&self.tree_appearance), "trees hold NaN or infinity")?;
        check(finite(&self.image_appearance) && finite(&self.image_hog), "image appearance or HOG holds NaN or infinity")?;
        check(self.globals.iter().all(|v| (0.0..=1.0).contains(v)), "global descriptor values outside [0, 1]")?;
        for i in 0..n {
            let (a, b) = (self.forest_offsets[i] as usize, self.forest_offsets[i + 1] as usize);
            let size = (b - a) as i32;
            let nb = &self.tree_neighbours[a * self.neighbour_slots..b * self.neighbour_slots];
            check(nb.iter().all(|&j| j >= -1 && j < size), "a neighbour index points outside its forest")?;
        }
        let mut seen = std::collections::HashSet::new();
        if let Some(dup) = self.ids.iter().find(|id| !seen.insert(id.as_str())) {
            return Err(format!("image id {dup:?} appears twice"));
        }
        Ok(())
    }
}
