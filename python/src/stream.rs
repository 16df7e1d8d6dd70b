//! `Localizer`: a stream of frames localized one at a time against a map (`semlook::stream`),
//! with sequence matching over the last frames and a loop-closure mode.

use crate::arrays::{setting, to_py_object};
use crate::encoder::{labels_from_array, rgb_from_array, PyConfig};
use crate::engine::engine_for;
use crate::errors::{invalid, OrPy};
use pyo3::prelude::*;
use semlook::input::FrameSource;
use semlook::stream::{Localizer, Pixels, StreamFrame, StreamOptions};
use std::path::PathBuf;
use std::sync::Mutex;

/// Localizes frames one at a time against the map at `path` (with `loop_closure`, created from
/// the stream where there is none). `setting` ranks the map (default "verified"); `sequence`
/// turns sequence matching over the last frames on (default); `config` as `Map.query`'s (default:
/// the map's); `backend` "cpu", "gpu" or "auto" (default `DEFAULT_BACKEND`): each localizer has
/// an engine of its own, which keeps the map resident on a GPU. `labelled_frames=True` says every
/// frame will come with its label map (`push(labels=)` or `labels_path=`): without it, a map that
/// holds labels and no segmenter (`segmenter=`, the config's, or the installed one) is refused
/// here, as `semlook localize` refuses it without `--labels`, with `InvalidInputError`.
#[pyclass(frozen, module = "semlook._native", name = "Localizer")]
pub struct PyLocalizer {
    inner: Mutex<Localizer>,
}

#[pymethods]
impl PyLocalizer {
    #[new]
    #[pyo3(signature = (path, setting="verified", sequence=true, loop_closure=false, config=None, backend=None, *, segmenter=None, camera=None, labelled_frames=false))]
    #[allow(clippy::too_many_arguments)]
    fn new(
        py: Python<'_>,
        path: PathBuf,
        setting: &str,
        sequence: bool,
        loop_closure: bool,
        config: Option<PyRef<'_, PyConfig>>,
        backend: Option<&str>,
        segmenter: Option<&Bound<'_, PyAny>>,
        camera: Option<PathBuf>,
        labelled_frames: bool,
    ) -> PyResult<Self> {
        // the camera file (`localize --camera`'s) is read and checked before the map is opened
        let camera = camera.map(|c| semlook::verify::pose::Camera::load(&c)).transpose().py_err()?;
        let s = self::setting(setting)?;
        if loop_closure && !sequence {
            return Err(invalid("sequence", "loop closure finds its closures by sequence matching: keep sequence=True"));
        }
        let (engine, _) = engine_for(py, backend, None)?;
        // the segmenter named replaces the config's (or the map's) choice
        let cfg = match (config.map(|c| c.inner.clone()), segmenter) {
            (cfg, None) => cfg,
            (cfg, seg) => {
                let base = match cfg {
                    Some(c) => c,
                    None => match semlook::map::manifest::read(&path).py_err()? {
                        Some(m) => semlook::map::manifest::query_config(&m),
                        None => semlook::config::Config::default(),
                    },
                };
                Some(crate::encoder::with_segmenter(base, seg)?)
            }
        };
        // photos without label maps on a map that holds labels, and no segmenter: refused now
        // (the command line's rule and error), unless the caller says every frame brings its labels
        let opts = StreamOptions { setting: s, sequence, loop_closure, labelled_frames, resume: false };
        let loc = py.detach(|| Localizer::open(&path, cfg, opts, engine)).map_err(|e| match e {
            semlook::Error::Refused { what, reason, remedy: remedy @ semlook::error::Remedy::GiveLabels } => semlook::Error::Refused {
                what,
                reason: format!("{reason}; pass segmenter=MODEL.onnx, or labelled_frames=True and every frame's labels"),
                remedy,
            },
            e => e,
        });
        let mut loc = loc.py_err()?;
        if let Some(c) = camera {
            loc = loc.with_camera(c).py_err()?;
        }
        Ok(PyLocalizer { inner: Mutex::new(loc) })
    }

    /// Localizes the next frame: `image` (uint8 [H, W, 3] RGB) and/or `labels` (integer [H, W]
    /// label ids), or a `path` to an image file (and `labels_path`), or the `data` of a JPEG or
    /// PNG file; `id` names it (default: the file's stem for `path`, else frame-N; in loop-closure
    /// mode the id it is stored under),
    /// `timestamp` in seconds must not go backwards. Returns a dict: `top_k` (the single-frame
    /// ranking: id, index, place, score, inliers), `sequence` (the sequence match: id, score,
    /// uniqueness, accepted, velocity, frames; None without evidence), `answer` (the stream's
    /// answer, a dict: id, index, place, score on the single-frame scale whatever the source,
    /// source "sequence" or "frame", accepted; None without a match), `pose` (the pose the map stores for
    /// the answer, as `Map.pose` gives it; None where it stores none), `relative_pose` (with
    /// `camera=`, for an accepted answer: rotation, quaternion, translation_unit, rotation_deg,
    /// inliers, matches; None otherwise), `closure`, `generation`,
    /// `latency` (ms per stage). A frame that cannot be used raises, and the stream goes on.
    #[pyo3(signature = (image=None, labels=None, *, path=None, labels_path=None, data=None, id=None, timestamp=None))]
    #[allow(clippy::too_many_arguments)]
    fn push<'py>(
        &self,
        py: Python<'py>,
        image: Option<&Bound<'py, PyAny>>,
        labels: Option<&Bound<'py, PyAny>>,
        path: Option<PathBuf>,
        labels_path: Option<PathBuf>,
        data: Option<Vec<u8>>,
        id: Option<String>,
        timestamp: Option<f64>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let mut loc = self.inner.lock().map_err(|_| invalid("localizer", "poisoned by a panic in an earlier call"))?;
        // a file's frame is named by its stem, as `localize --images` names it
        let stem = path.as_deref().and_then(|p| p.file_stem()).map(|s| s.to_string_lossy().into_owned());
        let id = id.or(stem).unwrap_or_else(|| format!("frame-{:06}", loc.counts().frames));
        let lab = labels.map(|l| labels_from_array(py, l, "labels", loc.encoder())).transpose()?;
        let pixels = match (image, path, data) {
            (Some(img), None, None) => Pixels::Rgb { image: rgb_from_array(py, img, "image")?, labels: lab },
            (None, Some(p), None) if lab.is_none() => Pixels::Files(FrameSource { id: id.clone(), image: Some(p), labels: labels_path }),
            (None, None, Some(bytes)) => Pixels::Bytes { bytes, labels: lab },
            (None, None, None) => match (lab, labels_path) {
                (Some(l), None) => Pixels::Labels(l),
                (None, Some(lp)) => Pixels::Files(FrameSource { id: id.clone(), image: None, labels: Some(lp) }),
                _ => return Err(invalid("push", "no frame: give image=, path= or data=")),
            },
            _ => return Err(invalid("push", "give one of image=, path= and data= (labels= with image= or data=, labels_path= with path=)")),
        };
        let frame = StreamFrame { id, pixels, timestamp };
        let l: &mut Localizer = &mut loc;
        let r = py.detach(|| l.push(frame)).py_err()?;
        let out = to_py_object(py, &r)?;
        out.set_item("pose", to_py_object(py, &r.pose)?)?;
        Ok(out)
    }

    /// Moves to the map's newest generation when another writer committed one; whether it did.
    fn refresh(&self, py: Python<'_>) -> PyResult<bool> {
        let mut loc = self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?;
        let l: &mut Localizer = &mut loc;
        py.detach(|| l.refresh()).py_err()
    }
    /// Forgets the stream's past: the next frame starts a new sequence.
    fn reset(&self) -> PyResult<()> {
        self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?.reset();
        Ok(())
    }
    /// Loop-closure mode: commits the frames added and not yet committed.
    fn finish(&self, py: Python<'_>) -> PyResult<()> {
        let mut loc = self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?;
        let l: &mut Localizer = &mut loc;
        py.detach(|| l.finish()).py_err()
    }
    /// `with Localizer(...) as loc:` commits on leaving the block, however it is left: an
    /// exception, or Ctrl-C's KeyboardInterrupt between frames, keeps every frame answered.
    fn __enter__(slf: PyRef<'_, Self>) -> PyRef<'_, Self> {
        slf
    }
    /// Commits ([`finish`](Self::finish)); the block's exception, if any, goes on.
    #[pyo3(signature = (*_exc))]
    fn __exit__(&self, py: Python<'_>, _exc: &Bound<'_, pyo3::types::PyTuple>) -> PyResult<bool> {
        self.finish(py)?;
        Ok(false)
    }
    /// Frames, refused frames, accepted sequence matches, closures, reloads, warm-up frames.
    #[getter]
    fn counts<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        to_py_object(py, &self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?.counts())
    }
    /// (frames in the ring, entries they hold): what the stream keeps, bounded.
    #[getter]
    fn state_size(&self) -> PyResult<(usize, usize)> {
        Ok(self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?.state_size())
    }
    /// The map generation frames are answered from (None while a loop-closure map warms up).
    #[getter]
    fn generation(&self) -> PyResult<Option<u64>> {
        Ok(self.inner.lock().map_err(|_| invalid("localizer", "poisoned"))?.map().map(|m| m.manifest.generation))
    }
    fn __repr__(&self) -> String {
        match self.inner.lock() {
            Ok(l) => format!(
                "Localizer({}, {}, {} frames)",
                l.map().map_or("(warming up)".into(), |m| m.path.display().to_string()),
                l.options().setting,
                l.counts().frames
            ),
            Err(_) => "Localizer(poisoned)".into(),
        }
    }
}
