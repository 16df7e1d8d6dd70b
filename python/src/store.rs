//! The `Map` class itself (the open generation of a map behind an `Arc`); its methods are in
//! `map`, so that the modules that take a map (`encoder`, `shard`) import the type without the
//! methods' imports.

use pyo3::prelude::*;
use semlook::config::Config;
use semlook::encode::Encoder;
use semlook::map::Map;
use std::sync::{Arc, Mutex, RwLock};

/// A map of places, opened from its directory. `add`, `remove` and `compact` commit a new
/// generation and this object then serves it; numpy views and running calls keep the
/// generation they started with.
#[pyclass(frozen, module = "semlook._native", name = "Map")]
pub struct PyMap {
    current: RwLock<Arc<Map>>,
    /// The encoder of raw query frames, with the config it was made for.
    encoder: Mutex<Option<(Config, Encoder)>>,
}

/// Keeps one generation of a map open: the owner of numpy views of its segments.
#[pyclass(frozen, module = "semlook._native", name = "_MapGeneration")]
pub struct MapGeneration {
    pub _map: Arc<Map>,
}

pub fn wrap(m: Map) -> PyMap {
    PyMap { current: RwLock::new(Arc::new(m)), encoder: Mutex::new(None) }
}

impl PyMap {
    /// The generation served now.
    pub fn map(&self) -> Arc<Map> {
        self.current.read().unwrap_or_else(|p| p.into_inner()).clone()
    }
    /// Serves `m` from now on, unless a later generation is already served (two edits racing).
    pub fn replace(&self, m: Map) {
        let mut cur = self.current.write().unwrap_or_else(|p| p.into_inner());
        if m.manifest.generation >= cur.manifest.generation {
            // the files both generations hold are not checked again
            m.inherit_checks(&cur);
            *cur = Arc::new(m);
        }
    }
    /// The encoder of `map`'s queries under `cfg` (kept for the next call with the same config).
    pub fn encoder(&self, map: &Map, cfg: &Config) -> semlook::Result<Encoder> {
        let mut key = cfg.clone();
        key.matching = Default::default();
        let mut slot = self.encoder.lock().unwrap_or_else(|p| p.into_inner());
        if let Some((_, e)) = slot.as_ref().filter(|(k, _)| *k == key) {
            return Ok(e.clone());
        }
        let e = Encoder::for_map(cfg, map)?;
        *slot = Some((key, e.clone()));
        Ok(e)
    }
}
