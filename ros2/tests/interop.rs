//! The node against a real ROS 2 peer: rclpy (Fast DDS, ROS 2 kilted from PyPI wheels, set up by
//! setup.sh in `.venv-ros/` with semlook_msgs built for it) publishes real photos to
//! `semlook_node` (RustDDS) and receives its matches, all on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE
//! = LOCALHOST, a domain of the test's own). Every frame is answered, and the answers equal
//! `semlook query` (single frame) and `semlook localize` (sequence) on the same frames. Then the
//! robustness cases: an unsupported encoding, a corrupt JPEG, the peer vanishing and another
//! coming, the map growing on disk, and a burst faster than the node serves. The map stores poses
//! (`map build --poses`): each frame's PoseStamped is the pose of the place it was matched to. The
//! node takes its camera's intrinsics from a `sensor_msgs/CameraInfo` topic (`camera_info_topic`)
//! the peer publishes beside its frames: the accepted matches carry the relative pose `semlook
//! localize --camera` gives with the same intrinsics.

use std::io::Read;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

fn repo() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_path_buf()
}

fn required() -> bool {
    std::env::var_os("CI").is_some() || std::env::var("REQUIRE_ROS").is_ok_and(|v| v == "1")
}

/// Skips (printing why, on a SKIPPED line) or, under CI or REQUIRE_ROS=1, fails.
fn skip(reason: &str) {
    if required() {
        panic!("required here (CI or REQUIRE_ROS=1) but missing: {reason}");
    }
    eprintln!("SKIPPED (interop): {reason}");
}

/// The `semlook` command line of this build (built with the workspace's tests).
fn semlook_bin() -> Option<PathBuf> {
    let exe = std::env::current_exe().ok()?;
    let dir = exe.parent()?.parent()?;
    let bin = dir.join("semlook");
    bin.exists().then_some(bin)
}

/// The environment of both DDS sides: this host only, a domain no other test run uses.
fn ros_env(cmd: &mut Command, domain: u16) {
    cmd.env("ROS_DOMAIN_ID", domain.to_string()).env("ROS_AUTOMATIC_DISCOVERY_RANGE", "LOCALHOST").env("ROS_DISTRO", "kilted");
    if std::env::var_os("SEMLOOK_MODELS").is_none() {
        cmd.env("SEMLOOK_MODELS", repo().join(".semlook"));
    }
}

struct Node {
    child: Child,
}

impl Node {
    /// Stops the node with SIGINT (Ctrl-C) and returns its stdout (the summary line) and stderr.
    fn stop(mut self) -> (String, String) {
        let _ = Command::new("kill").args(["-INT", &self.child.id().to_string()]).status();
        let t = Instant::now();
        while t.elapsed() < Duration::from_secs(30) {
            if let Ok(Some(_)) = self.child.try_wait() {
                break;
            }
            std::thread::sleep(Duration::from_millis(100));
        }
        let _ = self.child.kill();
        let _ = self.child.wait();
        let (mut out, mut err) = (String::new(), String::new());
        self.child.stdout.take().unwrap().read_to_string(&mut out).unwrap();
        self.child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
        (out, err)
    }
}

impl Drop for Node {
    fn drop(&mut self) {
        let _ = self.child.kill();
    }
}

/// Runs the rclpy peer on `plan`, returns its record.
fn peer(venv: &Path, plan: &serde_json::Value, dir: &Path, name: &str, domain: u16) -> serde_json::Value {
    let (plan_path, out_path) = (dir.join(format!("{name}-plan.json")), dir.join(format!("{name}-out.json")));
    std::fs::write(&plan_path, serde_json::to_vec(plan).unwrap()).unwrap();
    let msgs = venv.join("semlook_msgs");
    let mut cmd = Command::new(venv.join("bin/python"));
    cmd.arg(Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/peer.py")).arg(&plan_path).arg(&out_path);
    cmd.env("PYTHONPATH", msgs.join("python")).env("LD_LIBRARY_PATH", msgs.join("lib"));
    ros_env(&mut cmd, domain);
    let out = cmd.output().unwrap();
    assert!(out.status.success(), "peer {name} failed:\n{}", String::from_utf8_lossy(&out.stderr));
    serde_json::from_slice(&std::fs::read(&out_path).unwrap()).unwrap()
}

/// A frame of the plan: `kind` of the photo `file`, at second `sec`.
fn raw_frame(dir: &Path, file: &Path, kind: &str, sec: i64) -> serde_json::Value {
    // decoded as semlook decodes the file (jpeg-decoder at full scale), so the pixels are the ones
    // `semlook query` encodes
    let (rgb, (w, h)) = semlook::input::load_rgb_at_least(file, |full| full).unwrap();
    let bytes: Vec<u8> = match kind {
        "rgb8" => rgb.into_raw(),
        "bgr8" => rgb.pixels().flat_map(|p| [p[2], p[1], p[0]]).collect(),
        "16UC1" => vec![0; (w * h * 2) as usize],
        _ => unreachable!(),
    };
    let path = dir.join(format!("{sec}-{kind}.raw"));
    std::fs::write(&path, bytes).unwrap();
    serde_json::json!({ "kind": kind, "file": path, "width": w, "height": h, "sec": sec, "nanosec": 0 })
}

fn compressed_frame(file: &Path, kind: &str, sec: i64) -> serde_json::Value {
    serde_json::json!({ "kind": kind, "file": file, "sec": sec, "nanosec": 0 })
}

#[test]
fn the_node_answers_a_real_ros2_peer() {
    let venv = repo().join(".venv-ros");
    if !venv.join("semlook_msgs/python/semlook_msgs/__init__.py").exists() {
        return skip(&format!("no ROS 2 venv with semlook_msgs at {} (run setup.sh)", venv.display()));
    }
    let data = repo().join("../shared/data/real-vpr/gardenspoint-day-night-mini");
    if !data.exists() {
        return skip(&format!("{} is absent", data.display()));
    }
    let Some(semlook) = semlook_bin() else { return skip("the semlook binary is not built beside this test (cargo test --workspace builds it)") };
    if semlook::nn::onnx::find_model(semlook::networks::xfeat::XFEAT_WEIGHTS, Some(&repo().join(".semlook/xfeat.pt")), "XFeat").is_err() {
        return skip("no XFeat weights in .semlook (run setup.sh)");
    }
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map");
    let run = |args: &[&str]| {
        let mut cmd = Command::new(&semlook);
        cmd.args(args).arg("-q");
        ros_env(&mut cmd, 0);
        let out = cmd.output().unwrap();
        assert!(out.status.success(), "semlook {args:?}:\n{}", String::from_utf8_lossy(&out.stderr));
        String::from_utf8(out.stdout).unwrap()
    };
    let refs = data.join("ref");
    let queries = data.join("query");
    // a pose per place (world-to-camera quaternion and camera centre, as CMU Seasons lists them):
    // the camera turns about its y axis and moves along the route
    let mut ref_names: Vec<String> = std::fs::read_dir(&refs).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    ref_names.sort();
    let pose_of = |i: usize| {
        let a = 0.3 * i as f64;
        let q_wc = [(a / 2.0).cos(), 0.0, (a / 2.0).sin(), 0.0]; // w x y z
        let centre = [2.5 * i as f64, -1.0, 0.5 * i as f64];
        (q_wc, centre)
    };
    let poses_file = dir.path().join("poses.txt");
    let lines: Vec<String> = ref_names
        .iter()
        .enumerate()
        .map(|(i, n)| {
            let (q, c) = pose_of(i);
            format!("{n} {} {} {} {} {} {} {}", q[0], q[1], q[2], q[3], c[0], c[1], c[2])
        })
        .collect();
    std::fs::write(&poses_file, lines.join("\n") + "\n").unwrap();
    // what the node must publish for place `id`: the camera centre and the camera-to-world
    // rotation (the conjugate), x y z w
    let expected_pose = |id: &str| -> Option<([f64; 3], [f64; 4])> {
        let i = ref_names.iter().position(|n| n.strip_suffix(".jpg") == Some(id))?;
        let (q, c) = pose_of(i);
        Some((c, [-q[1], -q[2], -q[3], q[0]]))
    };
    run(&[
        "--backend",
        "cpu",
        "map",
        "build",
        "--images",
        refs.to_str().unwrap(),
        "--poses",
        poses_file.to_str().unwrap(),
        "--map",
        map.to_str().unwrap(),
    ]);
    // what the command line answers for the same frames
    let query: serde_json::Value =
        serde_json::from_str(&run(&["--backend", "cpu", "query", "--map", map.to_str().unwrap(), "--images", queries.to_str().unwrap(), "--json"]))
            .unwrap();
    let localize: Vec<serde_json::Value> =
        run(&["--backend", "cpu", "localize", "--map", map.to_str().unwrap(), "--images", queries.to_str().unwrap(), "--json"])
            .lines()
            .map(|l| serde_json::from_str(l).unwrap())
            .filter(|v: &serde_json::Value| v.get("frame").is_some())
            .collect();
    // the camera of the photos (960x540; a plausible focal length, the principal point at the
    // centre): the peer publishes it as CameraInfo, `semlook localize` reads it from a file
    let (fx, cx, cy, width, height) = (700.0, 479.5, 269.5, 960, 540);
    let camera_file = dir.path().join("camera.toml");
    std::fs::write(&camera_file, format!("fx = {fx}\nfy = {fx}\ncx = {cx}\ncy = {cy}\nwidth = {width}\nheight = {height}\n")).unwrap();
    let camera_info = serde_json::json!({
        "topic": "/camera/camera_info",
        "width": width,
        "height": height,
        "k": [fx, 0.0, cx, 0.0, fx, cy, 0.0, 0.0, 1.0],
        // a distortion the relative pose ignores: the node says so, once
        "distortion_model": "plumb_bob",
        "d": [-0.05, 0.01, 0.0, 0.0, 0.0],
    });
    let localize_camera: Vec<serde_json::Value> = run(&[
        "--backend",
        "cpu",
        "localize",
        "--map",
        map.to_str().unwrap(),
        "--images",
        queries.to_str().unwrap(),
        "--camera",
        camera_file.to_str().unwrap(),
        "--json",
    ])
    .lines()
    .map(|l| serde_json::from_str(l).unwrap())
    .filter(|v: &serde_json::Value| v.get("frame").is_some())
    .collect();
    let domain = 100 + (std::process::id() % 100) as u16;
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_semlook_node"));
    cmd.args(["--ros-args", "-p", &format!("map:={}", map.display()), "-p", "backend:=cpu", "-p", "queue_size:=2", "-p", "map_refresh_s:=0.5"]);
    cmd.args(["-p", "camera_info_topic:=/camera/camera_info"]);
    ros_env(&mut cmd, domain);

    // phase 1: the ten photos, alternating CompressedImage (jpeg) and Image (rgb8, bgr8), each
    // answered before the next; then an unsupported encoding and a corrupt JPEG, not answered
    let mut files: Vec<PathBuf> = std::fs::read_dir(&queries).unwrap().flatten().map(|e| e.path()).collect();
    files.sort();
    let mut frames: Vec<serde_json::Value> = files
        .iter()
        .enumerate()
        .map(|(i, f)| match i % 3 {
            0 => compressed_frame(f, "jpeg", 100 + i as i64),
            1 => raw_frame(dir.path(), f, "rgb8", 100 + i as i64),
            _ => raw_frame(dir.path(), f, "bgr8", 100 + i as i64),
        })
        .collect();
    let mut bad = raw_frame(dir.path(), &files[0], "16UC1", 200);
    bad["answered"] = false.into();
    let corrupt = dir.path().join("corrupt.jpg");
    let mut bytes = std::fs::read(&files[0]).unwrap();
    bytes.truncate(bytes.len() / 3);
    std::fs::write(&corrupt, &bytes).unwrap();
    let mut broken = compressed_frame(&corrupt, "jpeg", 201);
    broken["answered"] = false.into();
    frames.push(bad);
    frames.push(broken);
    // the first peer is up before the node (a camera already publishing): it sends its first
    // frame as soon as it sees the node's subscription, which must not lose it (3 of 4 runs did
    // before the node let discovery settle before subscribing)
    let plan = serde_json::json!({ "frames": frames, "wait": true, "expect": 10, "timeout": 180, "linger": 2.0, "camera_info": camera_info });
    let (one, node) = std::thread::scope(|s| {
        let first = s.spawn(|| peer(&venv, &plan, dir.path(), "one", domain));
        std::thread::sleep(Duration::from_secs(3));
        let mut node = Node { child: cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap() };
        std::thread::sleep(Duration::from_secs(2));
        if let Ok(Some(status)) = node.child.try_wait() {
            let (_, err) = node.stop();
            panic!("the node stopped at once ({status}):\n{err}");
        }
        (first.join().unwrap(), node)
    });
    let matches = one["matches"].as_array().unwrap();
    assert_eq!(matches.len(), 10, "every photo answered once, the two bad frames not: {matches:?}");
    for (i, m) in matches.iter().enumerate() {
        assert_eq!(m["sec"], 100 + i as i64, "in order, under the frame's own stamp");
        assert_eq!(m["frame"], i as u64, "frames received before it");
        let q = &query["queries"][i];
        let want_ids: Vec<&str> = q["top_k"].as_array().unwrap().iter().map(|c| c["reference"].as_str().unwrap()).collect();
        let got_ids: Vec<&str> = m["top_ids"].as_array().unwrap().iter().map(|v| v.as_str().unwrap()).collect();
        assert_eq!(got_ids, want_ids, "frame {i}: the single-frame ranking of `semlook query`");
        for (g, w) in m["top_scores"].as_array().unwrap().iter().zip(q["top_k"].as_array().unwrap()) {
            let (g, w) = (g.as_f64().unwrap(), w["score"].as_f64().unwrap());
            assert!((g - w).abs() <= 1e-5 * (1.0 + w.abs()), "frame {i}: score {g} against {w}");
        }
        let l = &localize[i];
        assert_eq!(m["sequence_id"].as_str().unwrap(), l["sequence"]["id"].as_str().unwrap_or(""), "frame {i}: the sequence of `semlook localize`");
        assert_eq!(m["accepted"], l["sequence"]["accepted"].as_bool().unwrap_or(false), "frame {i}");
        // the intrinsics came on the CameraInfo topic (each frame's just before it): the relative
        // pose is the one `semlook localize --camera` estimates with them from a file
        let want = &localize_camera[i]["relative_pose"];
        assert_eq!(m["has_relative_pose"], !want.is_null(), "frame {i}: {m} against {want}");
        if !want.is_null() {
            let (got, deg) = (m["relative_rotation_deg"].as_f64().unwrap(), want["rotation_deg"].as_f64().unwrap());
            assert!((got - deg).abs() < 1e-6, "frame {i}: rotation {got} against {deg} deg");
            assert_eq!(m["pose_inliers"].as_u64(), want["inliers"].as_u64(), "frame {i}");
        } else {
            assert_eq!(m["pose_inliers"], -1, "frame {i}");
        }
    }
    let posed = matches.iter().filter(|m| m["has_relative_pose"] == true).count();
    assert!(posed > 0, "accepted matches carry a relative pose once CameraInfo came: {matches:?}");
    // every answer's place has a pose: one PoseStamped per frame, under the frame's stamp, in the
    // map frame, the pose of the place the match names (and the one `semlook localize` gives)
    let poses = one["poses"].as_array().unwrap();
    assert_eq!(poses.len(), 10, "a pose per answered frame: {poses:?}");
    let close = |a: &serde_json::Value, b: &[f64]| a.as_array().unwrap().iter().zip(b).all(|(a, b)| (a.as_f64().unwrap() - b).abs() < 1e-9);
    for (i, (m, p)) in matches.iter().zip(poses).enumerate() {
        assert_eq!((&p["sec"], p["frame_id"].as_str()), (&m["sec"], Some("map")), "frame {i}: {p}");
        let (c, q) = expected_pose(m["place_id"].as_str().unwrap()).unwrap_or_else(|| panic!("frame {i}: place {} has no pose", m["place_id"]));
        assert!(close(&p["position"], &c) && close(&p["orientation"], &q), "frame {i} matched {}: {p} against {c:?} {q:?}", m["place_id"]);
        let l = &localize[i]["pose"];
        assert!(close(&l["position"], &c) && close(&l["orientation"], &q), "frame {i}: `semlook localize` gives {l}");
    }
    // phase 2: the map grows on disk (another writer adds the query photos as places, q00...)
    let g0 = matches[0]["map_generation"].as_u64().unwrap();
    let added = dir.path().join("added");
    std::fs::create_dir(&added).unwrap();
    for f in &files {
        std::fs::copy(f, added.join(format!("q{}", f.file_name().unwrap().to_string_lossy()))).unwrap();
    }
    run(&["--backend", "cpu", "map", "add", "--images", added.to_str().unwrap(), "--map", map.to_str().unwrap()]);
    std::thread::sleep(Duration::from_millis(1500));
    // the first peer has gone; a new one comes
    let frames: Vec<serde_json::Value> = files[..3].iter().enumerate().map(|(i, f)| compressed_frame(f, "jpeg", 300 + i as i64)).collect();
    let two = peer(&venv, &serde_json::json!({ "frames": frames, "wait": true, "expect": 3, "timeout": 120 }), dir.path(), "two", domain);
    let m2 = two["matches"].as_array().unwrap();
    assert_eq!(m2.len(), 3, "a new peer is answered: {m2:?}");
    assert!(m2.iter().all(|m| m["map_generation"].as_u64().unwrap() > g0), "the new generation: {m2:?}");
    // the query photo itself is now a place: it is its own best match
    assert_eq!(m2[0]["top_ids"][0].as_str().unwrap(), "q00", "{:?}", m2[0]["top_ids"]);
    // the added places have no pose: a frame answered by one gets no PoseStamped
    let posed = m2.iter().filter(|m| expected_pose(m["place_id"].as_str().unwrap()).is_some()).count();
    assert_eq!(two["poses"].as_array().unwrap().len(), posed, "poses only for places that have one: {m2:?} {}", two["poses"]);
    // phase 3: a burst of 30 frames, faster than the node localizes
    let frames: Vec<serde_json::Value> = (0..30).map(|i| compressed_frame(&files[i % files.len()], "jpeg", 400 + i as i64)).collect();
    let three = peer(
        &venv,
        &serde_json::json!({ "frames": frames, "wait": false, "expect": 0, "timeout": 120, "linger": 20.0 }),
        dir.path(),
        "three",
        domain,
    );
    let m3 = three["matches"].as_array().unwrap();
    // a frame's number counts every frame received before it, dropped ones included: the 12 of
    // phase 1 (two of them refused), the 3 of phase 2, then the burst's own
    for m in m3 {
        assert_eq!(m["frame"].as_i64().unwrap(), 15 + (m["sec"].as_i64().unwrap() - 400), "{m}");
    }
    let (out, err) = node.stop();
    let summary: serde_json::Value =
        out.lines().find_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).unwrap_or_else(|| panic!("no summary:\n{out}\n{err}"));
    let s = &summary["summary"];
    assert!(s["dropped"].as_u64().unwrap() > 0, "the burst dropped frames: {s}\n{err}");
    assert!(!m3.is_empty() && m3.len() < 30, "{} of the burst answered", m3.len());
    assert_eq!(s["unsupported"].as_u64().unwrap(), 1, "{s}");
    assert_eq!(s["localizer"]["refused"].as_u64().unwrap(), 1, "the corrupt JPEG: {s}");
    assert!(err.contains("16UC1") && err.contains("not supported"), "{err}");
    // the camera was set once (every frame of phase 1 had the same CameraInfo), its distortion
    // warned of once
    assert_eq!(err.matches("camera intrinsics from /camera/camera_info: fx 700").count(), 1, "{err}");
    assert!(!err.contains("camera intrinsics from /camera/camera_info changed"), "{err}");
    assert_eq!(err.matches("is ignored: relative poses take the images as undistorted").count(), 1, "{err}");
    eprintln!("{posed} of the 10 frames of phase 1 carry a relative pose");
    // a clean start and a clean Ctrl-C: no error line (the GPU probe's XDG_RUNTIME_DIR complaint,
    // the DDS stack's teardown)
    assert!(!err.contains("ERROR") && !err.contains("XDG_RUNTIME_DIR"), "{err}");
    let published = s["published"].as_u64().unwrap();
    assert_eq!(published, 13 + m3.len() as u64, "{s}");
    assert_eq!(
        s["received"].as_u64().unwrap(),
        published + s["dropped"].as_u64().unwrap() + 2,
        "every received frame was published, dropped, or refused: {s}"
    );
    assert!(s["receive_to_publish_ms"]["p50"].as_f64().unwrap() > 0.0);
    eprintln!("node summary: {s}");
}

/// The node with its defaults (backend `auto`: it looks for a GPU) starts and stops on Ctrl-C
/// without an error line: neither Mesa's `XDG_RUNTIME_DIR` complaint at start nor the DDS stack's
/// teardown (its spinner notified after its executor was gone, a multicast group left on
/// loopback).
#[test]
fn a_clean_start_and_ctrl_c_log_no_error() {
    let data = repo().join("../shared/data/real-vpr/gardenspoint-day-night-mini");
    if !data.exists() {
        return skip(&format!("{} is absent", data.display()));
    }
    let Some(semlook) = semlook_bin() else { return skip("the semlook binary is not built beside this test (cargo test --workspace builds it)") };
    if semlook::nn::onnx::find_model(semlook::networks::xfeat::XFEAT_WEIGHTS, Some(&repo().join(".semlook/xfeat.pt")), "XFeat").is_err() {
        return skip("no XFeat weights in .semlook (run setup.sh)");
    }
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map");
    let mut build = Command::new(&semlook);
    build.args(["-q", "--backend", "cpu", "map", "build", "--images"]).arg(data.join("ref")).arg("--map").arg(&map);
    ros_env(&mut build, 0);
    assert!(build.status().unwrap().success());
    let mut cmd = Command::new(env!("CARGO_BIN_EXE_semlook_node"));
    cmd.args(["--ros-args", "-p", &format!("map:={}", map.display())]).env_remove("XDG_RUNTIME_DIR");
    ros_env(&mut cmd, 200 + (std::process::id() % 50) as u16);
    let node = Node { child: cmd.stdout(Stdio::piped()).stderr(Stdio::piped()).spawn().unwrap() };
    std::thread::sleep(Duration::from_secs(5));
    let (out, err) = node.stop();
    assert!(out.contains("\"summary\""), "it stopped cleanly, with its summary:\n{out}\n{err}");
    assert!(err.contains("subscribed"), "{err}");
    assert!(!err.contains("ERROR") && !err.contains("XDG_RUNTIME_DIR"), "{err}");
}
