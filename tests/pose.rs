//! The relative pose of a verified pair (src/verify/pose.rs) on synthetic scenes of known pose:
//! random 3-D points seen by two cameras (known R, t), projected with intrinsics, pixel noise
//! and outlier matches added; and the degenerate inputs (too few matches, none, a camera that
//! only turned, points on one plane, all the same point), which give a typed error or a pose,
//! never a panic. And real frames: CamVid's daylight drive, whose poses are not published, held to
//! what any forward drive shows.

mod common;

use semlook::util::SplitMix64;
use semlook::verify::pose::{estimate, Camera, PoseError, PoseParams, RelativePose};

/// A 640 x 480 camera with a 60-degree horizontal field of view.
const CAM: Camera = Camera { fx: 554.3, fy: 554.3, cx: 320.0, cy: 240.0, width: 640, height: 480 };

/// Rotation error: largest allowed angle between the estimated and the true rotation, degrees.
const ROTATION_TOLERANCE_DEG: f64 = 1.0;
/// Translation error: largest allowed angle between the estimated and the true direction, degrees.
const DIRECTION_TOLERANCE_DEG: f64 = 3.0;

/// The rendered pairs (keypoints located to about a pixel) at baselines of about 5 m: direction
/// within this, degrees.
const RENDERED_DIRECTION_TOLERANCE_DEG: f64 = 5.0;
/// The rendered pairs at baselines of 0.6-1.4 m: rotation within this, degrees.
const SHORT_BASELINE_ROTATION_TOLERANCE_DEG: f64 = 2.5;

/// CamVid's consecutive frames (1 s apart): the translation within this of the optical axis, degrees.
const FORWARD_CONE_DEG: f64 = 30.0;
/// CamVid's consecutive frames: a turn of less than this, degrees.
const TURN_DEG: f64 = 30.0;

type M = [[f64; 3]; 3];

fn rotation(axis: [f64; 3], deg: f64) -> M {
    let n = (axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2]).sqrt();
    let [x, y, z] = axis.map(|v| v / n);
    let (s, c) = deg.to_radians().sin_cos();
    let k = 1.0 - c;
    [
        [c + x * x * k, x * y * k - z * s, x * z * k + y * s],
        [y * x * k + z * s, c + y * y * k, y * z * k - x * s],
        [z * x * k - y * s, z * y * k + x * s, c + z * z * k],
    ]
}

fn apply(r: &M, p: [f64; 3]) -> [f64; 3] {
    std::array::from_fn(|i| r[i][0] * p[0] + r[i][1] * p[1] + r[i][2] * p[2])
}

fn unit(v: [f64; 3]) -> [f64; 3] {
    let n = (v[0] * v[0] + v[1] * v[1] + v[2] * v[2]).sqrt();
    v.map(|x| x / n)
}

/// Angle between two rotations, degrees.
fn rotation_error(a: &M, b: &M) -> f64 {
    // trace(a^T b) = 1 + 2 cos(angle)
    let tr: f64 = (0..3).map(|i| (0..3).map(|k| a[k][i] * b[k][i]).sum::<f64>()).sum();
    ((tr - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees()
}

fn angle(a: [f64; 3], b: [f64; 3]) -> f64 {
    let (a, b) = (unit(a), unit(b));
    (a[0] * b[0] + a[1] * b[1] + a[2] * b[2]).clamp(-1.0, 1.0).acos().to_degrees()
}

/// Pixel position of a point in camera coordinates (None behind the camera or outside the image).
fn project(p: [f64; 3]) -> Option<[f64; 2]> {
    if p[2] <= 0.1 {
        return None;
    }
    let (u, v) = (CAM.fx * p[0] / p[2] + CAM.cx, CAM.fy * p[1] / p[2] + CAM.cy);
    (u >= 0.0 && u < CAM.width as f64 && v >= 0.0 && v < CAM.height as f64).then_some([u, v])
}

/// Normalised coordinates of a pixel, through the keypoints' units (fractions of the long side).
fn normalised(px: [f64; 2]) -> [f64; 2] {
    let long = CAM.width.max(CAM.height) as f64;
    CAM.normalise([px[0] / long, px[1] / long])
}

struct Scene {
    query: Vec<[f64; 2]>,
    reference: Vec<[f64; 2]>,
}

/// `inliers` points in front of the query camera (depth 3 to 12 m, or on the plane z = 6 with
/// `planar`) seen by a reference camera with X_ref = R X_query + t, pixel noise of `noise` px
/// (uniform, +-), and `outliers` matches between random pixels, shuffled.
fn scene(r: &M, t: [f64; 3], inliers: usize, outliers: usize, noise: f64, planar: bool, seed: u64) -> Scene {
    let mut rng = SplitMix64::new(seed);
    let mut rows = Vec::new();
    while rows.len() < inliers {
        let u = [rng.range(20.0, 620.0), rng.range(20.0, 460.0)];
        let depth = if planar { 6.0 } else { rng.range(3.0, 12.0) };
        let p = [(u[0] - CAM.cx) / CAM.fx * depth, (u[1] - CAM.cy) / CAM.fy * depth, depth];
        let q = apply(r, p);
        let Some(v) = project([q[0] + t[0], q[1] + t[1], q[2] + t[2]]) else { continue };
        let jitter = |rng: &mut SplitMix64, x: [f64; 2]| [x[0] + rng.range(-noise, noise), x[1] + rng.range(-noise, noise)];
        let (a, b) = (jitter(&mut rng, u), jitter(&mut rng, v));
        rows.push((rng.next_u64(), a, b));
    }
    for _ in 0..outliers {
        let a = [rng.range(0.0, 640.0), rng.range(0.0, 480.0)];
        let b = [rng.range(0.0, 640.0), rng.range(0.0, 480.0)];
        rows.push((rng.next_u64(), a, b));
    }
    rows.sort_by_key(|r| r.0);
    Scene { query: rows.iter().map(|r| normalised(r.1)).collect(), reference: rows.iter().map(|r| normalised(r.2)).collect() }
}

fn params() -> PoseParams {
    PoseParams::for_camera(&CAM, 7)
}

fn errors(pose: &RelativePose, r: &M, t: [f64; 3]) -> (f64, f64) {
    (rotation_error(&pose.rotation, r), angle(pose.translation_unit, t))
}

/// Poses of a robot's camera at a loop closure: turned by up to 30 degrees, moved sideways,
/// forwards and both, with 1 px of noise and 30 % outliers.
#[test]
fn the_pose_of_synthetic_scenes_is_found_within_a_degree() {
    let cases: [([f64; 3], f64, [f64; 3]); 5] = [
        ([0.0, 1.0, 0.0], 10.0, [1.0, 0.0, 0.0]),
        ([0.1, 1.0, 0.05], -25.0, [0.7, 0.05, 0.5]),
        ([1.0, 0.2, 0.0], 5.0, [0.0, 0.0, 1.0]),
        ([0.3, -1.0, 0.2], 30.0, [-0.4, 0.1, -0.8]),
        ([0.0, 0.0, 1.0], 3.0, [0.2, 0.9, 0.1]),
    ];
    let mut worst = (0.0f64, 0.0f64);
    for (k, &(axis, deg, t)) in cases.iter().enumerate() {
        let r = rotation(axis, deg);
        let s = scene(&r, t, 140, 60, 1.0, false, 100 + k as u64);
        let pose = estimate(&s.query, &s.reference, &params()).unwrap_or_else(|e| panic!("case {k}: {e}"));
        let (er, et) = errors(&pose, &r, t);
        eprintln!("case {k}: rotation error {er:.3} deg, direction error {et:.3} deg, {} of {} inliers", pose.inliers, pose.matches);
        assert!(er < ROTATION_TOLERANCE_DEG, "case {k}: rotation off by {er} deg");
        assert!(et < DIRECTION_TOLERANCE_DEG, "case {k}: translation direction off by {et} deg");
        // the true inliers are found, the outliers mostly not
        assert!(pose.inliers >= 130 && pose.inliers <= 150, "case {k}: {} inliers of 140 true", pose.inliers);
        assert_eq!(pose.matches, 200);
        // the reported forms agree: the quaternion's angle, unit length
        let n = pose.translation_unit.iter().map(|v| v * v).sum::<f64>().sqrt();
        assert!((n - 1.0).abs() < 1e-9);
        assert!((pose.rotation_deg - 2.0 * pose.quaternion[3].clamp(-1.0, 1.0).acos().to_degrees()).abs() < 1e-6);
        assert!((pose.rotation_deg - deg.abs()).abs() < ROTATION_TOLERANCE_DEG);
        worst = (worst.0.max(er), worst.1.max(et));
    }
    eprintln!("worst: rotation {:.3} deg, direction {:.3} deg", worst.0, worst.1);
}

/// The same seed gives the same pose; without noise the pose is exact.
#[test]
fn the_estimate_is_deterministic_and_exact_without_noise() {
    let r = rotation([0.2, 1.0, 0.0], 15.0);
    let t = [0.6, 0.0, 0.8];
    let s = scene(&r, t, 60, 0, 0.0, false, 3);
    let a = estimate(&s.query, &s.reference, &params()).unwrap();
    let b = estimate(&s.query, &s.reference, &params()).unwrap();
    assert_eq!(a, b);
    let (er, et) = errors(&a, &r, t);
    assert!(er < 1e-6 && et < 1e-6, "{er} {et}");
    assert_eq!(a.inliers, 60);
}

#[test]
fn too_few_or_no_matches_are_a_typed_error() {
    let r = rotation([0.0, 1.0, 0.0], 10.0);
    let s = scene(&r, [1.0, 0.0, 0.0], 7, 0, 0.5, false, 5);
    assert!(matches!(estimate(&s.query, &s.reference, &params()), Err(PoseError::TooFewMatches { have: 7, .. })));
    assert!(matches!(estimate(&[], &[], &params()), Err(PoseError::TooFewMatches { have: 0, .. })));
    // sides of different lengths: the shorter counts
    assert!(matches!(estimate(&s.query, &s.reference[..3], &params()), Err(PoseError::TooFewMatches { have: 3, .. })));
}

/// A camera that turned on the spot: every match is explained by the rotation, the translation
/// is not observable, and the estimate says so rather than making a direction up.
#[test]
fn a_pure_rotation_is_refused_as_without_parallax() {
    for (k, deg) in [8.0, 20.0].into_iter().enumerate() {
        let r = rotation([0.1, 1.0, 0.0], deg);
        let s = scene(&r, [0.0, 0.0, 0.0], 120, 30, 0.5, false, 20 + k as u64);
        match estimate(&s.query, &s.reference, &params()) {
            Err(PoseError::NoParallax { inliers, rotation_inliers }) => assert!(rotation_inliers * 10 >= inliers * 9),
            other => panic!("{deg} deg on the spot: {other:?}"),
        }
    }
}

/// Nothing to estimate from: random matches, all matches the same point, NaN positions, and
/// points on one plane (two poses explain them alike: the five-point solver's two-fold
/// ambiguity): typed errors, never a panic; a plane with a fifth of the points off it is no
/// longer ambiguous.
#[test]
fn degenerate_inputs_give_an_error_or_a_pose_never_a_panic() {
    let p = params();
    let r = rotation([0.0, 1.0, 0.0], 12.0);
    let noise = scene(&r, [1.0, 0.0, 0.0], 0, 80, 0.0, false, 9);
    assert!(matches!(estimate(&noise.query, &noise.reference, &p), Err(PoseError::NoModel { .. })), "random matches");
    let same = vec![[0.1, -0.05]; 40];
    assert!(estimate(&same, &same, &p).is_err(), "one point 40 times");
    let mut nan = scene(&r, [1.0, 0.0, 0.0], 40, 0, 0.5, false, 10);
    nan.query[3] = [f64::NAN, 0.0];
    assert!(estimate(&nan.query, &nan.reference, &p).is_err(), "a NaN position");
    let t = [1.0, 0.1, 0.3];
    for seed in 0..4 {
        let plane = scene(&r, t, 100, 20, 0.5, true, 30 + seed);
        match estimate(&plane.query, &plane.reference, &p) {
            Err(PoseError::Planar { inliers, plane_inliers }) => assert!(plane_inliers * 10 >= inliers * 9),
            other => panic!("seed {seed}: points on one plane gave {other:?}"),
        }
        // a fifth of the points off the plane: the pose again
        let mut off = scene(&r, t, 30, 0, 0.5, false, 40 + seed);
        off.query.extend(&plane.query);
        off.reference.extend(&plane.reference);
        let pose = estimate(&off.query, &off.reference, &p).unwrap_or_else(|e| panic!("seed {seed}, a plane and 30 points off it: {e}"));
        let (er, et) = errors(&pose, &r, t);
        eprintln!("plane and 30 points off it, seed {seed}: rotation error {er:.3} deg, direction error {et:.3} deg");
        assert!(er < ROTATION_TOLERANCE_DEG && et < DIRECTION_TOLERANCE_DEG, "seed {seed}: {er} {et}");
    }
}

/// Camera files: TOML or JSON; missing, malformed or implausible ones are errors naming the file
/// and the problem.
#[test]
fn camera_files_are_read_and_bad_ones_named() {
    let dir = tempfile::tempdir().unwrap();
    let toml = dir.path().join("cam.toml");
    std::fs::write(&toml, "fx = 554.3\nfy = 554.3\ncx = 320\ncy = 240\nwidth = 640\nheight = 480\n").unwrap();
    assert_eq!(Camera::load(&toml).unwrap(), CAM);
    let json = dir.path().join("cam.json");
    std::fs::write(&json, r#"{"fx": 554.3, "fy": 554.3, "cx": 320, "cy": 240, "width": 640, "height": 480}"#).unwrap();
    assert_eq!(Camera::load(&json).unwrap(), CAM);
    let err = |name: &str, text: &str| -> String {
        let path = dir.path().join(name);
        std::fs::write(&path, text).unwrap();
        let e = Camera::load(&path).unwrap_err().to_string();
        assert!(e.contains(name), "{e}");
        e
    };
    assert!(err("a.json", r#"{"fx": 554.3, "fy": 554.3, "cx": 320, "cy": 240, "width": 640}"#).contains("height"));
    assert!(err("b.toml", "fx = -5\nfy = 1\ncx = 1\ncy = 1\nwidth = 640\nheight = 480\n").contains("fx"));
    assert!(err("c.toml", "fx = 500\nfy = 500\ncx = 900\ncy = 1\nwidth = 640\nheight = 480\n").contains("cx"));
    assert!(err("d.json", "not json").contains("d.json"));
    assert!(err("e.toml", "fx = 500\nfy = 500\ncx = 1\ncy = 1\nwidth = 640\nheight = 480\nk1 = 0.1\n").contains("k1"));
    let missing = dir.path().join("missing.toml");
    assert!(Camera::load(&missing).unwrap_err().to_string().contains("missing.toml"));
    assert!(CAM.fits(1280, 960) && CAM.fits(320, 240) && !CAM.fits(640, 360));
}

/// A rendered pair of the synthetic street (`synth` knows its cameras: a pinhole of
/// `hfov_deg`, principal point at the centre, each frame's position and optical axis, no roll):
/// a query frame (traversal 1, jittered sideways, along and in yaw and pitch) against the
/// reference frame of its place, XFeat keypoints matched as verification matches them, against
/// the renderer's relative pose. Measured (seed 21): against the next place (baselines of
/// 4.8-6.3 m) rotation errors 0.16-0.66 degrees and direction errors 0.3-3.1 degrees; against the
/// same place (baselines of 0.6-1.4 m, the scene 5-100 m away) rotation errors 0.2-1.9 degrees
/// but direction errors of 10-21 degrees: a short baseline against deep scenes leaves the
/// direction poorly constrained. Held to: rotation within 1 degree and direction within
/// [`RENDERED_DIRECTION_TOLERANCE_DEG`] at the next place, rotation within
/// [`SHORT_BASELINE_ROTATION_TOLERANCE_DEG`] at the same place.
#[test]
fn the_pose_of_a_rendered_pair_is_the_renderers() {
    use semlook::appearance::{verification_keypoints, AppearanceModel};
    use semlook::config::{AppearanceConfig, ModelPaths, Sampling, VerificationConfig};
    use semlook::verify::pose::pair_pose;
    use semlook::verify::{pair_matches, VerifyParams};
    use semlook_cli::tools::synth::{condition::Condition, render_frame, Scene, SynthConfig};
    let model = match AppearanceModel::load(&AppearanceConfig { sampling: Sampling::Keypoints, ..Default::default() }, &ModelPaths::default()) {
        Ok(Some(m)) => m,
        other => {
            let why = other.err().map_or("no model".to_string(), |e| e.to_string());
            if std::env::var("REQUIRE_MODELS").is_ok_and(|v| v == "1") {
                panic!("XFeat weights (setup.sh): {why}");
            }
            eprintln!("skipped: XFeat weights (setup.sh): {why}");
            return;
        }
    };
    let cfg = SynthConfig { seed: 21, places: 10, width: 640, height: 480, ..Default::default() };
    let f = (cfg.width as f64 / 2.0) / (cfg.hfov_deg.to_radians() / 2.0).tan();
    // the renderer's pixel (i, j) is the ray through (i + 0.5, j + 0.5) from the image centre;
    // keypoint positions count pixels from their centres
    let cam = Camera { fx: f, fy: f, cx: 319.5, cy: 239.5, width: 640, height: 480 };
    let scene = Scene::new(&cfg);
    let table = semlook::classes::ClassTable::cityscapes();
    let keypoints = |frame: &semlook_cli::tools::synth::RenderedFrame| {
        let rgb = image::RgbImage::from_raw(640, 480, frame.rgb.clone()).unwrap();
        let labels = semlook::input::LabelMap::new(640, 480, frame.labels.clone(), &table).unwrap();
        verification_keypoints(&model.keypoints(&rgb).unwrap(), 1024, &labels, 640)
    };
    // the world-to-camera matrix (rows: right, down, forward) of a frame
    let frame_of = |p: &semlook::dataset::Pose| -> M {
        let fwd = p.forward;
        let yaw = fwd[0].atan2(fwd[2]);
        let right = [yaw.cos(), 0.0, -yaw.sin()];
        let up = [fwd[1] * right[2] - fwd[2] * right[1], fwd[2] * right[0] - fwd[0] * right[2], fwd[0] * right[1] - fwd[1] * right[0]];
        [right, up.map(|v| -v), fwd]
    };
    let vp = VerifyParams::new(&VerificationConfig::default());
    let mut seen = 0;
    for (place, step) in [(2, 0), (4, 0), (6, 0), (2, 1), (5, 1), (7, 1)] {
        let (q, r) = (render_frame(&cfg, &scene, &[], 1, place, Condition::Day), render_frame(&cfg, &scene, &[], 0, place + step, Condition::Day));
        let (mq, mr) = (frame_of(&q.pose), frame_of(&r.pose));
        // X_ref = Mr (X_w - p_r) = Mr Mq^T X_q + Mr (p_q - p_r)
        let rot: M = std::array::from_fn(|i| std::array::from_fn(|j| (0..3).map(|k| mr[i][k] * mq[j][k]).sum()));
        let d: [f64; 3] = std::array::from_fn(|i| q.pose.position[i] - r.pose.position[i]);
        let t = apply(&mr, d);
        let (kq, kr) = (keypoints(&q), keypoints(&r));
        let m = pair_matches(&vp, kq.as_ref(), kr.as_ref()).unwrap();
        match pair_pose(&cam, kq.as_ref(), kr.as_ref(), &m, &PoseParams::for_camera(&cam, 3)) {
            Ok(pose) => {
                let (er, et) = errors(&pose, &rot, t);
                eprintln!(
                    "place {place} against {}: true rotation {:.2} deg, baseline {:.2} m; rotation error {er:.3} deg, direction error {et:.3} deg, {} of {} matches",
                    place + step,
                    rotation_error(&rot, &rotation([0.0, 1.0, 0.0], 0.0)),
                    (t[0] * t[0] + t[1] * t[1] + t[2] * t[2]).sqrt(),
                    pose.inliers,
                    pose.matches
                );
                match step {
                    0 => assert!(er < SHORT_BASELINE_ROTATION_TOLERANCE_DEG, "place {place}: rotation off by {er} deg"),
                    _ => {
                        assert!(er < ROTATION_TOLERANCE_DEG, "place {place}: rotation off by {er} deg");
                        assert!(et < RENDERED_DIRECTION_TOLERANCE_DEG, "place {place}: translation direction off by {et} deg");
                    }
                }
                seen += 1;
            }
            Err(e) => eprintln!("place {place}: no pose ({e}; {} matches)", m.len()),
        }
    }
    assert!(seen >= 5, "a pose for most rendered pairs");
}

/// Real frames: CamVid's daylight drive (`Seq05VD_*`, 480 x 360, frames 1 s apart) from a car that
/// drives forward, turns at corners and stops at lights. No poses ship with it, so the check is what
/// a forward drive must show from a frame to the next: the later frame's camera ahead of the
/// earlier one's (the translation within [`FORWARD_CONE_DEG`] of the optical axis, forward) and a
/// turn of less than [`TURN_DEG`], for most of the pairs that get a pose. The intrinsics are
/// nominal (a 50-degree horizontal field of view, the principal point at the centre): the forward
/// direction does not hinge on the focal length. Pairs of a stopped car are refused as without
/// parallax, which is right.
/// CamVid's daylight drive, read for the real-frame tests: the folder, XFeat, the nominal camera
/// (a 50-degree horizontal field of view, the principal point at the centre) and the verification
/// keypoints of a frame. `None` (after a printed skip) without ../shared or the XFeat weights.
struct Drive {
    dir: std::path::PathBuf,
    model: semlook::appearance::AppearanceModel,
    cam: Camera,
}

impl Drive {
    fn open() -> Option<Drive> {
        use semlook::appearance::AppearanceModel;
        use semlook::config::{AppearanceConfig, ModelPaths, Sampling};
        let dir = common::shared_or_required("data/camvid-test/images")?;
        let model = match AppearanceModel::load(&AppearanceConfig { sampling: Sampling::Keypoints, ..Default::default() }, &ModelPaths::default()) {
            Ok(Some(m)) => m,
            other => {
                common::skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (setup.sh): {:?}", other.err()));
                return None;
            }
        };
        let f = 240.0 / 25f64.to_radians().tan();
        Some(Drive { dir, model, cam: Camera { fx: f, fy: f, cx: 239.5, cy: 179.5, width: 480, height: 360 } })
    }

    fn keypoints(&self, name: &str) -> semlook::descriptors::keypoints::ImageKeypoints {
        let table = semlook::classes::ClassTable::cityscapes();
        let rgb = semlook::input::load_rgb(&self.dir.join(name)).unwrap();
        assert_eq!(rgb.dimensions(), (480, 360), "{name}");
        let labels = semlook::input::LabelMap::new(480, 360, vec![2; 480 * 360], &table).unwrap();
        semlook::appearance::verification_keypoints(&self.model.keypoints(&rgb).unwrap(), 1024, &labels, 480)
    }

    /// The pose of frame `later` relative to frame `earlier`.
    fn pose(
        &self,
        later: &semlook::descriptors::keypoints::ImageKeypoints,
        earlier: &semlook::descriptors::keypoints::ImageKeypoints,
    ) -> Result<RelativePose, PoseError> {
        use semlook::config::VerificationConfig;
        use semlook::verify::pose::pair_pose;
        use semlook::verify::{pair_matches, VerifyParams};
        let vp = VerifyParams::new(&VerificationConfig::default());
        let m = pair_matches(&vp, later.as_ref(), earlier.as_ref()).unwrap();
        pair_pose(&self.cam, later.as_ref(), earlier.as_ref(), &m, &PoseParams::for_camera(&self.cam, 5))
    }
}

#[test]
fn consecutive_frames_of_a_real_drive_move_forward() {
    let Some(drive) = Drive::open() else { return };
    let mut names: Vec<String> =
        std::fs::read_dir(&drive.dir).unwrap().filter_map(|e| e.ok()?.file_name().into_string().ok()).filter(|n| n.starts_with("Seq05VD_")).collect();
    names.sort();
    assert!(names.len() > 40, "CamVid's daylight drive has 171 frames: {} found", names.len());
    let names = &names[..41];
    let (mut posed, mut forward, mut refused) = (0, 0, 0);
    let mut earlier = drive.keypoints(&names[0]);
    for pair in names.windows(2) {
        let later = drive.keypoints(&pair[1]);
        match drive.pose(&later, &earlier) {
            Ok(pose) => {
                let off_axis = angle(pose.translation_unit, [0.0, 0.0, 1.0]);
                let ok = off_axis < FORWARD_CONE_DEG && pose.rotation_deg < TURN_DEG;
                eprintln!(
                    "{} -> {}: turned {:.1} deg, moved {off_axis:.1} deg off the axis, {} of {} matches{}",
                    pair[0],
                    pair[1],
                    pose.rotation_deg,
                    pose.inliers,
                    pose.matches,
                    if ok { "" } else { "  <- not forward" }
                );
                posed += 1;
                forward += ok as usize;
            }
            Err(e) => {
                eprintln!("{} -> {}: no pose ({e})", pair[0], pair[1]);
                refused += 1;
            }
        }
        earlier = later;
    }
    eprintln!("{posed} of 40 pairs posed ({refused} refused), {forward} of them forward");
    assert!(posed >= 20, "a pose for most pairs of a moving car: {posed} of 40");
    assert!(forward as f64 >= 0.9 * posed as f64, "forward motion in most posed pairs: {forward} of {posed}");
}

/// The car waits at a red light from CamVid's frame f01890 on: the frames of the stop are nearly the
/// same picture, so the translation between them is not observable and no pose may go out (issue 57:
/// f01920 against f01890 gave a translation straight down the image's y axis from 153 inliers, sent
/// as a loop-closure constraint). Every pair of the stop is refused as without parallax.
#[test]
fn a_stopped_car_gets_no_pose() {
    let Some(drive) = Drive::open() else { return };
    let stop = ["Seq05VD_f01890.png", "Seq05VD_f01920.png", "Seq05VD_f01950.png"];
    let kp: Vec<_> = stop.iter().map(|n| drive.keypoints(n)).collect();
    for (i, j) in [(1, 0), (2, 1), (2, 0)] {
        match drive.pose(&kp[i], &kp[j]) {
            Err(PoseError::NoParallax { inliers, rotation_inliers }) => {
                eprintln!("{} -> {}: refused, {rotation_inliers} of {inliers} inliers explained by a rotation", stop[j], stop[i])
            }
            other => panic!("{} -> {}: a stopped car must get no pose (no parallax), got {other:?}", stop[j], stop[i]),
        }
    }
}
