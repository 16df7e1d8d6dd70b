//! Streams (beyond the paper): a camera's frames localized one at a time against a resident
//! map, with sequence matching over the last frames ([`sequence`]) and a loop-closure mode that
//! queries a growing map and then adds the frame to it.
//!
//! A [`Localizer`] holds one generation of a map open (memory-mapped; on the GPU the engine keeps
//! it resident), the encoder for it, the ring of the last frames' sparse score rows and, in
//! loop-closure mode, a writer. Each [`Localizer::push`] encodes the frame, ranks the map with the
//! setting, widens the candidates by their neighbours along the route and scores those too,
//! updates the ring, and returns the single-frame ranking, the sequence match and the latency of
//! every stage. What it keeps is bounded: the ring (`sequence.length` rows of at most K x
//! (2 `widen` + 1) entries), and in loop-closure mode at most `stream.commit_frames` encoded
//! frames before they are committed, and the stream's recent timestamps. Nothing grows with the
//! number of queries x the map.

pub mod input;
mod latency;
mod localizer;
mod replay;
pub mod sequence;
mod types;

pub use latency::*;
pub use localizer::*;
pub use replay::*;
pub use types::*;
