//! The node's errors, typed: what a caller (or a person reading the log) can act on is in the
//! fields, and each message reads as the node has always written it.

use semlook::matching::UnknownSetting;

/// Why the node did not start or stopped: its command line, the engine, the ROS 2 stack, or
/// its own threads. `Display` writes the line the node logs.
#[derive(Debug, thiserror::Error)]
pub enum NodeError {
    /// The command line is not one the node takes (see [`ArgumentError`]).
    #[error(transparent)]
    Argument(#[from] ArgumentError),
    /// The `setting` parameter names no matching setting.
    #[error("parameter setting: {0}")]
    Setting(#[from] UnknownSetting),
    /// The `backend` parameter names no backend (cpu, gpu, auto).
    #[error("backend {name:?} is unknown (cpu, gpu, auto)")]
    UnknownBackend {
        /// The name given.
        name: String,
    },
    /// What the engine reports: the config (its loading or checking), the map, the backend,
    /// the localizer.
    #[error(transparent)]
    Engine(#[from] semlook::Error),
    /// What the engine reports about what one parameter names (the camera file of
    /// `camera_info`, for one).
    #[error("parameter {param}: {source}")]
    EngineParam {
        /// The parameter whose value the engine refused.
        param: &'static str,
        /// What the engine said.
        #[source]
        source: semlook::Error,
    },
    /// `ROS_DOMAIN_ID` is set to something that is not a DDS domain number.
    #[error("ROS_DOMAIN_ID={value:?} is not a domain number")]
    DomainId {
        /// The variable's value.
        value: String,
        /// Why it does not parse.
        #[source]
        source: std::num::ParseIntError,
    },
    /// The ROS 2 stack refused to make something: the DDS participant, the context, the node
    /// (its name), a topic, a subscription, a publisher, the spinner.
    #[error("{what}: {reason}")]
    Ros {
        /// What could not be made (`DDS participant (domain 0)`, `topic "/camera/image_raw"`,
        /// `publisher`, ...).
        what: String,
        /// What the stack said (its error, as `Debug` writes it: its types have no `Display`).
        reason: String,
    },
    /// A received frame that cannot be localized (see [`FrameError`]).
    #[error(transparent)]
    Frame(#[from] FrameError),
    /// The SIGINT/SIGTERM handler could not be installed.
    #[error("signal handler: {0}")]
    SignalHandler(#[from] ctrlc::Error),
    /// The localizer thread could not be started.
    #[error("localizer thread: {0}")]
    LocalizerThread(#[source] std::io::Error),
    /// The localizer thread panicked (its panic message is on standard error).
    #[error("the localizer thread panicked")]
    LocalizerPanicked,
}

impl NodeError {
    /// What the person starting the node can do about this error, in the node's terms (its
    /// parameters), where the engine says what would help.
    pub fn hint(&self) -> Option<&'static str> {
        let engine = match self {
            NodeError::Engine(e) | NodeError::EngineParam { source: e, .. } => e,
            _ => return None,
        };
        match engine.remedy()? {
            // camera frames bring no label maps: a segmenter is the node's one way to label them
            semlook::error::Remedy::GiveLabels => {
                Some("start the node with a segmenter (-p segmenter:=MODEL.onnx, an ONNX segmentation model), or serve a map built without labels")
            }
            _ => None,
        }
    }
}

/// A command line the node does not take. Every one names the argument, parameter or value at
/// fault.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ArgumentError {
    /// `-p` or `-r` (`flag`) is the last argument: its `name:=value` (`from:=to`) is missing.
    #[error("{flag} needs {expected}")]
    MissingValue {
        /// The flag as given (`-p`, `--param`, `-r`, `--remap`).
        flag: String,
        /// The form it takes: `name:=value` or `from:=to`.
        expected: &'static str,
    },
    /// The argument after `-p` or `-r` (`flag`) has no `:=`.
    #[error("{flag} {argument}: expected {expected}")]
    Malformed {
        /// The flag as given (`-p`, `--param`, `-r`, `--remap`).
        flag: String,
        /// The argument after it.
        argument: String,
        /// The form it takes: `name:=value` or `from:=to`.
        expected: &'static str,
    },
    /// The node has no parameter of that name.
    #[error("unknown parameter {name:?}")]
    UnknownParameter {
        /// The name given.
        name: String,
    },
    /// A parameter's value is not one it takes.
    #[error("parameter {name}: {value:?} is not {expected}")]
    BadValue {
        /// The parameter.
        name: String,
        /// The value given.
        value: String,
        /// What it takes (`a positive integer`, `true or false`, `a number of seconds`).
        expected: &'static str,
    },
    /// A remapping other than `__node`, `__name` or `__ns` (topics are parameters here).
    #[error("remapping {from:?} is not supported: set the topic parameters instead")]
    UnsupportedRemapping {
        /// What the remapping remaps.
        from: String,
    },
    /// An argument after `--ros-args` that is neither `-p` nor `-r`.
    #[error("unsupported ROS argument {argument:?}")]
    UnsupportedRosArgument {
        /// The argument.
        argument: String,
    },
    /// An argument outside `--ros-args` (other than `--help`).
    #[error("unexpected argument {argument:?} (parameters go after --ros-args as -p name:=value)")]
    UnexpectedArgument {
        /// The argument.
        argument: String,
    },
    /// Two parameters given together that the node cannot run with (`sequence_length` or
    /// `loop_closure` with `sequence` false, `camera_info_topic` with `camera_info`).
    #[error("{param} {reason}")]
    Conflict {
        /// The parameter refused because of another's value.
        param: &'static str,
        /// Why (it continues the parameter's name: `is given but sequence is false`).
        reason: &'static str,
    },
    /// No `map` parameter.
    #[error("the map parameter is required (-p map:=DIR)")]
    MissingMap,
}

/// Why a received frame cannot be localized (it is counted and dropped; the node goes on).
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum FrameError {
    /// A raw image in an encoding other than rgb8, bgr8 and mono8.
    #[error("encoding {encoding:?} is not supported (rgb8, bgr8, mono8)")]
    Encoding {
        /// The image's encoding.
        encoding: String,
    },
    /// A raw image with no pixels or more than `max`.
    #[error("{width}x{height} pixels (1 to {max})")]
    Size {
        /// Its width in pixels.
        width: u64,
        /// Its height in pixels.
        height: u64,
        /// The most pixels a frame may have.
        max: u64,
    },
    /// A raw image whose data is too short for its size, or whose step is shorter than a row.
    #[error("{len} bytes with step {step} for {width}x{height} {encoding} pixels")]
    Data {
        /// The bytes of data the message holds.
        len: usize,
        /// Its row step in bytes.
        step: u64,
        /// Its width in pixels.
        width: u64,
        /// Its height in pixels.
        height: u64,
        /// Its encoding.
        encoding: String,
    },
    /// The converted pixels do not fill the image (not reached after the checks above).
    #[error("pixel count")]
    PixelCount,
    /// A compressed image in a format other than jpeg and png.
    #[error("format {format:?} is not supported (jpeg, png)")]
    Format {
        /// The message's format string.
        format: String,
    },
}

/// Why a received `sensor_msgs/CameraInfo` gives no intrinsics for the relative poses (it is
/// logged and the node goes on with the camera it had, if any).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CameraInfoError {
    /// No calibrated image size (an uncalibrated camera publishes zeros).
    #[error("{width}x{height} pixels: the calibrated image size must not be 0 (an uncalibrated camera?)")]
    Size {
        /// The message's `width`.
        width: u32,
        /// The message's `height`.
        height: u32,
    },
    /// The region of interest reaches outside the calibrated image.
    #[error("region of interest {width}x{height} at ({x_offset}, {y_offset}) is not inside the calibrated {image_width}x{image_height} image")]
    Region {
        /// Its left edge, pixels.
        x_offset: u32,
        /// Its top edge, pixels.
        y_offset: u32,
        /// Its width, pixels.
        width: u32,
        /// Its height, pixels.
        height: u32,
        /// The calibrated image's width.
        image_width: u32,
        /// The calibrated image's height.
        image_height: u32,
    },
    /// Intrinsics the relative pose cannot use ([`semlook::verify::pose::Camera::check`]: focal
    /// lengths positive and finite, the principal point inside the image).
    #[error("fx {fx}, fy {fy}, cx {cx}, cy {cy} for {width}x{height} pixels: {reason}", fx = camera.fx, fy = camera.fy, cx = camera.cx, cy = camera.cy, width = camera.width, height = camera.height)]
    Intrinsics {
        /// The intrinsics of the images the camera publishes (binning and region applied).
        camera: semlook::verify::pose::Camera,
        /// What `Camera::check` says.
        reason: String,
    },
}

/// A message's CDR bytes could not be written or read (the golden-byte tests' helpers).
#[cfg(test)]
#[derive(Debug, thiserror::Error)]
pub enum CdrError {
    /// What the CDR encoder or decoder said.
    #[error(transparent)]
    Cdr(#[from] cdr_encoding::Error),
    /// The bytes do not start with the little-endian CDR encapsulation header.
    #[error("not a little-endian CDR sample")]
    NotLittleEndianCdr,
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Every message is the line the node wrote when its errors were strings (the old
    /// `format!` of each, beside it).
    #[test]
    fn messages_read_as_the_node_always_wrote_them() {
        let engine = || semlook::Error::io("/cam.toml", std::io::Error::new(std::io::ErrorKind::NotFound, "gone"));
        let unknown = semlook::matching::Setting::parse("nope").unwrap_err();
        let parse = "x".parse::<u16>().unwrap_err();
        let spawn = || std::io::Error::other("no threads");
        let max = 7680u64 * 4320;
        let cases: Vec<(NodeError, String)> = vec![
            (ArgumentError::MissingMap.into(), "the map parameter is required (-p map:=DIR)".into()),
            (NodeError::Setting(unknown.clone()), format!("parameter setting: {unknown}")),
            (NodeError::UnknownBackend { name: "tpu".into() }, format!("backend {:?} is unknown (cpu, gpu, auto)", "tpu")),
            (engine().into(), engine().to_string()),
            (NodeError::EngineParam { param: "camera_info", source: engine() }, format!("parameter camera_info: {}", engine())),
            (NodeError::DomainId { value: "x".into(), source: parse }, format!("ROS_DOMAIN_ID={:?} is not a domain number", "x")),
            (NodeError::Ros { what: "publisher".into(), reason: format!("{:?}", "busy") }, format!("publisher: {:?}", "busy")),
            (NodeError::SignalHandler(ctrlc::Error::MultipleHandlers), format!("signal handler: {}", ctrlc::Error::MultipleHandlers)),
            (NodeError::LocalizerThread(spawn()), format!("localizer thread: {}", spawn())),
            (NodeError::LocalizerPanicked, "the localizer thread panicked".into()),
            (FrameError::Encoding { encoding: "16UC1".into() }.into(), format!("encoding {:?} is not supported (rgb8, bgr8, mono8)", "16UC1")),
            (FrameError::Size { width: 0, height: 2, max }.into(), format!("{}x{} pixels (1 to {max})", 0, 2)),
            (
                FrameError::Data { len: 11, step: 6, width: 2, height: 2, encoding: "rgb8".into() }.into(),
                format!("{} bytes with step {} for {}x{} {} pixels", 11, 6, 2, 2, "rgb8"),
            ),
            (FrameError::PixelCount.into(), "pixel count".into()),
            (FrameError::Format { format: "tiff".into() }.into(), format!("format {:?} is not supported (jpeg, png)", "tiff")),
        ];
        for (e, was) in cases {
            assert_eq!(e.to_string(), was, "{e:?}");
        }
        let camera = semlook::verify::pose::Camera { fx: 0.0, fy: 500.0, cx: 320.0, cy: 240.0, width: 640, height: 480 };
        for (e, says) in [
            (CameraInfoError::Size { width: 0, height: 0 }, "0x0 pixels: the calibrated image size must not be 0 (an uncalibrated camera?)"),
            (
                CameraInfoError::Region { x_offset: 600, y_offset: 0, width: 100, height: 480, image_width: 640, image_height: 480 },
                "region of interest 100x480 at (600, 0) is not inside the calibrated 640x480 image",
            ),
            (CameraInfoError::Intrinsics { camera, reason: "fx = 0: bad".into() }, "fx 0, fy 500, cx 320, cy 240 for 640x480 pixels: fx = 0: bad"),
        ] {
            assert_eq!(e.to_string(), says, "{e:?}");
        }
    }
}
