//! Matching for the baselines (`hog`, `appearance`): one vector per image, unit length, ranked by
//! cosine similarity (a dot product), streamed over tiles of the map into per-query top-K lists
//! like the coarse stage. Runs on the CPU whatever the backend: baselines are a floor to compare
//! against, not a path to accelerate.

use super::coarse_cpu::stream_topk;
use super::setting::Setting;
use crate::descriptors::source::RefSource;
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Result};
use crate::values::Values;
use rayon::prelude::*;

/// How a baseline reads a query's vector and a reference's.
type QueryVector = fn(&DescriptorSet, usize) -> &[f32];
type RefVector = fn(&dyn RefSource, usize) -> Values<'_>;

/// The vector a baseline compares, of query `i` and of reference `j`.
fn vectors(setting: Setting) -> (QueryVector, RefVector) {
    match setting {
        Setting::Hog => (DescriptorSet::image_hog, |r, j| Values::F32(r.image_hog(j))),
        _ => (DescriptorSet::image_appearance, |r, j| r.image_appearance(j)),
    }
}

/// Why `refs` and `queries` cannot be compared by `setting`, if they cannot.
pub fn unavailable(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting) -> Option<String> {
    match setting {
        Setting::Hog if refs.hog_dim() == 0 || queries.hog_dim == 0 => {
            Some("no HOG descriptors (store them when building the map, or evaluate without a stored map)".into())
        }
        Setting::Appearance if refs.appearance_dim() == 0 || queries.appearance_dim == 0 => {
            Some("no appearance (the keypoint network is off)".into())
        }
        _ => None,
    }
}

/// The cosine similarity `setting` gives query `q` and reference `r` (its vectors are unit
/// length; [`unavailable`] says whether both have them).
pub fn pair_cosine(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, q: usize, r: usize) -> f32 {
    let (query_vec, ref_vec) = vectors(setting);
    Values::F32(query_vec(queries, q)).dot(&ref_vec(refs, r))
}

/// For each query, the `k` references of highest cosine similarity under `setting`.
pub fn topk(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, k: usize, tile: usize) -> Result<Vec<Vec<(f32, u32)>>> {
    if let Some(why) = unavailable(refs, queries, setting) {
        if setting == Setting::Hog && refs.hog_dim() == 0 {
            return Err(Error::refused(format!("setting {setting}"), why, crate::error::Remedy::RebuildWithHog));
        }
        return Err(Error::invalid(format!("setting {setting}"), why));
    }
    let (query_vec, ref_vec) = vectors(setting);
    Ok(stream_topk(queries.len(), refs.len(), k, tile, semlook_kernels::ssim_topk::topk_merge, |tp, scores| {
        let (start, t) = (tp.tile_start as usize, tp.tile_len as usize);
        scores.par_iter_mut().enumerate().for_each(|(i, s)| {
            let (q, r) = (query_vec(queries, i / t), ref_vec(refs, start + i % t));
            *s = Values::F32(q).dot(&r);
        });
    }))
}
