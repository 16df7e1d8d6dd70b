//! `Descriptors`: an immutable batch of encoded images (a `DescriptorSet`), with read-only numpy
//! views of its columns (no copies), conversion to and from plain arrays, and pickling (so Ray
//! can ship query batches).

use crate::arrays::view;
use crate::errors::invalid;
use numpy::{Element, PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList};
use semlook::descriptors::DescriptorSet;
use semlook::values::ValueType;
use std::sync::Arc;

/// Encoded images: global descriptors, forests of trees, appearance vectors. Immutable; numpy
/// properties are read-only views that keep the batch alive.
#[pyclass(frozen, module = "semlook._native", name = "Descriptors")]
pub struct PyDescriptors {
    pub inner: Arc<DescriptorSet>,
}

impl PyDescriptors {
    pub fn new(set: DescriptorSet) -> Self {
        PyDescriptors { inner: Arc::new(set) }
    }
}

/// Every column as (name, shape) of a set.
fn columns(d: &DescriptorSet) -> Vec<(&'static str, Vec<usize>)> {
    let (n, t, k) = (d.len(), d.n_trees(), d.n_keypoints());
    vec![
        ("sizes", vec![n, 2]),
        ("globals", vec![n, d.global_len]),
        ("global_stats", vec![n, d.stats_len]),
        ("forest_offsets", vec![n + 1]),
        ("tree_classes", vec![t]),
        ("tree_areas", vec![t]),
        ("tree_centroids", vec![t, 2]),
        ("tree_neighbours", vec![t, d.neighbour_slots]),
        ("tree_appearance", vec![t, d.appearance_dim]),
        ("tree_has_appearance", vec![t]),
        ("tree_descriptors", vec![t]),
        ("image_appearance", vec![n, d.appearance_dim]),
        ("image_hog", vec![n, d.hog_dim]),
        ("image_embedding", vec![n, d.embedding_dim]),
        ("image_compact_hog", vec![n, d.compact_hog_dim]),
        ("keypoint_offsets", vec![n + 1]),
        ("keypoint_descriptors", vec![k, d.keypoint_dim]),
        ("keypoint_xy", vec![k, 2]),
        ("keypoint_classes", vec![k]),
    ]
}

fn column_view<'py>(owner: Bound<'py, PyAny>, d: &DescriptorSet, name: &str, shape: &[usize]) -> PyResult<Bound<'py, PyAny>> {
    Ok(match name {
        "sizes" => view(owner, d.sizes.as_flattened(), shape)?.into_any(),
        "globals" => view(owner, &d.globals, shape)?.into_any(),
        "global_stats" => view(owner, &d.global_stats, shape)?.into_any(),
        "forest_offsets" => view(owner, &d.forest_offsets, shape)?.into_any(),
        "tree_classes" => view(owner, &d.tree_classes, shape)?.into_any(),
        "tree_areas" => view(owner, &d.tree_areas, shape)?.into_any(),
        "tree_centroids" => view(owner, &d.tree_centroids, shape)?.into_any(),
        "tree_neighbours" => view(owner, &d.tree_neighbours, shape)?.into_any(),
        "tree_appearance" => view(owner, &d.tree_appearance, shape)?.into_any(),
        "tree_has_appearance" => view(owner, &d.tree_has_appearance, shape)?.into_any(),
        "tree_descriptors" => view(owner, &d.tree_descriptors, shape)?.into_any(),
        "image_appearance" => view(owner, &d.image_appearance, shape)?.into_any(),
        "image_hog" => view(owner, &d.image_hog, shape)?.into_any(),
        "image_embedding" => view(owner, &d.image_embedding, shape)?.into_any(),
        "image_compact_hog" => view(owner, &d.image_compact_hog, shape)?.into_any(),
        "keypoint_offsets" => view(owner, &d.keypoint_offsets, shape)?.into_any(),
        "keypoint_descriptors" => view(owner, &d.keypoint_descriptors, shape)?.into_any(),
        "keypoint_xy" => view(owner, &d.keypoint_xy, shape)?.into_any(),
        "keypoint_classes" => view(owner, &d.keypoint_classes, shape)?.into_any(),
        _ => return Err(invalid("descriptor column", format!("no column {name:?}"))),
    })
}

/// A column from a dict of arrays, copied, its shape checked.
fn take_column<T: Element + Copy>(d: &Bound<'_, PyDict>, name: &str, shape: &[usize]) -> PyResult<Vec<T>> {
    let a = d.get_item(name)?.ok_or_else(|| invalid("descriptor arrays", format!("no {name:?}")))?;
    let a: PyReadonlyArrayDyn<T> =
        a.extract().map_err(|e| invalid(&format!("descriptor arrays[{name:?}]"), format!("wrong dtype or not an array: {e}")))?;
    if a.shape() != shape {
        return Err(invalid(&format!("descriptor arrays[{name:?}]"), format!("shape {:?}, the layout needs {shape:?}", a.shape())));
    }
    Ok(a.as_array().iter().copied().collect())
}

fn dim(d: &Bound<'_, PyDict>, name: &str) -> PyResult<usize> {
    d.get_item(name)?
        .ok_or_else(|| invalid("descriptor arrays", format!("no {name:?}")))?
        .extract()
        .map_err(|e| invalid(&format!("descriptor arrays[{name:?}]"), e))
}

#[pymethods]
impl PyDescriptors {
    fn __len__(&self) -> usize {
        self.inner.len()
    }
    fn __repr__(&self) -> String {
        let d = &self.inner;
        format!("Descriptors({} images, {} trees, global {}, appearance {}, hog {})", d.len(), d.n_trees(), d.global_len, d.appearance_dim, d.hog_dim)
    }
    /// Image ids, in order.
    #[getter]
    fn ids(&self) -> Vec<String> {
        self.inner.ids.clone()
    }
    #[getter]
    fn n_trees(&self) -> usize {
        self.inner.n_trees()
    }
    /// SHA-256 of the VLAD codebook the appearance vectors were aggregated with (None without
    /// appearance); a map accepts only its own.
    #[getter]
    fn codebook(&self) -> Option<String> {
        self.inner.codebook.clone()
    }
    #[getter]
    fn appearance_dim(&self) -> usize {
        self.inner.appearance_dim
    }
    /// A read-only view of one column (see `columns()`), no copy.
    fn column<'py>(slf: Bound<'py, Self>, name: &str) -> PyResult<Bound<'py, PyAny>> {
        let d = slf.get().inner.clone();
        let shape = columns(&d)
            .into_iter()
            .find(|(n, _)| *n == name)
            .map(|(_, s)| s)
            .ok_or_else(|| invalid("descriptor column", format!("no column {name:?}")))?;
        column_view(slf.into_any(), &d, name, &shape)
    }
    /// Names of the columns, in the order `to_arrays` lists them.
    #[staticmethod]
    fn columns() -> Vec<&'static str> {
        columns(&DescriptorSet::for_storage(0, 0, 0, 0)).into_iter().map(|(n, _)| n).collect()
    }
    /// Global descriptors, float32 [images, global_len] (read-only view).
    #[getter]
    fn globals<'py>(slf: Bound<'py, Self>) -> PyResult<Bound<'py, PyAny>> {
        Self::column(slf, "globals")
    }
    /// Whole-image appearance vectors, float32 [images, appearance_dim] (read-only view).
    #[getter]
    fn image_appearance<'py>(slf: Bound<'py, Self>) -> PyResult<Bound<'py, PyAny>> {
        Self::column(slf, "image_appearance")
    }
    /// Every column as a read-only view, with `ids` and the layout's dimensions: what
    /// `from_arrays` takes back (and what pickling stores).
    fn to_arrays<'py>(slf: Bound<'py, Self>) -> PyResult<Bound<'py, PyDict>> {
        let py = slf.py();
        let d = slf.get().inner.clone();
        let out = PyDict::new(py);
        out.set_item("ids", PyList::new(py, &d.ids)?)?;
        for (k, v) in [
            ("global_len", d.global_len),
            ("stats_len", d.stats_len),
            ("neighbour_slots", d.neighbour_slots),
            ("appearance_dim", d.appearance_dim),
            ("hog_dim", d.hog_dim),
            ("keypoint_dim", d.keypoint_dim),
            ("embedding_dim", d.embedding_dim),
            ("compact_hog_dim", d.compact_hog_dim),
        ] {
            out.set_item(k, v)?;
        }
        out.set_item("codebook", d.codebook.clone())?;
        // what made the embeddings, as JSON (none without embeddings)
        let rec = d.embedding.as_ref().map(serde_json::to_string).transpose().map_err(|e| invalid("descriptor arrays", e.to_string()))?;
        out.set_item("embedding_record", rec)?;
        for (name, shape) in columns(&d) {
            out.set_item(name, column_view(slf.clone().into_any(), &d, name, &shape)?)?;
        }
        Ok(out)
    }
    /// A batch from `to_arrays`-style arrays (copied); every length and every value is checked
    /// (NaN, ranges, forest offsets), so bad arrays raise instead of reaching the engine.
    #[staticmethod]
    fn from_arrays(arrays: &Bound<'_, PyDict>) -> PyResult<PyDescriptors> {
        let ids: Vec<String> = arrays.get_item("ids")?.ok_or_else(|| invalid("descriptor arrays", "no \"ids\""))?.extract()?;
        let (g, sl, s, a, h) = (
            dim(arrays, "global_len")?,
            dim(arrays, "stats_len")?,
            dim(arrays, "neighbour_slots")?,
            dim(arrays, "appearance_dim")?,
            dim(arrays, "hog_dim")?,
        );
        let kd = dim(arrays, "keypoint_dim")?;
        // arrays of before embeddings have none
        let e = if arrays.contains("embedding_dim")? { dim(arrays, "embedding_dim")? } else { 0 };
        // and of before compact HOGs none
        let c = if arrays.contains("compact_hog_dim")? { dim(arrays, "compact_hog_dim")? } else { 0 };
        let n = ids.len();
        let offsets: Vec<u32> = take_column(arrays, "forest_offsets", &[n + 1])?;
        let t = offsets.last().copied().unwrap_or(0) as usize;
        let kp_offsets: Vec<u32> = take_column(arrays, "keypoint_offsets", &[n + 1])?;
        let k = kp_offsets.last().copied().unwrap_or(0) as usize;
        let sizes: Vec<u32> = take_column(arrays, "sizes", &[n, 2])?;
        let set = DescriptorSet {
            ids,
            sizes: sizes.chunks(2).map(|c| [c[0], c[1]]).collect(),
            global_len: g,
            stats_len: sl,
            globals: take_column(arrays, "globals", &[n, g])?,
            global_stats: take_column(arrays, "global_stats", &[n, sl])?,
            forest_offsets: offsets,
            tree_classes: take_column(arrays, "tree_classes", &[t])?,
            tree_areas: take_column(arrays, "tree_areas", &[t])?,
            tree_centroids: take_column(arrays, "tree_centroids", &[t, 2])?,
            neighbour_slots: s,
            tree_neighbours: take_column(arrays, "tree_neighbours", &[t, s])?,
            appearance_dim: a,
            tree_appearance: take_column(arrays, "tree_appearance", &[t, a])?,
            tree_has_appearance: take_column(arrays, "tree_has_appearance", &[t])?,
            tree_descriptors: take_column(arrays, "tree_descriptors", &[t])?,
            image_appearance: take_column(arrays, "image_appearance", &[n, a])?,
            hog_dim: h,
            image_hog: take_column(arrays, "image_hog", &[n, h])?,
            embedding_dim: e,
            image_embedding: if e > 0 { take_column(arrays, "image_embedding", &[n, e])? } else { vec![] },
            compact_hog_dim: c,
            image_compact_hog: if c > 0 { take_column(arrays, "image_compact_hog", &[n, c])? } else { vec![] },
            keypoint_dim: kd,
            keypoint_offsets: kp_offsets,
            keypoint_descriptors: take_column(arrays, "keypoint_descriptors", &[k, kd])?,
            keypoint_xy: take_column(arrays, "keypoint_xy", &[k, 2])?,
            keypoint_classes: take_column(arrays, "keypoint_classes", &[k])?,
            embedding: match arrays.get_item("embedding_record")? {
                Some(r) if !r.is_none() => {
                    let text: String = r.extract().map_err(|e| invalid("descriptor arrays[\"embedding_record\"]", format!("not a string: {e}")))?;
                    Some(serde_json::from_str(&text).map_err(|e| invalid("descriptor arrays[\"embedding_record\"]", e.to_string()))?)
                }
                _ => None,
            },
            // the arrays carry no poses (matching never reads them; a map keeps its own)
            poses: vec![None; n],
            codebook: match arrays.get_item("codebook")? {
                Some(c) if !c.is_none() => {
                    Some(c.extract().map_err(|e| invalid("descriptor arrays[\"codebook\"]", format!("not a SHA-256 string: {e}")))?)
                }
                _ => None,
            },
        };
        set.check_layout().map_err(|r| invalid("descriptor arrays", r))?;
        if set.global_stats.iter().any(|v| !v.is_finite()) {
            return Err(invalid("descriptor arrays", "global_stats hold NaN or infinity"));
        }
        for i in 0..set.len() {
            set.check_image(i, 256, ValueType::F32).map_err(|r| invalid("descriptor arrays", format!("image {:?}: {r}", set.ids[i])))?;
        }
        Ok(PyDescriptors::new(set))
    }
    /// The images at `indices`, in that order, as a new batch.
    fn take(&self, indices: Vec<usize>) -> PyResult<PyDescriptors> {
        let d = &self.inner;
        let mut out = d.empty_like();
        for &i in &indices {
            if i >= d.len() {
                return Err(invalid("take", format!("index {i} of a batch of {}", d.len())));
            }
            out.append_range(d, i, i + 1).map_err(|r| invalid("take", r))?;
        }
        Ok(PyDescriptors::new(out))
    }
    /// One batch of several (same layout).
    #[staticmethod]
    fn concat(parts: Vec<PyRef<'_, PyDescriptors>>) -> PyResult<PyDescriptors> {
        let first = parts.first().ok_or_else(|| invalid("concat", "no batches given"))?;
        let mut out = first.inner.empty_like();
        for p in &parts {
            out.append(&p.inner).map_err(|r| invalid("concat", format!("batches of different layouts (encoded with different configs): {r}")))?;
        }
        Ok(PyDescriptors::new(out))
    }
    fn __reduce__<'py>(slf: Bound<'py, Self>) -> PyResult<(Bound<'py, PyAny>, (Bound<'py, PyDict>,))> {
        let py = slf.py();
        let rebuild = py.import("semlook._pickle")?.getattr("rebuild_descriptors")?;
        Ok((rebuild, (Self::to_arrays(slf)?,)))
    }
}
