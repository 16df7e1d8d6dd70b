//! The messages the node reads and writes, as serde structs whose fields follow their `.msg`
//! definitions in order (CDR is positional): `sensor_msgs` Image, CompressedImage and CameraInfo in, the
//! node's own `semlook_msgs` PlaceMatch and LoopClosure out, and `geometry_msgs` PoseStamped (the
//! matched place's stored pose) out (`semlook_msgs/msg/*.msg`, a package a
//! ROS user builds with colcon, or rosidl alone: `scripts/build_msgs_py.sh`). Their wire format
//! is held to bytes rclpy wrote (`tests/golden/`, made by `scripts/golden.py`).

#[cfg(test)]
use crate::error::CdrError;
use serde::{Deserialize, Serialize};

/// `builtin_interfaces/msg/Time`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Time {
    pub sec: i32,
    pub nanosec: u32,
}

impl Time {
    /// Seconds since the epoch (of the sender's clock).
    pub fn seconds(self) -> f64 {
        self.sec as f64 + self.nanosec as f64 * 1e-9
    }
}

/// `std_msgs/msg/Header`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Header {
    pub stamp: Time,
    pub frame_id: String,
}

/// `sensor_msgs/msg/Image`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct Image {
    pub header: Header,
    pub height: u32,
    pub width: u32,
    pub encoding: String,
    pub is_bigendian: u8,
    pub step: u32,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/CompressedImage`.
#[derive(Debug, Clone, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct CompressedImage {
    pub header: Header,
    pub format: String,
    #[serde(with = "serde_bytes")]
    pub data: Vec<u8>,
}

/// `sensor_msgs/msg/RegionOfInterest`: the part of the calibrated image a camera publishes (all
/// zeros: the whole image).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct RegionOfInterest {
    pub x_offset: u32,
    pub y_offset: u32,
    pub height: u32,
    pub width: u32,
    pub do_rectify: bool,
}

/// `sensor_msgs/msg/CameraInfo`: a camera's calibration, published beside its images (the node
/// takes the pinhole intrinsics of `k`, with `binning_*` and `roi`; see `node::camera_of`).
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct CameraInfo {
    pub header: Header,
    /// The size of the images the camera was calibrated with.
    pub height: u32,
    pub width: u32,
    pub distortion_model: String,
    /// The distortion coefficients (their number depends on the model; plumb_bob has 5).
    pub d: Vec<f64>,
    /// The intrinsic matrix, row-major: fx 0 cx, 0 fy cy, 0 0 1.
    pub k: [f64; 9],
    /// The rectification rotation, row-major (stereo cameras).
    pub r: [f64; 9],
    /// The projection matrix of the rectified image, row-major 3x4.
    pub p: [f64; 12],
    /// Subsampling of the published images (0 and 1: none).
    pub binning_x: u32,
    pub binning_y: u32,
    pub roi: RegionOfInterest,
}

/// `geometry_msgs/msg/Point`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Point {
    pub x: f64,
    pub y: f64,
    pub z: f64,
}

/// `geometry_msgs/msg/Quaternion`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Quaternion {
    pub x: f64,
    pub y: f64,
    pub z: f64,
    pub w: f64,
}

impl Default for Quaternion {
    /// The identity, as the message's own default.
    fn default() -> Self {
        Quaternion { x: 0.0, y: 0.0, z: 0.0, w: 1.0 }
    }
}

/// `geometry_msgs/msg/Pose`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Pose {
    pub position: Point,
    pub orientation: Quaternion,
}

/// `geometry_msgs/msg/PoseStamped`.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PoseStamped {
    pub header: Header,
    pub pose: Pose,
}

/// `semlook_msgs/msg/PlaceMatch`: what the node answers for every frame.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct PlaceMatch {
    pub header: Header,
    pub frame: u64,
    pub place_id: String,
    pub place_index: u32,
    pub score: f32,
    pub sequence_matched: bool,
    pub sequence_id: String,
    pub sequence_score: f32,
    pub uniqueness: f32,
    pub accepted: bool,
    pub top_ids: Vec<String>,
    pub top_indices: Vec<u32>,
    pub top_scores: Vec<f32>,
    pub inliers: i32,
    pub map_generation: u64,
    pub latency_ms: f32,
    pub has_relative_pose: bool,
    pub relative_rotation: [f64; 4],
    pub relative_translation: [f64; 3],
    pub relative_rotation_deg: f64,
    pub pose_inliers: i32,
}

/// `semlook_msgs/msg/LoopClosure`: loop-closure mode, a frame matched a place passed before.
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
pub struct LoopClosure {
    pub header: Header,
    pub query_id: String,
    pub place_id: String,
    pub place_index: u32,
    pub score: f32,
    pub uniqueness: f32,
    pub inliers: i32,
    pub has_relative_pose: bool,
    pub relative_rotation: [f64; 4],
    pub relative_translation: [f64; 3],
    pub relative_rotation_deg: f64,
    pub pose_inliers: i32,
}

/// The CDR bytes of a message as a DDS sample carries them: the encapsulation header (CDR, little
/// endian) then the body (ros2-client writes them; the tests hold them to rclpy's).
#[cfg(test)]
pub fn to_cdr<T: Serialize>(m: &T) -> Result<Vec<u8>, CdrError> {
    let body = cdr_encoding::to_vec::<T, byteorder::LittleEndian>(m)?;
    Ok([&[0u8, 1, 0, 0][..], &body].concat())
}

/// A message from the bytes [`to_cdr`] writes (little-endian CDR only).
#[cfg(test)]
pub fn from_cdr<T: for<'de> Deserialize<'de>>(bytes: &[u8]) -> Result<T, CdrError> {
    match bytes.get(..4) {
        Some([0, 1, _, _]) => cdr_encoding::from_bytes::<T, byteorder::LittleEndian>(&bytes[4..]).map(|r| r.0).map_err(CdrError::from),
        _ => Err(CdrError::NotLittleEndianCdr),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The messages of `scripts/golden.py`, built here field for field.
    fn samples() -> (PlaceMatch, LoopClosure, Image, CompressedImage, PoseStamped, CameraInfo) {
        let header = Header { stamp: Time { sec: 1_700_000_123, nanosec: 456_789 }, frame_id: "cam0".into() };
        let m = PlaceMatch {
            header: header.clone(),
            frame: 7,
            place_id: "ref/012".into(),
            place_index: 12,
            score: 5.25,
            sequence_matched: true,
            sequence_id: "ref/012".into(),
            sequence_score: 1.5,
            uniqueness: 1.75,
            accepted: true,
            top_ids: vec!["ref/012".into(), "ref/013".into(), "ref/0".into()],
            top_indices: vec![12, 13, 0],
            top_scores: vec![5.25, 4.5, -0.125],
            inliers: 33,
            map_generation: 3,
            latency_ms: 87.5,
            has_relative_pose: true,
            relative_rotation: [0.0, 0.125, 0.0, 0.9921567416492215],
            relative_translation: [0.6, 0.0, 0.8],
            relative_rotation_deg: 14.36,
            pose_inliers: 57,
        };
        let c = LoopClosure {
            header: header.clone(),
            query_id: "1700000123.000456789".into(),
            place_id: "0".into(),
            place_index: 0,
            score: 2.5,
            uniqueness: 1000.0,
            inliers: -1,
            has_relative_pose: false,
            relative_rotation: [0.0, 0.0, 0.0, 1.0],
            relative_translation: [0.0, 0.0, 0.0],
            relative_rotation_deg: 0.0,
            pose_inliers: -1,
        };
        let img = Image { header: header.clone(), height: 2, width: 3, encoding: "rgb8".into(), is_bigendian: 0, step: 9, data: (0u8..18).collect() };
        let jpg = CompressedImage { header: header.clone(), format: "jpeg".into(), data: vec![0xFF, 0xD8, 0xFF, 0xD9] };
        let pose = PoseStamped {
            header: Header { frame_id: "map".into(), ..header },
            pose: Pose { position: Point { x: 12.5, y: -3.25, z: 0.75 }, orientation: Quaternion { x: 0.5, y: -0.5, z: 0.5, w: 0.5 } },
        };
        let info = CameraInfo {
            header: header.clone(),
            height: 540,
            width: 960,
            distortion_model: "plumb_bob".into(),
            d: vec![-0.25, 0.125, 0.001, -0.0005, 0.0],
            k: [700.0, 0.0, 479.5, 0.0, 701.5, 269.5, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [690.25, 0.0, 480.0, -0.5, 0.0, 692.75, 270.0, 0.0, 0.0, 0.0, 1.0, 0.0],
            binning_x: 2,
            binning_y: 3,
            roi: RegionOfInterest { x_offset: 8, y_offset: 4, height: 500, width: 900, do_rectify: true },
        };
        (m, c, img, jpg, pose, info)
    }

    fn golden(name: &str) -> Vec<u8> {
        let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/golden").join(name);
        let hex = std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
        let hex: String = hex.split_whitespace().collect();
        (0..hex.len()).step_by(2).map(|i| u8::from_str_radix(&hex[i..i + 2], 16).unwrap()).collect()
    }

    /// Our bytes equal rclpy's but where ours are alignment padding (zeros here; Fast DDS leaves
    /// whatever its buffer held there, different on every run: 20 bytes of PlaceMatch's padding
    /// after its bools and strings held garbage in the run that wrote the golden files): the bytes
    /// differ only where ours are zero, and the caller checks that rclpy's read back to exactly
    /// the message, so no differing byte belongs to a field.
    fn same_but_padding(ours: &[u8], theirs: &[u8], what: &str) {
        assert_eq!(ours.len(), theirs.len(), "{what}: length");
        let differ: Vec<usize> = (0..ours.len()).filter(|&i| ours[i] != theirs[i]).collect();
        assert!(differ.iter().all(|&i| ours[i] == 0), "{what}: bytes {differ:?} differ");
    }

    /// Our encoding of each message is what rclpy (Fast DDS's CDR) writes for it, and rclpy's
    /// bytes read back to the same message.
    #[test]
    fn messages_match_the_bytes_rclpy_writes() {
        let (m, c, img, jpg, pose, info) = samples();
        same_but_padding(&to_cdr(&m).unwrap(), &golden("PlaceMatch.hex"), "PlaceMatch");
        same_but_padding(&to_cdr(&c).unwrap(), &golden("LoopClosure.hex"), "LoopClosure");
        same_but_padding(&to_cdr(&img).unwrap(), &golden("Image.hex"), "Image");
        same_but_padding(&to_cdr(&jpg).unwrap(), &golden("CompressedImage.hex"), "CompressedImage");
        same_but_padding(&to_cdr(&pose).unwrap(), &golden("PoseStamped.hex"), "PoseStamped");
        same_but_padding(&to_cdr(&info).unwrap(), &golden("CameraInfo.hex"), "CameraInfo");
        assert_eq!(from_cdr::<PlaceMatch>(&golden("PlaceMatch.hex")).unwrap(), m);
        assert_eq!(from_cdr::<LoopClosure>(&golden("LoopClosure.hex")).unwrap(), c);
        assert_eq!(from_cdr::<Image>(&golden("Image.hex")).unwrap(), img);
        assert_eq!(from_cdr::<CompressedImage>(&golden("CompressedImage.hex")).unwrap(), jpg);
        assert_eq!(from_cdr::<PoseStamped>(&golden("PoseStamped.hex")).unwrap(), pose);
        assert_eq!(from_cdr::<CameraInfo>(&golden("CameraInfo.hex")).unwrap(), info);
        assert!(from_cdr::<Image>(&[0, 0, 0, 0, 1]).is_err(), "big-endian or garbage is refused");
    }
}
