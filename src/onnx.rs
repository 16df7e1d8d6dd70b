//! ONNX Runtime through `ort` (loaded dynamically: the shared library comes from the
//! `onnxruntime` PyPI wheel that `setup.sh` unpacks). One process-wide environment.

use crate::error::{Error, Result};
use ort::session::Session;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// Version of the library `setup.sh` installs (ort's `api-31` needs ONNX Runtime >= 1.31).
pub const ORT_LIBRARY: &str = "libonnxruntime.so.1.31.1";

static ENV: OnceLock<std::result::Result<ort::environment::Environment, String>> = OnceLock::new();

/// The folder `setup.sh` fills with models and libraries, or $SEMLOOK_MODELS.
pub fn models_dir() -> PathBuf {
    match std::env::var_os("SEMLOOK_MODELS") {
        Some(d) => PathBuf::from(d),
        None => Path::new(env!("CARGO_MANIFEST_DIR")).join(".semlook"),
    }
}

/// The ONNX Runtime library: `configured`, else $ORT_DYLIB_PATH, else the setup folder.
pub fn library_path(configured: Option<&Path>) -> PathBuf {
    configured
        .map(Path::to_path_buf)
        .or_else(|| std::env::var_os("ORT_DYLIB_PATH").map(PathBuf::from))
        .unwrap_or_else(|| models_dir().join(ORT_LIBRARY))
}

fn environment(library: Option<&Path>) -> Result<&'static ort::environment::Environment> {
    let env = ENV.get_or_init(|| {
        let path = library_path(library);
        if !path.exists() {
            return Err(format!("ONNX Runtime library {} not found: run `bash setup.sh` (it unpacks it from the onnxruntime wheel) or set ORT_DYLIB_PATH", path.display()));
        }
        ort::init_from(&path).map_err(|e| format!("{}: {e}", path.display()))?.with_name("semlook").build().map_err(|e| e.to_string())
    });
    env.as_ref().map_err(|e| Error::Model { path: library_path(library), reason: e.clone() })
}

/// Opens an ONNX model with intra-op threads for the whole machine.
pub fn session(model: &Path, library: Option<&Path>) -> Result<Session> {
    let env = environment(library)?;
    let fail = |reason: String| Error::Model { path: model.to_path_buf(), reason };
    if !model.exists() {
        return Err(fail("file not found".into()));
    }
    let threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    Session::builder(env)
        .map_err(|e| fail(e.to_string()))?
        .with_intra_threads(threads)
        .map_err(|e| fail(e.to_string()))?
        .commit_from_file(model)
        .map_err(|e| fail(e.to_string()))
}

/// Static dimensions of a session's output (negative where dynamic).
pub fn output_shape(session: &Session, index: usize) -> Vec<i64> {
    match session.outputs()[index].dtype() {
        ort::value::ValueType::Tensor { shape, .. } => shape.iter().copied().collect(),
        _ => vec![],
    }
}
