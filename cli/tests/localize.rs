//! `semlook localize` and `eval --sequence` from the command line: a folder in time order with a
//! time going back, images piped to standard input with garbage between them, and the sequence
//! columns of an evaluation.

mod common;

use common::{cli, cli_ok, p};
use std::io::Write;
use std::path::Path;

/// The tiny synthetic benchmark's folders: (reference RGB, reference labels, night RGB, night labels).
fn folders(root: &Path) -> (std::path::PathBuf, std::path::PathBuf, std::path::PathBuf, std::path::PathBuf) {
    let cam = semlook::dataset::SYNTHIA_CAMERA;
    let f = |t: &str, k: &str| root.join(t).join(k).join(cam);
    (f("day", "RGB"), f("day", "GT/LABELS"), f("night", "RGB"), f("night", "GT/LABELS"))
}

/// The loop-closure runs on standard input: the night frames of a tiny synthetic set of `places`
/// (`seed`) as PNG bytes, and a config whose first 8 frames make the map, then a commit every 4.
fn piped_loop_closure(dir: &Path, places: usize, seed: u64) -> (Vec<Vec<u8>>, std::path::PathBuf) {
    let data = dir.join("data");
    common::tiny_synth(&data, places, seed);
    let (_, _, q_rgb, _) = folders(&data);
    let frames = (0..places).map(|i| std::fs::read(q_rgb.join(format!("{i:06}.png"))).unwrap()).collect();
    let cfg = dir.join("lc.toml");
    std::fs::write(&cfg, "[stream]\nexclude_frames = 8\ncommit_frames = 4\n").unwrap();
    (frames, cfg)
}

/// `localize --stdin --loop-closure` on `map` with `cfg` (and `extra` arguments), its pipes open.
fn spawn_loop_closure(map: &Path, cfg: &Path, extra: &[&str]) -> std::process::Child {
    let args = ["--backend", "cpu", "localize", "--map", p(map), "--stdin", "--loop-closure", "--no-segmenter", "--config", p(cfg), "-q"];
    std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
        .args(args)
        .args(extra)
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap()
}

/// Writes `frames` to the child's standard input and reads its output until each has its answer
/// line; returns the pipes, still open (the camera connected, silent).
fn feed_and_await(child: &mut std::process::Child, frames: &[Vec<u8>]) -> (std::process::ChildStdin, std::io::BufReader<std::process::ChildStdout>) {
    use std::io::BufRead;
    let mut stdin = child.stdin.take().unwrap();
    for f in frames {
        stdin.write_all(f).unwrap();
    }
    stdin.flush().unwrap();
    let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
    let (mut answered, mut line) = (0, String::new());
    while answered < frames.len() {
        line.clear();
        assert!(out.read_line(&mut line).unwrap() > 0, "the run ended after {answered} of {} frames", frames.len());
        answered += usize::from(line.starts_with(char::is_numeric));
    }
    (stdin, out)
}

#[test]
fn a_folder_in_time_order_is_localized_frame_by_frame() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 24, 3);
    let (ref_rgb, ref_lab, q_rgb, q_lab) = folders(&data);
    let map = dir.path().join("map");
    cli_ok(&["map", "build", "--images", p(&ref_rgb), "--labels", p(&ref_lab), "--no-appearance", "--map", p(&map), "-q"]);
    // times in the reverse of the name order, but frame 000005's goes back
    let mut times = String::from("name,time\n");
    for i in 0..24 {
        let t = if i == 5 { 1.0 } else { 100.0 + i as f64 };
        times += &format!("{i:06}.png,{t}\n");
    }
    let tfile = dir.path().join("times.csv");
    std::fs::write(&tfile, times).unwrap();
    let args = ["--backend", "cpu", "localize", "--map", p(&map), "--images", p(&q_rgb), "--labels", p(&q_lab), "--timestamps", p(&tfile)];
    let out = cli_ok(&[&args[..], &["--setting", "forest", "--no-appearance", "--json", "-q"]].concat());
    let lines: Vec<serde_json::Value> = out.lines().map(|l| serde_json::from_str(l).unwrap()).collect();
    assert_eq!(lines.len(), 25, "one line per frame and the summary:\n{out}");
    // frame 000005 comes first (its time is the smallest), then the others in order
    assert_eq!(lines[0]["id"], "000005");
    assert_eq!(lines[1]["id"], "000000");
    let answered: Vec<&serde_json::Value> = lines.iter().filter(|l| l.get("top_k").is_some()).collect();
    assert_eq!(answered.len(), 24);
    assert!(answered.iter().all(|l| l["top_k"].as_array().is_some_and(|k| !k.is_empty())));
    assert!(answered.iter().skip(12).any(|l| l["sequence"]["accepted"] == true), "{out}");
    let summary = &lines[24]["summary"];
    assert_eq!(summary["counts"]["frames"], 24);
    assert!(summary["latency"]["p50"]["total_ms"].as_f64().unwrap() > 0.0);
    // a name the timestamps do not list is refused before any work
    std::fs::write(&tfile, "000000.png 1\n").unwrap();
    let bad = cli(&[&args[..], &["--setting", "forest", "--no-appearance", "-q"]].concat());
    assert!(!bad.status.success());
    let err = String::from_utf8_lossy(&bad.stderr);
    assert!(err.contains("times.csv") && err.contains("no time for 000001.png"), "{err}");
}

/// The columns of a `localize` CSV line by name.
fn csv_rows(text: &str) -> Vec<std::collections::HashMap<String, String>> {
    let mut lines = text.lines().filter(|l| !l.starts_with('#'));
    let header: Vec<String> = lines.next().unwrap().split(',').map(String::from).collect();
    lines.map(|l| header.iter().cloned().zip(l.split(',').map(String::from)).collect()).collect()
}

/// The printed answer (CSV `answer` columns, JSON `answer`) is the accepted sequence match where
/// one is accepted, else the single-frame best, its score on the single-frame scale either way.
#[test]
fn the_printed_answer_is_the_accepted_sequence_match() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 24, 3);
    let (ref_rgb, ref_lab, q_rgb, q_lab) = folders(&data);
    let map = dir.path().join("map");
    cli_ok(&["map", "build", "--images", p(&ref_rgb), "--labels", p(&ref_lab), "--no-appearance", "--map", p(&map), "-q"]);
    let args = [
        "--backend",
        "cpu",
        "localize",
        "--map",
        p(&map),
        "--images",
        p(&q_rgb),
        "--labels",
        p(&q_lab),
        "--setting",
        "global",
        "--no-appearance",
        "-q",
    ];
    let lines = cli_ok(&[&args[..], &["--json"]].concat());
    // the answer comes first in each frame's line, after the frame's number and id
    assert!(lines.lines().filter(|l| !l.contains("summary")).all(|l| l.starts_with("{\"frame\":") && l.contains(",\"answer\":")), "{lines}");
    let json: Vec<serde_json::Value> =
        lines.lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()).filter(|v| v.get("frame").is_some()).collect();
    let csv = csv_rows(&cli_ok(&args));
    assert_eq!((json.len(), csv.len()), (24, 24));
    let (mut from_sequence, mut differs) = (0, 0);
    for (j, c) in json.iter().zip(&csv) {
        let (a, seq, best) = (&j["answer"], &j["sequence"], &j["top_k"][0]);
        if seq["accepted"] == true {
            from_sequence += 1;
            assert_eq!(
                (&a["id"], &a["index"], &a["place"], &a["source"], &a["accepted"]),
                (&seq["id"], &seq["index"], &seq["place"], &"sequence".into(), &true.into()),
                "{j}"
            );
            differs += usize::from(seq["id"] != best["id"]);
            // on the single-frame scale: the place's score where the ranking holds it
            if let Some(c) = j["top_k"].as_array().unwrap().iter().find(|c| c["id"] == a["id"]) {
                assert!((c["score"].as_f64().unwrap() - a["score"].as_f64().unwrap()).abs() < 1e-6, "{j}");
            }
        } else {
            assert_eq!((&a["id"], &a["score"], &a["source"], &a["accepted"]), (&best["id"], &best["score"], &"frame".into(), &false.into()), "{j}");
        }
        // the CSV line says the same
        let place = format!("{}:{}", a["place"]["traversal"], a["place"]["position"]);
        assert_eq!(
            (c["answer"].as_str(), c["place"].as_str(), c["source"].as_str(), c["accepted"].as_str()),
            (a["id"].as_str().unwrap(), place.as_str(), a["source"].as_str().unwrap(), if a["accepted"] == true { "true" } else { "false" }),
            "{c:?} against {j}"
        );
        assert!((c["score"].parse::<f64>().unwrap() - a["score"].as_f64().unwrap()).abs() < 1e-3, "{c:?}");
        assert_eq!(c["best"].as_str(), best["id"].as_str().unwrap(), "{c:?}");
    }
    assert!(from_sequence >= 6, "{from_sequence} answers from an accepted sequence match");
    assert!(differs >= 1, "no frame where the accepted sequence match is not the single-frame best: the test would not tell them apart");
}

#[test]
fn piped_images_are_localized_and_garbage_costs_one_frame() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 16, 4);
    let (ref_rgb, _, q_rgb, _) = folders(&data);
    let map = dir.path().join("map");
    // photos alone, no segmenter: a map of appearance without labels, as a camera gives
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&map), "-q"]);
    let mut piped = Vec::new();
    for i in 0..16 {
        piped.extend(std::fs::read(q_rgb.join(format!("{i:06}.png"))).unwrap());
        if i == 7 {
            piped.extend_from_slice(b"this is not an image");
        }
    }
    let run = |json: &[&str]| {
        let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
            .args([&["--backend", "cpu", "localize", "--map", p(&map), "--stdin", "--no-segmenter", "-q"][..], json].concat())
            .stdin(std::process::Stdio::piped())
            .stdout(std::process::Stdio::piped())
            .stderr(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        child.stdin.take().unwrap().write_all(&piped).unwrap();
        let out = child.wait_with_output().unwrap();
        assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
        out
    };
    let out = run(&[]);
    let text = String::from_utf8(out.stdout).unwrap();
    let rows: Vec<&str> = text.lines().filter(|l| !l.starts_with('#') && !l.starts_with("frame,")).collect();
    // the garbage's row says `refused` in the accepted column, with no match
    let (refused, answered): (Vec<&str>, Vec<&str>) = rows.iter().partition(|r| r.split(',').nth(6) == Some("refused"));
    assert_eq!((answered.len(), refused.len()), (16, 1), "every piped image answered:\n{text}");
    assert!(answered.iter().all(|r| r.split(',').nth(2).is_some_and(|a| !a.is_empty())), "{text}");
    assert!(answered.iter().all(|r| r.split(',').nth(7).is_some_and(|best| !best.is_empty())), "{text}");
    assert!(refused[0].starts_with("8,") && refused[0].split(',').skip(2).filter(|c| !c.is_empty()).eq(["refused"]), "{text}");
    assert!(text.contains("# 17 frames (1 refused)"), "{text}");
    assert!(String::from_utf8_lossy(&out.stderr).contains("neither a JPEG nor a PNG"));
    // with --json the refusal's object says its reason and its kind (issue 57: free text before)
    let json = String::from_utf8(run(&["--json"]).stdout).unwrap();
    let refusals: Vec<serde_json::Value> =
        json.lines().filter_map(|l| serde_json::from_str::<serde_json::Value>(l).ok()).filter(|v| v.get("refused").is_some()).collect();
    assert_eq!(refusals.len(), 1, "{json}");
    assert_eq!((refusals[0]["frame"].as_u64(), refusals[0]["kind"].as_str()), (Some(8), Some("invalid_input")), "{json}");
    assert!(refusals[0]["refused"].as_str().unwrap().contains("neither a JPEG nor a PNG"), "{json}");
    // honest ends (issue 57 part 3): an empty stream fails, as an empty folder does; --timestamps
    // cannot name piped frames and is refused, not ignored (a file that does not exist too)
    let empty = std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
        .args(["--backend", "cpu", "localize", "--map", p(&map), "--stdin", "--no-segmenter", "-q"])
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    assert!(!empty.status.success(), "empty standard input exited 0:\n{}", String::from_utf8_lossy(&empty.stdout));
    assert!(String::from_utf8_lossy(&empty.stderr).contains("no frames"), "{}", String::from_utf8_lossy(&empty.stderr));
    let timed = std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
        .args(["--backend", "cpu", "localize", "--map", p(&map), "--stdin", "--timestamps", "/no/such/times.csv", "--no-segmenter", "-q"])
        .stdin(std::process::Stdio::null())
        .output()
        .unwrap();
    assert!(!timed.status.success() && String::from_utf8_lossy(&timed.stderr).contains("--timestamps"), "{}", String::from_utf8_lossy(&timed.stderr));
}

/// `localize --stdin` answers piped JPEGs exactly as `localize --images` answers the same files:
/// ranking, scores, sequence, answer, frame for frame.
#[test]
fn piped_jpegs_are_answered_as_the_folder_answers_them() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 20, 6);
    let (ref_rgb, _, q_rgb, _) = folders(&data);
    let map = dir.path().join("map");
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&map), "-q"]);
    // the night frames as JPEGs of several qualities (restart-free baseline JPEGs, as ffmpeg's
    // mjpeg writes them)
    let jpegs = dir.path().join("jpegs");
    std::fs::create_dir(&jpegs).unwrap();
    let mut piped = Vec::new();
    for i in 0..20 {
        let img = image::open(q_rgb.join(format!("{i:06}.png"))).unwrap().to_rgb8();
        let mut bytes = Vec::new();
        image::codecs::jpeg::JpegEncoder::new_with_quality(&mut bytes, 60 + (i as u8 % 4) * 10).encode_image(&img).unwrap();
        std::fs::write(jpegs.join(format!("{i:06}.jpg")), &bytes).unwrap();
        piped.extend(bytes);
    }
    let args = ["--backend", "cpu", "localize", "--map", p(&map), "--no-segmenter", "--json", "-q"];
    let answers = |text: &str| -> Vec<serde_json::Value> {
        text.lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v.get("frame").is_some())
            .map(|mut v| {
                let o = v.as_object_mut().unwrap();
                // what depends on the source alone: the frame's id (the file's stem, or frame-N) and the clock
                o.remove("id");
                o.remove("latency");
                v
            })
            .collect()
    };
    let folder = answers(&cli_ok(&[&args[..], &["--images", p(&jpegs)]].concat()));
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
        .args([&args[..], &["--stdin"]].concat())
        .stdin(std::process::Stdio::piped())
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    let mut stdin = child.stdin.take().unwrap();
    // written in uneven pieces, as a pipe delivers them
    let writer = std::thread::spawn(move || {
        for piece in piped.chunks(4093) {
            stdin.write_all(piece).unwrap();
        }
    });
    let out = child.wait_with_output().unwrap();
    writer.join().unwrap();
    assert!(out.status.success(), "{}", String::from_utf8_lossy(&out.stderr));
    let stdin = answers(&String::from_utf8(out.stdout).unwrap());
    assert_eq!(folder.len(), 20);
    assert_eq!(stdin.len(), folder.len(), "every piped image answered once");
    for (k, (a, b)) in folder.iter().zip(&stdin).enumerate() {
        assert_eq!(a, b, "frame {k}: the folder's answer against the pipe's");
    }
}

/// A `--loop-closure` run killed with SIGKILL and restarted with `--resume`: the restart skips
/// the frames the map holds (says how many), adds the others, and every frame is stored exactly
/// once, whatever was committed before the kill.
#[test]
fn a_killed_loop_closure_run_resumes_and_stores_every_frame_once() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let (frames, cfg) = piped_loop_closure(dir.path(), 24, 7);
    let map = dir.path().join("map");
    let run = |resume: bool| spawn_loop_closure(&map, &cfg, if resume { &["--resume"] } else { &[] });
    // the first run gets 14 frames, answers them, and is killed waiting for the 15th: frames 0-11
    // are committed (the map's 8, then 4), 12 and 13 were buffered
    let mut first = run(false);
    let (stdin, _out) = feed_and_await(&mut first, &frames[..14]);
    first.kill().unwrap(); // SIGKILL
    first.wait().unwrap();
    drop(stdin);
    let held = |map: &Path| -> Vec<String> {
        use semlook::descriptors::source::RefSource;
        let m = semlook::map::Map::open(map).unwrap();
        (0..m.len()).map(|i| m.id(i).to_string()).collect()
    };
    let before = held(&map);
    assert_eq!(before.len(), 12, "committed before the kill: {before:?}");
    // the restart gets every frame again from the first
    let mut second = run(true);
    let mut stdin = second.stdin.take().unwrap();
    let all: Vec<u8> = frames.concat();
    let writer = std::thread::spawn(move || stdin.write_all(&all).unwrap());
    let done = second.wait_with_output().unwrap();
    writer.join().unwrap();
    let (text, err) = (String::from_utf8_lossy(&done.stdout), String::from_utf8_lossy(&done.stderr));
    assert!(done.status.success(), "{err}");
    assert!(text.contains("# resumed: 12 frames skipped"), "{text}");
    assert!(text.contains("# 12 frames (0 refused)"), "the other 12 frames answered:\n{text}");
    let mut after = held(&map);
    assert_eq!(after.len(), 24, "{after:?}");
    after.sort();
    let want: Vec<String> = (0..24).map(|k| format!("frame-{k:06}")).collect();
    assert_eq!(after, want, "every frame stored exactly once");
    let m = semlook::map::Map::open(&map).unwrap();
    assert_eq!(semlook::map::manifest::traversal_names(&m.manifest).len(), 1, "the restart continued the stream's traversal");
}

/// SIGINT (Ctrl-C) or SIGTERM during `--loop-closure` on standard input, the camera still
/// connected but silent: the stream stops between frames, commits every frame it answered (the
/// number the summary prints is the map's), prints the summary and exits 128 + the signal (130,
/// 143), instead of dying with frames buffered and no summary (issue 57: 6 of 56 frames lost).
/// The SIGTERM run starts its new map with `--camera` (issue 57: refused before the map existed,
/// "the map stores no verification keypoints").
#[test]
#[cfg(unix)]
fn a_signal_during_loop_closure_commits_every_answered_frame_and_prints_the_summary() {
    use std::os::unix::process::ExitStatusExt;
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    // the first 8 frames make the map, then a commit every 4: 11 answered leave 3 buffered
    let (frames, cfg) = piped_loop_closure(dir.path(), 16, 9);
    let camera = dir.path().join("camera.toml");
    std::fs::write(&camera, "fx = 190.0\nfy = 190.0\ncx = 79.5\ncy = 59.5\nwidth = 160\nheight = 120\n").unwrap();
    for (signal, name, sent) in [("-INT", "SIGINT", 11), ("-TERM", "SIGTERM", 14)] {
        let map = dir.path().join(format!("map{name}"));
        let extra = if name == "SIGTERM" { vec!["--camera", p(&camera)] } else { vec![] };
        let mut child = spawn_loop_closure(&map, &cfg, &extra);
        let (stdin, mut out) = feed_and_await(&mut child, &frames[..sent]);
        // the camera stays connected (stdin open) and sends nothing more
        let kill = std::process::Command::new("kill").args([signal, &child.id().to_string()]).status().unwrap();
        assert!(kill.success());
        let mut rest = String::new();
        std::io::Read::read_to_string(&mut out, &mut rest).unwrap();
        let status = child.wait().unwrap();
        let mut err = String::new();
        std::io::Read::read_to_string(&mut child.stderr.take().unwrap(), &mut err).unwrap();
        drop(stdin);
        assert_eq!(status.code(), Some(if name == "SIGINT" { 130 } else { 143 }), "{name}: {status:?} {err}");
        assert!(status.signal().is_none(), "{name}: ended by the signal's default action, not by the stream");
        assert!(rest.contains(&format!("# interrupted by {name}")), "{name}: {rest}");
        assert!(rest.contains(&format!("# {sent} frames (0 refused)")), "{name}: the summary counts every answered frame: {rest}");
        let m = semlook::map::Map::open(&map).unwrap();
        assert_eq!(m.len(), sent, "{name}: every answered frame committed to the map");
    }
}

#[test]
fn eval_reports_sequence_matching_beside_single_frames() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 20, 5);
    let out =
        cli_ok(&["--backend", "cpu", "eval", "--dataset", p(&data), "--setting", "forest,global", "--sequence", "--no-appearance", "--json", "-q"]);
    let v: serde_json::Value = serde_json::from_str(&out).unwrap();
    for r in v["results"].as_array().unwrap() {
        let s = &r["sequence"];
        assert_eq!(s["outcomes"].as_array().unwrap().len(), r["queries"].as_u64().unwrap() as usize, "{r}");
        let r1 = s["recall_at_1"].as_f64().unwrap();
        assert!((0.0..=1.0).contains(&r1) && s["accepted_precision"].as_f64().is_some());
    }
    let table = cli_ok(&["--backend", "cpu", "eval", "--dataset", p(&data), "--setting", "forest", "--sequence", "--no-appearance", "-q"]);
    assert!(table.contains("sequence matching") && table.contains("seq R@1"), "{table}");
    let without = cli_ok(&["--backend", "cpu", "eval", "--dataset", p(&data), "--setting", "forest", "--no-appearance", "--json", "-q"]);
    assert!(!without.contains("\"sequence\""), "no sequence section unless asked");
}

/// `stream.embed_when_tracking = false`: a frame searched within the
/// tracking window is encoded without the whole-image embedding, a frame that searches the whole
/// map (the first, and those after tracking is lost at a jump) with it; on (the default), every
/// frame is embedded.
#[test]
fn tracked_frames_go_without_the_embedding_where_asked() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 40, 8);
    let (ref_rgb, _, _, _) = folders(&data);
    let q_rgb = data.join("overcast/RGB").join(semlook::dataset::SYNTHIA_CAMERA);
    let map = dir.path().join("map");
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&map), "-q"]);
    let info: serde_json::Value = serde_json::from_str(&cli_ok(&["map", "info", "--map", p(&map), "--json"])).unwrap();
    if info["embedding"].is_null() {
        common::skip_unless_required("REQUIRE_MODELS", "the map has no embeddings (embedding network not installed: run setup.sh)");
        return;
    }
    // the overcast frames 0..16, 10 frames of noise (a covered lens: nothing matches, tracking is
    // lost), then frames 26..40 (found again)
    let frames = dir.path().join("frames");
    std::fs::create_dir(&frames).unwrap();
    let mut rng = semlook::util::SplitMix64::new(5);
    for k in 0..40 {
        let to = frames.join(format!("{k:06}.png"));
        match k {
            16..26 => image::RgbImage::from_fn(160, 120, |_, _| image::Rgb([rng.below(256) as u8; 3])).save(&to).unwrap(),
            _ => drop(std::fs::copy(q_rgb.join(format!("{k:06}.png")), &to).unwrap()),
        }
    }
    let run = |embed: bool| -> Vec<serde_json::Value> {
        let cfg = dir.path().join(format!("stream-{embed}.toml"));
        std::fs::write(&cfg, format!("[sequence]\nlength = 5\n[stream]\ntrack_radius = 4\nlost_after = 2\nembed_when_tracking = {embed}\n")).unwrap();
        let args = ["--backend", "cpu", "localize", "--map", p(&map), "--images", p(&frames), "--no-segmenter", "--config", p(&cfg), "--json", "-q"];
        cli_ok(&args).lines().map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap()).filter(|v| v.get("frame").is_some()).collect()
    };
    let flag = |v: &serde_json::Value, k: &str| v[k].as_bool().unwrap_or_else(|| panic!("no {k} in {v}"));
    let lean = run(false);
    assert_eq!(lean.len(), 40);
    let pattern: String = lean.iter().map(|v| if flag(v, "tracking") { 't' } else { 'W' }).collect();
    let accepted: String = lean.iter().map(|v| if v["sequence"]["accepted"] == true { 'a' } else { '.' }).collect();
    eprintln!("frames searched within the tracking window (t) or the whole map (W): {pattern}\nsequence matches accepted (a):                                     {accepted}");
    assert!(!flag(&lean[0], "tracking") && flag(&lean[0], "embedded"), "the first frame searches the whole map, embedded: {}", lean[0]);
    for v in &lean {
        assert_eq!(flag(v, "embedded"), !flag(v, "tracking"), "embedded exactly where the whole map is searched: {v}");
    }
    let tracked = lean.iter().filter(|v| flag(v, "tracking")).count();
    assert!(tracked >= 20, "most frames are tracked: {pattern}");
    // lost in the noise: the whole map searched again (embedded), then tracked again
    assert!(pattern[16..].contains("tW") && pattern[16..].contains("Wt"), "tracking lost in the noise and found again: {pattern}");
    let full = run(true);
    assert!(full.iter().all(|v| flag(v, "embedded")), "embed_when_tracking = true embeds every frame");
    assert!(full.iter().any(|v| flag(v, "tracking")));
}

/// A map built with a profile (`map build --config FILE`) keeps its query sections, and queries and
/// streams without a `--config` take them (issue 57: a map built with configs/stream-realtime.toml
/// was localized with the default matching sections, though help says the default is the map's);
/// `map info` shows the profile; a `--config` replaces it; a map built with the defaults stores none.
#[test]
fn a_map_built_with_a_profile_is_searched_with_it() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 16, 3);
    let (ref_rgb, _, q_rgb, _) = folders(&data);
    let profile = dir.path().join("profile.toml");
    std::fs::write(&profile, "[matching]\ntop_k = 7\n[sequence]\nlength = 6\n").unwrap();
    let (map, plain) = (dir.path().join("map"), dir.path().join("plain"));
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&map), "--config", p(&profile), "-q"]);
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&plain), "-q"]);
    let info = cli_ok(&["map", "info", "--map", p(&map)]);
    assert!(info.contains("profile: built with query sections of its own ([matching], [sequence] differ"), "{info}");
    assert!(cli_ok(&["map", "info", "--map", p(&plain)]).contains("profile: none"));
    let m = semlook::map::Map::open(&map).unwrap();
    assert_eq!((m.query_config().matching.top_k, m.query_config().sequence.length), (7, 6));
    assert!(semlook::map::Map::open(&plain).unwrap().manifest.profile.is_none(), "the defaults store no profile");
    // the single-frame ranking of each frame: the profile's 7, the defaults' 16 (all places)
    let top_k = |map: &Path, config: Option<&Path>| -> Vec<usize> {
        let mut args = vec!["--backend", "cpu", "localize", "--map", p(map), "--images", p(&q_rgb), "--no-segmenter", "--json", "-q"];
        if let Some(c) = config {
            args.extend(["--config", p(c)]);
        }
        cli_ok(&args)
            .lines()
            .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
            .filter(|v| v.get("frame").is_some())
            .map(|v| v["top_k"].as_array().unwrap().len())
            .collect()
    };
    let with_profile = top_k(&map, None);
    assert!(!with_profile.is_empty() && with_profile.iter().all(|&n| n == 7), "the map's profile: {with_profile:?}");
    assert!(top_k(&plain, None).iter().all(|&n| n == 16));
    let defaults = dir.path().join("defaults.toml");
    std::fs::write(&defaults, "").unwrap();
    assert!(top_k(&map, Some(&defaults)).iter().all(|&n| n == 16), "a --config replaces the profile");
}

/// `localize --camera FILE`: accepted matches carry the frame's pose relative to the place's
/// (JSON `relative_pose`, CSV `rotation_deg` and `pose_inliers`), the synthetic street's camera
/// (hfov 80 degrees, principal point at the centre) against the renderer's frames; a missing or
/// malformed camera file is refused before the stream starts, naming the file and the problem.
#[test]
fn a_camera_file_gives_accepted_matches_a_relative_pose() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let synth = semlook_cli::tools::synth::SynthConfig {
        seed: 4,
        places: 24,
        width: 320,
        height: 240,
        queries: vec![semlook_cli::tools::synth::condition::Condition::Overcast],
        ..Default::default()
    };
    semlook_cli::tools::synth::generate(&synth, &data, &|| {}).unwrap();
    let cam = semlook::dataset::SYNTHIA_CAMERA;
    let (ref_rgb, q_rgb) = (data.join("day/RGB").join(cam), data.join("overcast/RGB").join(cam));
    let map = dir.path().join("map");
    cli_ok(&["--backend", "cpu", "map", "build", "--images", p(&ref_rgb), "--no-segmenter", "--map", p(&map), "-q"]);
    let f = 160.0 / 40f64.to_radians().tan();
    let camera = dir.path().join("camera.toml");
    std::fs::write(&camera, format!("fx = {f}\nfy = {f}\ncx = 159.5\ncy = 119.5\nwidth = 320\nheight = 240\n")).unwrap();
    let args = ["--backend", "cpu", "localize", "--map", p(&map), "--images", p(&q_rgb), "--no-segmenter", "--camera", p(&camera)];
    let lines: Vec<serde_json::Value> = cli_ok(&[&args[..], &["--json", "-q"]].concat())
        .lines()
        .map(|l| serde_json::from_str::<serde_json::Value>(l).unwrap())
        .filter(|v| v.get("frame").is_some())
        .collect();
    assert_eq!(lines.len(), 24);
    let accepted: Vec<&serde_json::Value> = lines.iter().filter(|v| v["answer"]["accepted"] == true).collect();
    let posed: Vec<&serde_json::Value> = accepted.iter().copied().filter(|v| !v["relative_pose"].is_null()).collect();
    eprintln!(
        "{} accepted, {} with a relative pose; rotations {:?} deg; refused: {:?}",
        accepted.len(),
        posed.len(),
        posed.iter().map(|v| v["relative_pose"]["rotation_deg"].as_f64().unwrap()).collect::<Vec<_>>(),
        accepted.iter().filter_map(|v| v.get("relative_pose_refused")).collect::<Vec<_>>()
    );
    assert!(accepted.len() >= 12, "{} accepted", accepted.len());
    assert!(posed.len() * 2 >= accepted.len(), "most accepted matches have a relative pose");
    // only accepted answers get one
    assert!(lines.iter().filter(|v| v["answer"]["accepted"] != true).all(|v| v["relative_pose"].is_null()));
    // the renderer's relative rotation (its cameras have no roll: right, down and forward from
    // the optical axis) against the estimate's angle
    let rows = |t: &str, id: &str| -> [[f64; 3]; 3] {
        let pose = semlook::dataset::read_synthia_pose(&data.join(t).join("CameraParams").join(cam).join(format!("{id}.txt"))).unwrap();
        let fwd = pose.forward;
        let yaw = fwd[0].atan2(fwd[2]);
        let right = [yaw.cos(), 0.0, -yaw.sin()];
        let up = [fwd[1] * right[2] - fwd[2] * right[1], fwd[2] * right[0] - fwd[0] * right[2], fwd[0] * right[1] - fwd[1] * right[0]];
        [right, up.map(|x| -x), fwd]
    };
    let mut offs = Vec::new();
    for v in &posed {
        let (mq, mr) = (rows("overcast", v["id"].as_str().unwrap()), rows("day", v["answer"]["id"].as_str().unwrap()));
        let trace: f64 = (0..3).map(|i| (0..3).map(|k| mr[i][k] * mq[i][k]).sum::<f64>()).sum();
        let truth = ((trace - 1.0) / 2.0).clamp(-1.0, 1.0).acos().to_degrees();
        let off = (v["relative_pose"]["rotation_deg"].as_f64().unwrap() - truth).abs();
        offs.push(off);
    }
    // 320 x 240 frames, overcast against day, 35-110 inliers, baselines of a metre or so: seen
    // (seed 4) a median of 0.6 degrees and a worst of 4.5 off the renderer's angle
    offs.sort_by(f64::total_cmp);
    let (median, worst) = (offs[offs.len() / 2], offs[offs.len() - 1]);
    eprintln!("rotation angle off the renderer's by {median:.3} deg (median), {worst:.3} (worst)");
    assert!(median < 1.0 && worst < 6.0, "rotation angles off the renderer's: {offs:?}");
    for v in &posed {
        let rp = &v["relative_pose"];
        let norm = |k: &str| rp[k].as_array().unwrap().iter().map(|x| x.as_f64().unwrap().powi(2)).sum::<f64>().sqrt();
        assert!((norm("quaternion") - 1.0).abs() < 1e-6 && (norm("translation_unit") - 1.0).abs() < 1e-6, "{rp}");
        // the query traversal turns by at most 6 degrees of yaw and 2 of pitch from the route
        assert!(rp["rotation_deg"].as_f64().unwrap() < 15.0, "{rp}");
        assert!(rp["inliers"].as_u64().unwrap() <= rp["matches"].as_u64().unwrap());
    }
    // the CSV's pose columns
    let csv = csv_rows(&cli_ok(&[&args[..], &["-q"]].concat()));
    assert_eq!(csv.iter().filter(|r| !r["rotation_deg"].is_empty() && !r["pose_inliers"].is_empty()).count(), posed.len());
    // a camera file missing, malformed or implausible: refused before any frame, named
    for (name, text, says) in [
        ("missing.toml", None, "missing.toml"),
        ("bad.json", Some("{\"fx\": 100}"), "missing field"),
        ("zero.toml", Some("fx = 0\nfy = 100\ncx = 10\ncy = 10\nwidth = 320\nheight = 240\n"), "fx = 0"),
    ] {
        let path = dir.path().join(name);
        if let Some(t) = text {
            std::fs::write(&path, t).unwrap();
        }
        let bad = [&args[..8], &["--camera", p(&path), "--json", "-q"]].concat();
        let out = cli(&bad);
        assert!(!out.status.success(), "{name}");
        let err = String::from_utf8_lossy(&out.stderr);
        assert!(err.contains(name) && err.contains(says), "{name}: {err}");
        assert!(out.stdout.is_empty(), "{name}: nothing localized before the refusal");
    }
}
