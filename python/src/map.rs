//! `Map`: a stored map (memory-mapped segments), its edits, queries against it, zero-copy numpy
//! views of its segments, and `evaluate`.

use crate::arrays::to_py_object;
use crate::arrays::{pool, setting, view};
use crate::descriptors::PyDescriptors;
use crate::encoder::{PyConfig, PyEncoder};
use crate::engine::{run, PyEngine};
use crate::errors::{invalid, OrPy};
use crate::matches::PyMatches;
use crate::store::{wrap, PyMap};
use pyo3::prelude::*;
use semlook::config::Config;
use semlook::map::{edit, Map, MapWriter, StoreOptions};
use semlook::matching::source::RefSource;
use semlook::values::{ValueType, Values};
use std::path::PathBuf;

fn store_options(segment_images: Option<usize>, f16: bool) -> PyResult<StoreOptions> {
    let mut o = StoreOptions { values: if f16 { ValueType::F16 } else { ValueType::F32 }, ..Default::default() };
    if let Some(n) = segment_images {
        if n == 0 {
            return Err(invalid("segment_images", "0; at least 1"));
        }
        o.segment_images = n;
    }
    Ok(o)
}

#[pymethods]
impl PyMap {
    /// Opens the map in `path` (reads the manifest and maps the segments; checksums are checked
    /// on first use).
    #[staticmethod]
    fn open(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        Ok(wrap(py.detach(|| Map::open(&path)).py_err()?))
    }
    /// Creates a map in `path` (which must not exist or be empty) from `descriptors` encoded by
    /// `encoder` (its config, keypoint network and codebook are recorded). `segment_images`:
    /// most images per segment file; `f16`: store global and appearance values as float16.
    #[staticmethod]
    #[pyo3(signature = (path, descriptors, encoder, segment_images=None, f16=false))]
    fn create(
        py: Python<'_>,
        path: PathBuf,
        descriptors: &PyDescriptors,
        encoder: &PyEncoder,
        segment_images: Option<usize>,
        f16: bool,
    ) -> PyResult<Self> {
        let (set, enc, opts) = (descriptors.inner.clone(), encoder.inner(), store_options(segment_images, f16)?);
        Ok(wrap(py.detach(|| Map::create_with(&path, enc.config(), &set, enc.appearance_record(), opts)).py_err()?))
    }
    /// Adds `descriptors` (encoded by `Encoder.for_map(map)`) as new segments; every image and id
    /// is checked before anything is written. Returns the map reopened.
    #[pyo3(signature = (descriptors, segment_images=None))]
    fn add(&self, py: Python<'_>, descriptors: &PyDescriptors, segment_images: Option<usize>) -> PyResult<Self> {
        let (set, dir, opts) = (descriptors.inner.clone(), self.inner.path.clone(), store_options(segment_images, false)?);
        Ok(wrap(
            py.detach(|| {
                let mut w = MapWriter::append(&dir, opts)?;
                w.push_set(&set)?;
                w.finish()
            })
            .py_err()?,
        ))
    }
    /// Marks the images `ids` removed (queries never return them; `compact` drops them from the
    /// files). Returns the map reopened.
    fn remove(&self, py: Python<'_>, ids: Vec<String>) -> PyResult<Self> {
        let dir = self.inner.path.clone();
        Ok(wrap(py.detach(|| edit::remove(&dir, &ids).and_then(|_| Map::open(&dir))).py_err()?))
    }
    /// Rewrites segments without their removed images, merging small ones; returns (map, report).
    fn compact<'py>(&self, py: Python<'py>) -> PyResult<(Self, Bound<'py, PyAny>)> {
        let dir = self.inner.path.clone();
        let (m, report) = py.detach(|| edit::compact(&dir, StoreOptions::default()).and_then(|r| Ok((Map::open(&dir)?, r)))).py_err()?;
        Ok((wrap(m), to_py_object(py, &report)?))
    }
    /// Checks every file (SHA-256, values); a dict naming each damaged file (raises only when the
    /// manifest itself is unreadable).
    fn verify<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let dir = self.inner.path.clone();
        let report = py.detach(|| edit::verify(&dir)).py_err()?;
        to_py_object(py, &report)
    }
    fn __len__(&self) -> usize {
        self.inner.len()
    }
    fn __repr__(&self) -> String {
        format!(
            "Map({:?}, {} images, {} segments, generation {})",
            self.inner.path,
            self.inner.len(),
            self.inner.segments().len(),
            self.inner.manifest.generation
        )
    }
    #[getter]
    fn path(&self) -> PathBuf {
        self.inner.path.clone()
    }
    #[getter]
    fn generation(&self) -> u64 {
        self.inner.manifest.generation
    }
    #[getter]
    fn n_segments(&self) -> usize {
        self.inner.segments().len()
    }
    /// The ids of the map's images, in reference order (removed images left out).
    fn ids(&self) -> Vec<String> {
        (0..self.inner.len()).map(|i| self.inner.id(i).to_string()).collect()
    }
    /// The manifest as a dict.
    fn manifest<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_object(py, &self.inner.manifest)
    }
    /// Rows of segment `s` that are not removed (reference order within the segment).
    fn live_rows(&self, s: usize) -> PyResult<Vec<usize>> {
        self.segment_index(s)?;
        Ok(self.inner.live_rows(s).collect())
    }
    /// Segment `s`'s stored values: `name` "globals" ([rows, height, width]) is a read-only numpy
    /// view, no copy (float32, or float16 on an f16 map; it keeps the map's mapping alive);
    /// "image_appearance" ([rows, dim]) is a new float32 array widened from the int8 blocks the
    /// map stores. Removed rows included (see `live_rows`). With `verify` (default) the segment's
    /// SHA-256 and values are checked first.
    #[pyo3(signature = (s, name, verify=true))]
    fn segment_view<'py>(slf: Bound<'py, Self>, s: usize, name: &str, verify: bool) -> PyResult<Bound<'py, PyAny>> {
        let map = slf.get().inner.clone();
        slf.get().segment_index(s)?;
        let seg = &map.segments()[s];
        if verify {
            seg.ensure().map_err(|r| crate::errors::to_py(semlook::Error::corrupt(&seg.path, r)))?;
        }
        let g = &map.manifest.config.global;
        let (values, shape) = match name {
            "globals" => (seg.globals(0, seg.len()), vec![seg.len(), g.height, g.width]),
            "image_appearance" => (seg.image_appearances(), vec![seg.len(), map.manifest.appearance_dim]),
            _ => return Err(invalid("segment_view", format!("{name:?} is not globals or image_appearance"))),
        };
        let owner = slf.into_any();
        Ok(match values {
            Values::F32(v) => view(owner, v, &shape)?.into_any(),
            // SAFETY: half::f16 is a transparent wrapper of its u16 bit pattern
            Values::F16(v) => view(owner, unsafe { std::slice::from_raw_parts(v.as_ptr() as *const half::f16, v.len()) }, &shape)?.into_any(),
            blocks @ Values::Blocks(_) => numpy::PyArrayMethods::reshape(&numpy::PyArray1::from_vec(owner.py(), blocks.to_vec()), shape)?.into_any(),
        })
    }
    /// Matches `queries` (from `Encoder.for_map(map)`) against the whole map on the CPU with
    /// `setting`; `k` candidates per query (default: the config's top_k), `config` as `semlook
    /// query --config` (default: `Config.for_map(map)`), `threads` for a pool of its own. With
    /// `engine` (an `Engine`), on its backend: on a GPU the map stays resident between calls.
    #[pyo3(signature = (queries, setting="verified", k=None, config=None, threads=None, engine=None))]
    #[allow(clippy::too_many_arguments)]
    fn query(
        &self,
        py: Python<'_>,
        queries: &PyDescriptors,
        setting: &str,
        k: Option<usize>,
        config: Option<PyRef<'_, PyConfig>>,
        threads: Option<usize>,
        engine: Option<PyRef<'_, PyEngine>>,
    ) -> PyResult<PyMatches> {
        let s = self::setting(setting)?;
        let cfg = query_config(&self.inner, config.map(|c| c.inner.clone()), k)?;
        let (map, set, engine) = (self.inner.clone(), queries.inner.clone(), engine.map(|e| e.shared()));
        let (matches, _) = run(py, pool(threads)?, engine.as_ref(), |e| e.match_batch(map.as_ref(), &set, s, &cfg))?;
        Ok(PyMatches::new(s, &set.ids, matches, |r| map.id(r as usize).to_string()))
    }
}

impl PyMap {
    fn segment_index(&self, s: usize) -> PyResult<()> {
        match s < self.inner.segments().len() {
            true => Ok(()),
            false => Err(invalid("segment", format!("{s} of a map of {} segments", self.inner.segments().len()))),
        }
    }
}

/// The config of a query: given, or the map's; with `k` candidates when given; checked.
pub fn query_config(map: &Map, config: Option<Config>, k: Option<usize>) -> PyResult<Config> {
    let mut cfg = config.unwrap_or_else(|| map.query_config());
    if let Some(k) = k {
        cfg.matching.top_k = k;
    }
    cfg.validate("query config").py_err()?;
    map.check_compatible(&cfg.encoding()).py_err()?;
    Ok(cfg)
}

/// Evaluates `settings` on a dataset (a dataset directory, or `references` and `queries`
/// folders with a `ground_truth` file) as `semlook eval` does; the report as a dict (the JSON of
/// `semlook eval --json`). With `map`, the references are read from it instead of encoded.
#[pyfunction]
#[pyo3(signature = (dataset=None, references=None, queries=None, ground_truth=None, settings=None, config=None, map=None, gt_distance=None, threads=None, engine=None))]
#[allow(clippy::too_many_arguments)]
pub fn evaluate<'py>(
    py: Python<'py>,
    dataset: Option<PathBuf>,
    references: Option<PathBuf>,
    queries: Option<PathBuf>,
    ground_truth: Option<PathBuf>,
    settings: Option<Vec<String>>,
    config: Option<PyRef<'_, PyConfig>>,
    map: Option<&PyMap>,
    gt_distance: Option<f64>,
    threads: Option<usize>,
    engine: Option<PyRef<'_, PyEngine>>,
) -> PyResult<Bound<'py, PyAny>> {
    use semlook::dataset::{Dataset, DatasetOptions};
    // every setting by default, as `semlook eval`
    let settings = match settings {
        Some(names) => names.iter().map(|s| setting(s)).collect::<PyResult<Vec<_>>>()?,
        None => semlook::matching::Setting::ALL.to_vec(),
    };
    let map = map.map(|m| m.inner.clone());
    let cfg = match (&config, &map) {
        (Some(c), _) => c.inner.clone(),
        (None, Some(m)) => m.query_config(),
        (None, None) => Config::default(),
    };
    let opts = DatasetOptions { max_distance: gt_distance, ..Default::default() };
    let engine = engine.map(|e| e.shared());
    let report = run(py, pool(threads)?, engine.as_ref(), |e| {
        let ds = Dataset::open_any(dataset.as_deref(), references.as_deref(), queries.as_deref(), ground_truth.as_deref(), &opts)?;
        let eo = semlook::eval::EvalOptions { settings, map: map.as_deref(), skip_invalid: false, quiet: true };
        semlook::eval::evaluate(&ds, &cfg, &eo, e)
    })?;
    to_py_object(py, &report)
}
