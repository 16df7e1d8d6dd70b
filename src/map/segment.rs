//! One map segment file: a [`DescriptorSet`] as safetensors (readable from Python with
//! `safetensors.numpy.load_file`), with the image ids in the header metadata.

use super::DescriptorSet;
use safetensors::tensor::{Dtype, TensorView};
use safetensors::SafeTensors;
use std::collections::HashMap;

fn view<'a>(dtype: Dtype, shape: Vec<usize>, bytes: &'a [u8]) -> TensorView<'a> {
    TensorView::new(dtype, shape, bytes).expect("shape matches data")
}

/// Serialises a descriptor set to safetensors bytes.
pub fn to_bytes(set: &DescriptorSet, gw: usize, gh: usize) -> Vec<u8> {
    let (n, t) = (set.len(), set.n_trees());
    let sizes: Vec<u32> = set.sizes.iter().flatten().copied().collect();
    let tensors = vec![
        ("global", view(Dtype::F32, vec![n, gh, gw], bytemuck::cast_slice(&set.globals))),
        ("global_stats", view(Dtype::F32, vec![n, set.stats_len], bytemuck::cast_slice(&set.global_stats))),
        ("image_size", view(Dtype::U32, vec![n, 2], bytemuck::cast_slice(&sizes))),
        ("forest_offsets", view(Dtype::U32, vec![n + 1], bytemuck::cast_slice(&set.forest_offsets))),
        ("tree_class", view(Dtype::U8, vec![t], &set.tree_classes)),
        ("tree_area", view(Dtype::F32, vec![t], bytemuck::cast_slice(&set.tree_areas))),
        ("tree_centroid", view(Dtype::F32, vec![t, 2], bytemuck::cast_slice(&set.tree_centroids))),
        ("tree_neighbours", view(Dtype::I32, vec![t, set.neighbour_slots], bytemuck::cast_slice(&set.tree_neighbours))),
        ("tree_appearance", view(Dtype::F32, vec![t, set.appearance_dim], bytemuck::cast_slice(&set.tree_appearance))),
        ("tree_has_appearance", view(Dtype::U8, vec![t], &set.tree_has_appearance)),
        ("tree_descriptors", view(Dtype::U32, vec![t], bytemuck::cast_slice(&set.tree_descriptors))),
        ("image_appearance", view(Dtype::F32, vec![n, set.appearance_dim], bytemuck::cast_slice(&set.image_appearance))),
        ("image_hog", view(Dtype::F32, vec![n, set.hog_dim], bytemuck::cast_slice(&set.image_hog))),
    ];
    let meta = HashMap::from([("ids".to_string(), serde_json::to_string(&set.ids).expect("ids serialise"))]);
    safetensors::serialize(tensors, Some(meta)).expect("tensors serialise")
}

/// Parses segment bytes; every shape and dtype is checked against the expected layout. The
/// caller validates the values (`DescriptorSet::validate`).
pub fn from_bytes(bytes: &[u8], gw: usize, gh: usize, stats_len: usize, slots: usize, dim: usize, hog_dim: usize) -> Result<DescriptorSet, String> {
    let (_, meta) = SafeTensors::read_metadata(bytes).map_err(|e| format!("not a safetensors file: {e}"))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| format!("not a safetensors file: {e}"))?;
    let ids: Vec<String> = meta
        .metadata()
        .as_ref()
        .and_then(|m| m.get("ids"))
        .ok_or("header metadata has no image ids")
        .and_then(|s| serde_json::from_str(s).map_err(|_| "image ids in the header are not a JSON list of strings"))?;
    let n = ids.len();
    let get = |name: &str, dtype: Dtype, shape: &[Option<usize>]| -> Result<&[u8], String> {
        let t = st.tensor(name).map_err(|_| format!("tensor {name:?} is missing"))?;
        let ok = t.dtype() == dtype
            && t.shape().len() == shape.len()
            && t.shape().iter().zip(shape).all(|(a, b)| b.is_none_or(|b| *a == b));
        if !ok {
            return Err(format!("tensor {name:?} is {:?} {:?}, expected {dtype:?} {shape:?}", t.dtype(), t.shape()));
        }
        Ok(t.data())
    };
    let f32s = |b: &[u8]| -> Vec<f32> { bytemuck::pod_collect_to_vec(b) };
    let offsets: Vec<u32> = bytemuck::pod_collect_to_vec(get("forest_offsets", Dtype::U32, &[Some(n + 1)])?);
    let t = *offsets.last().ok_or("forest offsets are empty")? as usize;
    let sizes: Vec<u32> = bytemuck::pod_collect_to_vec(get("image_size", Dtype::U32, &[Some(n), Some(2)])?);
    Ok(DescriptorSet {
        sizes: sizes.chunks_exact(2).map(|c| [c[0], c[1]]).collect(),
        global_len: gw * gh,
        stats_len,
        globals: f32s(get("global", Dtype::F32, &[Some(n), Some(gh), Some(gw)])?),
        global_stats: f32s(get("global_stats", Dtype::F32, &[Some(n), Some(stats_len)])?),
        forest_offsets: offsets,
        tree_classes: get("tree_class", Dtype::U8, &[Some(t)])?.to_vec(),
        tree_areas: f32s(get("tree_area", Dtype::F32, &[Some(t)])?),
        tree_centroids: f32s(get("tree_centroid", Dtype::F32, &[Some(t), Some(2)])?),
        neighbour_slots: slots,
        tree_neighbours: bytemuck::pod_collect_to_vec(get("tree_neighbours", Dtype::I32, &[Some(t), Some(slots)])?),
        appearance_dim: dim,
        tree_appearance: f32s(get("tree_appearance", Dtype::F32, &[Some(t), Some(dim)])?),
        tree_has_appearance: get("tree_has_appearance", Dtype::U8, &[Some(t)])?.to_vec(),
        tree_descriptors: bytemuck::pod_collect_to_vec(get("tree_descriptors", Dtype::U32, &[Some(t)])?),
        image_appearance: f32s(get("image_appearance", Dtype::F32, &[Some(n), Some(dim)])?),
        hog_dim,
        image_hog: f32s(get("image_hog", Dtype::F32, &[Some(n), Some(hog_dim)])?),
        ids,
    })
}
