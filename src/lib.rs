//! # semlook
//!
//! Visual place recognition with the SemLook descriptor (Chen et al., Sensors 2024, 24(7) 2203):
//! a coarse global descriptor (distance transform of semantic edges, compared by SSIM) selects
//! candidates from a map, and a fine local descriptor (a "forest" of per-object "trees" with
//! class, area, position, appearance and neighbours) re-ranks them.
//!
//! The modules follow the data through the pipeline:
//! [`input`] (images, label maps; labels from a network, [`networks::segmenter`]) -> [`global`]
//! (whole-image descriptors: the semantic SSIM descriptor, VLAD, the embedding, HOG), [`objects`]
//! (semantic regions) and [`local`] (their trees), [`appearance`] (XFeat descriptors) ->
//! [`encode`] (one frame through all of them; [`batch`] for many) -> [`map`] (the stored map;
//! [`index`], its approximate index) -> [`matching`] (coarse top-K, fine re-ranking) and
//! [`verify`] (keypoint matches, RANSAC, relative pose) -> [`eval`] (VPR-Bench metrics) and
//! [`stream`] (frames one at a time, sequences, loop closure). The stages call the networks of
//! [`networks`] (XFeat, LighterGlue, the embedding, the segmenter: one module each, forward pass,
//! weights and device executor together); under them [`nn`] (the runtime: convolutions, ONNX
//! Runtime, weight readers); under the stages, [`descriptors`]
//! (descriptor sets, the source traits matching reads, value checks), the layer encoding, the map
//! store, matching and appearance share. [`engine`] runs encoding and matching on the CPU or
//! [`gpu`]. Beside the engine, in crates of their own: `semlook-kernels` (the WGSL kernels, their CPU
//! twins and the host ABI) under it, and `semlook-cli` (the command line and the developer tools:
//! synthetic benchmark, pictures, benchmarks, sweeps) over it.
//!
//! The example of `docs/library.md` (compiled here):
//!
//! ```no_run
//! # fn main() -> semlook::Result<()> {
//! use semlook::{config::Config, encode::Encoder, engine::{Backend, Engine}, input::FrameSource, map::Map, matching::Setting};
//!
//! let frame = |id: &str| FrameSource { id: id.into(), image: Some(format!("{id}.png").into()), labels: Some(format!("{id}_labels.png").into()) };
//! let cfg = Config::default(); // XFeat appearance: needs the weights setup.sh fetches
//! let (mut engine, _) = Engine::new(Backend::Auto, &Default::default())?;
//! let refs = vec![frame("ref0"), frame("ref1")];
//! let mut encoder = Encoder::new(&cfg)?;
//! encoder.train_codebook(&refs, &|| {})?; // VLAD codebook from the references
//! let mut set = encoder.descriptor_set();
//! for r in engine.encode_all(&encoder, &refs, Default::default(), &|| {})? {
//!     set.push(&r?.0);
//! }
//! let map = Map::create("my-map".as_ref(), &cfg.encoding(), &set, encoder.appearance_record())?;
//! // later, or elsewhere: Map::open, then an encoder that checks config, network and codebook
//! let encoder = Encoder::for_map(&cfg, &map)?;
//! let mut queries = encoder.descriptor_set();
//! for r in engine.encode_all(&encoder, &[frame("query")], Default::default(), &|| {})? {
//!     queries.push(&r?.0);
//! }
//! let (matches, times) = engine.match_batch(&map, &queries, Setting::Semlook, &cfg)?;
//! println!("{:?} (coarse {:.2} ms, fine {:.2} ms)", matches[0].best(), times.coarse_ms, times.fine_ms);
//! # Ok(()) }
//! ```

// every public item is documented; clippy -D warnings (the test command) turns this into an error
#![warn(missing_docs)]

pub mod appearance;
pub mod batch;
pub mod choice;
pub mod classes;
pub mod config;
pub mod dataset;
pub mod descriptors;
// the device runtime the GPU executors run on (wgpu: context, pipelines, buffers, timer); its
// public types are `gpu`'s
mod device;
pub mod encode;
pub mod engine;
pub mod error;
pub mod eval;
pub mod global;
pub mod gpu;
pub mod hloc;
pub mod index;
pub mod input;
pub mod local;
pub mod map;
pub mod matching;
pub mod models;
pub mod networks;
pub mod nn;
pub mod objects;
pub mod progress;
pub mod stream;
/// Internal, public for the binary and tests only: small helpers the command line and the tests share (atomic writes, hashing); not the API.
#[doc(hidden)]
pub mod util;
pub mod verify;

pub use choice::Choice;
pub use error::{Error, ErrorKind, Result};
/// The parameters of the SSIM and tree-similarity kernels, which `config` makes
/// ([`config::GlobalConfig::ssim_params`], [`config::SimilarityConfig::tree_params`]) and the
/// matching functions take: the kernels crate's.
pub use semlook_kernels::abi::{SsimParams, TreeSimParams};
/// The value views stages read (f32, f16, int8 blocks): the kernels crate's, where the twins read them.
pub use semlook_kernels::values;
