//! The node's parameters, given as ROS 2 passes them (`--ros-args -p name:=value`, node name and
//! namespace by `-r __node:=NAME`, `-r __ns:=/NS`), and declared on the node so that parameter
//! clients see them.

use crate::error::ArgumentError;
use std::path::PathBuf;

pub const USAGE: &str = "usage: semlook_node --ros-args -p map:=DIR [-p name:=value ...] [-r __node:=NAME] [-r __ns:=/NS]

parameters (defaults in brackets):
  map              the map directory (in loop-closure mode: created from the stream where there is none)
  setting          the matching setting [verified]; one of hog, appearance, global, forest, local,
                   global-forest, semlook, fused, verified
  top_k            candidates of the coarse stage and ids in each match [the map's, 30]
  sequence         sequence matching over the last frames [true]
  sequence_length  frames a sequence spans [the config's]
  loop_closure     query the map, then add the frame to it; closures on ~/closure [false]
  backend          cpu, gpu or auto [auto]
  config           a semlook TOML config (its encoding sections must be the map's) [the map's]
  segmenter        the segmentation model (ONNX) that labels the frames of a map that holds labels;
                   none: no segmenter (such a map is then refused) [the installed default one]
  image_topic      sensor_msgs/Image frames [/camera/image_raw]
  compressed_topic sensor_msgs/CompressedImage frames [/camera/image_raw/compressed]
  queue_size       frames waiting to be localized; beyond it the oldest is dropped [2]
  map_refresh_s    seconds between checks for a newer map generation; 0: never [1.0]
  pose_frame_id    frame_id of the ~/pose messages: the frame the map's poses are in [map]
  camera_info      a camera file (TOML or JSON: fx, fy, cx, cy, width, height of the images they
                   are for): accepted matches and closures then carry the frame's pose relative
                   to the place's (relative_rotation, relative_translation) [none]
  camera_info_topic
                   sensor_msgs/CameraInfo to take the intrinsics from instead of a file (usually
                   /camera/camera_info; not with camera_info): fx, fy, cx, cy of its K, its size,
                   binning and region of interest; the first valid one sets the camera, a later one
                   that differs replaces it, frames before the first get no relative pose;
                   distortion (D) is ignored [none: off]";

/// What the node runs with.
#[derive(Debug, Clone, PartialEq)]
pub struct Params {
    pub map: PathBuf,
    pub setting: String,
    pub top_k: Option<usize>,
    pub sequence: bool,
    pub sequence_length: Option<usize>,
    pub loop_closure: bool,
    pub backend: String,
    pub config: Option<PathBuf>,
    /// `None`: the installed default segmenter; `Some(None)`: none; `Some(Some(path))`: that model.
    pub segmenter: Option<Option<PathBuf>>,
    pub image_topic: String,
    pub compressed_topic: String,
    pub queue_size: usize,
    pub map_refresh_s: f64,
    pub pose_frame_id: String,
    /// A camera file: the intrinsics of the relative poses.
    pub camera_info: Option<PathBuf>,
    /// A `sensor_msgs/CameraInfo` topic: the intrinsics of the relative poses, as they come.
    pub camera_info_topic: Option<String>,
    pub node_name: String,
    pub namespace: String,
}

impl Params {
    /// The parameters of a command line; `None` for `--help`. Every error names the argument.
    pub fn parse(args: &[String]) -> Result<Option<Params>, ArgumentError> {
        let mut p = Params {
            map: PathBuf::new(),
            setting: "verified".into(),
            top_k: None,
            sequence: true,
            sequence_length: None,
            loop_closure: false,
            backend: "auto".into(),
            config: None,
            segmenter: None,
            image_topic: "/camera/image_raw".into(),
            compressed_topic: "/camera/image_raw/compressed".into(),
            queue_size: 2,
            map_refresh_s: 1.0,
            pose_frame_id: "map".into(),
            camera_info: None,
            camera_info_topic: None,
            node_name: "semlook".into(),
            namespace: "/".into(),
        };
        let mut map = None;
        let mut it = args.iter();
        let mut in_ros_args = false;
        while let Some(a) = it.next() {
            match a.as_str() {
                "-h" | "--help" => return Ok(None),
                "--ros-args" => in_ros_args = true,
                "--" => in_ros_args = false,
                "-p" | "--param" if in_ros_args => {
                    let kv = it.next().ok_or_else(|| ArgumentError::MissingValue { flag: a.clone(), expected: "name:=value" })?;
                    let (k, v) = kv.split_once(":=").ok_or_else(|| ArgumentError::Malformed {
                        flag: a.clone(),
                        argument: kv.clone(),
                        expected: "name:=value",
                    })?;
                    let bad = |expected: &'static str| ArgumentError::BadValue { name: k.into(), value: v.into(), expected };
                    match k {
                        "map" => map = Some(PathBuf::from(v)),
                        "setting" => p.setting = v.into(),
                        "top_k" => p.top_k = Some(v.parse().ok().filter(|&k| k > 0).ok_or_else(|| bad("a positive integer"))?),
                        "sequence" => p.sequence = parse_bool(v).ok_or_else(|| bad("true or false"))?,
                        "sequence_length" => p.sequence_length = Some(v.parse().ok().filter(|&k| k > 0).ok_or_else(|| bad("a positive integer"))?),
                        "loop_closure" => p.loop_closure = parse_bool(v).ok_or_else(|| bad("true or false"))?,
                        "backend" => p.backend = v.into(),
                        "config" => p.config = Some(PathBuf::from(v)),
                        "segmenter" => p.segmenter = Some(Some(PathBuf::from(v)).filter(|_| v != "none")),
                        "image_topic" => p.image_topic = v.into(),
                        "compressed_topic" => p.compressed_topic = v.into(),
                        "pose_frame_id" => p.pose_frame_id = v.into(),
                        "camera_info" => p.camera_info = Some(PathBuf::from(v)),
                        "camera_info_topic" => p.camera_info_topic = Some(v.to_string()).filter(|t| !t.is_empty() && t != "none"),
                        "queue_size" => p.queue_size = v.parse().ok().filter(|&k| k > 0).ok_or_else(|| bad("a positive integer"))?,
                        "map_refresh_s" => {
                            p.map_refresh_s = v.parse().ok().filter(|s: &f64| s.is_finite() && *s >= 0.0).ok_or_else(|| bad("a number of seconds"))?
                        }
                        other => return Err(ArgumentError::UnknownParameter { name: other.into() }),
                    }
                }
                "-r" | "--remap" if in_ros_args => {
                    let kv = it.next().ok_or_else(|| ArgumentError::MissingValue { flag: a.clone(), expected: "from:=to" })?;
                    match kv.split_once(":=") {
                        Some(("__node" | "__name", v)) => p.node_name = v.into(),
                        Some(("__ns", v)) => p.namespace = if v.starts_with('/') { v.into() } else { format!("/{v}") },
                        Some((from, _)) => return Err(ArgumentError::UnsupportedRemapping { from: from.into() }),
                        None => return Err(ArgumentError::Malformed { flag: a.clone(), argument: kv.clone(), expected: "from:=to" }),
                    }
                }
                other if in_ros_args => return Err(ArgumentError::UnsupportedRosArgument { argument: other.into() }),
                other => return Err(ArgumentError::UnexpectedArgument { argument: other.into() }),
            }
        }
        if p.sequence_length.is_some() && !p.sequence {
            return Err(ArgumentError::Conflict { param: "sequence_length", reason: "is given but sequence is false" });
        }
        if p.loop_closure && !p.sequence {
            return Err(ArgumentError::Conflict { param: "loop_closure", reason: "finds its closures by sequence matching: keep sequence true" });
        }
        if p.camera_info.is_some() && p.camera_info_topic.is_some() {
            return Err(ArgumentError::Conflict {
                param: "camera_info_topic",
                reason: "is given with camera_info: the intrinsics come from a file or a topic, not both",
            });
        }
        p.map = map.ok_or(ArgumentError::MissingMap)?;
        Ok(Some(p))
    }
}

fn parse_bool(v: &str) -> Option<bool> {
    match v.to_ascii_lowercase().as_str() {
        "true" | "1" | "yes" | "on" => Some(true),
        "false" | "0" | "no" | "off" => Some(false),
        _ => None,
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn ros_arguments_parse_and_bad_ones_are_named() {
        let p = Params::parse(&args("--ros-args -p map:=/m -p top_k:=10 -p sequence:=false -r __node:=loc -r __ns:=robot")).unwrap().unwrap();
        assert_eq!((p.map.to_str(), p.top_k, p.sequence, p.node_name.as_str(), p.namespace.as_str()), (Some("/m"), Some(10), false, "loc", "/robot"));
        assert_eq!(Params::parse(&args("--help")).unwrap(), None);
        // the camera's intrinsics: off by default, from a topic, from a file, not both
        let p = Params::parse(&args("--ros-args -p map:=/m")).unwrap().unwrap();
        assert_eq!((p.camera_info, p.camera_info_topic), (None, None));
        let p = Params::parse(&args("--ros-args -p map:=/m -p camera_info_topic:=/camera/camera_info")).unwrap().unwrap();
        assert_eq!((p.camera_info, p.camera_info_topic.as_deref()), (None, Some("/camera/camera_info")));
        let p = Params::parse(&args("--ros-args -p map:=/m -p camera_info_topic:=none")).unwrap().unwrap();
        assert_eq!(p.camera_info_topic, None);
        let p = Params::parse(&args("--ros-args -p map:=/m -p camera_info:=/cam.toml")).unwrap().unwrap();
        assert_eq!((p.camera_info.as_deref(), p.camera_info_topic), (Some(std::path::Path::new("/cam.toml")), None));
        for (bad, says) in [
            ("--ros-args -p top_k:=0 -p map:=/m", "top_k"),
            ("--ros-args -p colour:=red -p map:=/m", "colour"),
            ("--ros-args -p sequence:=maybe -p map:=/m", "sequence"),
            ("--ros-args -p setting:=verified", "map parameter is required"),
            ("--map /m", "unexpected argument"),
            ("--ros-args -p map:=/m -p loop_closure:=true -p sequence:=false", "loop_closure"),
            ("--ros-args -p map:=/m -r /camera:=/cam", "remapping"),
        ] {
            let e = Params::parse(&args(bad)).unwrap_err();
            assert!(e.to_string().contains(says), "{bad}: {e}");
        }
    }

    /// Each refusal is its own variant, with the parameter and value at fault in its fields (a
    /// caller can act on them without reading the message), and writes the line it always wrote.
    #[test]
    fn refusals_are_typed_and_carry_what_is_at_fault() {
        let e = Params::parse(&args("--ros-args -p top_k:=0 -p map:=/m")).unwrap_err();
        assert_eq!(e, ArgumentError::BadValue { name: "top_k".into(), value: "0".into(), expected: "a positive integer" });
        assert_eq!(e.to_string(), r#"parameter top_k: "0" is not a positive integer"#);
        let e = Params::parse(&args("--ros-args -p setting:=verified")).unwrap_err();
        assert_eq!(e, ArgumentError::MissingMap);
        assert_eq!(e.to_string(), "the map parameter is required (-p map:=DIR)");
        for (bad, is, says) in [
            ("--ros-args -p", ArgumentError::MissingValue { flag: "-p".into(), expected: "name:=value" }, "-p needs name:=value"),
            (
                "--ros-args --param map=/m",
                ArgumentError::Malformed { flag: "--param".into(), argument: "map=/m".into(), expected: "name:=value" },
                "--param map=/m: expected name:=value",
            ),
            ("--ros-args -r", ArgumentError::MissingValue { flag: "-r".into(), expected: "from:=to" }, "-r needs from:=to"),
            (
                "--ros-args -r __node",
                ArgumentError::Malformed { flag: "-r".into(), argument: "__node".into(), expected: "from:=to" },
                "-r __node: expected from:=to",
            ),
            ("--ros-args -p colour:=red", ArgumentError::UnknownParameter { name: "colour".into() }, r#"unknown parameter "colour""#),
            (
                "--ros-args -p map_refresh_s:=-1",
                ArgumentError::BadValue { name: "map_refresh_s".into(), value: "-1".into(), expected: "a number of seconds" },
                r#"parameter map_refresh_s: "-1" is not a number of seconds"#,
            ),
            (
                "--ros-args -r /camera:=/cam",
                ArgumentError::UnsupportedRemapping { from: "/camera".into() },
                r#"remapping "/camera" is not supported: set the topic parameters instead"#,
            ),
            (
                "--ros-args --log-level",
                ArgumentError::UnsupportedRosArgument { argument: "--log-level".into() },
                r#"unsupported ROS argument "--log-level""#,
            ),
            (
                "--map /m",
                ArgumentError::UnexpectedArgument { argument: "--map".into() },
                r#"unexpected argument "--map" (parameters go after --ros-args as -p name:=value)"#,
            ),
            (
                "--ros-args -p map:=/m -p sequence:=false -p sequence_length:=4",
                ArgumentError::Conflict { param: "sequence_length", reason: "is given but sequence is false" },
                "sequence_length is given but sequence is false",
            ),
            (
                "--ros-args -p map:=/m -p loop_closure:=true -p sequence:=false",
                ArgumentError::Conflict { param: "loop_closure", reason: "finds its closures by sequence matching: keep sequence true" },
                "loop_closure finds its closures by sequence matching: keep sequence true",
            ),
            (
                "--ros-args -p map:=/m -p camera_info:=/cam.toml -p camera_info_topic:=/camera/camera_info",
                ArgumentError::Conflict {
                    param: "camera_info_topic",
                    reason: "is given with camera_info: the intrinsics come from a file or a topic, not both",
                },
                "camera_info_topic is given with camera_info: the intrinsics come from a file or a topic, not both",
            ),
        ] {
            let e = Params::parse(&args(bad)).unwrap_err();
            assert_eq!(e, is, "{bad}");
            assert_eq!(e.to_string(), says, "{bad}");
        }
    }
}
