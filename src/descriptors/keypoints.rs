//! The verification keypoints an image stores (the `verify` stage matches them): its best detected keypoints (XFeat's detector,
//! SuperPoint-style decoding) with int8 descriptors, u16 positions and the semantic class under
//! each, so that a query is verified against a reference without the reference image.
//!
//! Per keypoint: `dim` int8 values (`DESCRIPTOR_SCALE` x the unit descriptor), two u16
//! coordinates (fractions of the image's long side at the working size, times `COORD_SCALE`) and
//! one class byte (`classes::VOID` where the label map has none): 64 + 4 + 1 = 69 bytes with XFeat.

/// int8 value = round(DESCRIPTOR_SCALE x component) of the unit-length descriptor. The largest
/// component of XFeat's descriptors over 40,960 keypoints of the Gardens Point frames was 0.58
/// (x 200 = 117 < 127, so nothing clips); rounding moves a vector's norm by 0.14 % (std), so the
/// integer dot product is the cosine x DESCRIPTOR_SCALE^2 within about 0.3 %.
pub const DESCRIPTOR_SCALE: f32 = 200.0;
/// u16 coordinate = round(COORD_SCALE x position / long side): 1/8 px at a long side of 8192.
pub const COORD_SCALE: f32 = 65535.0;

/// The verification keypoints of one image.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ImageKeypoints {
    /// `dim` values per keypoint.
    pub descriptors: Vec<i8>,
    /// (x, y) per keypoint.
    pub xy: Vec<u16>,
    /// Semantic class under each keypoint (`classes::VOID` where the label map has none).
    pub classes: Vec<u8>,
    /// Descriptor length (int8 values per keypoint).
    pub dim: usize,
}

impl ImageKeypoints {
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.classes.len()
    }
    /// Whether there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.classes.is_empty()
    }
    /// The keypoints borrowed.
    pub fn as_ref(&self) -> KeypointsRef<'_> {
        KeypointsRef { descriptors: &self.descriptors, xy: &self.xy, classes: &self.classes, dim: self.dim }
    }
}

/// Borrowed verification keypoints (of a set, a map segment or one image).
#[derive(Debug, Clone, Copy)]
pub struct KeypointsRef<'a> {
    /// `dim` values per keypoint.
    pub descriptors: &'a [i8],
    /// (x, y) per keypoint.
    pub xy: &'a [u16],
    /// Semantic class under each keypoint.
    pub classes: &'a [u8],
    /// Descriptor length (int8 values per keypoint).
    pub dim: usize,
}

impl<'a> KeypointsRef<'a> {
    /// No keypoints.
    pub const EMPTY: KeypointsRef<'static> = KeypointsRef { descriptors: &[], xy: &[], classes: &[], dim: 0 };
    /// Number of keypoints.
    pub fn len(&self) -> usize {
        self.classes.len()
    }
    /// Whether there are no keypoints.
    pub fn is_empty(&self) -> bool {
        self.classes.is_empty()
    }
    /// Position of keypoint `i` in fractions of the long side.
    #[inline]
    pub fn position(&self, i: usize) -> [f64; 2] {
        [self.xy[2 * i] as f64 / COORD_SCALE as f64, self.xy[2 * i + 1] as f64 / COORD_SCALE as f64]
    }
}

/// int8 of one unit-length descriptor component.
#[inline]
pub fn quantise(v: f32) -> i8 {
    (v * DESCRIPTOR_SCALE).round().clamp(-127.0, 127.0) as i8
}
