//! ONNX Runtime through `ort` (loaded dynamically: the shared library comes from the
//! `onnxruntime` PyPI wheel that `setup.sh` unpacks). One process-wide environment.

use crate::error::{Error, Result};
use ort::session::Session;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Version of the library `setup.sh` installs (ort's `api-31` needs ONNX Runtime >= 1.31).
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

static ENV: OnceLock<std::result::Result<ort::environment::Environment, String>> = OnceLock::new();

/// The folders searched for model files, in order: $SEMLOOK_MODELS, `.semlook` in the working
/// directory, `.semlook` beside the executable and up to three folders above it (the repository of
/// a `target/release/semlook`), then the user's data directory ($XDG_DATA_HOME or
/// ~/.local/share, `semlook/models`).
pub fn model_dirs() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    if let Some(d) = std::env::var_os("SEMLOOK_MODELS") {
        dirs.push(PathBuf::from(d));
    }
    if let Ok(cwd) = std::env::current_dir() {
        dirs.push(cwd.join(".semlook"));
    }
    if let Ok(exe) = std::env::current_exe() {
        for dir in exe.ancestors().skip(1).take(4) {
            dirs.push(dir.join(".semlook"));
        }
    }
    let data = std::env::var_os("XDG_DATA_HOME").map(PathBuf::from).or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/share")));
    if let Some(d) = data {
        dirs.push(d.join("semlook/models"));
    }
    dirs.dedup();
    dirs
}

/// A model file: `configured` (an option or config key) if given, else `name` in the first of
/// [`model_dirs`] that has it. The error lists every place it looked.
pub fn find_model(name: &str, configured: Option<&Path>, what: &str) -> Result<PathBuf> {
    if let Some(p) = configured {
        return if p.exists() { Ok(p.to_path_buf()) } else { Err(Error::Model { path: p.to_path_buf(), reason: format!("{what}: file not found") }) };
    }
    let dirs = model_dirs();
    if let Some(found) = dirs.iter().map(|d| d.join(name)).find(|p| p.exists()) {
        return Ok(found);
    }
    let looked: Vec<String> = dirs.iter().map(|d| d.join(name).display().to_string()).collect();
    Err(Error::Model { path: name.into(), reason: format!("{what} not found; looked in: {} (run `bash setup.sh`, set SEMLOOK_MODELS, or give the path)", looked.join(", ")) })
}

/// The ONNX Runtime library: `configured`, else $ORT_DYLIB_PATH, else the model folders.
pub fn library_path(configured: Option<&Path>) -> PathBuf {
    configured
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("ORT_DYLIB_PATH").map(PathBuf::from))
        .or_else(|| find_model(ORT_LIBRARY, None, "ONNX Runtime").ok())
        .unwrap_or_else(|| PathBuf::from(ORT_LIBRARY))
}

fn environment(library: Option<&Path>) -> Result<&'static ort::environment::Environment> {
    let env = ENV.get_or_init(|| {
        let path = library_path(library);
        if !path.exists() {
            let looked: Vec<String> = model_dirs().iter().map(|d| d.join(ORT_LIBRARY).display().to_string()).collect();
            return Err(format!("ONNX Runtime library {} not found (looked in {}): run `bash setup.sh` (it unpacks it from the onnxruntime wheel) or set ORT_DYLIB_PATH", path.display(), looked.join(", ")));
        }
        ort::init_from(&path).map_err(|e| format!("{}: {e}", path.display()))?.with_name("semlook").build().map_err(|e| e.to_string())
    });
    env.as_ref().map_err(|e| Error::Model { path: library_path(library), reason: e.clone() })
}

/// Opens an ONNX model with intra-op threads for the whole machine.
pub fn session(model: &Path, library: Option<&Path>) -> Result<Session> {
    session_with_threads(model, library, std::thread::available_parallelism().map_or(1, |n| n.get()))
}

/// Opens an ONNX model with `threads` intra-op threads that do not spin when idle (so that
/// they leave the cores to rayon's workers between runs).
pub fn session_with_threads(model: &Path, library: Option<&Path>, threads: usize) -> Result<Session> {
    let env = environment(library)?;
    let fail = |reason: String| Error::Model { path: model.to_path_buf(), reason };
    if !model.exists() {
        return Err(fail("file not found".into()));
    }
    Session::builder(env)
        .map_err(|e| fail(e.to_string()))?
        .with_intra_threads(threads)
        .map_err(|e| fail(e.to_string()))?
        .with_inter_threads(1)
        .map_err(|e| fail(e.to_string()))?
        .with_intra_op_spinning(false)
        .map_err(|e| fail(e.to_string()))?
        .commit_from_file(model)
        .map_err(|e| fail(e.to_string()))
}

/// Sessions of one model that never oversubscribe the cores together with rayon: a call from
/// inside a rayon worker runs on that worker's own single-threaded session (created on first
/// use), so N workers run N frames on N threads; a call from outside the pool (one frame, a
/// test) runs on a session with a thread per core.
pub struct SessionPool {
    model: std::path::PathBuf,
    library: Option<std::path::PathBuf>,
    shared: std::sync::Mutex<Session>,
    workers: std::sync::OnceLock<Vec<std::sync::Mutex<Option<Session>>>>,
}

impl SessionPool {
    pub fn new(model: &Path, library: Option<&Path>) -> Result<SessionPool> {
        Ok(SessionPool { shared: std::sync::Mutex::new(session(model, library)?), model: model.into(), library: library.map(Path::to_path_buf), workers: Default::default() })
    }
    /// The session opened first (for reading the model's inputs and outputs).
    pub fn with_shared<R>(&self, f: impl FnOnce(&mut Session) -> R) -> R {
        let mut s = self.shared.lock().unwrap_or_else(|p| p.into_inner());
        f(&mut s)
    }
    /// Runs `f` on the session for the calling thread.
    pub fn run<R>(&self, f: impl FnOnce(&mut Session) -> Result<R>) -> Result<R> {
        match rayon::current_thread_index() {
            Some(i) if rayon::current_num_threads() > 1 => {
                let workers = self.workers.get_or_init(|| (0..rayon::current_num_threads()).map(|_| std::sync::Mutex::new(None)).collect());
                let Some(slot) = workers.get(i) else { return self.with_shared(f) };
                let mut guard = slot.lock().unwrap_or_else(|p| p.into_inner());
                if guard.is_none() {
                    *guard = Some(session_with_threads(&self.model, self.library.as_deref(), 1)?);
                }
                match guard.as_mut() {
                    Some(s) => f(s),
                    None => self.with_shared(f),
                }
            }
            _ => self.with_shared(f),
        }
    }
}

/// Static dimensions of a session's output (negative where dynamic).
pub fn output_shape(session: &Session, index: usize) -> Vec<i64> {
    match session.outputs()[index].dtype() {
        ort::value::ValueType::Tensor { shape, .. } => shape.iter().copied().collect(),
        _ => vec![],
    }
}
