//! The `Map` class itself (an open map behind an `Arc`); its methods are in `map`, so that the
//! modules that take a map (`encoder`, `shard`) import the type without the methods' imports.

use pyo3::prelude::*;
use semlook::map::Map;
use std::sync::Arc;

/// A map of places, opened from its directory. An open map never changes: `add`, `remove` and
/// `compact` commit a new generation and return the map reopened.
#[pyclass(frozen, module = "semlook._native", name = "Map")]
pub struct PyMap {
    pub inner: Arc<Map>,
}

pub fn wrap(m: Map) -> PyMap {
    PyMap { inner: Arc::new(m) }
}
