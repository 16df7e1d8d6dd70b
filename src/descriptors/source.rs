//! Where matching reads reference descriptors from, tile by tile: a descriptor set in memory, a
//! stored (memory-mapped) map, or any other store (a synthetic map far larger than memory in the
//! benchmarks). Tiles are the unit of streaming: no stage ever needs the whole map at once.

use super::DescriptorSet;
use crate::local::ForestRef;
use crate::values::Values;

/// Reusable storage for tiles that a source must assemble (copy or generate).
#[derive(Debug, Default)]
pub struct TileBuf {
    pub globals: Vec<f32>,
    pub stats: Vec<f32>,
}

/// Global descriptors and SSIM statistics of a map, readable by tiles.
pub trait GlobalSource: Sync {
    fn len(&self) -> usize;
    fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Descriptors and stats of references `start..end`, borrowed from the source or built in `buf`.
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]);
    /// Whether everything read so far was sound. A stored map checks each segment's checksum and
    /// values the first time it is read; a segment that fails is served as empty (zeros, no
    /// trees) and reported here, naming its file. Matching calls this after reading.
    fn check(&self) -> crate::Result<()> {
        Ok(())
    }
}

impl GlobalSource for DescriptorSet {
    fn len(&self) -> usize {
        self.ids.len()
    }
    fn tile<'a>(&'a self, start: usize, end: usize, _buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        (&self.globals[start * self.global_len..end * self.global_len], &self.global_stats[start * self.stats_len..end * self.stats_len])
    }
}

/// Everything matching reads about references: tiles of global descriptors, and forests and ids
/// by index. Implemented by a [`DescriptorSet`] and by a stored [`crate::map::Map`]. Indices run
/// over the references a source serves (a map leaves out removed images), `0..len()`.
pub trait RefSource: GlobalSource {
    fn id(&self, i: usize) -> &str;
    fn forest(&self, i: usize) -> ForestRef<'_>;
    fn neighbour_slots(&self) -> usize;
    fn appearance_dim(&self) -> usize;
    /// The whole-image appearance vector of reference i (`appearance_dim` values).
    fn image_appearance(&self, i: usize) -> Values<'_>;
    /// Values of each reference's HOG descriptor (0: the source holds none).
    fn hog_dim(&self) -> usize;
    fn image_hog(&self, i: usize) -> &[f32];
}

impl RefSource for DescriptorSet {
    fn id(&self, i: usize) -> &str {
        &self.ids[i]
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        DescriptorSet::forest(self, i)
    }
    fn neighbour_slots(&self) -> usize {
        self.neighbour_slots
    }
    fn appearance_dim(&self) -> usize {
        self.appearance_dim
    }
    fn image_appearance(&self, i: usize) -> Values<'_> {
        Values::F32(DescriptorSet::image_appearance(self, i))
    }
    fn hog_dim(&self) -> usize {
        self.hog_dim
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        DescriptorSet::image_hog(self, i)
    }
}
