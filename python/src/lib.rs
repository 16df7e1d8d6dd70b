//! `semlook._native`: the Python bindings of semlook (pyo3, abi3). Heavy calls release the GIL
//! and run on a rayon pool (`threads=`); errors arrive as exceptions of the `SemlookError`
//! family carrying the engine's message. The Python package `semlook` (python/semlook/) wraps
//! this module and adds the Ray driver.

mod arrays;
mod descriptors;
mod encoder;
mod engine;
mod errors;
mod hloc;
mod map;
mod matches;
mod shard;
mod store;
mod stream;

use pyo3::prelude::*;

#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    errors::register(m)?;
    m.add_class::<encoder::PyConfig>()?;
    m.add_class::<encoder::PyEncoder>()?;
    m.add_class::<engine::PyEngine>()?;
    m.add_class::<descriptors::PyDescriptors>()?;
    m.add_class::<store::PyMap>()?;
    m.add_class::<matches::PyMatches>()?;
    m.add_class::<shard::PyShard>()?;
    m.add_class::<stream::PyLocalizer>()?;
    m.add_function(wrap_pyfunction!(map::evaluate, m)?)?;
    m.add_function(wrap_pyfunction!(engine::default_engine, m)?)?;
    m.add_function(wrap_pyfunction!(hloc::hloc_names, m)?)?;
    m.add_function(wrap_pyfunction!(shard::plan_shards, m)?)?;
    m.add_function(wrap_pyfunction!(shard::merge_candidates, m)?)?;
    m.add_function(wrap_pyfunction!(shard::rank, m)?)?;
    m.add_function(wrap_pyfunction!(shard::list_len, m)?)?;
    m.add_function(wrap_pyfunction!(shard::settings, m)?)?;
    m.add_function(wrap_pyfunction!(shard::reranks, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    // the defaults of the command line, from the engine (what `Engine()` and `evaluate` take)
    m.add("DEFAULT_BACKEND", semlook::engine::Backend::DEFAULT.name())?;
    m.add("EVAL_SETTINGS", pyo3::types::PyTuple::new(m.py(), semlook::eval::DEFAULT_SETTINGS.map(|s| s.name()))?)?;
    Ok(())
}
