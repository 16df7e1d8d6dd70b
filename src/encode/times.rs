//! Milliseconds per encoding stage, as the paper's Table 2 splits them.

/// Milliseconds spent per stage on one image.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize)]
pub struct StageTimes {
    /// Reading and decoding the input files, and bringing them to the working size.
    pub decode_ms: f64,
    /// The segmentation network (frames without a label map).
    pub segment_ms: f64,
    /// "Edge (coarse)": edges, distance transform, pooling, SSIM stats.
    pub global_ms: f64,
    /// "Forest": objects, trees and neighbours.
    pub forest_ms: f64,
    /// Appearance: keypoint network, decoding and per-object VLAD.
    pub appearance_ms: f64,
    /// Of `appearance_ms`, the network alone.
    pub network_ms: f64,
    /// The HOG baseline descriptor.
    pub hog_ms: f64,
    /// The whole-image embedding.
    pub embedding_ms: f64,
    /// Of `network_ms`, the milliseconds the keypoint network ran on the device (the GPU path with
    /// the native XFeat; 0 where it ran on the host): where the network ran.
    pub network_device_ms: f64,
    /// Of `embedding_ms`, the milliseconds the embedding network ran on the device (the GPU path
    /// with the network run natively from its checkpoint; 0 where it ran on the host).
    pub embedding_device_ms: f64,
    /// Of the stages above, the milliseconds that ran beside another (a frame encoded alone,
    /// outside a thread pool, runs the embedding beside the appearance stage): `encode_ms`
    /// subtracts them, so that it stays the wall clock of encoding.
    pub overlap_ms: f64,
}

impl StageTimes {
    /// Encoding as the paper counts it: descriptors only (no decoding, segmentation, baselines),
    /// with the whole-image embedding where there is one.
    pub fn encode_ms(&self) -> f64 {
        self.global_ms + self.forest_ms + self.appearance_ms + self.embedding_ms - self.overlap_ms
    }
    /// Everything but the segmentation network.
    pub fn without_segmentation_ms(&self) -> f64 {
        self.decode_ms + self.encode_ms()
    }
    /// Each field of `self` through `f` with the same field of `o`.
    fn zip(self, o: StageTimes, f: impl Fn(f64, f64) -> f64) -> StageTimes {
        StageTimes {
            decode_ms: f(self.decode_ms, o.decode_ms),
            segment_ms: f(self.segment_ms, o.segment_ms),
            global_ms: f(self.global_ms, o.global_ms),
            forest_ms: f(self.forest_ms, o.forest_ms),
            appearance_ms: f(self.appearance_ms, o.appearance_ms),
            network_ms: f(self.network_ms, o.network_ms),
            hog_ms: f(self.hog_ms, o.hog_ms),
            embedding_ms: f(self.embedding_ms, o.embedding_ms),
            network_device_ms: f(self.network_device_ms, o.network_device_ms),
            embedding_device_ms: f(self.embedding_device_ms, o.embedding_device_ms),
            overlap_ms: f(self.overlap_ms, o.overlap_ms),
        }
    }
    /// Every field multiplied by `by`.
    pub fn scaled(self, by: f64) -> StageTimes {
        self.zip(self, |a, _| a * by)
    }
    /// Per-field medians of `times`.
    pub fn median(times: &[StageTimes]) -> StageTimes {
        let pick = |f: fn(&StageTimes) -> f64| -> f64 {
            let mut v: Vec<f64> = times.iter().map(f).collect();
            v.sort_by(f64::total_cmp);
            match v.len() {
                0 => 0.0,
                n if n % 2 == 1 => v[n / 2],
                n => 0.5 * (v[n / 2 - 1] + v[n / 2]),
            }
        };
        StageTimes {
            decode_ms: pick(|t| t.decode_ms),
            segment_ms: pick(|t| t.segment_ms),
            global_ms: pick(|t| t.global_ms),
            forest_ms: pick(|t| t.forest_ms),
            appearance_ms: pick(|t| t.appearance_ms),
            network_ms: pick(|t| t.network_ms),
            hog_ms: pick(|t| t.hog_ms),
            embedding_ms: pick(|t| t.embedding_ms),
            network_device_ms: pick(|t| t.network_device_ms),
            embedding_device_ms: pick(|t| t.embedding_device_ms),
            overlap_ms: pick(|t| t.overlap_ms),
        }
    }
}

impl std::ops::AddAssign for StageTimes {
    fn add_assign(&mut self, o: StageTimes) {
        *self = self.zip(o, |a, b| a + b);
    }
}
