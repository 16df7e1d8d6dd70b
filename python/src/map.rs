//! `Map`: a stored map (memory-mapped segments), its edits, queries against it, zero-copy numpy
//! views of its segments, and `evaluate`.

use crate::arrays::to_py_object;
use crate::arrays::{pool, setting, view};
use crate::descriptors::PyDescriptors;
use crate::encoder::{labels_from_array, rgb_from_array, shape_of};
use crate::encoder::{PyConfig, PyEncoder};
use crate::engine::{resolve, run, PyEngine};
use crate::errors::{invalid, OrPy};
use crate::matches::PyMatches;
use crate::store::{wrap, MapGeneration, PyMap};
use image::RgbImage;
use numpy::{PyUntypedArray, PyUntypedArrayMethods};
use pyo3::prelude::*;
use rayon::prelude::*;
use semlook::config::Config;
use semlook::descriptors::source::RefSource;
use semlook::descriptors::DescriptorSet;
use semlook::encode::Encoder;
use semlook::input::LabelMap;
use semlook::map::{edit, Map, MapWriter, StoreOptions};
use semlook::values::{ValueType, Values};
use std::path::PathBuf;
use std::sync::Arc;

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
        let (set, enc, opts) = (descriptors.inner.clone(), encoder.inner().clone(), store_options(segment_images, f16)?);
        // photos encoded without labels (no label maps, no segmenter): a map marked so, which
        // serves the settings that need none and refuses the others by name
        let without_labels = !set.is_empty() && set.n_trees() == 0 && !enc.frames().can_segment();
        let m = py.detach(|| -> semlook::Result<Map> {
            let dims = semlook::map::ColumnDims {
                appearance: set.appearance_dim,
                hog: set.hog_dim,
                keypoints: set.keypoint_dim,
                compact_hog: set.compact_hog_dim,
            };
            let mut w = MapWriter::create(&path, enc.config(), dims, enc.appearance_record(), opts, false)?.with_embedding(set.embedding.clone())?;
            if without_labels {
                w = w.without_labels()?;
            }
            w.push_set(&set)?;
            w.finish()
        });
        Ok(wrap(m.py_err()?))
    }
    /// Builds a map in `path` from image files in one call, as `semlook map build` does: the
    /// VLAD codebook trained on them, every frame encoded and committed segment by segment.
    /// `images` and/or `labels`: lists of paths (one per id), or a folder of images (png, jpg:
    /// ids are the file stems; label maps `<stem>.png` in the `labels` folder). `segmenter` as
    /// `Encoder`'s (False: photos without label maps make a map without labels, for the
    /// settings that need none). `ids`: with lists, default the file stems. `index` as
    /// `semlook map build --index`: "auto" (from `index.min_places` images with appearance),
    /// "ivf" (always) or "none". It is the command's job (`semlook::batch::build_map`): the same
    /// folder and config give the same map, its index and the null of `verified`'s evidence
    /// included.
    #[staticmethod]
    #[pyo3(signature = (path, images=None, labels=None, ids=None, config=None, segmenter=None, segment_images=None, f16=false, engine=None, *, index="auto"))]
    #[allow(clippy::too_many_arguments)]
    fn build(
        py: Python<'_>,
        path: PathBuf,
        images: Option<&Bound<'_, PyAny>>,
        labels: Option<&Bound<'_, PyAny>>,
        ids: Option<Vec<String>>,
        config: Option<PyRef<'_, PyConfig>>,
        segmenter: Option<&Bound<'_, PyAny>>,
        segment_images: Option<usize>,
        f16: bool,
        engine: Option<PyRef<'_, PyEngine>>,
        index: &str,
    ) -> PyResult<Self> {
        let index = <semlook::batch::IndexPolicy as semlook::Choice>::parse_name(index).map_err(|why| invalid("index", why))?;
        let cfg = crate::encoder::with_segmenter(config.map_or_else(Config::default, |c| c.inner.clone()), segmenter)?;
        let frames = build_frames(images, labels, ids, ["images", "labels"])?;
        let new = semlook::batch::NewMapOptions { store: store_options(segment_images, f16)?, quiet: true, ..Default::default() };
        let opts = semlook::batch::BuildOptions { new, index, frame_interval: None };
        let engine = resolve(py, engine)?;
        let m = run(py, None, engine.as_ref(), |e| semlook::batch::build_map(e, &cfg, &frames, Default::default(), None, &path, &opts, &|_| {}))?;
        Ok(wrap(m))
    }
    /// Adds `descriptors` (encoded by `Encoder.for_map(map)`) as new segments; every image and id
    /// is checked before anything is written. This map then serves the new generation.
    #[pyo3(signature = (descriptors, segment_images=None))]
    fn add(&self, py: Python<'_>, descriptors: &PyDescriptors, segment_images: Option<usize>) -> PyResult<()> {
        let (set, dir, opts) = (descriptors.inner.clone(), self.map().path.clone(), store_options(segment_images, false)?);
        let m = py
            .detach(|| {
                let mut w = MapWriter::append(&dir, opts)?;
                w.push_set(&set)?;
                w.finish()
            })
            .py_err()?;
        self.replace(m);
        Ok(())
    }
    /// Marks the images `ids` removed (queries never return them; `compact` drops them from the
    /// files). This map then serves the new generation.
    fn remove(&self, py: Python<'_>, ids: Vec<String>) -> PyResult<()> {
        let dir = self.map().path.clone();
        self.replace(py.detach(|| edit::remove(&dir, &ids).and_then(|_| Map::open(&dir))).py_err()?);
        Ok(())
    }
    /// Rewrites segments without their removed images, merging small ones; this map then serves
    /// the new generation. Returns the report (a dict).
    fn compact<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let dir = self.map().path.clone();
        let (m, report) = py.detach(|| edit::compact(&dir, StoreOptions::default()).and_then(|r| Ok((Map::open(&dir)?, r)))).py_err()?;
        self.replace(m);
        to_py_object(py, &report)
    }
    /// Checks every file (SHA-256, values); a dict naming each damaged file (raises only when the
    /// manifest itself is unreadable).
    fn verify<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let dir = self.map().path.clone();
        let report = py.detach(|| edit::verify(&dir)).py_err()?;
        to_py_object(py, &report)
    }
    fn __len__(&self) -> usize {
        self.map().len()
    }
    fn __repr__(&self) -> String {
        let m = self.map();
        format!("Map({:?}, {} images, {} segments, generation {})", m.path, m.len(), m.segments().len(), m.manifest.generation)
    }
    #[getter]
    fn path(&self) -> PathBuf {
        self.map().path.clone()
    }
    #[getter]
    fn generation(&self) -> u64 {
        self.map().manifest.generation
    }
    #[getter]
    fn n_segments(&self) -> usize {
        self.map().segments().len()
    }
    /// The ids of the map's images, in reference order (removed images left out).
    #[getter]
    fn ids(&self) -> Vec<String> {
        let m = self.map();
        (0..m.len()).map(|i| m.id(i).to_string()).collect()
    }
    /// The pose stored with image `i` (reference order): a dict with "position" [x, y, z] and
    /// "orientation" [x, y, z, w] (camera to world; None where the source gave a position alone),
    /// or None where the image has none (`semlook map build --poses`, or a dataset's own poses).
    fn pose<'py>(&self, py: Python<'py>, i: usize) -> PyResult<Bound<'py, PyAny>> {
        let m = self.map();
        if i >= m.len() {
            return Err(pyo3::exceptions::PyIndexError::new_err(format!("image {i} of a map of {}", m.len())));
        }
        to_py_object(py, &m.pose(i))
    }
    /// The manifest as a dict.
    fn manifest<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_object(py, &self.map().manifest)
    }
    /// Rows of segment `s` that are not removed (reference order within the segment).
    fn live_rows(&self, s: usize) -> PyResult<Vec<usize>> {
        let m = self.map();
        segment_index(&m, s)?;
        Ok(m.live_rows(s).collect())
    }
    /// Segment `s`'s stored values: `name` "globals" ([rows, height, width]) is a read-only numpy
    /// view, no copy (float32, or float16 on an f16 map; it keeps the map's mapping alive);
    /// "image_appearance" ([rows, dim]) is a new float32 array widened from the int8 blocks the
    /// map stores. Removed rows included (see `live_rows`). With `verify` (default) the segment's
    /// SHA-256 and values are checked first.
    #[pyo3(signature = (s, name, verify=true))]
    fn segment_view<'py>(slf: Bound<'py, Self>, s: usize, name: &str, verify: bool) -> PyResult<Bound<'py, PyAny>> {
        let map = slf.get().map();
        segment_index(&map, s)?;
        let seg = &map.segments()[s];
        if verify {
            seg.ensure().map_err(crate::errors::to_py)?;
        }
        let g = &map.manifest.config.global;
        let (values, shape) = match name {
            "globals" => (seg.globals(0, seg.len()), vec![seg.len(), g.height, g.width]),
            "image_appearance" => (seg.image_appearances(), vec![seg.len(), map.manifest.appearance_dim]),
            _ => return Err(invalid("segment_view", format!("{name:?} is not globals or image_appearance"))),
        };
        // the views keep this generation open, whatever this object serves later
        let owner = Bound::new(slf.py(), MapGeneration { _map: map.clone() })?.into_any();
        Ok(match values {
            Values::F32(v) => view(owner, v, &shape)?.into_any(),
            // the stored bit patterns as half::f16 (a Pod wrapper of its u16), no copy
            Values::F16(v) => view(owner, bytemuck::cast_slice::<u16, half::f16>(v), &shape)?.into_any(),
            blocks @ Values::Blocks(_) => numpy::PyArrayMethods::reshape(&numpy::PyArray1::from_vec(owner.py(), blocks.to_vec()), shape)?.into_any(),
        })
    }
    /// Matches query frames against the whole map with `setting`. `queries`: `Descriptors` (from
    /// `Encoder.for_map(map)`), or frames as arrays, all label maps (integer [H, W] of label ids)
    /// or all RGB images (uint8 [H, W, 3]); or, instead, `images` and/or `labels`, one per frame
    /// (both for frames that have both). Frames are encoded with `Encoder.for_map(map, config)` as
    /// its `encode` does (on the CPU), named by `ids` (default q0, q1, ...). Files instead of
    /// arrays: a folder or a list of paths (as `queries`, `images` or `labels`), ids the file
    /// stems unless `ids` are given, as `Map.build` reads them. `k` candidates per
    /// query (default: the config's top_k), `config` as `semlook query --config` (default:
    /// `Config.for_map(map)`), `threads` for a pool of its own, `engine` the `Engine` matching
    /// runs on (default: `default_engine()`).
    #[pyo3(signature = (queries=None, setting="verified", k=None, config=None, threads=None, engine=None, *, images=None, labels=None, ids=None, segmenter=None))]
    #[allow(clippy::too_many_arguments)]
    fn query(
        &self,
        py: Python<'_>,
        queries: Option<&Bound<'_, PyAny>>,
        setting: &str,
        k: Option<usize>,
        config: Option<PyRef<'_, PyConfig>>,
        threads: Option<usize>,
        engine: Option<PyRef<'_, PyEngine>>,
        images: Option<&Bound<'_, PyAny>>,
        labels: Option<&Bound<'_, PyAny>>,
        ids: Option<Vec<String>>,
        segmenter: Option<&Bound<'_, PyAny>>,
    ) -> PyResult<PyMatches> {
        let map = self.map();
        let s = self::setting(setting)?;
        let cfg = crate::encoder::with_segmenter(query_config(&map, config.map(|c| c.inner.clone()), k)?, segmenter)?;
        let input = match queries.map(|q| q.cast::<PyDescriptors>()) {
            Some(Ok(d)) => match (images, labels, ids) {
                (None, None, None) => Input::Encoded(d.get().inner.clone()),
                (Some(_), ..) | (_, Some(_), _) => return Err(invalid("queries", "Descriptors, and images= or labels= too: give one of them")),
                (.., Some(_)) => return Err(invalid("ids", "given with Descriptors, which carry their ids")),
            },
            _ => {
                let enc = py.detach(|| self.encoder(&map, &cfg)).py_err()?.for_setting(s);
                // files: a folder or a list of paths (as queries=, images= or labels=)
                match (queries, images, labels) {
                    (Some(q), None, None) if are_paths(q) => Input::Files(Box::new(enc), build_frames(Some(q), None, ids, ["queries", "labels"])?),
                    (None, im, lb) if im.is_some_and(are_paths) || lb.is_some_and(are_paths) => {
                        Input::Files(Box::new(enc), build_frames(im, lb, ids, ["images", "labels"])?)
                    }
                    _ => {
                        let frames = raw_frames(py, &enc, queries, images, labels, ids)?;
                        // photos without label maps: segmented, label-free where nothing reads
                        // labels, else refused before any encoding (`Encoder::labels_rule`)
                        let photos = frames.iter().filter(|f| f.1.is_some() && f.2.is_none()).map(|f| f.0.clone()).next();
                        let enc = match photos {
                            Some(first) => {
                                let free = enc.photos_rule(Some(s), &format!("frame {first:?}")).py_err()?;
                                enc.without_labels(free)
                            }
                            None => enc,
                        };
                        Input::Frames(Box::new(enc), frames)
                    }
                }
            }
        };
        let engine = resolve(py, engine)?;
        let (set, matches) = run(py, pool(threads)?, engine.as_ref(), |e| {
            let set = match input {
                Input::Encoded(set) => set,
                Input::Frames(enc, frames) => Arc::new(encode_frames(&enc, frames)?),
                Input::Files(enc, frames) => {
                    // photos without label maps: segmented, label-free where nothing reads
                    // labels, else refused before any encoding (`Encoder::labels_rule`)
                    let label_free = enc.labels_rule(Some(s), &frames)?;
                    let enc = (*enc).without_labels(label_free);
                    let fmt = semlook::input::LabelFormat::default();
                    Arc::new(semlook::batch::encode_frames(e, &enc, &frames, fmt, "queries", false, true)?.set)
                }
            };
            let (matches, _) = e.match_batch(map.as_ref(), &set, s, &cfg)?;
            Ok((set, matches))
        })?;
        Ok(PyMatches::new(s, &set.ids, matches, |r| map.id(r as usize).to_string()))
    }
}

/// The frames of `Map.build` and `Map.query`'s files: folders (ids: the file stems), or one
/// file or a list of paths (with `ids`, default the stems). `names`: the arguments' names in
/// messages (images, labels).
fn build_frames(
    images: Option<&Bound<'_, PyAny>>,
    labels: Option<&Bound<'_, PyAny>>,
    ids: Option<Vec<String>>,
    names: [&str; 2],
) -> PyResult<Vec<semlook::input::FrameSource>> {
    use semlook::input::FrameSource;
    let stem = |p: &std::path::Path| p.file_stem().map(|s| s.to_string_lossy().into_owned()).unwrap_or_default();
    let as_dir = |o: Option<&Bound<'_, PyAny>>| -> Option<PathBuf> { o.and_then(|x| x.extract::<PathBuf>().ok()).filter(|p| p.is_dir()) };
    let as_list = |o: Option<&Bound<'_, PyAny>>, what: &str| -> PyResult<Option<Vec<PathBuf>>> {
        match o {
            None => Ok(None),
            // one path: a file is one frame; anything else is named
            Some(x) if !x.is_instance_of::<pyo3::types::PyList>() && !x.is_instance_of::<pyo3::types::PyTuple>() => match x.extract::<PathBuf>() {
                Ok(p) if p.is_file() => Ok(Some(vec![p])),
                Ok(p) => Err(invalid(what, format!("{}: no such file or folder", p.display()))),
                Err(_) => Err(invalid(what, "expected a folder, a file, or a list of paths")),
            },
            Some(x) => x.extract::<Vec<PathBuf>>().map(Some).map_err(|_| invalid(what, "expected a folder, a file, or a list of paths")),
        }
    };
    let (dir_images, dir_labels) = (as_dir(images), as_dir(labels));
    if ids.is_some() && (dir_images.is_some() || dir_labels.is_some()) {
        return Err(invalid("ids", "given with a folder, whose frames are named by their file stems: give lists of paths to name them"));
    }
    let frames: Vec<FrameSource> = match (dir_images, dir_labels) {
        (Some(dir), lab) => return semlook::dataset::frames_from_folders(Some(&dir), lab.as_deref()).py_err(),
        (None, Some(dir)) if images.is_none() => return semlook::dataset::frames_from_folders(None, Some(&dir)).py_err(),
        _ => {
            let (im, lb) = (as_list(images, names[0])?, as_list(labels, names[1])?);
            let n = im.as_ref().or(lb.as_ref()).map_or(0, Vec::len);
            if n == 0 {
                return Err(invalid(names[0], "no frames: give images= and/or labels= (folders or lists of paths)"));
            }
            if let (Some(a), Some(b)) = (&im, &lb) {
                if a.len() != b.len() {
                    return Err(invalid(names[1], format!("{} label maps for {} images", b.len(), a.len())));
                }
            }
            let ids = match ids {
                Some(v) if v.len() != n => return Err(invalid("ids", format!("{} ids for {n} frames", v.len()))),
                Some(v) => v,
                None => (0..n).map(|i| stem(im.as_ref().or(lb.as_ref()).map(|l| l[i].as_path()).unwrap_or(std::path::Path::new("")))).collect(),
            };
            ids.into_iter()
                .enumerate()
                .map(|(i, id)| FrameSource { id, image: im.as_ref().map(|v| v[i].clone()), labels: lb.as_ref().map(|v| v[i].clone()) })
                .collect()
        }
    };
    semlook::dataset::unique_ids(&frames).py_err()?;
    Ok(frames)
}

/// What `Map.query` matches: descriptors, or frames to encode first.
enum Input {
    Encoded(Arc<DescriptorSet>),
    Frames(Box<Encoder>, Vec<Frame>),
    Files(Box<Encoder>, Vec<semlook::input::FrameSource>),
}

/// Whether `obj` names files: a path (str, os.PathLike) or a list of them.
fn are_paths(obj: &Bound<'_, PyAny>) -> bool {
    let path = |o: &Bound<'_, PyAny>| o.is_instance_of::<pyo3::types::PyString>() || o.hasattr("__fspath__").unwrap_or(false);
    if path(obj) {
        return true;
    }
    // a list or a tuple of them: a sequence whose first item is one
    let sequence = obj.is_instance_of::<pyo3::types::PyList>() || obj.is_instance_of::<pyo3::types::PyTuple>();
    sequence && obj.get_item(0).is_ok_and(|first| path(&first))
}

/// A query frame from arrays: id, RGB image, label map.
type Frame = (String, Option<RgbImage>, Option<LabelMap>);

/// The frames of `Map.query`'s arrays: `queries` (all label maps or all images), or `images`
/// and/or `labels`; named by `ids` (default q0, q1, ...).
fn raw_frames(
    py: Python<'_>,
    enc: &Encoder,
    queries: Option<&Bound<'_, PyAny>>,
    images: Option<&Bound<'_, PyAny>>,
    labels: Option<&Bound<'_, PyAny>>,
    ids: Option<Vec<String>>,
) -> PyResult<Vec<Frame>> {
    let (mut rgb, mut lab) = (Vec::new(), Vec::new());
    match (queries, images, labels) {
        (Some(_), Some(_), _) | (Some(_), _, Some(_)) => {
            return Err(invalid("queries", "frames given both as queries and as images= or labels=: give one of them"))
        }
        (None, None, None) => return Err(invalid("queries", "nothing to match: give Descriptors, arrays of frames, or images= and/or labels=")),
        (Some(q), None, None) => {
            // (index, is an image) of the first frame: the others must be of its kind
            let mut first: Option<(usize, bool)> = None;
            for (i, a) in frames_of(q, "queries")?.iter().enumerate() {
                let what = format!("queries[{i}]");
                let shape = shape_of(py, a, &what)?;
                let image = match shape.len() {
                    2 => false,
                    3 if shape[2] == 3 => true,
                    _ => return Err(invalid(&what, format!("shape {shape:?}: expected a label map [H, W] or an RGB image [H, W, 3]"))),
                };
                if let Some((j, _)) = first.filter(|&(_, f)| f != image) {
                    let (this, that) = if image { ("an image", "a label map") } else { ("a label map", "an image") };
                    return Err(invalid(&what, format!("{this}, but queries[{j}] is {that}: give frames of one kind, or images= and labels=")));
                }
                first.get_or_insert((i, image));
                match image {
                    true => rgb.push(Some(rgb_from_array(py, a, &what)?)),
                    false => lab.push(Some(labels_from_array(py, a, &what, enc)?)),
                }
            }
        }
        (None, im, lb) => {
            let im = im.map(|x| frames_of(x, "images")).transpose()?;
            let lb = lb.map(|x| frames_of(x, "labels")).transpose()?;
            if let (Some(i), Some(l)) = (&im, &lb) {
                if i.len() != l.len() {
                    return Err(invalid("labels", format!("{} label maps for {} images", l.len(), i.len())));
                }
            }
            for (i, a) in im.iter().flatten().enumerate() {
                rgb.push(Some(rgb_from_array(py, a, &format!("images[{i}]"))?));
            }
            for (i, a) in lb.iter().flatten().enumerate() {
                lab.push(Some(labels_from_array(py, a, &format!("labels[{i}]"), enc)?));
            }
        }
    }
    let n = rgb.len().max(lab.len());
    let ids = match ids {
        Some(v) if v.len() != n => return Err(invalid("ids", format!("{} ids for {n} frames", v.len()))),
        Some(v) => v,
        None => (0..n).map(|i| format!("q{i}")).collect(),
    };
    let (mut rgb, mut lab) = (rgb.into_iter(), lab.into_iter());
    Ok(ids.into_iter().map(|id| (id, rgb.next().flatten(), lab.next().flatten())).collect())
}

/// The items of a sequence of frames named `what` (a list, or an array stacking frames).
fn frames_of<'py>(obj: &Bound<'py, PyAny>, what: &str) -> PyResult<Vec<Bound<'py, PyAny>>> {
    if obj.is_instance_of::<pyo3::types::PyString>() || obj.is_instance_of::<pyo3::types::PyBytes>() {
        return Err(invalid(what, "a string, not a sequence of arrays (files: Encoder.encode_files)"));
    }
    if let Ok(a) = obj.cast::<PyUntypedArray>() {
        let shape = a.shape();
        // one frame is not a sequence of them: its rows would be taken as frames
        if shape.len() < 3 || (shape.len() == 3 && shape[2] == 3) {
            return Err(invalid(what, format!("one array of shape {shape:?}: give a sequence of frames (a list, or an array stacking them)")));
        }
    }
    obj.try_iter().map_err(|_| invalid(what, "not a sequence of arrays"))?.collect()
}

/// Encodes frames in parallel (on the current pool), in order; the first failure is the error.
fn encode_frames(enc: &Encoder, frames: Vec<Frame>) -> semlook::Result<DescriptorSet> {
    let encoded: Vec<semlook::Result<_>> = frames
        .into_par_iter()
        .map_init(Default::default, |scratch, (id, rgb, labels)| {
            let loaded = enc.frames().load_arrays(&id, rgb, labels)?;
            Ok(enc.encode_loaded(&id, &loaded, scratch)?.0)
        })
        .collect();
    let mut set = enc.descriptor_set();
    for img in encoded {
        let img = img?;
        set.push(&img).map_err(|e| e.named(|r| semlook::Error::invalid(format!("image {:?}", img.id), r)))?;
    }
    Ok(set)
}

fn segment_index(map: &Map, s: usize) -> PyResult<()> {
    match s < map.segments().len() {
        true => Ok(()),
        false => Err(invalid("segment", format!("{s} of a map of {} segments", map.segments().len()))),
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
    settings: Option<&Bound<'py, PyAny>>,
    config: Option<PyRef<'_, PyConfig>>,
    map: Option<&PyMap>,
    gt_distance: Option<f64>,
    threads: Option<usize>,
    engine: Option<PyRef<'_, PyEngine>>,
) -> PyResult<Bound<'py, PyAny>> {
    use semlook::dataset::{Dataset, DatasetOptions};
    // as `semlook eval`: the default settings, and without a config or map the defaults
    // adapted to the dataset's label files
    // one name ("verified") or a list of them
    let settings = match settings {
        Some(s) if s.is_instance_of::<pyo3::types::PyString>() => vec![setting(&s.extract::<String>()?)?],
        Some(s) => {
            let names: Vec<String> = s.extract().map_err(|_| invalid("settings", "expected a setting name or a list of them (e.g. \"verified\")"))?;
            names.iter().map(|s| setting(s)).collect::<PyResult<Vec<_>>>()?
        }
        None => semlook::eval::DEFAULT_SETTINGS.to_vec(),
    };
    let map = map.map(|m| m.map());
    let opts = DatasetOptions { max_distance: gt_distance, ..Default::default() };
    let engine = resolve(py, engine)?;
    let config = config.map(|c| c.inner.clone());
    let report = run(py, pool(threads)?, engine.as_ref(), |e| {
        let ds = Dataset::open_any(dataset.as_deref(), references.as_deref(), queries.as_deref(), ground_truth.as_deref(), &opts)?;
        let cfg = match (config, &map) {
            (Some(c), _) => c,
            (None, Some(m)) => m.query_config(),
            (None, None) => ds.adapt_config(Config::default()),
        };
        let eo = semlook::eval::EvalOptions { settings, map: map.as_deref(), skip_invalid: false, quiet: true, sequence: false, label_cache: None };
        semlook::eval::evaluate(&ds, &cfg, &eo, e)
    })?;
    to_py_object(py, &report)
}
