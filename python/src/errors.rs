//! Exceptions: `SemlookError` and one subclass per kind of engine error, each also deriving from
//! the builtin a Python caller expects (`ValueError` for bad values and arrays, `OSError` for
//! files, `FileNotFoundError` for a missing one, `RuntimeError` for the GPU), so `except
//! ValueError` works. The message is the engine's own (it names the file, field or image), and
//! `path`/`field`/`id` are attributes where the error has them.

use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use pyo3::types::{PyDict, PyTuple, PyType};
use semlook::{Error, ErrorKind};

/// Each class: name, its semlook parent (`None`: `SemlookError` itself), the builtin it also
/// derives from, and its doc.
const CLASSES: [(&str, Option<&str>, &str, &str); 13] = [
    ("SemlookError", None, "Exception", "Any error of the semlook engine."),
    ("InputFileError", Some("SemlookError"), "OSError", "An image or label file that cannot be read or decoded, or whose content is not usable."),
    ("MissingFileError", Some("InputFileError"), "FileNotFoundError", "A file or folder that does not exist."),
    ("InvalidConfigError", Some("SemlookError"), "ValueError", "A configuration value out of range or unreadable; the message names the field."),
    ("CorruptMapError", Some("SemlookError"), "OSError", "A map file that fails its checks; the message names the file."),
    ("MapVersionError", Some("SemlookError"), "OSError", "A map written by an unsupported format version."),
    ("IncompatibleConfigError", Some("SemlookError"), "ValueError", "Queries encoded differently from the map."),
    ("DuplicateImageIdError", Some("SemlookError"), "ValueError", "An image id the map already stores, or one given to two images."),
    ("InvalidImageError", Some("SemlookError"), "ValueError", "Descriptors refused before anything was written (NaN, out-of-range values)."),
    ("DatasetError", Some("SemlookError"), "ValueError", "A dataset folder, manifest or ground-truth file that cannot be used."),
    ("InvalidInputError", Some("SemlookError"), "ValueError", "An argument the engine cannot use (wrong shape, unknown setting, ...)."),
    ("ModelError", Some("SemlookError"), "OSError", "A model file that is missing or of the wrong kind."),
    ("GpuError", Some("SemlookError"), "RuntimeError", "A failure of the GPU backend."),
];

static TYPES: PyOnceLock<Vec<Py<PyType>>> = PyOnceLock::new();

/// The classes of [`CLASSES`], made once per interpreter with `type(name, bases, namespace)`.
fn types(py: Python<'_>) -> PyResult<&Vec<Py<PyType>>> {
    TYPES.get_or_try_init(py, || {
        let builtins = py.import("builtins")?;
        let make = builtins.getattr("type")?;
        let mut made: Vec<Py<PyType>> = Vec::new();
        for (name, parent, builtin, doc) in CLASSES {
            let mut bases = vec![];
            if let Some(parent) = parent {
                let k = CLASSES.iter().position(|c| c.0 == parent).expect("parents come first");
                bases.push(made[k].bind(py).clone().into_any());
            }
            bases.push(builtins.getattr(builtin)?);
            let ns = PyDict::new(py);
            ns.set_item("__doc__", doc)?;
            ns.set_item("__module__", "semlook._native")?;
            let t = make.call1((name, PyTuple::new(py, bases)?, ns))?;
            made.push(t.cast_into::<PyType>()?.unbind());
        }
        Ok(made)
    })
}

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    for (t, (name, ..)) in types(m.py())?.iter().zip(CLASSES) {
        m.add(name, t.bind(m.py()))?;
    }
    Ok(())
}

/// The class named `name` of [`CLASSES`].
fn class(py: Python<'_>, name: &str) -> PyResult<Py<PyType>> {
    let k = CLASSES.iter().position(|c| c.0 == name).expect("a listed class");
    Ok(types(py)?[k].clone_ref(py))
}

/// The class of each [`ErrorKind`] (the engine says which kind an error is: `Error::kind`).
fn class_name(kind: ErrorKind) -> &'static str {
    match kind {
        ErrorKind::MissingFile => "MissingFileError",
        ErrorKind::InputFile => "InputFileError",
        ErrorKind::InvalidConfig => "InvalidConfigError",
        ErrorKind::CorruptMap => "CorruptMapError",
        ErrorKind::MapVersion => "MapVersionError",
        ErrorKind::IncompatibleConfig => "IncompatibleConfigError",
        ErrorKind::DuplicateImageId => "DuplicateImageIdError",
        ErrorKind::InvalidImage => "InvalidImageError",
        ErrorKind::Dataset => "DatasetError",
        ErrorKind::InvalidInput => "InvalidInputError",
        ErrorKind::Model => "ModelError",
        ErrorKind::Gpu => "GpuError",
        _ => "SemlookError",
    }
}

/// The Python exception of an engine error: the class of its kind, and the `path`, `field` and
/// `id` it names.
pub fn to_py(e: Error) -> PyErr {
    let msg = e.to_string();
    let name = class_name(e.kind());
    let shown = |p: &std::path::Path| Some(p.display().to_string());
    let (path, field, id): (Option<String>, Option<String>, Option<String>) = match &e {
        Error::Io { path, .. }
        | Error::ImageDecode { path, .. }
        | Error::EmptyImage { path, .. }
        | Error::UnknownClassId { path, .. }
        | Error::UnknownClassColor { path, .. }
        | Error::UnsupportedLabelFormat { path, .. }
        | Error::CorruptMap { path, .. }
        | Error::DamagedIndex { path, .. }
        | Error::MapVersion { path, .. }
        | Error::Dataset { path, .. }
        | Error::Model { path, .. } => (shown(path), None, None),
        Error::SizeMismatch { labels, .. } => (shown(labels), None, None),
        Error::NoLabels { image } => (shown(image), None, None),
        Error::InvalidConfig { source_name, .. } => (Some(source_name.clone()), None, None),
        Error::IncompatibleConfig { map, field, .. } => (shown(map), Some(field.clone()), None),
        Error::DuplicateImageId { map, id } | Error::RepeatedImageId { map, id, .. } => (shown(map), None, Some(id.clone())),
        Error::InvalidImage { id, .. } => (None, None, Some(id.clone())),
        Error::InvalidInput { what, .. } | Error::Refused { what, .. } => (None, Some(what.clone()), None),
        _ => (None, None, None),
    };
    Python::attach(|py| {
        let err = match class(py, name) {
            Ok(t) => PyErr::from_type(t.into_bound(py), msg),
            Err(e) => return e,
        };
        // `path`, not OSError's `filename`: with that set, str() shows errno and file, not the message
        let v = err.value(py);
        for (attr, value) in [("path", path), ("field", field), ("id", id)] {
            let _ = v.setattr(attr, value);
        }
        err
    })
}

/// An argument error in the bindings themselves.
pub fn invalid(what: &str, reason: impl std::fmt::Display) -> PyErr {
    to_py(Error::invalid(what, reason.to_string()))
}

pub trait OrPy<T> {
    fn py_err(self) -> PyResult<T>;
}
impl<T> OrPy<T> for semlook::Result<T> {
    fn py_err(self) -> PyResult<T> {
        self.map_err(to_py)
    }
}
