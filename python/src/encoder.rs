//! `Config` and `Encoder`: a configuration (TOML, the CLI's format) and the encoder of frames
//! (from files, or from numpy arrays) into `Descriptors`.

use crate::arrays::{detached, pool};
use crate::descriptors::PyDescriptors;
use crate::engine::{resolve, run, PyEngine};
use crate::errors::{invalid, OrPy};
use crate::store::PyMap;
use numpy::{PyReadonlyArrayDyn, PyUntypedArrayMethods};
use pyo3::prelude::*;
use semlook::config::Config;
use semlook::encode::Encoder;
use semlook::input::{self, FrameSource, LabelFormat};
use semlook::map::Map;
use std::path::PathBuf;

/// A semlook configuration (the TOML of `semlook --config`; missing keys take the defaults).
#[pyclass(frozen, module = "semlook._native", name = "Config")]
#[derive(Clone)]
pub struct PyConfig {
    pub inner: Config,
}

#[pymethods]
impl PyConfig {
    /// The defaults (XFeat appearance on), or the config given: TOML text, or the path of a
    /// TOML file (a `pathlib.Path`, or a string naming an existing file); values are checked.
    #[new]
    #[pyo3(signature = (toml=None))]
    fn new(toml: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let Some(t) = toml else { return Ok(PyConfig { inner: Config::default() }) };
        let path: Option<PathBuf> = match t.extract::<String>() {
            // one line without `=` is no TOML a config can be: a file name (missing ones named)
            Ok(s) if !s.contains('\n') && !s.contains('=') && !s.trim().is_empty() => Some(s.into()),
            Ok(_) => None,
            Err(_) => Some(t.extract::<PathBuf>().map_err(|_| invalid("Config", "expected TOML text or the path of a TOML file"))?),
        };
        let inner = match path {
            Some(p) => Config::load(&p).py_err()?,
            None => Config::from_toml(&t.extract::<String>()?, "Config(toml)").py_err()?,
        };
        Ok(PyConfig { inner })
    }
    /// The config of a TOML file.
    #[staticmethod]
    fn from_file(path: PathBuf) -> PyResult<Self> {
        Ok(PyConfig { inner: Config::load(&path).py_err()? })
    }
    /// The defaults with appearance off: label maps alone suffice to encode.
    #[staticmethod]
    fn without_appearance() -> Self {
        PyConfig { inner: Config::without_appearance() }
    }
    /// What `semlook query` uses on this map without --config: the map's encoding, default matching.
    #[staticmethod]
    fn for_map(map: &PyMap) -> Self {
        PyConfig { inner: map.map().query_config() }
    }
    /// `for_map` from the map directory's manifest alone (no segment file is read: a driver need
    /// not hold them).
    #[staticmethod]
    fn for_map_dir(map_dir: PathBuf) -> PyResult<Self> {
        Ok(PyConfig { inner: semlook::map::manifest::query_config(&semlook::map::manifest::read_existing(&map_dir).py_err()?) })
    }
    fn to_toml(&self) -> PyResult<String> {
        self.inner.to_toml().py_err()
    }
    /// Candidates the coarse stage keeps per query (K).
    #[getter]
    fn top_k(&self) -> usize {
        self.inner.matching.top_k
    }
    /// How the final score combines the stages: "fine" or "fine_times_global".
    #[getter]
    fn score_fusion(&self) -> &'static str {
        match self.inner.matching.score {
            semlook::config::ScoreFusion::Fine => "fine",
            semlook::config::ScoreFusion::FineTimesGlobal => "fine_times_global",
        }
    }
    /// A copy with K candidates per query.
    fn with_top_k(&self, k: usize) -> PyResult<Self> {
        let mut inner = self.inner.clone();
        inner.matching.top_k = k;
        inner.validate("with_top_k").py_err()?;
        Ok(PyConfig { inner })
    }
    fn __repr__(&self) -> String {
        format!("Config(appearance {:?}, top_k {})", self.inner.appearance.model, self.inner.matching.top_k)
    }
}

fn label_format(name: &str) -> PyResult<LabelFormat> {
    <LabelFormat as semlook::Choice>::parse_name(name).map_err(|why| invalid("label_format", why))
}

/// Encodes frames with one configuration (and, with appearance, its keypoint network and VLAD
/// codebook, which `train_codebook` sets in place).
#[pyclass(frozen, module = "semlook._native", name = "Encoder")]
pub struct PyEncoder {
    inner: std::sync::RwLock<Encoder>,
}

/// The config with the segmenter `segmenter` names: None keeps the config's (the installed
/// default one), False none (frames without label maps are encoded without labels), a path
/// that ONNX model.
pub fn with_segmenter(mut cfg: Config, segmenter: Option<&Bound<'_, PyAny>>) -> PyResult<Config> {
    match segmenter {
        None => {}
        Some(s) if s.is_instance_of::<pyo3::types::PyBool>() => {
            if s.extract::<bool>()? {
                return Err(invalid("segmenter", "True is the default already: give False (none) or the path of a model"));
            }
            cfg.models.default_segmenter = false;
            cfg.models.segmenter_onnx = None;
        }
        Some(s) => {
            cfg.models.segmenter_onnx = Some(s.extract::<PathBuf>().map_err(|_| invalid("segmenter", "expected False or the path of an ONNX model"))?)
        }
    }
    Ok(cfg)
}

#[pymethods]
impl PyEncoder {
    /// An encoder for `config` (default: the defaults, which need the XFeat weights; see
    /// `SEMLOOK_MODELS`), with `segmenter` (None: the installed default one; False: none, photos
    /// without label maps are then encoded without labels, for the settings that need none; a
    /// path: that ONNX model). With appearance, train a codebook before encoding.
    #[new]
    #[pyo3(signature = (config=None, segmenter=None))]
    fn new(py: Python<'_>, config: Option<PyRef<'_, PyConfig>>, segmenter: Option<&Bound<'_, PyAny>>) -> PyResult<Self> {
        let cfg = with_segmenter(config.map_or_else(Config::default, |c| c.inner.clone()), segmenter)?;
        Ok(Self::wrap(py.detach(|| Encoder::new(&cfg)).py_err()?))
    }
    /// The encoder a map's queries need: its config (or `config`, checked against the map),
    /// keypoint network and codebook.
    #[staticmethod]
    #[pyo3(signature = (map, config=None))]
    fn for_map(py: Python<'_>, map: &PyMap, config: Option<PyRef<'_, PyConfig>>) -> PyResult<Self> {
        let m = map.map();
        let cfg = config.map_or_else(|| m.query_config(), |c| c.inner.clone());
        Ok(Self::wrap(py.detach(|| Encoder::for_map(&cfg, &m)).py_err()?))
    }
    /// `for_map` from the map directory's manifest and codebook alone: no segment file is
    /// opened, so a driver need not hold them (they live on the shards' nodes).
    #[staticmethod]
    #[pyo3(signature = (map_dir, config=None))]
    fn for_map_dir(py: Python<'_>, map_dir: PathBuf, config: Option<PyRef<'_, PyConfig>>) -> PyResult<Self> {
        let config = config.map(|c| c.inner.clone());
        let enc = py.detach(|| {
            let head = Map::open_header(&map_dir)?;
            Encoder::for_map(&config.unwrap_or_else(|| head.query_config()), &head)
        });
        Ok(Self::wrap(enc.py_err()?))
    }
    /// Values per appearance vector (0 without appearance).
    #[getter]
    fn appearance_dim(&self) -> usize {
        self.inner().appearance_dim()
    }
    /// Trains this encoder's VLAD codebook on these frames (files, as in `encode_files`) and
    /// sets it, in place (as `Map.add` changes the map); returns the encoder itself. Without
    /// appearance, nothing to train.
    #[pyo3(signature = (ids, images, labels=None, threads=None))]
    fn train_codebook<'py>(
        slf: &Bound<'py, Self>,
        py: Python<'py>,
        ids: Vec<String>,
        images: Vec<PathBuf>,
        labels: Option<Vec<PathBuf>>,
        threads: Option<usize>,
    ) -> PyResult<Bound<'py, Self>> {
        let frames = frames(ids, Some(images), labels)?;
        let enc = slf.get().inner().clone();
        let enc = enc.clone().without_labels(enc.labels_rule(None, &frames).py_err()?);
        let mut trained = enc;
        detached(py, pool(threads)?, || semlook::batch::train_codebook(&mut trained, &frames, true)).py_err()?;
        if let Some(cb) = trained.codebook() {
            slf.get().inner.write().map_err(|_| invalid("encoder", "poisoned"))?.set_codebook(cb.clone());
        }
        Ok(slf.clone())
    }
    /// Encodes frames from files: `images` (RGB; needed with appearance or a segmenter) and/or
    /// `labels` (label maps), one per id, in parallel. With `skip_invalid`, frames that fail are
    /// left out (else the first failure raises, naming the file). With `engine` on a GPU, the
    /// global descriptors and VLAD run there (as `semlook --backend gpu`).
    #[pyo3(signature = (ids, images=None, labels=None, label_format="auto", skip_invalid=false, threads=None, engine=None))]
    #[allow(clippy::too_many_arguments)]
    fn encode_files(
        &self,
        py: Python<'_>,
        ids: Vec<String>,
        images: Option<Vec<PathBuf>>,
        labels: Option<Vec<PathBuf>>,
        label_format: &str,
        skip_invalid: bool,
        threads: Option<usize>,
        engine: Option<PyRef<'_, PyEngine>>,
    ) -> PyResult<PyDescriptors> {
        let frames = frames(ids, images, labels)?;
        let fmt = self::label_format(label_format)?;
        // photos without label maps and no segmenter: encoded without labels (as `map build`)
        let enc = self.inner();
        let enc = enc.clone().without_labels(enc.labels_rule(None, &frames).py_err()?);
        let engine = resolve(py, engine)?;
        let encoded =
            run(py, pool(threads)?, engine.as_ref(), |e| semlook::batch::encode_frames(e, &enc, &frames, fmt, "frames", skip_invalid, true))?;
        Ok(PyDescriptors::new(encoded.set))
    }
    /// Encodes one frame from memory: `image` uint8 [H, W, 3] (RGB) and/or `labels` [H, W] of
    /// label ids (any integer type; translated by the config's class table like a grey PNG).
    #[pyo3(signature = (id, image=None, labels=None))]
    fn encode(&self, py: Python<'_>, id: String, image: Option<&Bound<'_, PyAny>>, labels: Option<&Bound<'_, PyAny>>) -> PyResult<PyDescriptors> {
        let rgb = image.map(|a| rgb_from_array(py, a, &format!("image of {id:?}"))).transpose()?;
        let enc = self.inner().clone();
        let labels = labels.map(|l| labels_from_array(py, l, &format!("labels of {id:?}"), &enc)).transpose()?;
        let free = match rgb.is_some() && labels.is_none() {
            true => enc.photos_rule(None, &format!("frame {id:?}")).py_err()?,
            false => false,
        };
        let enc = enc.clone().without_labels(free);
        let set = py
            .detach(|| -> semlook::Result<_> {
                let loaded = enc.frames().load_arrays(&id, rgb, labels)?;
                let (img, _) = enc.encode_loaded(&id, &loaded, &mut Default::default())?;
                let mut set = enc.descriptor_set();
                set.push(&img).map_err(|e| e.named(|r| semlook::Error::invalid(format!("image {id:?}"), r)))?;
                Ok(set)
            })
            .py_err()?;
        Ok(PyDescriptors::new(set))
    }
}

impl PyEncoder {
    pub fn wrap(e: Encoder) -> Self {
        PyEncoder { inner: std::sync::RwLock::new(e) }
    }
    /// The encoder as it is now (a codebook training writes it; a poisoned lock still reads).
    pub fn inner(&self) -> std::sync::RwLockReadGuard<'_, Encoder> {
        self.inner.read().unwrap_or_else(|e| e.into_inner())
    }
}

/// Frame sources from parallel lists of ids, image paths and label paths.
fn frames(ids: Vec<String>, images: Option<Vec<PathBuf>>, labels: Option<Vec<PathBuf>>) -> PyResult<Vec<FrameSource>> {
    for (what, list) in [("images", &images), ("labels", &labels)] {
        if let Some(l) = list.as_ref().filter(|l| l.len() != ids.len()) {
            return Err(invalid(what, format!("{} paths for {} ids", l.len(), ids.len())));
        }
    }
    let at = |l: &Option<Vec<PathBuf>>, i: usize| l.as_ref().map(|v| v[i].clone());
    Ok(ids.into_iter().enumerate().map(|(i, id)| FrameSource { id, image: at(&images, i), labels: at(&labels, i) }).collect())
}

/// `obj` as a numpy array (lists and other array-likes converted), or an `InvalidInputError`
/// naming `what`.
fn as_array<'py>(py: Python<'py>, obj: &Bound<'py, PyAny>, what: &str) -> PyResult<Bound<'py, PyAny>> {
    let a = py.import("numpy")?.call_method1("asarray", (obj,)).map_err(|e| invalid(what, format!("not an array: {e}")))?;
    Ok(a)
}

/// The name of an array's dtype.
fn dtype_of(a: &Bound<'_, PyAny>) -> PyResult<String> {
    a.getattr("dtype")?.str()?.extract()
}

/// An RGB image from a uint8 array [H, W, 3] (H, W at most 32768); errors name `what`.
pub fn rgb_from_array(py: Python<'_>, obj: &Bound<'_, PyAny>, what: &str) -> PyResult<image::RgbImage> {
    let a = as_array(py, obj, what)?;
    if dtype_of(&a)? != "uint8" {
        return Err(invalid(what, format!("dtype {}, expected uint8 RGB", dtype_of(&a)?)));
    }
    let a: PyReadonlyArrayDyn<'_, u8> = a.extract().map_err(|e| invalid(what, e))?;
    let s = a.shape();
    if s.len() != 3 || s[2] != 3 || s[0] == 0 || s[1] == 0 || s[0] > 1 << 15 || s[1] > 1 << 15 {
        return Err(invalid(what, format!("shape {s:?}, expected [H, W, 3] uint8 (H, W at most 32768)")));
    }
    let (h, w) = (s[0] as u32, s[1] as u32);
    let pixels: Vec<u8> = a.as_array().iter().copied().collect();
    image::RgbImage::from_raw(w, h, pixels).ok_or_else(|| invalid(what, "size"))
}

/// A label map from an integer array [H, W] of label ids, translated by `enc`'s class table like
/// a grey PNG; errors name `what`.
pub fn labels_from_array(py: Python<'_>, obj: &Bound<'_, PyAny>, what: &str, enc: &Encoder) -> PyResult<input::LabelMap> {
    let l = as_array(py, obj, what)?;
    let kind: String = l.getattr("dtype")?.getattr("kind")?.extract()?;
    if kind != "i" && kind != "u" {
        // floats are not truncated into ids, nor strings or objects converted
        return Err(invalid(what, format!("dtype {}, expected an integer array of label ids", dtype_of(&l)?)));
    }
    let s: Vec<usize> = l.getattr("shape")?.extract()?;
    if s.len() != 2 {
        return Err(invalid(what, format!("shape {s:?}, expected [H, W]")));
    }
    // uint64 ids above i64::MAX would wrap in int64; every other integer type fits
    let itemsize: usize = l.getattr("dtype")?.getattr("itemsize")?.extract()?;
    if kind == "u" && itemsize == 8 && s[0] * s[1] > 0 {
        let top: u64 = l.call_method0("max")?.extract()?;
        if top > u64::from(u32::MAX) {
            return Err(invalid(what, format!("label id {top} is not a class id (0 to {})", u32::MAX)));
        }
    }
    let ids: PyReadonlyArrayDyn<'_, i64> = l.call_method1("astype", ("int64",))?.extract().map_err(|e| invalid(what, e))?;
    let mut v = Vec::with_capacity(s[0] * s[1]);
    for (i, &x) in ids.as_array().iter().enumerate() {
        let id = u32::try_from(x)
            .map_err(|_| invalid(what, format!("label id {x} at pixel (x {}, y {}) is not a class id (0 to {})", i % s[1], i / s[1], u32::MAX)))?;
        v.push(id);
    }
    // an id the class table lacks is a bad value here, not a bad file
    input::label_map_from_ids(s[1] as u32, s[0] as u32, &v, std::path::Path::new(what), enc.class_table()).map_err(|e| match e {
        semlook::Error::UnknownClassId { id, x, y, .. } => {
            invalid(what, format!("pixel (x {x}, y {y}) has class id {id}, which the class table does not know (and is not void)"))
        }
        e => crate::errors::to_py(e),
    })
}

/// The shape of `obj` as a numpy array.
pub fn shape_of(py: Python<'_>, obj: &Bound<'_, PyAny>, what: &str) -> PyResult<Vec<usize>> {
    as_array(py, obj, what)?.getattr("shape")?.extract()
}
