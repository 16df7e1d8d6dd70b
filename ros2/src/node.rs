//! The node: DDS participant, subscriptions and publishers on one thread (an async executor),
//! the localizer on another, a bounded queue between them (and, with `camera_info_topic`, a slot
//! for the newest camera intrinsics the localizer thread takes before its next frame).

use crate::error::{CameraInfoError, FrameError, NodeError};
use crate::msgs::{CameraInfo, CompressedImage, Header, Image, LoopClosure, PlaceMatch, Point, Pose, PoseStamped, Quaternion};
use crate::params::Params;
use futures::{FutureExt, StreamExt};
use ros2_client::dds::rustdds::DomainParticipantBuilder;
use ros2_client::parameters::ParameterValue;
use ros2_client::qos::{Durability, History, WhenFull};
use ros2_client::{Context, MessageTypeName, Name, NodeName, NodeOptions, QosProfile};
use semlook::config::Config;
use semlook::engine::{Backend, Engine};
use semlook::map::Map;
use semlook::matching::Setting;
use semlook::stream::{FrameResult, Latency, LatencyStats, Localizer, Pixels, StreamFrame, StreamOptions};
use semlook::verify::pose::Camera;
use std::collections::VecDeque;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Condvar, Mutex};
use std::time::{Duration, Instant};

/// Most pixels a raw frame may have (a 8K frame); larger ones are refused.
const MAX_PIXELS: u64 = 7680 * 4320;

/// Set once the node has stopped (its summary written): what the DDS stack says while it tears
/// down (RustDDS fails to leave a multicast group it joined on loopback, for one) is not an error
/// of the node's, and shows only with `SEMLOOK_LOG=debug`.
static TEARING_DOWN: AtomicBool = AtomicBool::new(false);

/// Log lines on standard error (`SEMLOOK_LOG=debug` for one line per frame).
pub fn init_logging() {
    struct Stderr(log::LevelFilter);
    impl log::Log for Stderr {
        fn enabled(&self, m: &log::Metadata) -> bool {
            // the DDS stack's own warnings (multicast joins on a loopback-only host, readers
            // without locators during discovery) only with SEMLOOK_LOG=debug
            let ours = m.target().starts_with("semlook");
            let stack_error = m.level() <= log::Level::Error && !TEARING_DOWN.load(Ordering::Relaxed);
            m.level() <= self.0 && (ours || stack_error || self.0 >= log::LevelFilter::Debug)
        }
        fn log(&self, r: &log::Record) {
            if self.enabled(r.metadata()) {
                use std::io::Write;
                let _ = writeln!(std::io::stderr(), "[semlook_node] {}: {}", r.level(), r.args());
            }
        }
        fn flush(&self) {}
    }
    let level = match std::env::var("SEMLOOK_LOG").as_deref() {
        Ok("debug") => log::LevelFilter::Debug,
        Ok("warn") => log::LevelFilter::Warn,
        _ => log::LevelFilter::Info,
    };
    if log::set_boxed_logger(Box::new(Stderr(level))).is_ok() {
        log::set_max_level(level);
    }
}

/// A frame waiting to be localized.
struct Incoming {
    header: Header,
    pixels: Pixels,
    received: Instant,
    /// Frames the node received before this one (dropped and refused ones included): the
    /// `frame` of its PlaceMatch.
    number: u64,
}

/// The frames between the DDS thread and the localizer: at most `cap`; a frame arriving at a full
/// queue pushes out the oldest.
struct Queue {
    items: Mutex<VecDeque<Incoming>>,
    ready: Condvar,
    cap: usize,
    dropped: AtomicU64,
}

impl Queue {
    fn push(&self, f: Incoming) {
        let mut q = self.items.lock().unwrap_or_else(|e| e.into_inner());
        if q.len() >= self.cap {
            q.pop_front();
            self.dropped.fetch_add(1, Ordering::Relaxed);
        }
        q.push_back(f);
        self.ready.notify_one();
    }
    fn pop(&self, wait: Duration) -> Option<Incoming> {
        let q = self.items.lock().unwrap_or_else(|e| e.into_inner());
        let (mut q, _) = self.ready.wait_timeout_while(q, wait, |q| q.is_empty()).unwrap_or_else(|e| e.into_inner());
        q.pop_front()
    }
}

/// Counts the node keeps (and logs in its summary).
#[derive(Default)]
struct Counts {
    received: AtomicU64,
    /// Frames refused before the localizer: unsupported encoding or format, bad sizes.
    unsupported: AtomicU64,
    published: AtomicU64,
}

/// A received frame (its pixels, or why they cannot be used) counted and queued: every frame
/// gets the next number, whether it is localized, dropped from a full queue or refused, so
/// that a PlaceMatch's `frame` counts every frame before it.
fn receive(queue: &Queue, counts: &Counts, header: Header, pixels: Result<Pixels, FrameError>, received: Instant) {
    let number = counts.received.fetch_add(1, Ordering::Relaxed);
    match pixels {
        Ok(pixels) => queue.push(Incoming { header, pixels, received, number }),
        Err(why) => {
            counts.unsupported.fetch_add(1, Ordering::Relaxed);
            log::warn!("frame {} refused: {why}", frame_id(&header));
        }
    }
}

/// An `Image` as pixels: rgb8, bgr8 and mono8 (rows of `step` bytes); others refused.
pub fn image_pixels(m: &Image) -> Result<Pixels, FrameError> {
    let ch = match m.encoding.as_str() {
        "rgb8" | "bgr8" => 3,
        "mono8" => 1,
        other => return Err(FrameError::Encoding { encoding: other.into() }),
    };
    let (w, h, step) = (m.width as u64, m.height as u64, m.step as u64);
    if w == 0 || h == 0 || w * h > MAX_PIXELS {
        return Err(FrameError::Size { width: w, height: h, max: MAX_PIXELS });
    }
    if step < w * ch || (m.data.len() as u64) < step * (h - 1) + w * ch {
        return Err(FrameError::Data { len: m.data.len(), step, width: w, height: h, encoding: m.encoding.clone() });
    }
    let mut rgb = Vec::with_capacity((w * h * 3) as usize);
    for y in 0..h as usize {
        let row = &m.data[y * step as usize..y * step as usize + (w * ch) as usize];
        match m.encoding.as_str() {
            "rgb8" => rgb.extend_from_slice(row),
            "bgr8" => rgb.extend(row.chunks_exact(3).flat_map(|p| [p[2], p[1], p[0]])),
            _ => rgb.extend(row.iter().flat_map(|&v| [v, v, v])),
        }
    }
    let image = image::RgbImage::from_raw(m.width, m.height, rgb).ok_or(FrameError::PixelCount)?;
    Ok(Pixels::Rgb { image, labels: None })
}

/// A `CompressedImage` as bytes to decode: jpeg or png (the format string says which, as
/// image_transport writes it: "jpeg", "png", or "rgb8; jpeg compressed bgr8").
pub fn compressed_pixels(m: &CompressedImage) -> Result<Pixels, FrameError> {
    let f = m.format.to_ascii_lowercase();
    if !(f.contains("jpeg") || f.contains("jpg") || f.contains("png")) {
        return Err(FrameError::Format { format: m.format.clone() });
    }
    Ok(Pixels::Bytes { bytes: m.data.clone(), labels: None })
}

/// The intrinsics a `CameraInfo` gives for the images its camera publishes, as the relative pose
/// takes them: fx = K[0], fy = K[4], cx = K[2], cy = K[5], the calibrated `width` x `height`. A
/// region of interest and binning (REP 104: K is of the calibrated image; the camera publishes
/// the region, binned) are applied: cx - x_offset and cy - y_offset, then fx, cx and the width
/// divided by `binning_x`, fy, cy and the height by `binning_y` (0 and 1: none; an all-zero region:
/// the whole image). Refused: no image size, a region outside the image, intrinsics
/// [`Camera::check`] refuses. The distortion (`d`) is not used: the relative pose takes the
/// images as undistorted.
pub fn camera_of(m: &CameraInfo) -> Result<Camera, CameraInfoError> {
    if m.width == 0 || m.height == 0 {
        return Err(CameraInfoError::Size { width: m.width, height: m.height });
    }
    let roi = m.roi;
    let (x0, y0, w, h) = match roi.width == 0 || roi.height == 0 {
        true => (0, 0, m.width, m.height),
        false => (roi.x_offset, roi.y_offset, roi.width, roi.height),
    };
    if x0 as u64 + w as u64 > m.width as u64 || y0 as u64 + h as u64 > m.height as u64 {
        return Err(CameraInfoError::Region {
            x_offset: roi.x_offset,
            y_offset: roi.y_offset,
            width: roi.width,
            height: roi.height,
            image_width: m.width,
            image_height: m.height,
        });
    }
    let (bx, by) = (m.binning_x.max(1), m.binning_y.max(1));
    let camera = Camera {
        fx: m.k[0] / bx as f64,
        fy: m.k[4] / by as f64,
        cx: (m.k[2] - x0 as f64) / bx as f64,
        cy: (m.k[5] - y0 as f64) / by as f64,
        width: w / bx,
        height: h / by,
    };
    camera.check().map_err(|reason| CameraInfoError::Intrinsics { camera, reason })?;
    Ok(camera)
}

/// What the node makes of the `CameraInfo` messages of `camera_info_topic` (a camera publishes
/// one with every image): the first valid one gives the camera, a later one whose intrinsics
/// differ replaces it, the same again changes nothing; each refusal and the distortion the
/// relative pose ignores are logged once, not at the camera's rate.
struct CameraInfos {
    topic: String,
    /// The last message, without its header: the same again is not looked at twice.
    last: Option<CameraInfo>,
    /// The intrinsics given to the localizer last.
    camera: Option<Camera>,
    /// The distortion warning was logged.
    distortion_warned: bool,
}

impl CameraInfos {
    fn new(topic: &str) -> CameraInfos {
        CameraInfos { topic: topic.to_string(), last: None, camera: None, distortion_warned: false }
    }

    /// The intrinsics to give the localizer after `m`: `None` where they stay as they are.
    fn receive(&mut self, mut m: CameraInfo) -> Option<Camera> {
        m.header = Header::default();
        if self.last.as_ref() == Some(&m) {
            return None;
        }
        if !self.distortion_warned && m.d.iter().any(|&c| c != 0.0) {
            self.distortion_warned = true;
            log::warn!(
                "camera info on {}: distortion {:?} with D = {:?} is ignored: relative poses take the images as undistorted (rectified images give better ones)",
                self.topic,
                m.distortion_model,
                m.d
            );
        }
        let got = camera_of(&m);
        self.last = Some(m);
        match got {
            Err(e) => {
                log::warn!("camera info on {} refused: {e}", self.topic);
                None
            }
            Ok(c) if self.camera == Some(c) => None,
            Ok(c) => {
                self.camera = Some(c);
                Some(c)
            }
        }
    }
}

/// Intrinsics from `camera_info_topic` waiting for the localizer thread, which takes them before
/// its next frame (the newest only).
struct CameraSlot {
    topic: String,
    pending: Mutex<Option<Camera>>,
}

impl CameraSlot {
    fn put(&self, c: Camera) {
        *self.pending.lock().unwrap_or_else(|e| e.into_inner()) = Some(c);
    }
    fn take(&self) -> Option<Camera> {
        self.pending.lock().unwrap_or_else(|e| e.into_inner()).take()
    }
}

/// The localizer thread gives the localizer the intrinsics waiting in `slot`, if any, and says so.
fn apply_camera(loc: &mut Localizer, slot: Option<&CameraSlot>) {
    let Some((slot, c)) = slot.and_then(|s| s.take().map(|c| (s, c))) else { return };
    let says = |c: &Camera| format!("fx {}, fy {}, cx {}, cy {} for {}x{} pixels", c.fx, c.fy, c.cx, c.cy, c.width, c.height);
    let was = loc.camera();
    match loc.set_camera(c) {
        Ok(()) => match was {
            None => log::info!("camera intrinsics from {}: {}; accepted matches carry relative poses from now on", slot.topic, says(&c)),
            Some(was) => log::info!("camera intrinsics from {} changed: {} (were {})", slot.topic, says(&c), says(&was)),
        },
        Err(e) => log::warn!("camera intrinsics from {} not used: {e}", slot.topic),
    }
}

/// The id a frame gets (and is stored under in loop-closure mode): its stamp.
pub fn frame_id(h: &Header) -> String {
    format!("{}.{:09}", h.stamp.sec, h.stamp.nanosec)
}

/// The PlaceMatch of a localized frame; `number`: frames the node received before it (dropped
/// and refused ones included).
pub fn place_match(h: &Header, number: u64, r: &FrameResult, latency_ms: f32) -> PlaceMatch {
    let best = r.best();
    let seq = r.sequence.as_ref();
    let (place_id, score) = r.place().map_or((String::new(), 0.0), |a| (a.id.clone(), a.score));
    let place_index = r.place_index().unwrap_or(0);
    PlaceMatch {
        header: h.clone(),
        frame: number,
        place_id,
        place_index,
        score,
        sequence_matched: seq.is_some(),
        sequence_id: seq.map_or(String::new(), |s| s.id.clone()),
        sequence_score: seq.map_or(0.0, |s| s.matched.score),
        uniqueness: seq.map_or(0.0, |s| s.matched.uniqueness),
        accepted: seq.is_some_and(|s| s.matched.accepted),
        top_ids: r.top_k.iter().map(|c| c.id.clone()).collect(),
        top_indices: r.top_k.iter().map(|c| c.index).collect(),
        top_scores: r.top_k.iter().map(|c| c.score).collect(),
        inliers: best.and_then(|b| b.inliers).map_or(-1, |i| i.min(i32::MAX as u32) as i32),
        map_generation: r.generation,
        latency_ms,
        ..relative_pose_fields(r.relative_pose.as_ref())
    }
}

/// The relative-pose fields of a PlaceMatch (a LoopClosure has the same), from a pose or none.
fn relative_pose_fields(p: Option<&semlook::verify::pose::RelativePose>) -> PlaceMatch {
    match p {
        Some(p) => PlaceMatch {
            has_relative_pose: true,
            relative_rotation: p.quaternion,
            relative_translation: p.translation_unit,
            relative_rotation_deg: p.rotation_deg,
            pose_inliers: p.inliers.min(i32::MAX as u32) as i32,
            ..Default::default()
        },
        None => PlaceMatch { relative_rotation: [0.0, 0.0, 0.0, 1.0], pose_inliers: -1, ..Default::default() },
    }
}

/// The PoseStamped of a localized frame: the pose the map stores for its answer, stamped with the
/// frame's time, in `frame_id` (the map's frame); none where the map stores no pose for it. A
/// pose without an orientation (positions alone, as from UTM names) gets the identity rotation.
pub fn pose_stamped(h: &Header, r: &FrameResult, frame_id: &str) -> Option<PoseStamped> {
    let p = r.pose?;
    let orientation = p.orientation.map_or(Quaternion::default(), |[x, y, z, w]| Quaternion { x, y, z, w });
    let [x, y, z] = p.position;
    Some(PoseStamped { header: Header { stamp: h.stamp, frame_id: frame_id.to_string() }, pose: Pose { position: Point { x, y, z }, orientation } })
}

/// What the localizer thread publishes to.
struct Outputs {
    matches: ros2_client::Publisher<PlaceMatch>,
    closures: ros2_client::Publisher<LoopClosure>,
    poses: ros2_client::Publisher<PoseStamped>,
    pose_frame_id: String,
}

/// The configuration the node localizes with: the file given, else the map's, with the
/// parameters that override it.
fn config(p: &Params, map: Option<&Map>) -> Result<Option<Config>, NodeError> {
    let mut cfg = match (&p.config, map) {
        (Some(f), _) => Config::load(f)?,
        (None, Some(m)) => m.query_config(),
        (None, None) => Config::default(),
    };
    if let Some(k) = p.top_k {
        cfg.matching.top_k = k;
    }
    match &p.segmenter {
        None => {}
        Some(None) => {
            cfg.models.default_segmenter = false;
            cfg.models.segmenter_onnx = None;
        }
        Some(Some(path)) => cfg.models.segmenter_onnx = Some(path.clone()),
    }
    if let Some(n) = p.sequence_length {
        cfg.sequence.length = n;
        cfg.sequence.min_frames = cfg.sequence.min_frames.min(n);
    }
    cfg.validate("node parameters")?;
    Ok(Some(cfg))
}

/// The DDS context: `ROS_DOMAIN_ID`; only the loopback network where ROS 2 would stay on this
/// host (`ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST`, or the older `ROS_LOCALHOST_ONLY=1`).
fn context() -> Result<Context, NodeError> {
    let domain = match std::env::var("ROS_DOMAIN_ID") {
        Ok(v) if !v.is_empty() => v.parse::<u16>().map_err(|source| NodeError::DomainId { value: v, source })?,
        _ => 0,
    };
    let local = std::env::var("ROS_AUTOMATIC_DISCOVERY_RANGE").is_ok_and(|v| v.eq_ignore_ascii_case("LOCALHOST"))
        || std::env::var("ROS_LOCALHOST_ONLY").is_ok_and(|v| v == "1");
    let mut b = DomainParticipantBuilder::new(domain).same_host_loopback(true);
    if local {
        b = b.with_only_networks([std::net::Ipv4Addr::LOCALHOST]);
    }
    let dp = b.build().map_err(|e| ros(format!("DDS participant (domain {domain})"), e))?;
    log::info!("DDS domain {domain}{}", if local { ", loopback only" } else { "" });
    Context::from_domain_participant(dp).map_err(|e| ros("ROS 2 context", e))
}

/// A ROS 2 stack error: what could not be made, and the stack's error as `Debug` writes it.
fn ros(what: impl Into<String>, e: impl std::fmt::Debug) -> NodeError {
    NodeError::Ros { what: what.into(), reason: format!("{e:?}") }
}

/// Runs the node until SIGINT or SIGTERM (or the end of its subscriptions), then writes its
/// summary.
pub fn run(p: Params) -> Result<(), NodeError> {
    // the localizer first: a bad map or parameter fails before any DDS traffic
    let setting = Setting::parse(&p.setting)?;
    let backend = <Backend as semlook::Choice>::named(&p.backend).ok_or_else(|| NodeError::UnknownBackend { name: p.backend.clone() })?;
    let (engine, why) = Engine::new(backend, &Default::default())?;
    if let Some(why) = why {
        log::info!("backend auto: {why}");
    }
    // the camera's intrinsics are read and checked before the map is opened
    let camera = match &p.camera_info {
        Some(path) => Some(semlook::verify::pose::Camera::load(path).map_err(|source| NodeError::EngineParam { param: "camera_info", source })?),
        None => None,
    };
    // the map is opened once: its configuration, then the localizer over it (in loop-closure
    // mode a folder without a map gets one from the stream)
    let map = Localizer::open_map(&p.map, p.loop_closure)?;
    let cfg = config(&p, map.as_ref())?;
    let opts = StreamOptions { setting, sequence: p.sequence, loop_closure: p.loop_closure, ..Default::default() };
    let mut loc = Localizer::over(map, &p.map, cfg, opts, engine)?;
    if let Some(c) = camera {
        loc = loc.with_camera(c).map_err(|source| NodeError::EngineParam { param: "camera_info", source })?;
    }
    match loc.map() {
        Some(m) => {
            let (posed, oriented) = m.pose_counts();
            log::info!(
                "map {}: {} places ({posed} with a pose, {oriented} with an orientation), generation {}; setting {setting}; {}",
                p.map.display(),
                m.len(),
                m.manifest.generation,
                loc.engine().describe()
            );
            if posed > oriented {
                log::info!("{} places have a position but no orientation: their poses are published with the identity rotation", posed - oriented);
            }
        }
        None => log::info!("map {}: made from the stream (loop closure)", p.map.display()),
    }
    let ctx = context()?;
    let mut options = NodeOptions::new().enable_rosout(false).start_parameter_services(true);
    let values = declared(&p);
    for (name, value) in &values {
        options = options.declare_parameter(name, value.clone());
    }
    // the node runs with what it was started with: any other value is refused, with the reason
    let options = options.parameter_validator(Box::new(move |name: &str, v: &ParameterValue| match values.iter().find(|(n, _)| *n == name) {
        Some((_, now)) if now == v => Ok(()),
        _ => Err(format!("{name} is read-only: restart the node to change it")),
    }));
    let node_name = NodeName::new(&p.namespace, &p.node_name).map_err(|e| ros(format!("node name {:?} in {:?}", p.node_name, p.namespace), e))?;
    let mut node = ctx.new_node(node_name, options).map_err(|e| ros("node", e))?;
    let ex = smol::LocalExecutor::new();
    ex.spawn(node.spinner().map_err(|e| ros("spinner", e))?.spin()).detach();
    let sensor =
        QosProfile::subscription_default().reliability_best_effort().durability(Durability::Volatile).history(History::KeepLast { depth: 5 });
    let reliable = QosProfile::publisher_default()
        .reliability_reliable(WhenFull::DEFAULT)
        .durability(Durability::Volatile)
        .history(History::KeepLast { depth: 10 });
    let topic = |node: &mut ros2_client::Node, name: &str, pkg: &str, ty: &str, qos: &QosProfile| {
        let n = Name::parse(name).map_err(|e| ros(format!("topic {name:?}"), e))?;
        node.create_topic(&n, MessageTypeName::new(pkg, ty), qos).map_err(|e| ros(format!("topic {name:?}"), e))
    };
    let own = |base: &str| format!("{}/{}/{base}", p.namespace.trim_end_matches('/'), p.node_name);
    let t_img = topic(&mut node, &p.image_topic, "sensor_msgs", "Image", &sensor)?;
    let t_cmp = topic(&mut node, &p.compressed_topic, "sensor_msgs", "CompressedImage", &sensor)?;
    let t_match = topic(&mut node, &own("match"), "semlook_msgs", "PlaceMatch", &reliable)?;
    let t_closure = topic(&mut node, &own("closure"), "semlook_msgs", "LoopClosure", &reliable)?;
    let t_pose = topic(&mut node, &own("pose"), "geometry_msgs", "PoseStamped", &reliable)?;
    // the camera's intrinsics on a topic (best effort as the frames: a reader that takes both
    // best-effort and reliable writers, and a camera publishes one with every image)
    let t_info = match &p.camera_info_topic {
        Some(name) => Some(topic(&mut node, name, "sensor_msgs", "CameraInfo", &sensor)?),
        None => None,
    };
    // the publishers already up are known before our subscriptions are announced: a camera that
    // sees them matched then sends to a reader that knows it (else its first frames are dropped)
    let known = settle_discovery(&ctx.domain_participant());
    log::info!("discovery settled: {known} remote writers known");
    let sub_img = node.create_subscription::<Image>(&t_img, None).map_err(|e| ros("subscription", e))?;
    let sub_cmp = node.create_subscription::<CompressedImage>(&t_cmp, None).map_err(|e| ros("subscription", e))?;
    let sub_info = match &t_info {
        Some(t) => Some(node.create_subscription::<CameraInfo>(t, None).map_err(|e| ros("subscription", e))?),
        None => None,
    };
    let pub_match = node.create_publisher::<PlaceMatch>(&t_match, None).map_err(|e| ros("publisher", e))?;
    let pub_closure = node.create_publisher::<LoopClosure>(&t_closure, None).map_err(|e| ros("publisher", e))?;
    let pub_pose = node.create_publisher::<PoseStamped>(&t_pose, None).map_err(|e| ros("publisher", e))?;
    log::info!("subscribed {} and {}; publishing {}, {} and {}", p.image_topic, p.compressed_topic, own("match"), own("closure"), own("pose"));
    if let Some(t) = &p.camera_info_topic {
        log::info!("subscribed {t}: frames answered before its first valid camera info get no relative pose");
    }
    let out = Outputs { matches: pub_match, closures: pub_closure, poses: pub_pose, pose_frame_id: p.pose_frame_id.clone() };

    let stop = Arc::new(AtomicBool::new(false));
    {
        let stop = stop.clone();
        ctrlc::set_handler(move || stop.store(true, Ordering::SeqCst))?;
    }
    let queue = Arc::new(Queue { items: Mutex::new(VecDeque::new()), ready: Condvar::new(), cap: p.queue_size, dropped: AtomicU64::new(0) });
    let counts = Arc::new(Counts::default());
    let slot = p.camera_info_topic.as_ref().map(|t| Arc::new(CameraSlot { topic: t.clone(), pending: Mutex::new(None) }));
    let worker = {
        let (queue, counts, stop, slot) = (queue.clone(), counts.clone(), stop.clone(), slot.clone());
        let refresh = (p.map_refresh_s > 0.0).then(|| Duration::from_secs_f64(p.map_refresh_s));
        std::thread::Builder::new()
            .name("localizer".into())
            .spawn(move || localize(loc, &queue, &counts, &stop, refresh, &out, slot.as_deref()))
            .map_err(NodeError::LocalizerThread)?
    };
    smol::block_on(ex.run(async {
        let mut imgs = Box::pin(sub_img.async_stream());
        let mut cmps = Box::pin(sub_cmp.async_stream());
        // no topic: a stream that never yields
        let mut infos = match &sub_info {
            Some(s) => s.async_stream().boxed_local().fuse(),
            None => futures::stream::pending().boxed_local().fuse(),
        };
        let mut cameras = CameraInfos::new(p.camera_info_topic.as_deref().unwrap_or_default());
        while !stop.load(Ordering::SeqCst) {
            let tick = FutureExt::fuse(smol::Timer::after(Duration::from_millis(100)));
            futures::pin_mut!(tick);
            let got = futures::select! {
                m = imgs.next() => m.map(|r| r.map(|(m, _)| (m.header.clone(), image_pixels(&m)))),
                m = cmps.next() => m.map(|r| r.map(|(m, _)| (m.header.clone(), compressed_pixels(&m)))),
                m = infos.next() => {
                    match m {
                        Some(Ok((m, _))) => {
                            if let (Some(c), Some(slot)) = (cameras.receive(m), &slot) {
                                slot.put(c);
                            }
                        }
                        Some(Err(e)) => log::warn!("a camera info sample could not be read: {e:?}"),
                        None => break,
                    }
                    continue;
                }
                _ = tick => continue,
            };
            let received = Instant::now();
            match got {
                Some(Ok((header, pixels))) => receive(&queue, &counts, header, pixels, received),
                Some(Err(e)) => log::warn!("a sample could not be read: {e:?}"),
                None => break,
            }
        }
    }));
    stop.store(true, Ordering::SeqCst);
    queue.ready.notify_all();
    let summary = worker.join().map_err(|_| NodeError::LocalizerPanicked)?;
    // the node tells its spinner to stop while the executor (and the spinner's task) still
    // exists: dropped after it, the node logged an error on every clean stop
    drop(node);
    let s = serde_json::json!({
        "summary": {
            "received": counts.received.load(Ordering::Relaxed),
            "unsupported": counts.unsupported.load(Ordering::Relaxed),
            "dropped": queue.dropped.load(Ordering::Relaxed),
            "published": counts.published.load(Ordering::Relaxed),
            "localizer": summary.0,
            "receive_to_publish_ms": { "p50": summary.1.p50.total_ms, "p99": summary.1.p99.total_ms, "mean": summary.1.mean.total_ms, "frames": summary.1.frames },
            "stage_ms_p50": summary.1.p50,
        }
    });
    log::info!("stopped: {s}");
    println!("{s}");
    TEARING_DOWN.store(true, Ordering::Relaxed);
    Ok(())
}

/// Shortest wait for discovery at start.
const SETTLE_MIN: Duration = Duration::from_millis(1500);
/// Discovery counts as settled once no new remote writer came for this long.
const SETTLE_QUIET: Duration = Duration::from_millis(1000);
/// Longest wait for discovery at start.
const SETTLE_MAX: Duration = Duration::from_secs(6);

/// Waits until the remote writers the DDS participant knows stop changing (at least
/// [`SETTLE_MIN`], at most [`SETTLE_MAX`]); returns how many it knows. A best-effort sample from a
/// writer the node has not discovered yet is dropped by the DDS stack (RustDDS keeps no sample of
/// an unknown writer), and a ROS 2 publisher already running sends as soon as it sees the node's
/// subscription: announcing the subscriptions only after the publishers present are known keeps
/// their first frames (issue 48: 3 of 4 runs of a publisher started before the node lost its
/// first frame).
fn settle_discovery(dp: &ros2_client::dds::rustdds::DomainParticipant) -> usize {
    let start = Instant::now();
    let (mut known, mut changed) = (dp.discovered_writers().len(), Instant::now());
    while start.elapsed() < SETTLE_MAX && (start.elapsed() < SETTLE_MIN || changed.elapsed() < SETTLE_QUIET) {
        std::thread::sleep(Duration::from_millis(100));
        let n = dp.discovered_writers().len();
        if n != known {
            (known, changed) = (n, Instant::now());
        }
    }
    known
}

/// The parameters as the node declares them (what parameter clients read back).
fn declared(p: &Params) -> Vec<(&'static str, ParameterValue)> {
    let s = |v: &str| ParameterValue::String(v.to_string());
    vec![
        ("map", s(&p.map.display().to_string())),
        ("setting", s(&p.setting)),
        ("top_k", ParameterValue::Integer(p.top_k.map_or(0, |k| k as i64))),
        ("sequence", ParameterValue::Boolean(p.sequence)),
        ("sequence_length", ParameterValue::Integer(p.sequence_length.map_or(0, |k| k as i64))),
        ("loop_closure", ParameterValue::Boolean(p.loop_closure)),
        ("backend", s(&p.backend)),
        ("config", s(&p.config.as_ref().map_or(String::new(), |c| c.display().to_string()))),
        (
            "segmenter",
            s(&match &p.segmenter {
                None => String::new(),
                Some(None) => "none".into(),
                Some(Some(path)) => path.display().to_string(),
            }),
        ),
        ("image_topic", s(&p.image_topic)),
        ("compressed_topic", s(&p.compressed_topic)),
        ("queue_size", ParameterValue::Integer(p.queue_size as i64)),
        ("map_refresh_s", ParameterValue::Double(p.map_refresh_s)),
        ("pose_frame_id", s(&p.pose_frame_id)),
        ("camera_info", s(&p.camera_info.as_ref().map_or(String::new(), |c| c.display().to_string()))),
        ("camera_info_topic", s(p.camera_info_topic.as_deref().unwrap_or_default())),
    ]
}

/// The localizer thread: frames from the queue, answers to the publishers, until `stop`; before
/// each frame, the camera intrinsics waiting in `camera` (`camera_info_topic`), if any.
/// Returns the localizer's counts and the latencies (total: receive to publish).
fn localize(
    mut loc: Localizer,
    queue: &Queue,
    counts: &Counts,
    stop: &AtomicBool,
    refresh: Option<Duration>,
    out: &Outputs,
    camera: Option<&CameraSlot>,
) -> (semlook::stream::StreamCounts, semlook::stream::LatencySummary) {
    let mut stats = LatencyStats::default();
    let mut checked = Instant::now();
    loop {
        if refresh.is_some_and(|r| checked.elapsed() >= r) {
            checked = Instant::now();
            match loc.refresh() {
                Ok(true) => log::info!("moved to map generation {}", loc.map().map_or(0, |m| m.manifest.generation)),
                Ok(false) => {}
                Err(e) => log::warn!("kept map generation {}: {e}", loc.map().map_or(0, |m| m.manifest.generation)),
            }
        }
        let Some(f) = queue.pop(Duration::from_millis(100)) else {
            if stop.load(Ordering::SeqCst) {
                break;
            }
            continue;
        };
        apply_camera(&mut loc, camera);
        let id = frame_id(&f.header);
        let frame = StreamFrame { id: id.clone(), pixels: f.pixels, timestamp: Some(f.header.stamp.seconds()) };
        let refused = loc.counts().refused;
        match loc.push(frame) {
            Ok(r) => {
                if let Some(c) = &r.closure {
                    let msg = LoopClosure {
                        header: f.header.clone(),
                        query_id: c.frame.clone(),
                        place_id: c.place.id.clone(),
                        place_index: c.place.index,
                        score: c.place.score,
                        uniqueness: c.uniqueness,
                        inliers: c.place.inliers.map_or(-1, |i| i.min(i32::MAX as u32) as i32),
                        has_relative_pose: false,
                        relative_rotation: [0.0, 0.0, 0.0, 1.0],
                        relative_translation: [0.0; 3],
                        relative_rotation_deg: 0.0,
                        pose_inliers: -1,
                    };
                    let rp = relative_pose_fields(c.relative_pose.as_ref());
                    let msg = LoopClosure {
                        has_relative_pose: rp.has_relative_pose,
                        relative_rotation: rp.relative_rotation,
                        relative_translation: rp.relative_translation,
                        relative_rotation_deg: rp.relative_rotation_deg,
                        pose_inliers: rp.pose_inliers,
                        ..msg
                    };
                    if let Err(e) = out.closures.publish(msg) {
                        log::warn!("closure of frame {id} not published: {e:?}");
                    }
                }
                let latency = f.received.elapsed().as_secs_f64() * 1e3;
                let msg = place_match(&f.header, f.number, &r, latency as f32);
                // the pose first: a subscriber that has a frame's match has its pose too
                if let Some(pose) = pose_stamped(&f.header, &r, &out.pose_frame_id) {
                    if let Err(e) = out.poses.publish(pose) {
                        log::warn!("pose of frame {id} not published: {e:?}");
                    }
                }
                match out.matches.publish(msg) {
                    Ok(()) => {
                        counts.published.fetch_add(1, Ordering::Relaxed);
                        let total = f.received.elapsed().as_secs_f64() * 1e3;
                        stats.push(&Latency { total_ms: total, ..r.latency });
                        log::debug!("frame {id}: {:?} in {total:.1} ms", r.place().map(|a| (&a.id, a.score, a.source)));
                    }
                    Err(e) => log::warn!("match of frame {id} not published: {e:?}"),
                }
                let n = counts.published.load(Ordering::Relaxed);
                if n.is_multiple_of(100) {
                    let s = stats.summary();
                    log::info!(
                        "{n} frames published, {} dropped; receive to publish p50 {:.1} ms, p99 {:.1} ms",
                        queue.dropped.load(Ordering::Relaxed),
                        s.p50.total_ms,
                        s.p99.total_ms
                    );
                }
            }
            Err(e) if loc.counts().refused > refused => log::warn!("frame {id} refused: {e}"),
            Err(e) => {
                log::error!("frame {id}: {e}; stopping");
                stop.store(true, Ordering::SeqCst);
                break;
            }
        }
    }
    if let Err(e) = loc.finish() {
        log::error!("the last frames were not committed: {e}");
    }
    (loc.counts(), stats.summary())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Issue 57 part 4: a map that holds labels and a node without a segmenter
    /// (`segmenter:=none`): refused before any frame or DDS traffic, in words about frames (it said
    /// "this photo" before any frame came), with a hint naming the node's own remedy,
    /// `-p segmenter:=`.
    #[test]
    fn a_labelled_map_without_a_segmenter_is_refused_with_the_segmenter_hint() {
        let dir = tempfile::tempdir().unwrap();
        let map = dir.path().join("map");
        let cfg = Config::without_appearance();
        let enc = semlook::encode::Encoder::new(&cfg).unwrap();
        let table = semlook::classes::ClassTable::cityscapes();
        let mut set = enc.descriptor_set();
        let mut scratch = Default::default();
        for k in 0..3usize {
            // road below, sky above, a building whose width differs per place
            let classes: Vec<u8> = (0..64 * 48)
                .map(|i| {
                    if i / 64 >= 24 {
                        0
                    } else if i % 64 < 10 + 15 * k {
                        2
                    } else {
                        10
                    }
                })
                .collect();
            let labels = semlook::input::LabelMap::new(64, 48, classes, &table).unwrap();
            set.push(&enc.encode_labels(&format!("p{k}"), &labels, &mut scratch).unwrap().0).unwrap();
        }
        Map::create(&map, &cfg.encoding(), &set, None).unwrap();
        let args: Vec<String> =
            ["--ros-args", "-p", &format!("map:={}", map.display()), "-p", "segmenter:=none", "-p", "backend:=cpu", "-p", "setting:=forest"]
                .iter()
                .map(|a| a.to_string())
                .collect();
        let e = run(Params::parse(&args).unwrap().unwrap()).unwrap_err();
        let text = e.to_string();
        assert!(text.contains("photos without label maps need a segmenter") && !text.contains("this photo"), "{text}");
        assert!(e.hint().is_some_and(|h| h.contains("-p segmenter:=")), "{text}: {:?}", e.hint());
    }

    fn image(encoding: &str, w: u32, h: u32, step: u32, data: Vec<u8>) -> Image {
        Image { header: Header::default(), height: h, width: w, encoding: encoding.into(), is_bigendian: 0, step, data }
    }

    #[test]
    fn raw_encodings_convert_and_others_are_refused_with_the_reason() {
        // 2x2 with one byte of padding per row
        let bgr = image("bgr8", 2, 2, 7, vec![1, 2, 3, 4, 5, 6, 0, 7, 8, 9, 10, 11, 12, 0]);
        let Pixels::Rgb { image: img, .. } = image_pixels(&bgr).unwrap() else { panic!() };
        assert_eq!(img.as_raw(), &[3, 2, 1, 6, 5, 4, 9, 8, 7, 12, 11, 10]);
        let mono = image("mono8", 2, 1, 2, vec![5, 9]);
        let Pixels::Rgb { image: img, .. } = image_pixels(&mono).unwrap() else { panic!() };
        assert_eq!(img.as_raw(), &[5, 5, 5, 9, 9, 9]);
        for (m, says) in [
            (image("16UC1", 2, 2, 4, vec![0; 8]), "16UC1"),
            (image("rgb8", 2, 2, 5, vec![0; 12]), "step 5"),
            (image("rgb8", 2, 2, 6, vec![0; 11]), "11 bytes"),
            (image("rgb8", 0, 2, 0, vec![]), "0x2"),
        ] {
            let e = image_pixels(&m).err().unwrap();
            assert!(e.to_string().contains(says), "{e}");
        }
        let c = CompressedImage { header: Header::default(), format: "tiff".into(), data: vec![1] };
        assert!(compressed_pixels(&c).err().unwrap().to_string().contains("tiff"));
        let c = CompressedImage { format: "rgb8; jpeg compressed bgr8".into(), ..c };
        assert!(compressed_pixels(&c).is_ok());
    }

    /// A calibrated 960x540 camera, as `camera_calibration` writes one (plumb_bob, 5 coefficients).
    fn info() -> CameraInfo {
        CameraInfo {
            header: Header { stamp: crate::msgs::Time { sec: 5, nanosec: 0 }, frame_id: "cam0".into() },
            height: 540,
            width: 960,
            distortion_model: "plumb_bob".into(),
            d: vec![0.0; 5],
            k: [700.0, 0.0, 479.5, 0.0, 701.5, 269.5, 0.0, 0.0, 1.0],
            r: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
            p: [700.0, 0.0, 479.5, 0.0, 0.0, 701.5, 269.5, 0.0, 0.0, 0.0, 1.0, 0.0],
            ..Default::default()
        }
    }

    /// fx, fy, cx, cy from K, the calibrated size; binning and a region of interest applied as
    /// REP 104 has them.
    #[test]
    fn camera_info_gives_the_intrinsics_of_its_k() {
        let c = camera_of(&info()).unwrap();
        assert_eq!(c, Camera { fx: 700.0, fy: 701.5, cx: 479.5, cy: 269.5, width: 960, height: 540 });
        // binning 1 is none, as 0 is; a region of all zeros is the whole image
        let m = CameraInfo { binning_x: 1, binning_y: 1, ..info() };
        assert_eq!(camera_of(&m).unwrap(), c);
        // the camera publishes the 800x400 region at (100, 60), binned by 2 across and 4 down
        let m = CameraInfo {
            binning_x: 2,
            binning_y: 4,
            roi: crate::msgs::RegionOfInterest { x_offset: 100, y_offset: 60, width: 800, height: 400, do_rectify: false },
            ..info()
        };
        assert_eq!(camera_of(&m).unwrap(), Camera { fx: 350.0, fy: 701.5 / 4.0, cx: 189.75, cy: 52.375, width: 400, height: 100 });
    }

    /// A message the relative pose cannot use is refused with what is wrong in the error's fields:
    /// no size (an uncalibrated camera's zeros), focal lengths zero, negative or not finite, a
    /// principal point outside the image, a region outside the image.
    #[test]
    fn camera_info_the_pose_cannot_use_is_refused() {
        let uncalibrated = CameraInfo { width: 0, height: 0, k: [0.0; 9], ..info() };
        assert_eq!(camera_of(&uncalibrated), Err(CameraInfoError::Size { width: 0, height: 0 }));
        assert_eq!(camera_of(&CameraInfo { height: 0, ..info() }), Err(CameraInfoError::Size { width: 960, height: 0 }));
        let with_k = |i: usize, v: f64| {
            let mut m = info();
            m.k[i] = v;
            m
        };
        for (m, says) in [
            (with_k(0, 0.0), "fx = 0"),
            (with_k(0, -700.0), "fx = -700"),
            (with_k(4, f64::NAN), "fy = NaN"),
            (with_k(4, f64::INFINITY), "fy = inf"),
            (with_k(2, 2000.0), "principal point"),
            (CameraInfo { k: [0.0; 9], ..info() }, "fx = 0"),
        ] {
            match camera_of(&m) {
                Err(CameraInfoError::Intrinsics { camera, reason }) => {
                    assert_eq!((camera.fx, camera.cx, camera.width, camera.height), (m.k[0], m.k[2], 960, 540));
                    assert!(reason.contains(says), "{reason} (want {says})");
                }
                other => panic!("{:?}: {other:?}", m.k),
            }
        }
        let outside =
            CameraInfo { roi: crate::msgs::RegionOfInterest { x_offset: 600, y_offset: 0, width: 400, height: 540, do_rectify: false }, ..info() };
        assert_eq!(
            camera_of(&outside),
            Err(CameraInfoError::Region { x_offset: 600, y_offset: 0, width: 400, height: 540, image_width: 960, image_height: 540 })
        );
    }

    /// The first valid message gives the camera; the same again (another stamp) gives nothing;
    /// other intrinsics replace it; a refused one leaves it; distortion is warned of once.
    #[test]
    fn camera_infos_set_the_camera_once_and_replace_it_when_it_changes() {
        let mut infos = CameraInfos::new("/camera/camera_info");
        assert_eq!(infos.receive(CameraInfo { width: 0, ..info() }), None, "refused");
        assert_eq!(infos.camera, None);
        let first = infos.receive(info()).expect("the first valid one sets the camera");
        assert_eq!(first.fx, 700.0);
        let later = CameraInfo { header: Header { stamp: crate::msgs::Time { sec: 6, nanosec: 0 }, ..info().header }, ..info() };
        assert_eq!(infos.receive(later), None, "the same intrinsics again");
        assert!(!infos.distortion_warned);
        // distortion alone changes nothing the pose uses; it is warned of, once
        let distorted = CameraInfo { d: vec![-0.25, 0.1, 0.0, 0.0, 0.0], ..info() };
        assert_eq!(infos.receive(distorted.clone()), None);
        assert!(infos.distortion_warned);
        let mut zoomed = distorted;
        zoomed.k[0] = 900.0;
        zoomed.k[4] = 900.0;
        assert_eq!(infos.receive(zoomed).map(|c| (c.fx, c.fy)), Some((900.0, 900.0)), "other intrinsics replace the camera");
        assert_eq!(infos.receive(CameraInfo { k: [0.0; 9], ..info() }), None, "refused: the camera stays");
        assert_eq!(infos.camera.map(|c| c.fx), Some(900.0));
        assert_eq!(infos.receive(info()), Some(first), "back to the first");
    }

    /// A burst into a full queue: the oldest frames are dropped and counted, the queue never holds
    /// more than its size, every frame received (dropped and refused ones too) is numbered, and
    /// the PlaceMatch of a frame that is localized carries its number, not the localizer's count.
    #[test]
    fn a_burst_drops_the_oldest_frames_and_the_counters_count_them() {
        let q = Queue { items: Mutex::new(VecDeque::new()), ready: Condvar::new(), cap: 2, dropped: AtomicU64::new(0) };
        let counts = Counts::default();
        for sec in 0..12 {
            let header = Header { stamp: crate::msgs::Time { sec, nanosec: 0 }, frame_id: String::new() };
            // frame 3 has an encoding the node cannot read
            let pixels = match sec {
                3 => Err(FrameError::Encoding { encoding: "16UC1".into() }),
                _ => Ok(Pixels::Bytes { bytes: vec![], labels: None }),
            };
            receive(&q, &counts, header, pixels, Instant::now());
            assert!(q.items.lock().unwrap().len() <= 2);
        }
        let (received, unsupported, dropped) =
            (counts.received.load(Ordering::Relaxed), counts.unsupported.load(Ordering::Relaxed), q.dropped.load(Ordering::Relaxed));
        assert_eq!((received, unsupported, dropped), (12, 1, 9));
        let left: Vec<Incoming> = std::iter::from_fn(|| q.pop(Duration::from_millis(1))).collect();
        assert_eq!(left.iter().map(|f| (f.header.stamp.sec, f.number)).collect::<Vec<_>>(), [(10, 10), (11, 11)]);
        assert_eq!(received, left.len() as u64 + dropped + unsupported, "every frame received is queued, dropped or refused");
        // the localizer saw none of the dropped frames: its own count is 0 for the first it gets
        let r = FrameResult {
            frame: 0,
            id: frame_id(&left[0].header),
            answer: None,
            timestamp: Some(10.0),
            generation: 1,
            top_k: vec![],
            sequence: None,
            closure: None,
            size_changed: false,
            tracking: false,
            embedded: false,
            relative_pose: None,
            relative_pose_refused: None,
            warming_up: false,
            pose: None,
            latency: Latency::default(),
        };
        assert_eq!(place_match(&left[0].header, left[0].number, &r, 1.0).frame, 10, "frames before it, dropped ones included");
    }
}
