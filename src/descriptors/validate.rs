//! The value checks of one stored image: what a map refuses before it writes an image, and what it
//! checks again when it first reads a segment. Each check says what is wrong (an [`Error::Check`]);
//! the caller names the image or the file ([`Error::named`]).

use crate::error::{Error, Result};
use crate::values::{ValueType, Values, F16_MAX};
use semlook_kernels::tree_similarity::ForestRef;

/// Longest image id, in bytes: ids are file stems or dataset keys, and a bound keeps a damaged or
/// hostile id table from producing megabyte-long messages and lines.
pub const MAX_ID_BYTES: usize = 1024;

/// Where a global descriptor value may lie: the encoder's pooled distance transform is in [0, 1].
const GLOBAL_RANGE: std::ops::RangeInclusive<f32> = 0.0..=1.0;
/// Longest appearance vector accepted: VLAD vectors are L2-normalised, and rounding to the stored
/// int8 blocks moves a length by well under 1 %.
pub const MAX_APPEARANCE_NORM: f32 = 1.02;
/// Where a tree's area fraction may lie.
const AREA_RANGE: std::ops::RangeInclusive<f32> = 0.0..=1.0;

/// Checks an image id: not empty, at most [`MAX_ID_BYTES`], no control characters (ids are written
/// one per line and into CSV files).
pub fn id(id: &str) -> Result<()> {
    if id.is_empty() || id.len() > MAX_ID_BYTES {
        return Err(Error::check(format!("image id is empty or longer than {MAX_ID_BYTES} bytes")));
    }
    if id.chars().any(char::is_control) {
        return Err(Error::check("image id holds a control character"));
    }
    Ok(())
}

/// Checks every value of one image: id, size, global descriptor in [0, 1], tree classes below
/// `n_classes`, areas in [0, 1], finite centroids, neighbour indices inside the forest, finite
/// appearance and HOG values, and, for f16 storage, appearance values that f16 can hold.
#[allow(clippy::too_many_arguments)]
pub fn image(
    id_: &str,
    size: [u32; 2],
    global: Values,
    forest: ForestRef,
    appearance: Values,
    hog: &[f32],
    n_classes: usize,
    store: ValueType,
) -> Result<()> {
    id(id_)?;
    if size[0] == 0 || size[1] == 0 {
        return Err(Error::check(format!("image size {}x{} is empty", size[0], size[1])));
    }
    if let Some((k, v)) = global.position(|v| !GLOBAL_RANGE.contains(&v)) {
        return Err(Error::check(format!("global descriptor value {k} is {v}, outside [0, 1]")));
    }
    let t = forest.len();
    let f = &forest;
    if f.areas.len() != t
        || f.centroids.len() != 2 * t
        || f.neighbours.len() != t * f.neighbour_slots
        || f.has_appearance.len() != t
        || f.appearance.len() != t * f.dim
    {
        return Err(Error::check("tree arrays have different lengths"));
    }
    if let Some(c) = f.classes.iter().find(|&&c| c as usize >= n_classes) {
        return Err(Error::check(format!("a tree has class {c}, outside the class table of {n_classes}")));
    }
    if let Some(a) = f.areas.iter().find(|a| !AREA_RANGE.contains(*a)) {
        return Err(Error::check(format!("a tree has area fraction {a}, outside [0, 1]")));
    }
    if f.centroids.iter().any(|c| !c.is_finite()) {
        return Err(Error::check("a tree centroid is NaN or infinite"));
    }
    if let Some(j) = f.neighbours.iter().find(|&&j| j < -1 || j >= t as i32) {
        return Err(Error::check(format!("a neighbour index {j} points outside the forest of {t} trees")));
    }
    if f.has_appearance.iter().any(|&h| h > 1) {
        return Err(Error::check("an appearance flag is neither 0 nor 1"));
    }
    let limit = if store == ValueType::F16 { F16_MAX } else { f32::MAX };
    let bad = |v: Values| v.position(|x| !x.is_finite() || x.abs() > limit).is_some();
    if bad(f.appearance) || bad(appearance) {
        return Err(Error::check(format!("an appearance value is NaN, infinite or beyond what {} holds", store.name())));
    }
    // VLAD vectors have unit length (or none): longer ones are not the encoder's, and one of
    // them would outscore every true match
    let long = |v: Values, dim: usize| -> Option<f32> {
        let wide = v.to_vec();
        wide.chunks(dim.max(1)).map(|c| c.iter().map(|x| x * x).sum::<f32>().sqrt()).find(|&n| n > MAX_APPEARANCE_NORM)
    };
    if let Some(n) = long(f.appearance, f.dim).or_else(|| long(appearance, appearance.len())) {
        return Err(Error::check(format!("an appearance vector has length {n}; the encoder's have length 1 (at most {MAX_APPEARANCE_NORM})")));
    }
    if hog.iter().any(|x| !x.is_finite()) {
        return Err(Error::check("a HOG value is NaN or infinite"));
    }
    Ok(())
}

/// Checks an image's whole-image embedding: finite values of length 1 (the network's output is
/// L2-normalised, then rounded to f16) or none. A longer one would outscore every true match; a
/// zero one (an image pushed without its embedding) would be served as a place unlike any other.
pub fn embedding(e: Values) -> Result<()> {
    if e.is_empty() {
        return Ok(());
    }
    let e = e.to_vec();
    if e.iter().any(|x| !x.is_finite()) {
        return Err(Error::check("an embedding value is NaN or infinite"));
    }
    let n = e.iter().map(|x| x * x).sum::<f32>().sqrt();
    if !(2.0 - MAX_APPEARANCE_NORM..=MAX_APPEARANCE_NORM).contains(&n) {
        return Err(Error::check(format!("the embedding has length {n}; the encoder's have length 1 (within {:.2})", MAX_APPEARANCE_NORM - 1.0)));
    }
    Ok(())
}

/// Checks an image's compact HOG ([`crate::global::hog::compact_hog`]): finite values, none negative (a
/// histogram), of length at most 1 (the encoder's are L2-normalised, or all zero for a flat
/// image), or none.
pub fn compact_hog(v: Values) -> Result<()> {
    if v.is_empty() {
        return Ok(());
    }
    let v = v.to_vec();
    if v.iter().any(|x| !x.is_finite() || *x < 0.0) {
        return Err(Error::check("a compact HOG value is negative, NaN or infinite"));
    }
    let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
    if n > MAX_APPEARANCE_NORM {
        return Err(Error::check(format!("the compact HOG has length {n}; the encoder's have length 1 (at most {MAX_APPEARANCE_NORM})")));
    }
    Ok(())
}

/// Checks an image's verification keypoints: as many positions, classes and descriptor values as
/// keypoints, classes in the table (or void), and descriptors no int8 rounding of a unit vector
/// exceeds (every value above -128, the vector's norm at most 1.01 x the scale).
pub fn keypoints(k: crate::descriptors::keypoints::KeypointsRef, n_classes: usize) -> Result<()> {
    let n = k.len();
    if k.xy.len() != 2 * n || k.descriptors.len() != n * k.dim {
        return Err(Error::check("keypoint arrays have different lengths"));
    }
    if let Some(c) = k.classes.iter().find(|&&c| c != crate::classes::VOID && c as usize >= n_classes) {
        return Err(Error::check(format!("a keypoint has class {c}, outside the class table of {n_classes}")));
    }
    let limit = (1.01 * crate::descriptors::keypoints::DESCRIPTOR_SCALE).powi(2);
    for (i, d) in k.descriptors.chunks(k.dim.max(1)).enumerate() {
        let n2: f32 = d.iter().map(|&v| (v as f32).powi(2)).sum();
        if d.contains(&i8::MIN) || n2 > limit {
            return Err(Error::check(format!("keypoint {i}'s descriptor is not a quantised unit vector (squared norm {n2})")));
        }
    }
    Ok(())
}

/// Checks a stored pose row (`x y z qx qy qz qw`, [`crate::descriptors::PlacePose::to_row`]): all
/// NaN (no pose), or a finite position with no quaternion (NaN) or a unit one.
pub fn pose_row(row: &[f64]) -> Result<()> {
    crate::descriptors::pose::PlacePose::from_row(row).map(|_| ()).map_err(|e| Error::check(e.to_string()))
}
