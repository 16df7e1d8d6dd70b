//! Streams: the localizer's causality, stops, jumps, traversal boundaries, loop closure, bad
//! frames and a map edited under it, on CamVid's real label maps (a drive of 233 frames and a
//! copy of it shifted sideways), label-only encoding so that a test takes seconds.

mod common;

use semlook::config::{AppearanceModelKind, Config};
use semlook::descriptors::source::{Place, RefSource};
use semlook::engine::Engine;
use semlook::input::FrameSource;
use semlook::map::{Map, MapWriter, StoreOptions, TraversalPlan};
use semlook::matching::Setting;
use semlook::stream::{FrameResult, Localizer, Pixels, StreamFrame, StreamOptions};
use semlook_cli::tools::synth::camvid::{self, Change};
use std::path::{Path, PathBuf};

/// CamVid's labels as a label-only configuration.
fn config() -> Config {
    let mut c = Config::camvid();
    c.appearance.model = AppearanceModelKind::None;
    c
}

/// The drive (`reference`) and its shifted copy (`shift`) under `dir`, frames in order.
fn drive(dir: &Path) -> Option<(Vec<FrameSource>, Vec<FrameSource>)> {
    let src = common::shared_or_required("data/camvid-test")?;
    camvid::generate(&src, dir, &[Change::Shift], 1, &|| {}).unwrap();
    let frames = |t: &str| -> Vec<FrameSource> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(dir.join(t).join("labels")).unwrap().flatten().map(|e| e.path()).collect();
        v.sort();
        v.into_iter().map(|p| FrameSource { id: format!("{t}/{}", p.file_stem().unwrap().to_string_lossy()), image: None, labels: Some(p) }).collect()
    };
    Some((frames("reference"), frames("shift")))
}

/// A map of `frames` in `dir`, in traversals of the given lengths (one writer each).
fn build(dir: &Path, frames: &[FrameSource], traversals: &[usize]) {
    let cfg = config();
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let mut start = 0;
    for (k, &n) in traversals.iter().enumerate() {
        let mut w = match k {
            0 => MapWriter::create(dir, &cfg.encoding(), Default::default(), None, StoreOptions::default(), false).unwrap(),
            _ => MapWriter::append(dir, StoreOptions::default()).unwrap().with_traversal(TraversalPlan::New).unwrap(),
        };
        let mut scratch = Default::default();
        for f in &frames[start..start + n] {
            w.push(&enc.encode_source(f, Default::default(), &mut scratch).unwrap().0).unwrap();
        }
        w.finish().unwrap();
        start += n;
    }
}

fn localizer(map: &Path, setting: Setting) -> Localizer {
    // the frames come with their label maps: no segmenter is looked for
    Localizer::open(map, Some(config()), StreamOptions { setting, labelled_frames: true, ..Default::default() }, Engine::cpu()).unwrap()
}

fn frame(f: &FrameSource) -> StreamFrame {
    StreamFrame { id: f.id.clone(), pixels: Pixels::Files(f.clone()), timestamp: None }
}

/// The frame number in a CamVid id ("shift/0001TP_008550" -> its index in the drive).
fn index_of(frames: &[FrameSource], id: &str) -> usize {
    let stem = id.rsplit('/').next().unwrap();
    frames.iter().position(|f| f.id.ends_with(stem)).unwrap()
}

/// A result without its timings (what must not depend on anything but the frames).
fn answer(r: &FrameResult) -> serde_json::Value {
    let mut v = serde_json::to_value(r).unwrap();
    v.as_object_mut().unwrap().remove("latency");
    v
}

#[test]
fn the_answer_at_frame_t_does_not_depend_on_the_frames_after_it() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    build(&map, &refs, &[refs.len()]);
    // two streams share frames 0..30 and then go different ways
    let a: Vec<&FrameSource> = (0..60).map(|i| &shift[i]).collect();
    let b: Vec<&FrameSource> = (0..30).chain(150..180).map(|i| &shift[i]).collect();
    let (mut la, mut lb) = (localizer(&map, Setting::Forest), localizer(&map, Setting::Forest));
    let ra: Vec<FrameResult> = a.iter().map(|f| la.push(frame(f)).unwrap()).collect();
    let rb: Vec<FrameResult> = b.iter().map(|f| lb.push(frame(f)).unwrap()).collect();
    for t in 0..30 {
        assert_eq!(answer(&ra[t]), answer(&rb[t]), "frame {t}");
    }
    assert_ne!(answer(&ra[40]), answer(&rb[40]), "the streams differ after frame 30");
    // the stream keeps a bounded ring whatever its length
    let cfg = config();
    let (frames, entries) = la.state_size();
    assert!(frames <= cfg.sequence.length, "{frames}");
    assert!(entries <= cfg.sequence.length * cfg.matching.top_k.max(10) * (2 * cfg.sequence.widen + 1), "{entries}");
}

/// Share of results whose answer lies within `tol` frames of the frame the stream shows.
fn near(results: &[(usize, FrameResult)], refs: &[FrameSource], tol: usize) -> f64 {
    let ok = results.iter().filter(|(truth, r)| r.place().is_some_and(|a| index_of(refs, &a.id).abs_diff(*truth) <= tol)).count();
    ok as f64 / results.len().max(1) as f64
}

#[test]
fn a_stop_of_twenty_frames_keeps_the_place() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    build(&map, &refs, &[refs.len()]);
    let mut l = localizer(&map, Setting::Forest);
    // drive 60 frames, stand at frame 60 for 20 frames, drive on
    let route: Vec<usize> = (0..60).chain(std::iter::repeat_n(60, 20)).chain(61..90).collect();
    let results: Vec<(usize, FrameResult)> = route.iter().map(|&i| (i, l.push(frame(&shift[i])).unwrap())).collect();
    let stop: Vec<(usize, FrameResult)> = results[65..80].to_vec();
    let accepted = stop.iter().filter(|(_, r)| r.sequence.as_ref().is_some_and(|s| s.matched.accepted)).count();
    assert!(near(&stop, &refs, 2) >= 0.9, "during the stop: {:.2} near", near(&stop, &refs, 2));
    assert!(accepted >= 10, "{accepted} of 15 stop frames accepted");
    assert!(stop.iter().any(|(_, r)| r.sequence.as_ref().is_some_and(|s| s.matched.velocity == 0.0)), "a standing trajectory wins");
    assert!(near(&results[85..], &refs, 2) >= 0.9, "after the stop");
}

#[test]
fn a_jump_elsewhere_is_recovered_within_the_sequence_length() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    build(&map, &refs, &[refs.len()]);
    let mut l = localizer(&map, Setting::Forest);
    let ds = config().sequence.length;
    let route: Vec<usize> = (20..70).chain(150..200).collect();
    let results: Vec<(usize, FrameResult)> = route.iter().map(|&i| (i, l.push(frame(&shift[i])).unwrap())).collect();
    // from ds frames after the jump on, the stream is where the frames are again
    let after = &results[50 + ds..];
    assert!(near(after, &refs, 2) >= 0.9, "{:.2}", near(after, &refs, 2));
    let sequence_near = after.iter().filter(|(t, r)| r.sequence.as_ref().is_some_and(|s| index_of(&refs, &s.id).abs_diff(*t) <= 2)).count();
    assert!(sequence_near as f64 >= 0.9 * after.len() as f64, "the trajectory itself moved: {sequence_near} of {}", after.len());
}

#[test]
fn trajectories_stop_at_a_traversal_boundary() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    // the drive stored as two traversals: frames 0..100 and 100..233
    build(&map, &refs, &[100, refs.len() - 100]);
    let m = Map::open(&map).unwrap();
    assert_eq!((m.traversal_len(0), m.traversal_len(1)), (100, refs.len() as u32 - 100));
    assert_eq!(m.place(105), Place { traversal: 1, position: 5 });
    assert_eq!(m.at(Place { traversal: 1, position: 5 }), Some(105));
    // the same drive as one traversal: trajectories there may run across position 100
    let whole = dir.path().join("whole");
    build(&whole, &refs, &[refs.len()]);
    let (mut l, mut lw) = (localizer(&map, Setting::Forest), localizer(&whole, Setting::Forest));
    let mut crossed = 0;
    for i in 80..130 {
        let r = l.push(frame(&shift[i])).unwrap();
        let rw = lw.push(frame(&shift[i])).unwrap();
        if let Some(s) = &r.sequence {
            let m = &s.matched;
            assert!(m.frames <= config().sequence.length, "frame {i}: {s:?}");
            assert_eq!(m.place.traversal, m.end.traversal, "frame {i}: refined within the trajectory's traversal");
            if i >= 110 {
                assert_eq!(s.matched.place.traversal, 1, "frame {i}: {s:?}");
            }
            // for `length` frames after the boundary a trajectory on traversal 1 has only the
            // frames since it (on this drive, at length 20, the best stands at 99 until frame 108,
            // then ends on traversal 1 scoring 1.9, rising to 4.1 at 119): it scores below the
            // one-traversal map's, which counts the frames before the boundary too
            let w = rw.sequence.as_ref().unwrap();
            if (100..100 + config().sequence.length).contains(&i) && m.end.traversal == 1 && w.matched.end.position >= 100 {
                assert!(m.score < w.matched.score, "frame {i}: {} on two traversals, {} on one", m.score, w.matched.score);
                crossed += 1;
            }
        }
    }
    assert!(crossed >= 3, "only {crossed} frames near the boundary compared");
}

#[test]
fn loop_closure_finds_the_repeated_drive_and_nothing_recent() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    closes_the_loop(&dir.path().join("loop-map"), &config(), Setting::Forest, &refs, &shift, None);
}

/// A synthetic route driven twice (by day, then overcast), photos and label maps, `verified`,
/// with the renderer's camera from the first frame on (the map does not exist yet: its keypoints
/// come with the codebook its first frames train): the second pass's closures carry relative
/// poses (issue 57: `--loop-closure --camera` on a new map was refused for a map without keypoints).
#[test]
fn loop_closure_finds_the_repeated_synthetic_route_and_nothing_recent() {
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("synth");
    // a route that repeats, not perceptual aliasing: no repeated layout templates (the
    // renderer's default, 0.6, gives distinct places one layout)
    let synth = semlook_cli::tools::synth::SynthConfig {
        seed: 11,
        places: 90,
        width: 320,
        height: 240,
        aliasing: 0.0,
        queries: vec![semlook_cli::tools::synth::condition::Condition::Overcast],
        ..Default::default()
    };
    semlook_cli::tools::synth::generate(&synth, &data, &|| {}).unwrap();
    let frames = |t: &str| -> Vec<FrameSource> {
        let d = data.join(t).join("GT/LABELS").join(semlook::dataset::SYNTHIA_CAMERA);
        let mut v: Vec<PathBuf> = std::fs::read_dir(&d).unwrap().flatten().map(|e| e.path()).collect();
        v.sort();
        v.into_iter()
            .map(|p| {
                let image = data.join(t).join("RGB").join(semlook::dataset::SYNTHIA_CAMERA).join(p.file_name().unwrap());
                FrameSource { id: format!("{t}/{}", p.file_stem().unwrap().to_string_lossy()), image: Some(image), labels: Some(p) }
            })
            .collect()
    };
    let cfg = Config::default();
    let f = 160.0 / 40f64.to_radians().tan();
    let camera = semlook::verify::pose::Camera { fx: f, fy: f, cx: 159.5, cy: 119.5, width: 320, height: 240 };
    closes_the_loop(&dir.path().join("loop-map"), &cfg, Setting::Verified, &frames("day"), &frames("overcast"), Some(camera));
}

/// Streams `first` and then `second` (the same route again) through a loop-closure localizer
/// that starts the map at `map`: the second pass closes loops on the right places (within two),
/// the first almost never, and no closure is on a frame of the excluded recent window. With a
/// `camera`, set before the first frame, most closures carry the relative pose.
fn closes_the_loop(
    map: &Path,
    cfg: &Config,
    setting: Setting,
    first_pass: &[FrameSource],
    second_pass: &[FrameSource],
    camera: Option<semlook::verify::pose::Camera>,
) {
    let opts = StreamOptions { setting, loop_closure: true, ..Default::default() };
    let mut l = Localizer::open(map, Some(cfg.clone()), opts, Engine::cpu()).unwrap();
    if let Some(c) = camera {
        l = l.with_camera(c).expect("a camera on a map the stream starts");
    }
    let (mut first, mut second) = (vec![], vec![]);
    for (k, f) in first_pass.iter().chain(second_pass).enumerate() {
        let r = l.push(frame(f)).unwrap();
        // each generation the stream moved to was checked before it answered from it (the
        // checks of a large map are not paid by a frame: Map::prepare)
        assert_eq!(l.map().map_or(0, Map::unchecked), 0, "frame {k}: files of the map unchecked");
        if let Some(c) = &r.closure {
            // never a recent frame: the match is older than the excluded window
            assert!(c.place.index as usize + cfg.stream.exclude_frames <= k, "frame {k} closed on {}", c.place.index);
            match k < first_pass.len() {
                true => first.push(c.clone()),
                false => second.push((k - first_pass.len(), c.clone())),
            }
        }
    }
    l.finish().unwrap();
    let wrong: Vec<(usize, usize)> =
        second.iter().map(|(t, c)| (*t, index_of(first_pass, &c.place.id))).filter(|(t, i)| t.abs_diff(*i) > 2).collect();
    eprintln!("closures: {} in the first pass, {} in the second, wrong there (frame, place): {wrong:?}", first.len(), second.len());
    assert!(second.len() >= first_pass.len() / 2, "{} closures in the second pass", second.len());
    assert!(wrong.len() as f64 <= 0.05 * second.len() as f64, "{} of {} wrong: {wrong:?}", wrong.len(), second.len());
    assert!(first.len() <= first_pass.len() / 20, "{} closures in the first pass, where the route does not repeat", first.len());
    if camera.is_some() {
        let posed = second.iter().filter(|(_, c)| c.relative_pose.is_some()).count();
        eprintln!("{posed} of the {} closures with a relative pose", second.len());
        assert!(posed * 2 >= second.len(), "most closures carry a relative pose: {posed} of {}", second.len());
    }
    // the map holds the stream, committed through the store
    let m = Map::open(map).unwrap();
    assert_eq!(m.len(), first_pass.len() + second_pass.len());
    assert!(semlook::map::edit::verify(map).unwrap().damaged().next().is_none());
}

#[test]
fn bad_frames_are_refused_counted_and_the_stream_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    build(&map, &refs, &[refs.len()]);
    let mut l = localizer(&map, Setting::Forest);
    let at = |i: usize, t: f64| StreamFrame { timestamp: Some(t), ..frame(&shift[i]) };
    for i in 0..10 {
        l.push(at(i, i as f64)).unwrap();
    }
    // a corrupt file
    let bad = dir.path().join("bad.png");
    std::fs::write(&bad, b"\x89PNG\r\n\x1a\nnot really").unwrap();
    let corrupt = StreamFrame {
        id: "bad".into(),
        pixels: Pixels::Files(FrameSource { id: "bad".into(), image: None, labels: Some(bad) }),
        timestamp: Some(10.0),
    };
    assert!(l.push(corrupt).is_err());
    // a time going backwards
    let e = l.push(at(10, 3.0)).unwrap_err().to_string();
    assert!(e.contains("before the previous frame"), "{e}");
    assert_eq!(l.counts().refused, 2);
    // a frame of another size: answered, and flagged
    let small = dir.path().join("small.png");
    let lm = image::open(shift[11].labels.as_ref().unwrap()).unwrap().resize_exact(240, 180, image::imageops::FilterType::Nearest);
    lm.save(&small).unwrap();
    let r = l
        .push(StreamFrame {
            id: "small".into(),
            pixels: Pixels::Files(FrameSource { id: "small".into(), image: None, labels: Some(small) }),
            timestamp: Some(11.0),
        })
        .unwrap();
    assert!(r.size_changed && r.best().is_some(), "{r:?}");
    let r = l.push(at(12, 12.0)).unwrap();
    assert!(r.size_changed, "back to the full size");
    assert_eq!(l.counts().frames, 14);
    assert_eq!(l.counts().refused, 2);
}

#[test]
fn a_map_edited_while_streaming_is_seen_at_one_generation() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    build(&map, &refs, &[150]);
    let mut l = localizer(&map, Setting::Forest);
    let g0 = Map::open(&map).unwrap().manifest.generation;
    for i in 0..20 {
        assert_eq!(l.push(frame(&shift[i])).unwrap().generation, g0);
    }
    // another writer adds the rest of the drive and removes frames, then compacts
    let cfg = config();
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let mut w = MapWriter::append(&map, StoreOptions { segment_images: 16, ..Default::default() }).unwrap();
    let mut scratch = Default::default();
    for f in &refs[150..] {
        w.push(&enc.encode_source(f, Default::default(), &mut scratch).unwrap().0).unwrap();
    }
    w.finish().unwrap();
    let gone: Vec<String> = refs[0..5].iter().map(|f| f.id.clone()).collect();
    semlook::map::edit::remove(&map, &gone).unwrap();
    semlook::map::edit::compact(&map, StoreOptions::default()).unwrap();
    // the stream keeps answering from the generation it holds (its files were replaced)
    let r = l.push(frame(&shift[20])).unwrap();
    assert_eq!(r.generation, g0);
    assert!(r.best().is_some());
    // until it moves on: then the new generation, the ring carried over by id
    assert!(l.refresh().unwrap());
    let m = Map::open(&map).unwrap();
    let r = l.push(frame(&shift[21])).unwrap();
    assert_eq!(r.generation, m.manifest.generation);
    assert!(r.generation > g0);
    let s = r.sequence.expect("the ring survived the move");
    assert!(index_of(&refs, &s.id).abs_diff(21) <= 2, "{s:?}");
    assert_eq!(m.id(s.index as usize), s.id);
    assert!(r.top_k.iter().all(|c| !gone.contains(&c.id)));
    assert!(!l.refresh().unwrap(), "nothing new");
}

#[test]
fn places_follow_traversals_through_add_remove_and_compact() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = config();
    let maps = common::label_maps(30, 64, 48);
    let set = common::encode(&cfg, &maps, "f");
    let map = dir.path().join("map");
    let opts = StoreOptions { segment_images: 4, ..Default::default() };
    let mut w = MapWriter::create(&map, &cfg.encoding(), Default::default(), None, opts, false).unwrap();
    w.push_set(&set.slice(0, 10)).unwrap();
    w.finish().unwrap();
    let mut w = MapWriter::append(&map, opts).unwrap().with_traversal(TraversalPlan::Named("second".into())).unwrap();
    w.push_set(&set.slice(10, 20)).unwrap();
    w.finish().unwrap();
    // continuing a traversal by name, and another writer's new one
    let mut w = MapWriter::append(&map, opts).unwrap().with_traversal(TraversalPlan::Named("second".into())).unwrap();
    w.push_set(&set.slice(20, 25)).unwrap();
    w.finish().unwrap();
    let mut w = MapWriter::append(&map, opts).unwrap();
    w.push_set(&set.slice(25, 30)).unwrap();
    w.finish().unwrap();
    let check = |removed: &[usize]| {
        let m = Map::open(&map).unwrap();
        assert_eq!(semlook::map::manifest::traversal_names(&m.manifest), ["0", "second", "2"]);
        // positions along each traversal in the order the frames were added, removed ones left out
        let mut want: Vec<(String, Place)> = vec![];
        let mut pos = [0u32; 3];
        for i in 0..30 {
            let t = match i {
                0..10 => 0,
                10..25 => 1,
                _ => 2,
            };
            if !removed.contains(&i) {
                want.push((format!("f{i}"), Place { traversal: t, position: pos[t as usize] }));
                pos[t as usize] += 1;
            }
        }
        assert_eq!(m.len(), want.len());
        for (i, (id, p)) in want.iter().enumerate() {
            assert_eq!((m.id(i), m.place(i)), (id.as_str(), *p));
            assert_eq!(m.at(*p), Some(i));
        }
        assert_eq!(m.at(Place { traversal: 1, position: pos[1] }), None);
        assert_eq!((m.traversal_len(0), m.traversal_len(1), m.traversal_len(2), m.traversal_len(3)), (pos[0], pos[1], pos[2], 0));
    };
    check(&[]);
    semlook::map::edit::remove(&map, &["f3".into(), "f12".into()]).unwrap();
    check(&[3, 12]);
    let before = Map::open(&map).unwrap().manifest.segments.len();
    semlook::map::edit::compact(&map, StoreOptions { segment_images: 64, ..Default::default() }).unwrap();
    let m = Map::open(&map).unwrap();
    // small segments merged, but never across a traversal
    assert!(m.manifest.segments.len() < before);
    assert_eq!(m.manifest.segments.iter().map(|s| s.traversal).collect::<Vec<_>>(), [0, 1, 2]);
    check(&[3, 12]);
}

/// A camera at an eighth of the map's frame rate moves 8 positions a frame, beyond the default
/// range (0 to 4): with timestamps on both sides the range follows the rate, the stream's answers
/// stay near the truth and its sequence matches are accepted; without them the best trajectory
/// runs at the range's edge or without the newest frame's support (both counted, toward the
/// warning) and is accepted less often; what it accepts lies behind the camera unless the newest
/// frame must vouch for it strongly (`sequence.support` 0.5, which costs streams of look-alike
/// places, sweep 20).
#[test]
fn the_velocity_range_follows_the_frame_rates_of_map_and_stream() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, shift)) = drive(&dir.path().join("data")) else { return };
    let map = dir.path().join("map");
    let cfg = config();
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    // the map recorded at 30 frames/s
    let mut w = MapWriter::create(&map, &cfg.encoding(), Default::default(), None, StoreOptions::default(), false)
        .unwrap()
        .with_frame_interval(1.0 / 30.0)
        .unwrap();
    let mut scratch = Default::default();
    for f in &refs {
        w.push(&enc.encode_source(f, Default::default(), &mut scratch).unwrap().0).unwrap();
    }
    let m = w.finish().unwrap();
    assert_eq!(m.frame_interval(0), Some(1.0 / 30.0));
    drop(m);
    // the camera at 3.75 frames/s: every 8th frame of the drive
    let route: Vec<usize> = (0..refs.len()).step_by(8).collect();
    let stream_with = |timed: bool, support: f64| {
        let mut cfg = config();
        cfg.sequence.support = support;
        let opts = StreamOptions { setting: Setting::Forest, labelled_frames: true, ..Default::default() };
        let mut l = Localizer::open(&map, Some(cfg), opts, Engine::cpu()).unwrap();
        let results: Vec<(usize, FrameResult)> = route
            .iter()
            .enumerate()
            .map(|(k, &i)| {
                let f = StreamFrame { timestamp: timed.then_some(k as f64 / 3.75), ..frame(&shift[i]) };
                (i, l.push(f).unwrap())
            })
            .collect();
        (results, l.counts())
    };
    let stream = |timed: bool| stream_with(timed, config().sequence.support);
    let (timed, timed_counts) = stream(true);
    let (untimed, untimed_counts) = stream(false);
    let scale = timed.last().unwrap().1.sequence.as_ref().unwrap().velocity_scale;
    assert!((scale - 8.0).abs() < 1e-6, "the stream's interval over the map's: {scale}");
    let (with, without) = (near(&timed[10..], &refs, 2), near(&untimed[10..], &refs, 2));
    assert!(with >= 0.9, "with timestamps: {with:.2} near");
    assert!(without >= 0.8, "without timestamps: {without:.2} near");
    let off = |c: &semlook::stream::StreamCounts| c.velocity_edge + c.unsupported;
    assert!(off(&untimed_counts) > off(&timed_counts), "{untimed_counts:?} against {timed_counts:?}");
    // what the untimed stream accepts is where the camera is
    let accepted = |r: &[(usize, FrameResult)]| -> Vec<(usize, FrameResult)> {
        r.iter().filter(|(_, f)| f.sequence.as_ref().is_some_and(|s| s.matched.accepted)).cloned().collect()
    };
    let (a_timed, a_untimed) = (accepted(&timed), accepted(&untimed));
    assert!(a_timed.len() > a_untimed.len(), "accepted with timestamps {}, without {}", a_timed.len(), a_untimed.len());
    // behind the camera: with the default's support (any evidence of the newest frame near the
    // match) most of the few accepted are (a camera beyond the range: give timestamps); where the
    // newest frame must give half of its strongest evidence there, at most one
    let behind = |a: &[(usize, FrameResult)]| a.len() - (near(a, &refs, 2) * a.len() as f64).round() as usize;
    let strict = accepted(&stream_with(false, 0.5).0);
    assert!(
        behind(&strict) <= 1 && behind(&strict) < behind(&a_untimed),
        "behind the camera: {} of {} accepted, {} of {} at support 0.5",
        behind(&a_untimed),
        a_untimed.len(),
        behind(&strict),
        strict.len()
    );
}

/// A damaged map is refused when the stream starts, naming the file, not at its first frame:
/// the localizer runs the map's checks before it answers (Map::prepare); before, it opened and
/// the first frame's search found the damage. Seen failing with the checks left to the search.
#[test]
fn a_damaged_map_is_refused_when_the_stream_starts() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map");
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(4, 80, 60), "r");
    let m = Map::create(&map, &cfg.encoding(), &set, None).unwrap();
    let seg = map.join(&m.manifest.segments[0].file);
    drop(m);
    common::damage(&seg, 2, 0x10);
    let opened =
        Localizer::open(&map, Some(cfg), StreamOptions { setting: Setting::Global, labelled_frames: true, ..Default::default() }, Engine::cpu());
    match opened {
        Err(semlook::error::Error::CorruptMap { path, .. }) => assert_eq!(path, seg),
        Err(e) => panic!("refused otherwise: {e}"),
        Ok(_) => panic!("a damaged map opened for a stream"),
    }
}

/// A new generation with a damaged file (another writer's add, damaged on disk): `refresh` refuses
/// it, naming the file, the stream goes on answering from the old one, the next try is refused
/// again (at once: its checks are kept), and a later generation is checked anew and taken up once
/// the damage is gone. Seen failing with the checks left out of `refresh` (the damaged generation
/// taken up, its first search failing) and with a refused generation's checks kept for the next.
#[test]
fn a_damaged_new_generation_is_refused_and_the_stream_goes_on() {
    let dir = tempfile::tempdir().unwrap();
    let map = dir.path().join("map");
    let cfg = Config::without_appearance();
    let maps = common::label_maps(6, 80, 60);
    let set = common::encode(&cfg, &maps[..4], "r");
    drop(Map::create(&map, &cfg.encoding(), &set, None).unwrap());
    let mut l = Localizer::open(
        &map,
        Some(cfg.clone()),
        StreamOptions { setting: Setting::Global, labelled_frames: true, ..Default::default() },
        Engine::cpu(),
    )
    .unwrap();
    let push =
        |l: &mut Localizer, k: usize| l.push(StreamFrame { id: format!("q{k}"), pixels: Pixels::Labels(maps[k % 4].clone()), timestamp: None });
    let first = push(&mut l, 0).unwrap();
    // another writer adds two places; the new segment is damaged on disk
    let mut other = Map::open(&map).unwrap();
    other.add(&common::encode(&cfg, &maps[4..], "added")).unwrap();
    let seg = map.join(&other.manifest.segments[1].file);
    let good = common::damage(&seg, 3, 0x40);
    for _ in 0..2 {
        match l.refresh() {
            Err(semlook::error::Error::CorruptMap { path, .. }) => assert_eq!(path, seg),
            other => panic!("the damaged generation was not refused: {other:?}"),
        }
        let r = push(&mut l, 1).unwrap();
        assert_eq!(r.generation, first.generation, "answered from the damaged generation");
    }
    // the file mended and another generation committed: that one is checked anew and taken up
    std::fs::write(&seg, &good).unwrap();
    other.add(&common::encode(&cfg, &maps[..1], "more")).unwrap();
    assert!(l.refresh().unwrap());
    let r = push(&mut l, 2).unwrap();
    assert_eq!(r.generation, other.manifest.generation);
}
