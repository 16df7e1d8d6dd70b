//! The store's soak test (issue 20; ignored by default, it runs for half an hour):
//! `SEMLOOK_SOAK_SECS=1800 cargo test --release --test soak -- --ignored --nocapture`.
//!
//! Three workers run `semlook map add / remove / compact` and `query` against one map at once,
//! and a random share of the processes is killed (SIGKILL) at a random moment. Each worker adds
//! and removes only its own ids, so after every command it knows for each of them whether the map
//! holds it (a killed command's outcome is read back from the map). At the end, after one last
//! compaction: `map verify` passes and lists no leftover temporaries; every id a worker knows to be
//! stored is there and no removed one is; every stored image equals, bit for bit, the same frame
//! built into a map of its own; and the map folder never held more than a bounded multiple of
//! the full map's bytes.

mod common;

use common::p;
use semlook::map::Map;
use semlook::util::SplitMix64;
use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

/// Frames in the pool (each worker owns a third of them).
const FRAMES: usize = 36;
const WORKERS: usize = 3;
/// Share of the commands that are killed at a random moment.
const KILL_SHARE: f64 = 0.3;
/// A killed command dies within this many milliseconds of its start.
const KILL_WITHIN_MS: u64 = 60;
/// The folder may hold at most this multiple of the bytes of a map of every frame: a compaction
/// writes its new segment before the old ones go, and a killed writer's temporaries stay until
/// the next writer takes the lock.
const SPACE_FACTOR: u64 = 4;

#[derive(Clone, Copy, PartialEq, Debug)]
enum Held {
    Yes,
    No,
}

fn semlook() -> Command {
    let mut c = Command::new(env!("CARGO_BIN_EXE_semlook"));
    c.stdout(Stdio::null()).stderr(Stdio::piped());
    c
}

/// Bytes of every file under `dir` (temporaries included).
fn bytes_under(dir: &Path) -> u64 {
    std::fs::read_dir(dir).into_iter().flatten().flatten().filter_map(|e| e.metadata().ok()).filter(|m| m.is_file()).map(|m| m.len()).sum()
}

fn stored_ids(map: &Path) -> Vec<String> {
    // a reader may meet a compaction that deletes segments between its reads: open retries
    Map::open(map).and_then(|m| m.to_descriptor_set()).map(|s| s.ids).unwrap_or_else(|e| panic!("map does not open: {e}"))
}

/// What the workers saw go wrong (not kills).
#[derive(Default)]
struct Tally {
    commands: u64,
    killed: u64,
    failures: Vec<String>,
}

/// A folder of links to `ids`' image and label files, for one command.
fn frames_dir(pool: &Path, at: &Path, ids: &[String]) -> PathBuf {
    let _ = std::fs::remove_dir_all(at);
    for sub in ["images", "labels"] {
        std::fs::create_dir_all(at.join(sub)).unwrap();
        for id in ids {
            std::fs::hard_link(pool.join(sub).join(format!("{id}.png")), at.join(sub).join(format!("{id}.png"))).unwrap();
        }
    }
    at.to_path_buf()
}

/// `semlook COMMAND --map MAP` on the frames linked into `dir` (label-only, CPU), with `extra`.
fn on_frames(command: &[&str], map: &Path, dir: &Path, extra: &[&str]) -> Command {
    let mut c = semlook();
    c.args(command).args(["--map", p(map), "--images", p(&dir.join("images")), "--labels", p(&dir.join("labels"))]);
    c.args(extra).args(["--no-segmenter", "--backend", "cpu", "-q"]);
    c
}

#[allow(clippy::too_many_arguments)]
fn worker(
    w: usize,
    seed: u64,
    pool: PathBuf,
    map: PathBuf,
    scratch: PathBuf,
    mine: Vec<String>,
    deadline: Instant,
    tally: Arc<Mutex<Tally>>,
) -> BTreeMap<String, Held> {
    let mut rng = SplitMix64::new(seed ^ ((w as u64 + 1) * 0x9E37_79B9));
    let stored = stored_ids(&map);
    let mut held: BTreeMap<String, Held> = mine.iter().map(|id| (id.clone(), if stored.contains(id) { Held::Yes } else { Held::No })).collect();
    let mut n = 0u64;
    while Instant::now() < deadline {
        n += 1;
        let pick = |rng: &mut SplitMix64, state: Held, most: usize, held: &BTreeMap<String, Held>| -> Vec<String> {
            let mut c: Vec<String> = held.iter().filter(|(_, &h)| h == state).map(|(id, _)| id.clone()).collect();
            let mut out = Vec::new();
            while !c.is_empty() && out.len() < most {
                out.push(c.swap_remove(rng.below(c.len())));
            }
            out
        };
        let at = scratch.join(format!("w{w}-{n}"));
        let (what, touched, mut cmd) = match rng.below(10) {
            0..=3 => {
                let most = 1 + rng.below(4);
                let ids = pick(&mut rng, Held::No, most, &held);
                if ids.is_empty() {
                    continue;
                }
                let d = frames_dir(&pool, &at, &ids);
                ("add", ids, on_frames(&["map", "add"], &map, &d, &[]))
            }
            4..=5 => {
                let most = 1 + rng.below(3);
                let ids = pick(&mut rng, Held::Yes, most, &held);
                if ids.is_empty() {
                    continue;
                }
                let mut c = semlook();
                c.args(["map", "remove", "--map", p(&map), "--ids"]).args(&ids).arg("-q");
                ("remove", ids, c)
            }
            6 => {
                let mut c = semlook();
                c.args(["map", "compact", "--map", p(&map), "-q"]);
                ("compact", vec![], c)
            }
            _ => {
                let id = &mine[rng.below(mine.len())];
                let d = frames_dir(&pool, &at, std::slice::from_ref(id));
                ("query", vec![], on_frames(&["query"], &map, &d, &["--setting", "local"]))
            }
        };
        let kill_at = rng.chance(KILL_SHARE).then(|| Duration::from_millis(rng.below(KILL_WITHIN_MS as usize) as u64));
        let mut child = cmd.spawn().expect("semlook starts");
        let started = Instant::now();
        let mut killed = false;
        let status = loop {
            if let Some(s) = child.try_wait().unwrap() {
                break s;
            }
            if kill_at.is_some_and(|k| started.elapsed() >= k) {
                child.kill().unwrap();
                killed = true;
                break child.wait().unwrap();
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        let mut err = String::new();
        if let Some(mut e) = child.stderr.take() {
            let _ = std::io::Read::read_to_string(&mut e, &mut err);
        }
        let mut t = tally.lock().unwrap();
        t.commands += 1;
        if killed && !status.success() {
            t.killed += 1;
            drop(t);
            // the killed command committed or did not: the map says which
            let now = stored_ids(&map);
            for id in &touched {
                held.insert(id.clone(), if now.contains(id) { Held::Yes } else { Held::No });
            }
        } else if status.success() {
            drop(t);
            let state = match what {
                "add" => Held::Yes,
                _ => Held::No,
            };
            for id in &touched {
                held.insert(id.clone(), state);
            }
        } else {
            t.failures.push(format!("worker {w}: {what} {touched:?} failed ({status}): {err}"));
        }
        let _ = std::fs::remove_dir_all(&at);
    }
    held
}

#[test]
#[ignore]
fn three_processes_with_random_kills_lose_nothing_committed() {
    let secs: f64 = std::env::var("SEMLOOK_SOAK_SECS").ok().and_then(|s| s.parse().ok()).unwrap_or(1800.0);
    let seed: u64 = std::env::var("SEMLOOK_SOAK_SEED").ok().and_then(|s| s.parse().ok()).unwrap_or(20261202);
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::cli_ok(&["synth", "--out", p(&data), "--places", &FRAMES.to_string(), "--size", "96x72", "-q"]);
    let pool = dir.path().join("pool");
    for (sub, from) in [("images", "RGB/Stereo_Left/Omni_F"), ("labels", "GT/LABELS/Stereo_Left/Omni_F")] {
        std::fs::create_dir_all(pool.join(sub)).unwrap();
        for e in std::fs::read_dir(data.join("day").join(from)).unwrap().flatten() {
            std::fs::copy(e.path(), pool.join(sub).join(e.file_name())).unwrap();
        }
    }
    let mut ids: Vec<String> =
        std::fs::read_dir(pool.join("images")).unwrap().flatten().map(|e| e.path().file_stem().unwrap().to_str().unwrap().to_string()).collect();
    ids.sort();
    assert_eq!(ids.len(), FRAMES);
    let label_only = ["--no-appearance", "--no-segmenter", "--backend", "cpu", "-q"];
    // the reference: every frame in a map of its own, built once without interference
    let truth = dir.path().join("truth");
    common::cli_ok(
        &[&["map", "build", "--images", p(&pool.join("images")), "--labels", p(&pool.join("labels")), "--map", p(&truth)][..], &label_only].concat(),
    );
    let full_bytes = bytes_under(&truth);
    // the map under test starts with every worker's first two frames
    let scratch = dir.path().join("scratch");
    std::fs::create_dir_all(&scratch).unwrap();
    let first: Vec<String> = (0..WORKERS).flat_map(|w| ids.iter().skip(w).step_by(WORKERS).take(2).cloned()).collect();
    let start = frames_dir(&pool, &scratch.join("start"), &first);
    let map = dir.path().join("map");
    common::cli_ok(
        &[
            &["map", "build", "--images", p(&start.join("images")), "--labels", p(&start.join("labels")), "--map", p(&map), "--segment-images", "4"]
                [..],
            &label_only,
        ]
        .concat(),
    );

    let deadline = Instant::now() + Duration::from_secs_f64(secs);
    let tally = Arc::new(Mutex::new(Tally::default()));
    let (stop, peak) = (Arc::new(AtomicBool::new(false)), Arc::new(AtomicU64::new(0)));
    let watcher = {
        let (stop, peak, map) = (stop.clone(), peak.clone(), map.clone());
        std::thread::spawn(move || {
            while !stop.load(Ordering::Relaxed) {
                peak.fetch_max(bytes_under(&map), Ordering::Relaxed);
                std::thread::sleep(Duration::from_millis(20));
            }
        })
    };
    let handles: Vec<_> = (0..WORKERS)
        .map(|w| {
            let mine: Vec<String> = ids.iter().skip(w).step_by(WORKERS).cloned().collect();
            let (pool, map, scratch, tally) = (pool.clone(), map.clone(), scratch.clone(), tally.clone());
            std::thread::spawn(move || worker(w, seed, pool, map, scratch, mine, deadline, tally))
        })
        .collect();
    let mut held = BTreeMap::new();
    for h in handles {
        held.extend(h.join().expect("worker"));
    }
    stop.store(true, Ordering::Relaxed);
    watcher.join().unwrap();

    // one last compaction (not killed) removes what killed writers left; verify then finds none
    common::cli_ok(&["map", "compact", "--map", p(&map), "-q"]);
    let verify: serde_json::Value = serde_json::from_str(&common::cli_ok(&["map", "verify", "--map", p(&map), "--json"])).unwrap();
    assert_eq!(verify["leftovers"].as_array().map(Vec::len), Some(0), "leftover temporaries: {verify}");
    let t = tally.lock().unwrap();
    eprintln!(
        "{} commands ({} killed) in {secs} s by {WORKERS} workers; peak folder size {} bytes (a map of every frame: {full_bytes})",
        t.commands,
        t.killed,
        peak.load(Ordering::Relaxed)
    );
    assert!(t.failures.is_empty(), "{} commands failed without being killed:\n{}", t.failures.len(), t.failures.join("\n"));
    assert!(t.killed > 0 && t.commands > t.killed, "the soak ran too short to kill anything");

    let stored = Map::open(&map).unwrap().to_descriptor_set().unwrap();
    let reference = Map::open(&truth).unwrap().to_descriptor_set().unwrap();
    for (id, h) in &held {
        assert_eq!(stored.ids.contains(id), *h == Held::Yes, "{id}: the workers know it as {h:?}");
    }
    assert_eq!(stored.ids.len(), held.values().filter(|&&h| h == Held::Yes).count(), "the map holds ids no worker added");
    for (i, id) in stored.ids.iter().enumerate() {
        let j = reference.ids.iter().position(|r| r == id).unwrap();
        assert!(stored.slice(i, i + 1) == reference.slice(j, j + 1), "{id}: the stored image differs from the same frame built alone");
    }
    let peak = peak.load(Ordering::Relaxed);
    assert!(peak <= SPACE_FACTOR * full_bytes, "the folder held {peak} bytes, above {SPACE_FACTOR} x {full_bytes}");
}
