//! The bottom layer that encoding, the map store, matching and appearance share: the columnar
//! [`DescriptorSet`] and one encoded image ([`EncodedImage`]) with its [`PlacePose`], the [`source`] traits matching
//! reads references through, and the value checks of a stored image ([`validate`]). It imports
//! none of those stages, so none of them imports another in a circle.

mod embedding;
pub mod keypoints;
pub mod null;
mod pose;
mod set;
pub mod source;
pub mod validate;

pub use embedding::EmbeddingRecord;
pub use pose::{PlacePose, PoseRowError};
pub use set::{DescriptorSet, EncodedImage};
