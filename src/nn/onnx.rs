//! ONNX Runtime through `ort` (loaded dynamically: the shared library comes from the
//! `onnxruntime` PyPI wheel that `setup.sh` unpacks). One process-wide environment.

use crate::error::{Error, Result};
use ort::logging::LogLevel;
use ort::session::Session;
use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::sync::OnceLock;

/// Version of the library `setup.sh` installs (ort's `api-31` needs ONNX Runtime >= 1.31).
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

static ENV: OnceLock<std::result::Result<ort::environment::Environment, String>> = OnceLock::new();

/// The environment variable naming a folder of model files; it comes before the data folders.
pub const MODELS_ENV: &str = "SEMLOOK_MODELS";

/// With this environment variable set to 1, $SEMLOOK_MODELS is the only folder searched: what a
/// machine with only that folder sees (CI's newcomer step runs so, where the repository's
/// `.semlook` holds models a fresh machine cannot make).
pub const MODELS_ONLY_ENV: &str = "SEMLOOK_MODELS_ONLY";

/// The folders searched for model files, in order: $SEMLOOK_MODELS, then the data folders:
/// `.semlook` in the working directory, `.semlook` beside the executable and up to three
/// folders above it (a repository's `target/release/semlook`), `share/semlook/models` beside
/// the executable's prefix (an installed `PREFIX/bin/semlook`), the user's data directory
/// ($XDG_DATA_HOME or ~/.local/share) and the system ones ($XDG_DATA_DIRS or /usr/local/share
/// and /usr/share), each with `semlook/models`; with $SEMLOOK_MODELS_ONLY=1, $SEMLOOK_MODELS
/// alone ([`MODELS_ONLY_ENV`]). Nothing is fixed at build time.
pub fn model_dirs() -> Vec<PathBuf> {
    let mut dirs = Vec::new();
    if let Some(d) = std::env::var_os(MODELS_ENV).filter(|d| !d.is_empty()) {
        dirs.push(PathBuf::from(d));
    }
    if std::env::var_os(MODELS_ONLY_ENV).is_some_and(|v| v == "1") {
        return dirs;
    }
    if let Ok(cwd) = std::env::current_dir() {
        dirs.push(cwd.join(".semlook"));
    }
    if let Ok(exe) = std::env::current_exe() {
        for dir in exe.ancestors().skip(1).take(4) {
            dirs.push(dir.join(".semlook"));
        }
        if let Some(prefix) = exe.parent().and_then(Path::parent) {
            dirs.push(prefix.join("share/semlook/models"));
        }
    }
    let var = |k: &str| std::env::var_os(k).filter(|v| !v.is_empty());
    let user = var("XDG_DATA_HOME").map(PathBuf::from).or_else(|| var("HOME").map(|h| PathBuf::from(h).join(".local/share")));
    dirs.extend(user.map(|d| d.join("semlook/models")));
    let system = var("XDG_DATA_DIRS").unwrap_or_else(|| "/usr/local/share:/usr/share".into());
    dirs.extend(std::env::split_paths(&system).filter(|d| d.is_absolute()).map(|d| d.join("semlook/models")));
    let mut seen = std::collections::HashSet::new();
    dirs.retain(|d| seen.insert(d.clone()));
    dirs
}

/// `name` in $SEMLOOK_MODELS, when that folder is set and holds it.
pub fn env_model(name: &str) -> Option<PathBuf> {
    std::env::var_os(MODELS_ENV).filter(|d| !d.is_empty()).map(|d| PathBuf::from(d).join(name)).filter(|p| p.is_file())
}

/// A model file: `configured` (an option or a config key) if given, else `name` in the first of
/// [`model_dirs`] that has it. The error lists every place it looked.
pub fn find_model(name: &str, configured: Option<&Path>, what: &str) -> Result<PathBuf> {
    if let Some(p) = configured {
        return if p.is_file() {
            Ok(p.to_path_buf())
        } else {
            Err(Error::Model { path: p.to_path_buf(), reason: format!("{what}: file not found") })
        };
    }
    let dirs = model_dirs();
    if let Some(found) = dirs.iter().map(|d| d.join(name)).find(|p| p.is_file()) {
        return Ok(found);
    }
    let looked: Vec<String> = dirs.iter().map(|d| d.join(name).display().to_string()).collect();
    Err(Error::Model { path: name.into(), reason: format!("{what} not found; no path was given (option or config key) and it is in none of: {} (run `bash setup.sh`, set {MODELS_ENV}, or give the path)", looked.join(", ")) })
}

/// The ONNX Runtime library: $ORT_DYLIB_PATH, else the file in $SEMLOOK_MODELS, else
/// `configured` (`models.onnxruntime`), else the data folders; failing those, the bare name (the
/// system's library search).
pub fn library_path(configured: Option<&Path>) -> PathBuf {
    std::env::var_os("ORT_DYLIB_PATH")
        .filter(|p| !p.is_empty())
        .map(PathBuf::from)
        .or_else(|| env_model(ORT_LIBRARY))
        .or_else(|| configured.map(Path::to_path_buf))
        .or_else(|| find_model(ORT_LIBRARY, None, "ONNX Runtime").ok())
        .unwrap_or_else(|| PathBuf::from(ORT_LIBRARY))
}

/// ONNX Runtime's own messages go to the `log` crate, never straight to stderr. Its errors come
/// back as errors of the call too, so they are logged as warnings; its warnings are debug detail.
fn route_log(level: LogLevel, _category: &str, _id: &str, _location: &str, message: &str) {
    match level {
        LogLevel::Fatal | LogLevel::Error => log::warn!("ONNX Runtime: {message}"),
        LogLevel::Warning => log::debug!("ONNX Runtime: {message}"),
        LogLevel::Info | LogLevel::Verbose => log::trace!("ONNX Runtime: {message}"),
    }
}

fn environment(library: Option<&Path>) -> Result<&'static ort::environment::Environment> {
    let env = ENV.get_or_init(|| {
        let path = library_path(library);
        if !path.exists() {
            let looked: Vec<String> = model_dirs().iter().map(|d| d.join(ORT_LIBRARY).display().to_string()).collect();
            return Err(format!("ONNX Runtime library {} not found (looked at $ORT_DYLIB_PATH, models.onnxruntime and {}): run `bash setup.sh` (it unpacks it from the onnxruntime wheel) or set ORT_DYLIB_PATH", path.display(), looked.join(", ")));
        }
        ort::init_from(&path).map_err(|e| format!("{}: {e}", path.display()))?.with_name("semlook").with_logger(Arc::new(route_log)).build().map_err(|e| e.to_string())
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
        .with_log_level(LogLevel::Warning)
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
        Ok(SessionPool {
            shared: std::sync::Mutex::new(session(model, library)?),
            model: model.into(),
            library: library.map(Path::to_path_buf),
            workers: Default::default(),
        })
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

/// Static dimensions of a session's output (negative where dynamic; empty for a missing output
/// or one that is not a tensor).
pub fn output_shape(session: &Session, index: usize) -> Vec<i64> {
    match session.outputs().get(index).map(|o| o.dtype()) {
        Some(ort::value::ValueType::Tensor { shape, .. }) => shape.iter().copied().collect(),
        _ => vec![],
    }
}
