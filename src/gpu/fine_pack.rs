//! Forests in the layout of `shaders/tree_similarity.wgsl`: tree records, appearance vectors and
//! each forest's (first tree, tree count); the map's forests chunked for residency.

use super::resident::{ChunkData, ChunkPlan};
use crate::descriptors::source::{RefSource, SourceKey};
use crate::device::context::{GpuContext, GpuError};
use crate::values::Values;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::abi::{GpuTree, MAX_SLOTS};
use semlook_kernels::tree_similarity::ForestRef;

/// Forests packed for the shader.
#[derive(Default)]
pub(crate) struct Packed {
    pub trees: Vec<GpuTree>,
    pub app: Vec<f32>,
    /// (first tree, tree count) per forest.
    pub spans: Vec<[u32; 2]>,
    pub max_trees: usize,
}

pub(crate) fn pack<'a>(forests: impl Iterator<Item = ForestRef<'a>>, dim: usize, params: &TreeSimParams) -> Packed {
    let mut p = Packed::default();
    for f in forests {
        p.spans.push([p.trees.len() as u32, f.len() as u32]);
        p.max_trees = p.max_trees.max(f.len());
        for t in 0..f.len() {
            let mut nb = [-1i32; MAX_SLOTS];
            let slots = f.neighbour_slots.min(MAX_SLOTS);
            nb[..slots].copy_from_slice(&f.neighbours[t * f.neighbour_slots..t * f.neighbour_slots + slots]);
            p.trees.push(GpuTree {
                class_id: f.classes[t] as u32,
                has_app: f.has_appearance[t] as u32,
                area: f.areas[t],
                cx: f.centroids[2 * t],
                cy: f.centroids[2 * t + 1],
                weight: params.tree_weight(f.areas[t], f.descriptors[t]),
                nb,
            });
        }
        if dim > 0 {
            f.appearance.extend_into(&mut p.app);
        }
    }
    // a storage binding of `array<Tree>` holds at least one record: forests without trees (a map
    // without labels has none) bind one that no span points to
    if p.trees.is_empty() {
        p.trees.push(bytemuck::Zeroable::zeroed());
    }
    p
}

/// Bytes of the three buffers of packed forests: spans, trees (at least the one record of
/// [`pack`]), appearance.
pub(crate) fn packed_bytes(forests: usize, trees: usize, dim: usize) -> [u64; 3] {
    [(forests * 8) as u64, (trees.max(1) * std::mem::size_of::<GpuTree>()) as u64, (trees * dim * 4) as u64]
}

/// The chunks of a map's forests and what the dispatcher needs of every reference: its tree count.
pub(crate) struct ChunkedForests {
    pub plans: Vec<ChunkPlan>,
    /// The map's largest forest.
    pub max_trees: usize,
    /// Trees per reference (saturating at `u16::MAX`), read once per map key: which pairs
    /// `tree_similarity_small` takes is decided from these, never from the forests per batch.
    pub sizes: std::sync::Arc<[u16]>,
}

/// Chunks of the map's forests, each buffer within `limit` bytes, with every reference's tree
/// count. A typed error names a forest too large for one binding.
pub(crate) fn plan_chunks(ctx: &GpuContext, refs: &dyn RefSource, limit: u64) -> Result<ChunkedForests, GpuError> {
    let dim = refs.appearance_dim();
    let (mut plans, mut max_trees, mut sizes) = (Vec::new(), 0, Vec::with_capacity(refs.len()));
    let (mut first, mut trees) = (0, 0);
    for i in 0..refs.len() {
        let t = refs.forest(i).len();
        sizes.push(t.min(u16::MAX as usize) as u16);
        max_trees = max_trees.max(t);
        let fits = |n: usize, tr: usize| packed_bytes(n, tr, dim).iter().all(|&b| b <= limit);
        if !fits(1, t) {
            return Err(GpuError::LimitsTooSmall {
                adapter: ctx.describe(),
                what: format!("the forest of reference {i} in one binding"),
                needed: packed_bytes(1, t, dim).into_iter().max().unwrap_or(0),
                available: limit,
            });
        }
        if !fits(i + 1 - first, trees + t) {
            plans.push(ChunkPlan { first, len: i - first, bytes: packed_bytes(i - first, trees, dim).to_vec() });
            (first, trees) = (i, 0);
        }
        trees += t;
    }
    if refs.len() > first {
        plans.push(ChunkPlan { first, len: refs.len() - first, bytes: packed_bytes(refs.len() - first, trees, dim).to_vec() });
    }
    Ok(ChunkedForests { plans, max_trees, sizes: sizes.into() })
}

/// The map's forests, packed chunk by chunk with the tree weights of `params`.
pub(crate) struct ForestChunks<'a> {
    pub refs: &'a dyn RefSource,
    pub params: TreeSimParams,
}

impl ChunkData for ForestChunks<'_> {
    fn write(&self, ctx: &GpuContext, plan: &ChunkPlan, buffers: &[&wgpu::Buffer]) -> Result<(), GpuError> {
        let p = pack((plan.first..plan.first + plan.len).map(|i| self.refs.forest(i)), self.refs.appearance_dim(), &self.params);
        ctx.write(buffers[0], 0, bytemuck::cast_slice(&p.spans));
        ctx.write(buffers[1], 0, bytemuck::cast_slice(&p.trees));
        ctx.write(buffers[2], 0, bytemuck::cast_slice(&p.app));
        Ok(())
    }
}

/// Forests sampled into the key of a source without a generation (evenly spaced, first and last
/// included), as [`SourceKey::of`] samples descriptors.
pub(crate) const FOREST_SAMPLES: usize = crate::descriptors::source::FINGERPRINT_SAMPLES;
/// Appearance values sampled per sampled forest (evenly spaced over its vectors).
const APPEARANCE_SAMPLES: usize = 16;

/// The key of a map's packed forests, with the tree-weight rule (the packed weights) folded in.
///
/// - A source with a generation (a stored map: its random identity and the generation it was
///   opened at, which any add, remove or compaction changes) is keyed by that alone, with its
///   length and sizes: no forest is read, nothing hashed.
/// - A source without one (an in-memory [`crate::descriptors::DescriptorSet`]) falls back to a
///   cheap sampled key: its length, where its first forest lies in memory, and a hash of
///   [`FOREST_SAMPLES`] forests' tree records (classes, areas, centroids, neighbours, descriptor
///   counts, appearance flags: tens of words a forest) with [`APPEARANCE_SAMPLES`] raw appearance
///   values each (never the whole vectors: at 4,096 values a tree those were megabytes a batch).
///   An edit in place of values not sampled keeps the key: call `forget_map` after one.
pub(crate) fn forest_key(refs: &dyn RefSource, params: &TreeSimParams) -> SourceKey {
    let n = refs.len();
    let sizes = (refs.appearance_dim(), refs.neighbour_slots());
    let rule = (params.tree_weight as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    if let Some(generation) = refs.generation() {
        return SourceKey { len: n, generation: Some(generation), sizes, address: 0, fingerprint: rule };
    }
    let address = if n > 0 { refs.forest(0).classes.as_ptr() as usize } else { 0 };
    let mut h = 0xcbf2_9ce4_8422_2325 ^ rule;
    let mut mix = |w: u32| h = (h ^ w as u64).wrapping_mul(0x0000_0100_0000_01b3);
    let samples = FOREST_SAMPLES.min(n);
    for j in 0..samples {
        let i = if samples == 1 { 0 } else { j * (n - 1) / (samples - 1) };
        let f = refs.forest(i);
        mix(i as u32);
        f.classes.iter().for_each(|&c| mix(c as u32));
        f.areas.iter().chain(f.centroids).for_each(|v| mix(v.to_bits()));
        f.neighbours.iter().for_each(|&v| mix(v as u32));
        f.descriptors.iter().for_each(|&v| mix(v));
        f.has_appearance.iter().for_each(|&v| mix(v as u32));
        sample_values(&f.appearance, APPEARANCE_SAMPLES, &mut mix);
    }
    SourceKey { len: n, generation: None, sizes, address, fingerprint: h }
}

/// Feeds `count` evenly spaced stored values of `v` (their raw bits; for blocks, the stored block
/// ids, exponents and values) to `mix`, without widening the run.
fn sample_values(v: &Values, count: usize, mix: &mut impl FnMut(u32)) {
    fn spaced<T: Copy>(s: &[T], count: usize, mut f: impl FnMut(T)) {
        let k = count.min(s.len());
        for j in 0..k {
            f(s[if k == 1 { 0 } else { j * (s.len() - 1) / (k - 1) }]);
        }
    }
    mix(v.len() as u32);
    match v {
        Values::F32(s) => spaced(s, count, |x| mix(x.to_bits())),
        Values::F16(s) => spaced(s, count, |x| mix(x as u32)),
        Values::Blocks(b) => {
            spaced(b.offsets, count, &mut *mix);
            spaced(b.ids, count, |x| mix(x as u32));
            spaced(b.exponents, count, |x| mix(x as u32));
            spaced(b.values, count, |x| mix(x as u32));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::descriptors::keypoints::KeypointsRef;
    use crate::descriptors::source::{GlobalSource, TileBuf};
    use crate::descriptors::DescriptorSet;
    use std::sync::atomic::{AtomicUsize, Ordering};

    /// A set served with or without a generation, counting its forest reads.
    struct Counted<'a> {
        set: &'a DescriptorSet,
        generation: Option<u64>,
        reads: AtomicUsize,
    }

    impl GlobalSource for Counted<'_> {
        fn len(&self) -> usize {
            self.set.len()
        }
        fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
            self.set.tile(start, end, buf)
        }
        fn generation(&self) -> Option<u64> {
            self.generation
        }
    }

    impl RefSource for Counted<'_> {
        fn id(&self, i: usize) -> &str {
            self.set.id(i)
        }
        fn forest(&self, i: usize) -> ForestRef<'_> {
            self.reads.fetch_add(1, Ordering::Relaxed);
            self.set.forest(i)
        }
        fn neighbour_slots(&self) -> usize {
            self.set.neighbour_slots
        }
        fn appearance_dim(&self) -> usize {
            self.set.appearance_dim
        }
        fn image_appearance(&self, i: usize) -> Values<'_> {
            RefSource::image_appearance(self.set, i)
        }
        fn hog_dim(&self) -> usize {
            0
        }
        fn image_hog(&self, _: usize) -> &[f32] {
            &[]
        }
        fn keypoint_dim(&self) -> usize {
            0
        }
        fn keypoints(&self, i: usize) -> KeypointsRef<'_> {
            self.set.keypoints(i)
        }
    }

    /// `n` images of 20 trees each with `dim` appearance values per tree.
    fn set(n: usize, dim: usize) -> DescriptorSet {
        let p = crate::config::GlobalConfig::default().ssim_params();
        let mut set = DescriptorSet::new(&p, 3, dim, 0);
        for i in 0..n {
            let trees = 20;
            let f = crate::local::Forest {
                classes: (0..trees).map(|t| (t % 7) as u8).collect(),
                areas: (0..trees).map(|t| 0.01 * (1 + t + i) as f32).collect(),
                centroids: vec![0.5; 2 * trees],
                neighbours: vec![-1; 3 * trees],
                neighbour_slots: 3,
                appearance: (0..trees * dim).map(|k| ((k + i) % 13) as f32 / 13.0).collect(),
                has_appearance: vec![1; trees],
                descriptors: vec![3; trees],
                dim,
            };
            let img = crate::descriptors::EncodedImage {
                id: format!("i{i}"),
                width: 10,
                height: 10,
                global: vec![0.5; p.len()],
                global_stats: vec![0.0; p.stats_len()],
                forest: f,
                appearance: vec![0.0; dim],
                hog: vec![],
                embedding: vec![],
                compact_hog: vec![],
                keypoints: Default::default(),
                pose: None,
            };
            set.push(&img).unwrap();
        }
        set
    }

    /// A source with a generation (a stored map's identity and generation) is keyed by it alone:
    /// no forest is read for the key; another generation or tree-weight rule is another key.
    #[test]
    fn a_source_with_a_generation_is_keyed_without_reading_a_forest() {
        let s = set(100, 64);
        let p = crate::config::SimilarityConfig::default().tree_params(true, 3);
        let src = Counted { set: &s, generation: Some(7), reads: AtomicUsize::new(0) };
        let key = forest_key(&src, &p);
        assert_eq!(src.reads.load(Ordering::Relaxed), 0, "forests read for a generation's key");
        assert_eq!((key.generation, key.len), (Some(7), 100));
        assert_eq!(key, forest_key(&src, &p));
        let next = Counted { set: &s, generation: Some(8), reads: AtomicUsize::new(0) };
        assert_ne!(key, forest_key(&next, &p), "a new generation (add, remove, compact) is a new key");
        let sqrt = TreeSimParams { tree_weight: 2, ..p };
        assert_ne!(key, forest_key(&src, &sqrt), "other packed weights are another map");
    }

    /// Without a generation, the key reads at most FOREST_SAMPLES forests and never their whole
    /// appearance: it is the same with 16 or 4,096 values a tree except for the sampled values.
    #[test]
    fn a_source_without_one_gets_a_cheap_sampled_key() {
        let p = crate::config::SimilarityConfig::default().tree_params(true, 3);
        let mut s = set(200, 4096);
        let key_of = |s: &DescriptorSet| {
            let src = Counted { set: s, generation: None, reads: AtomicUsize::new(0) };
            let key = forest_key(&src, &p);
            assert!(src.reads.load(Ordering::Relaxed) <= FOREST_SAMPLES + 1, "{} forests read", src.reads.load(Ordering::Relaxed));
            key
        };
        let key = key_of(&s);
        assert_eq!(key, key_of(&s), "the same set, the same key");
        assert_ne!(key, key_of(&s.clone()), "a copy lies elsewhere");
        let mut words = 0;
        sample_values(&s.forest(0).appearance, APPEARANCE_SAMPLES, &mut |_| words += 1);
        assert_eq!(words, 1 + APPEARANCE_SAMPLES, "appearance words hashed for 20 trees of 4,096 values");
        // an edit in place of a sampled forest's record or sampled appearance is another key
        s.tree_areas[0] += 1.0;
        let area = key_of(&s);
        assert_ne!(key, area);
        s.tree_appearance[0] += 1.0;
        assert_ne!(area, key_of(&s));
    }
}
