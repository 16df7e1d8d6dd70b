//! `Engine`: where matching and encoding run, the CPU path or the WGSL kernels on a GPU through
//! wgpu (the CLI's `--backend`). An engine keeps its device, pipelines and scratch buffers, and
//! the last map it matched stays resident on the device, so later batches against that map
//! upload only their queries: keep one engine per process and pass it to every call.

use crate::errors::{invalid, OrPy};
use pyo3::prelude::*;
use pyo3::sync::PyOnceLock;
use rayon::ThreadPool;
use semlook::engine::{Backend, Engine};
use semlook::gpu::GpuOptions;
use std::sync::{Arc, Mutex};

/// Where heavy work runs: `backend` "cpu", "gpu" (any adapter, software ones such as lavapipe
/// included; raises `GpuError` if there is none) or "auto" (a hardware GPU when there is one,
/// else the CPU; `fallback_reason` says why); None: `DEFAULT_BACKEND`, the command line's default
/// ("auto"). `adapter` picks the n-th GPU in order of preference
/// (discrete first) on a machine with several. Calls through one engine run one at a time.
#[pyclass(frozen, module = "semlook._native", name = "Engine")]
pub struct PyEngine {
    inner: Arc<Mutex<Engine>>,
    fallback: Option<String>,
}

#[pymethods]
impl PyEngine {
    #[new]
    #[pyo3(signature = (backend=None, adapter=None))]
    fn new(py: Python<'_>, backend: Option<&str>, adapter: Option<usize>) -> PyResult<Self> {
        let (engine, fallback) = engine_for(py, backend, adapter)?;
        Ok(PyEngine { inner: Arc::new(Mutex::new(engine)), fallback })
    }
    /// Whether work runs on a GPU (false after "auto" found none, or fell back after a failure).
    #[getter]
    fn is_gpu(&self, py: Python<'_>) -> bool {
        py.detach(|| self.inner.lock().is_ok_and(|e| e.is_gpu()))
    }
    /// "cpu (N threads of the global pool)" or "gpu: adapter (backend, device type)", now.
    #[getter]
    fn describe(&self, py: Python<'_>) -> String {
        py.detach(|| self.inner.lock().map_or_else(|_| "poisoned by a panic in an earlier call".into(), |e| e.describe()))
    }
    /// Why the CPU is used with "auto": no hardware GPU when made, or a GPU failure during
    /// work; else None.
    #[getter]
    fn fallback_reason(&self, py: Python<'_>) -> Option<String> {
        self.fallback.clone().or_else(|| py.detach(|| self.inner.lock().ok().and_then(|e| e.fell_back().map(str::to_string))))
    }
    /// Calls (query, shard candidates or fine scores, encode) in which the GPU did work so far
    /// (the `hog` and `appearance` baselines always run on the CPU).
    #[getter]
    fn gpu_calls(&self, py: Python<'_>) -> u64 {
        py.detach(|| self.inner.lock().map_or(0, |e| e.gpu_calls()))
    }
    /// Bytes of the last map kept on the device: (coarse descriptors and statistics, fine-stage
    /// forests); (0, 0) on the CPU or when the map was streamed.
    #[getter]
    fn device_map_bytes(&self, py: Python<'_>) -> (u64, u64) {
        py.detach(|| self.inner.lock().ok().and_then(|mut e| e.gpu_stages().map(|g| g.map_bytes())).unwrap_or((0, 0)))
    }
    fn __repr__(&self, py: Python<'_>) -> String {
        format!("Engine({})", self.describe(py))
    }
}

impl PyEngine {
    pub fn shared(&self) -> Arc<Mutex<Engine>> {
        self.inner.clone()
    }
}

/// An engine for `backend` ("cpu", "gpu", "auto"; None: `Backend::DEFAULT`) on GPU `adapter`,
/// and with "auto" the reason it runs on the CPU.
pub fn engine_for(py: Python<'_>, backend: Option<&str>, adapter: Option<usize>) -> PyResult<(Engine, Option<String>)> {
    let b = match backend {
        None => Backend::DEFAULT,
        Some(name) => <Backend as semlook::Choice>::parse_name(name).map_err(|why| invalid("backend", why))?,
    };
    let opts = GpuOptions { adapter, ..Default::default() };
    py.detach(|| Engine::new(b, &opts)).py_err()
}

/// The engine of calls given no `engine=`: `Engine(DEFAULT_BACKEND)`, made on first use, and
/// whether it was a GPU one then.
static DEFAULT_ENGINE: PyOnceLock<(Py<PyEngine>, bool)> = PyOnceLock::new();

fn default_engine_of(py: Python<'_>) -> PyResult<&(Py<PyEngine>, bool)> {
    DEFAULT_ENGINE.get_or_try_init(py, || {
        let e = PyEngine::new(py, None, None)?;
        let gpu = e.is_gpu(py);
        Ok((Py::new(py, e)?, gpu))
    })
}

/// The engine calls run on when given no `engine=`: `Engine(DEFAULT_BACKEND)`, made on first
/// use and kept for the process (on a GPU, the last map stays resident between calls).
#[pyfunction]
pub fn default_engine(py: Python<'_>) -> PyResult<Py<PyEngine>> {
    Ok(default_engine_of(py)?.0.clone_ref(py))
}

/// The engine a call runs on: `engine`, else the default one. `None` where that is the CPU:
/// each call then runs on a CPU engine of its own, so calls from several threads run at once.
pub fn resolve(py: Python<'_>, engine: Option<PyRef<'_, PyEngine>>) -> PyResult<Option<Arc<Mutex<Engine>>>> {
    match engine {
        Some(e) => Ok(Some(e.shared())),
        None => match default_engine_of(py)? {
            (e, true) => Ok(Some(e.get().shared())),
            (_, false) => Ok(None),
        },
    }
}

/// Runs `work` without the GIL, on `pool` (or the global pool), with `engine` (`None`: a CPU
/// engine of the call's own; see `resolve`). The engine is locked on the calling thread before entering the
/// pool, never on a pool worker: a worker blocked on the lock could be the one another call's
/// parallel work waits for (two Python threads sharing an engine and a `threads=` pool).
pub fn run<T: Send>(
    py: Python<'_>,
    pool: Option<Arc<ThreadPool>>,
    engine: Option<&Arc<Mutex<Engine>>>,
    work: impl FnOnce(&mut Engine) -> semlook::Result<T> + Send,
) -> PyResult<T> {
    py.detach(|| -> semlook::Result<T> {
        let mut own;
        let mut guard;
        let e: &mut Engine = match engine {
            Some(m) => {
                guard = m.lock().map_err(|_| semlook::Error::invalid("engine", "poisoned by a panic in an earlier call"))?;
                &mut guard
            }
            None => {
                own = Engine::cpu();
                &mut own
            }
        };
        match pool {
            Some(p) => p.install(|| work(e)),
            None => work(e),
        }
    })
    .py_err()
}
