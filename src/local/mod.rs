//! Stage 2b: the local descriptor, a "forest" of one "tree" per semantic object (`docs/design/method.md` §2.5-2.6).
//!
//! A tree holds its object's class C, area A (fraction of the image), centroid P (pixels divided
//! by the image diagonal, so that ||P_t - P_u|| is method.md §2.8's ||ΔP|| / D), an appearance vector V
//! (SuperPoint/XFeat-VLAD; absent until an appearance model fills it), and the indices of its
//! neighbour trees in the same image. Neighbours are not copied: their class and appearance are
//! read through the index (method.md §2.6 storage note).

use crate::config::LocalConfig;
use crate::objects::ObjectMap;
use crate::values::Values;
use semlook_kernels::tree_similarity::ForestRef;

/// Marks an empty neighbour slot.
pub const NO_NEIGHBOUR: i32 = -1;

/// The forest of one image, as parallel arrays (the layout of the map file and of the GPU).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Forest {
    /// Semantic class of each tree.
    pub classes: Vec<u8>,
    /// Area of each tree's object, as a fraction of the image.
    pub areas: Vec<f32>,
    /// (x, y) per tree, in image diagonals.
    pub centroids: Vec<f32>,
    /// `neighbour_slots` entries per tree: indices into this forest, or [`NO_NEIGHBOUR`].
    pub neighbours: Vec<i32>,
    /// Neighbour slots per tree.
    pub neighbour_slots: usize,
    /// `dim` values per tree (zeros where `has_appearance` is 0).
    pub appearance: Vec<f32>,
    /// 1 where a tree has an appearance vector, else 0.
    pub has_appearance: Vec<u8>,
    /// Appearance descriptors (keypoints or dense cells) inside each tree's object.
    pub descriptors: Vec<u32>,
    /// Values per appearance vector (0: no appearance).
    pub dim: usize,
}

impl Forest {
    /// Number of trees.
    pub fn len(&self) -> usize {
        self.classes.len()
    }
    /// Whether the forest has no trees.
    pub fn is_empty(&self) -> bool {
        self.classes.is_empty()
    }
    /// The forest borrowed.
    pub fn as_ref(&self) -> ForestRef<'_> {
        ForestRef {
            classes: &self.classes,
            areas: &self.areas,
            centroids: &self.centroids,
            neighbours: &self.neighbours,
            neighbour_slots: self.neighbour_slots,
            appearance: Values::F32(&self.appearance),
            has_appearance: &self.has_appearance,
            descriptors: &self.descriptors,
            dim: self.dim,
        }
    }
    /// Neighbour indices of tree `k` (filled slots only).
    pub fn neighbours_of(&self, k: usize) -> Vec<usize> {
        self.as_ref().neighbours_of(k).collect()
    }
    /// Sets (or replaces) the appearance vectors: `vectors` holds `dim` values per tree,
    /// `counts` the descriptors each was aggregated from; trees with fewer than `min_count`
    /// (and at least one) have no appearance. Other lengths fail (an [`crate::Error::Check`]), the
    /// forest unchanged.
    pub fn set_appearance(&mut self, dim: usize, mut vectors: Vec<f32>, counts: Vec<u32>, min_count: usize) -> crate::Result<()> {
        if vectors.len() != dim * self.len() || counts.len() != self.len() {
            return Err(crate::Error::check(format!(
                "{} appearance values and {} counts for {} trees of dimension {dim}",
                vectors.len(),
                counts.len(),
                self.len()
            )));
        }
        let present: Vec<u8> = counts.iter().map(|&c| (c > 0 && c as usize >= min_count) as u8).collect();
        for (k, &p) in present.iter().enumerate() {
            if p == 0 {
                vectors[k * dim..(k + 1) * dim].fill(0.0);
            }
        }
        self.dim = dim;
        self.appearance = vectors;
        self.has_appearance = present;
        self.descriptors = counts;
        Ok(())
    }
}

/// Builds the forest of an image's objects; appearance is left empty (dim 0).
///
/// Neighbour rule (method.md §2.5, \[Q\] with \[R\] tolerance): candidates are ordered by centroid distance;
/// repeatedly, among the remaining candidates within `tie_tolerance` of the nearest remaining one,
/// the largest (then the nearest, then the first) is taken, until `neighbours` are chosen.
pub fn build_forest(objects: &ObjectMap, cfg: &LocalConfig) -> Forest {
    let (w, h) = (objects.width as f64, objects.height as f64);
    let diag = (w * w + h * h).sqrt();
    let n = objects.objects.len();
    let slots = cfg.neighbours;
    let mut forest = Forest { neighbour_slots: slots, ..Default::default() };
    for o in &objects.objects {
        forest.classes.push(o.class);
        forest.areas.push((o.area / (w * h)) as f32);
        forest.centroids.push((o.centroid[0] / diag) as f32);
        forest.centroids.push((o.centroid[1] / diag) as f32);
    }
    forest.has_appearance = vec![0; n];
    forest.descriptors = vec![0; n];
    let pos = |k: usize| [forest.centroids[2 * k] as f64, forest.centroids[2 * k + 1] as f64];
    let mut cand: Vec<(f64, usize)> = Vec::with_capacity(n);
    for k in 0..n {
        let pk = pos(k);
        cand.clear();
        cand.extend((0..n).filter(|&j| j != k).map(|j| {
            let pj = pos(j);
            (((pk[0] - pj[0]).powi(2) + (pk[1] - pj[1]).powi(2)).sqrt(), j)
        }));
        cand.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1)));
        let mut chosen = Vec::with_capacity(slots);
        while chosen.len() < slots && !cand.is_empty() {
            let limit = cand[0].0 + cfg.tie_tolerance;
            let group = cand.iter().take_while(|c| c.0 < limit).count().max(1);
            let best = (0..group)
                .max_by(|&a, &b| {
                    let (aa, ab) = (objects.objects[cand[a].1].area, objects.objects[cand[b].1].area);
                    aa.total_cmp(&ab).then(b.cmp(&a)) // larger area; on equal area the earlier (nearer)
                })
                .unwrap_or(0); // group >= 1
            chosen.push(cand.remove(best).1 as i32);
        }
        chosen.resize(slots, NO_NEIGHBOUR);
        forest.neighbours.extend(chosen);
    }
    forest
}

#[cfg(test)]
mod tree_similarity_tests;

#[cfg(test)]
mod tests {
    use super::*;
    use crate::objects::SemanticObject;

    fn obj(class: u8, area: f64, x: f64, y: f64) -> SemanticObject {
        SemanticObject { class, area, pixel_count: area as u32, centroid: [x, y], bbox: [0, 0, 1, 1] }
    }

    #[test]
    fn neighbours_nearest_first_and_ties_go_to_the_larger() {
        // image 300 x 400: diagonal 500; tolerance 0.02 -> 10 px
        let objects = vec![
            obj(0, 100.0, 100.0, 100.0), // 0: the tree under test
            obj(1, 10.0, 150.0, 100.0),  // 1: 50 px
            obj(2, 500.0, 100.0, 155.0), // 2: 55 px, within 10 px of #1 and larger
            obj(3, 50.0, 100.0, 300.0),  // 3: 200 px
            obj(4, 60.0, 300.0, 100.0),  // 4: 200 px, tie with #3, larger
        ];
        let om = ObjectMap { width: 300, height: 400, objects, object_of_pixel: vec![] };
        let f = build_forest(&om, &LocalConfig::default());
        assert_eq!(f.neighbours_of(0), vec![2, 1, 4]);
        assert!((f.centroids[0] - 0.2).abs() < 1e-6 && (f.areas[2] - 500.0 / 120000.0).abs() < 1e-9);
        let strict = build_forest(&om, &LocalConfig { tie_tolerance: 0.0, ..Default::default() });
        assert_eq!(strict.neighbours_of(0), vec![1, 2, 3]);
    }

    #[test]
    fn small_forests_leave_slots_empty() {
        let om = ObjectMap { width: 10, height: 10, objects: vec![obj(0, 5.0, 1.0, 1.0), obj(1, 5.0, 5.0, 5.0)], object_of_pixel: vec![] };
        let f = build_forest(&om, &LocalConfig::default());
        assert_eq!(&f.neighbours[..3], &[1, NO_NEIGHBOUR, NO_NEIGHBOUR]);
    }
}
