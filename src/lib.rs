//! # semlook
//!
//! Visual place recognition with the SemLook descriptor (Chen et al., Sensors 2024, 24(7) 2203):
//! a coarse global descriptor (distance transform of semantic edges, compared by SSIM) selects
//! candidates from a map, and a fine local descriptor (a "forest" of per-object "trees" with
//! class, area, position, appearance and neighbours) re-ranks them.
//!
//! The modules follow the data through the pipeline:
//! [`input`] (images, label maps) -> [`objects`] (semantic regions) -> [`global`] and [`local`]
//! (descriptors; [`encode`] runs both) -> [`map`] (the stored map) -> [`matching`] (coarse top-K,
//! fine re-ranking) -> [`eval`] (VPR-Bench metrics). [`synth`] renders a procedural benchmark.
//!
//! ```no_run
//! use semlook::{config::Config, encode::Encoder, matching::{match_batch, Setting}};
//! # fn main() -> semlook::error::Result<()> {
//! // label maps only; with appearance (the default), see `Encoder::load` and `train_codebook`
//! let cfg = Config::without_appearance();
//! let encoder = Encoder::new(&cfg)?;
//! let table = encoder.class_table().clone();
//! let fmt = semlook::input::LabelFormat::Auto;
//! let mut scratch = Default::default();
//! let mut refs = encoder.descriptor_set();
//! for (i, path) in ["a.png", "b.png"].iter().enumerate() {
//!     let labels = semlook::input::load_label_map(path.as_ref(), &table, fmt)?;
//!     refs.push(&encoder.encode_labels(&format!("ref{i}"), &labels, &mut scratch)?.0);
//! }
//! let labels = semlook::input::load_label_map("query.png".as_ref(), &table, fmt)?;
//! let mut queries = encoder.descriptor_set();
//! queries.push(&encoder.encode_labels("q", &labels, &mut scratch)?.0);
//! let (matches, _) = match_batch(&refs, &queries, Setting::Semlook, &cfg);
//! println!("best reference: {:?}", matches[0].best());
//! # Ok(()) }
//! ```

pub mod appearance;
pub mod bench;
pub mod classes;
pub mod config;
pub mod encode;
pub mod engine;
pub mod error;
pub mod eval;
pub mod global;
pub mod gpu;
pub mod input;
pub mod local;
pub mod map;
pub mod matching;
pub mod objects;
pub mod onnx;
pub mod progress;
pub mod segmentation;
pub mod util;

pub use error::{Error, Result};
pub mod synth;
