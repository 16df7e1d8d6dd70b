//! Exceptions: `SemlookError` and one subclass per kind of engine error; the message is the
//! engine's own (it names the file, field or image), and `path`/`field`/`id` are attributes
//! where the error has them.

use pyo3::create_exception;
use pyo3::exceptions::PyException;
use pyo3::prelude::*;
use semlook::Error;

create_exception!(_native, SemlookError, PyException, "Any error of the semlook engine.");
create_exception!(_native, InputFileError, SemlookError, "An image or label file that cannot be read or decoded, or whose content is not usable.");
create_exception!(_native, InvalidConfigError, SemlookError, "A configuration value out of range or unreadable; the message names the field.");
create_exception!(_native, CorruptMapError, SemlookError, "A map file that fails its checks; the message names the file.");
create_exception!(_native, MapVersionError, SemlookError, "A map written by an unsupported format version.");
create_exception!(_native, IncompatibleConfigError, SemlookError, "Queries encoded differently from the map.");
create_exception!(_native, DuplicateImageIdError, SemlookError, "An image id the map already stores.");
create_exception!(_native, InvalidImageError, SemlookError, "Descriptors refused before anything was written (NaN, out-of-range values).");
create_exception!(_native, DatasetError, SemlookError, "A dataset folder, manifest or ground-truth file that cannot be used.");
create_exception!(_native, InvalidInputError, SemlookError, "An argument the engine cannot use (wrong shape, unknown setting, ...).");
create_exception!(_native, ModelError, SemlookError, "A model file that is missing or of the wrong kind.");
create_exception!(_native, GpuError, SemlookError, "A failure of the GPU backend.");

pub fn register(m: &Bound<'_, PyModule>) -> PyResult<()> {
    let py = m.py();
    m.add("SemlookError", py.get_type::<SemlookError>())?;
    m.add("InputFileError", py.get_type::<InputFileError>())?;
    m.add("InvalidConfigError", py.get_type::<InvalidConfigError>())?;
    m.add("CorruptMapError", py.get_type::<CorruptMapError>())?;
    m.add("MapVersionError", py.get_type::<MapVersionError>())?;
    m.add("IncompatibleConfigError", py.get_type::<IncompatibleConfigError>())?;
    m.add("DuplicateImageIdError", py.get_type::<DuplicateImageIdError>())?;
    m.add("InvalidImageError", py.get_type::<InvalidImageError>())?;
    m.add("DatasetError", py.get_type::<DatasetError>())?;
    m.add("InvalidInputError", py.get_type::<InvalidInputError>())?;
    m.add("ModelError", py.get_type::<ModelError>())?;
    m.add("GpuError", py.get_type::<GpuError>())?;
    Ok(())
}

/// The Python exception of an engine error.
pub fn to_py(e: Error) -> PyErr {
    let msg = e.to_string();
    let (err, path, field, id): (PyErr, Option<String>, Option<String>, Option<String>) = match &e {
        Error::Io { path, .. }
        | Error::ImageDecode { path, .. }
        | Error::EmptyImage { path, .. }
        | Error::UnknownClassId { path, .. }
        | Error::UnknownClassColor { path, .. }
        | Error::UnsupportedLabelFormat { path, .. } => (InputFileError::new_err(msg), Some(path.display().to_string()), None, None),
        Error::SizeMismatch { labels, .. } => (InputFileError::new_err(msg), Some(labels.display().to_string()), None, None),
        Error::NoLabels { image } => (InputFileError::new_err(msg), Some(image.display().to_string()), None, None),
        Error::InvalidConfig { source_name, .. } => (InvalidConfigError::new_err(msg), Some(source_name.clone()), None, None),
        Error::CorruptMap { path, .. } => (CorruptMapError::new_err(msg), Some(path.display().to_string()), None, None),
        Error::MapVersion { path, .. } => (MapVersionError::new_err(msg), Some(path.display().to_string()), None, None),
        Error::IncompatibleConfig { map, field, .. } => {
            (IncompatibleConfigError::new_err(msg), Some(map.display().to_string()), Some(field.clone()), None)
        }
        Error::DuplicateImageId { map, id } => (DuplicateImageIdError::new_err(msg), Some(map.display().to_string()), None, Some(id.clone())),
        Error::InvalidImage { id, .. } => (InvalidImageError::new_err(msg), None, None, Some(id.clone())),
        Error::Dataset { path, .. } => (DatasetError::new_err(msg), Some(path.display().to_string()), None, None),
        Error::InvalidInput { what, .. } => (InvalidInputError::new_err(msg), None, Some(what.clone()), None),
        Error::Model { path, .. } => (ModelError::new_err(msg), Some(path.display().to_string()), None, None),
        Error::Gpu(_) => (GpuError::new_err(msg), None, None, None),
        #[allow(unreachable_patterns)]
        _ => (SemlookError::new_err(msg), None, None, None),
    };
    Python::attach(|py| {
        let v = err.value(py);
        for (name, value) in [("path", path), ("field", field), ("id", id)] {
            let _ = v.setattr(name, value);
        }
    });
    err
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
