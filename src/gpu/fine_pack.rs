//! Forests in the layout of `shaders/tree_similarity.wgsl`: tree records, appearance vectors and
//! each forest's (first tree, tree count); the map's forests chunked for residency.

use super::context::{GpuContext, GpuError};
use super::resident::{ChunkData, ChunkPlan};
use crate::kernels::abi::TreeSimParams;
use crate::kernels::abi::{GpuTree, MAX_SLOTS};
use crate::kernels::tree_similarity::ForestRef;
use crate::matching::source::{RefSource, SourceKey};

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
    p
}

/// Bytes of the three buffers of packed forests: spans, trees, appearance.
pub(crate) fn packed_bytes(forests: usize, trees: usize, dim: usize) -> [u64; 3] {
    [(forests * 8) as u64, (trees * std::mem::size_of::<GpuTree>()) as u64, (trees * dim * 4) as u64]
}

/// Chunks of the map's forests, each buffer within `limit` bytes, and the map's largest forest.
/// A typed error names a forest too large for one binding.
pub(crate) fn plan_chunks(ctx: &GpuContext, refs: &dyn RefSource, limit: u64) -> Result<(Vec<ChunkPlan>, usize), GpuError> {
    let dim = refs.appearance_dim();
    let (mut plans, mut max_trees) = (Vec::new(), 0);
    let (mut first, mut trees) = (0, 0);
    for i in 0..refs.len() {
        let t = refs.forest(i).len();
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
    Ok((plans, max_trees))
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

/// The key of a map's packed forests: the map's key, with the hash of sampled forests (classes,
/// areas, centroids, neighbours, descriptor counts, appearance) and the tree-weight rule folded in.
pub(crate) fn forest_key(refs: &dyn RefSource, params: &TreeSimParams) -> SourceKey {
    let mut key = SourceKey::of(refs);
    let n = refs.len();
    let samples = crate::matching::source::FINGERPRINT_SAMPLES.min(n);
    let mut h = key.fingerprint ^ (params.tree_weight as u64).wrapping_mul(0x9e37_79b9_7f4a_7c15);
    for j in 0..samples {
        let i = if samples == 1 { 0 } else { j * (n - 1) / (samples - 1) };
        let f = refs.forest(i);
        let app = f.appearance.to_vec();
        let words = f
            .classes
            .iter()
            .map(|&c| c as u32)
            .chain(f.areas.iter().chain(f.centroids).chain(&app).map(|v| v.to_bits()))
            .chain(f.neighbours.iter().map(|&v| v as u32))
            .chain(f.descriptors.iter().copied())
            .chain(f.has_appearance.iter().map(|&v| v as u32));
        for w in words {
            h = (h ^ w as u64).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }
    key.fingerprint = h;
    key
}
