//! Shared helpers: read-only numpy views that keep their owner alive, JSON values as Python
//! objects, thread pools per `threads=` count, and names of settings.

use crate::errors::invalid;
use numpy::ndarray::{ArrayViewD, IxDyn};
use numpy::{Element, PyArrayDyn};
use pyo3::prelude::*;
use pyo3::types::IntoPyDict;
use rayon::ThreadPool;
use semlook::matching::Setting;
use std::collections::HashMap;
use std::sync::{Arc, Mutex, OnceLock};

/// A read-only numpy array over `data` (borrowed, not copied) whose `base` is `owner`, so the
/// memory lives as long as the array. `data` must belong to `owner` and never change or move
/// while `owner` lives: descriptor sets are immutable once wrapped, and map segments are
/// read-only mappings of files the store never rewrites.
pub fn view<'py, T: Element>(owner: Bound<'py, PyAny>, data: &[T], shape: &[usize]) -> PyResult<Bound<'py, PyArrayDyn<T>>> {
    let v = ArrayViewD::from_shape(IxDyn(shape), data).map_err(|e| invalid("array view", e))?;
    // SAFETY: see above; the array is made read-only below, so Python cannot write through it
    let arr = unsafe { PyArrayDyn::borrow_from_array(&v, owner) };
    arr.call_method("setflags", (), Some(&[("write", false)].into_py_dict(arr.py())?))?;
    Ok(arr)
}

/// A rayon pool of `threads` threads (kept for the process), or `None` for the global pool.
pub fn pool(threads: Option<usize>) -> PyResult<Option<Arc<ThreadPool>>> {
    static POOLS: OnceLock<Mutex<HashMap<usize, Arc<ThreadPool>>>> = OnceLock::new();
    let Some(n) = threads else { return Ok(None) };
    if n == 0 || n > 1024 {
        return Err(invalid("threads", format!("{n} asked for, 1 to 1024 possible")));
    }
    let mut pools = POOLS.get_or_init(Default::default).lock().map_err(|_| invalid("threads", "pool registry poisoned by an earlier panic"))?;
    if let Some(p) = pools.get(&n) {
        return Ok(Some(p.clone()));
    }
    let p = Arc::new(rayon::ThreadPoolBuilder::new().num_threads(n).build().map_err(|e| invalid("threads", e))?);
    pools.insert(n, p.clone());
    Ok(Some(p))
}

/// Runs `f` without the GIL, on `pool` (or the global pool).
pub fn detached<T: Send>(py: Python<'_>, pool: Option<Arc<ThreadPool>>, f: impl FnOnce() -> T + Send) -> T {
    py.detach(move || match pool {
        Some(p) => p.install(f),
        None => f(),
    })
}

pub fn setting(name: &str) -> PyResult<Setting> {
    Setting::parse(name).map_err(|reason| invalid("setting", reason))
}

pub fn fusion(name: &str) -> PyResult<semlook::config::ScoreFusion> {
    use semlook::config::ScoreFusion;
    match name {
        "fine" => Ok(ScoreFusion::Fine),
        "fine_times_global" => Ok(ScoreFusion::FineTimesGlobal),
        _ => Err(invalid("score fusion", format!("{name:?} is not fine or fine_times_global"))),
    }
}

/// A JSON-serialisable value as a Python object (dicts, lists, numbers, strings).
pub fn to_py_object<'py>(py: Python<'py>, v: &impl serde::Serialize) -> PyResult<Bound<'py, PyAny>> {
    let text = serde_json::to_string(v).map_err(|e| invalid("result", e))?;
    py.import("json")?.call_method1("loads", (text,))
}
