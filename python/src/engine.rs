//! `Engine`: where matching and encoding run, the CPU path or the WGSL kernels on a GPU through
//! wgpu (the CLI's `--backend`). An engine keeps its device, pipelines and scratch buffers, and
//! the last map it matched stays resident on the device, so later batches against that map
//! upload only their queries: keep one engine per process and pass it to every call.

use crate::errors::{invalid, OrPy};
use pyo3::prelude::*;
use semlook::engine::{Backend, Engine};
use semlook::gpu::GpuOptions;
use std::sync::{Arc, Mutex};

/// Where heavy work runs: `backend` "cpu", "gpu" (any adapter, software ones such as lavapipe
/// included; raises `GpuError` if there is none) or "auto" (a hardware GPU when there is one,
/// else the CPU; `fallback_reason` says why). Calls through one engine run one at a time (the
/// engine is locked without the GIL held, so a thread waiting for it does not stall the others).
#[pyclass(frozen, module = "semlook._native", name = "Engine")]
pub struct PyEngine {
    inner: Arc<Mutex<Engine>>,
    described: String,
    fallback: Option<String>,
}

#[pymethods]
impl PyEngine {
    #[new]
    #[pyo3(signature = (backend="auto"))]
    pub fn new(py: Python<'_>, backend: &str) -> PyResult<Self> {
        let b = match backend {
            "cpu" => Backend::Cpu,
            "gpu" => Backend::Gpu,
            "auto" => Backend::Auto,
            other => return Err(invalid("backend", format!("{other:?} is not one of cpu, gpu, auto"))),
        };
        let (engine, fallback) = py.detach(|| Engine::new(b, &GpuOptions::default())).py_err()?;
        Ok(PyEngine { described: engine.describe(), inner: Arc::new(Mutex::new(engine)), fallback })
    }
    /// Whether work runs on a GPU (false after "auto" found none).
    #[getter]
    fn is_gpu(&self, py: Python<'_>) -> bool {
        py.detach(|| self.inner.lock().is_ok_and(|e| e.is_gpu()))
    }
    /// "cpu (N threads)" or "gpu: adapter (backend, device type)", as when it was made.
    #[getter]
    fn describe(&self) -> &str {
        &self.described
    }
    /// Calls (query, shard candidates or fine scores, encode) completed on the GPU so far.
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
    /// With "auto" and no hardware GPU: why the CPU is used; else None.
    #[getter]
    fn fallback_reason(&self) -> Option<&str> {
        self.fallback.as_deref()
    }
    fn __repr__(&self) -> String {
        format!("Engine({})", self.described)
    }
}

impl PyEngine {
    /// The engine, shared with the caller's closure (lock it without the GIL: see [`with`]).
    pub fn shared(&self) -> Arc<Mutex<Engine>> {
        self.inner.clone()
    }
}

/// Runs `work` with the engine locked; call inside `detached` so a thread waiting for the engine
/// does not hold the GIL. `None`: a CPU engine of the call's own.
pub fn with<T>(engine: Option<&Arc<Mutex<Engine>>>, work: impl FnOnce(&mut Engine) -> semlook::Result<T>) -> PyResult<T> {
    match engine {
        Some(e) => {
            let mut guard = e.lock().map_err(|_| invalid("engine", "poisoned by a panic in an earlier call"))?;
            work(&mut guard).py_err()
        }
        None => work(&mut Engine::cpu()).py_err(),
    }
}
