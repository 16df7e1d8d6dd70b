//! hloc's names of map images (`semlook.hloc` writes its global-feats files with them).

use crate::errors::OrPy;
use pyo3::prelude::*;
use std::path::PathBuf;

/// hloc's names of the images `ids` (map ids: file stems or dataset ids), each found once in
/// `folders` (the folders the map was built from) and named by its path relative to `root`
/// (default: the deepest folder holding their parents, so names keep their folder: `ref/00.jpg`,
/// as `semlook query --pairs` names them), `/`-separated. An id with no file, with two,
/// or sharing one with another id, and a name with whitespace, raise `InvalidInputError`.
#[pyfunction]
#[pyo3(signature = (ids, folders, root=None))]
pub fn hloc_names(py: Python<'_>, ids: Vec<String>, folders: Vec<PathBuf>, root: Option<PathBuf>) -> PyResult<Vec<String>> {
    py.detach(|| {
        let root = match root {
            Some(r) => r,
            None => semlook::hloc::default_root(&folders)?,
        };
        let ids: Vec<&str> = ids.iter().map(String::as_str).collect();
        semlook::hloc::reference_names(&ids, &folders, &root)
    })
    .py_err()
}
