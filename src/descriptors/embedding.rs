//! The record of what made a set's or a map's whole-image embeddings (the network itself is
//! [`crate::networks::embedding`]'s): stored with the descriptors, compared when a query meets a map.

use serde::{Deserialize, Serialize};

/// What made a set's or a map's whole-image embeddings: the network file's name, its SHA-256, the width of
/// its output and the long side images were resized to.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct EmbeddingRecord {
    /// The file name, looked up in the model folders.
    pub network: String,
    /// SHA-256 of the file.
    pub sha256: String,
    /// Values per embedding.
    pub dim: usize,
    /// The long side, in pixels, of the image the network saw.
    pub long_side: u32,
}

impl EmbeddingRecord {
    /// Whether two records name the same network seeing the same size (the file's bytes, its
    /// width and the long side; the file's name may differ).
    pub fn same_network(&self, other: &EmbeddingRecord) -> bool {
        self.sha256 == other.sha256 && self.dim == other.dim && self.long_side == other.long_side
    }
}
