//! Progress a user can follow: with stderr not a terminal, long commands print plain progress
//! lines there (never bar redraws), `--quiet` silences them, and `--json` stdout stays clean.

mod common;

use common::{cli, p};

/// stdout and stderr of a run that must succeed.
fn run(args: &[&str]) -> (String, String) {
    let out = cli(args);
    let err = String::from_utf8(out.stderr).unwrap();
    assert!(out.status.success(), "semlook {args:?} failed:\n{err}");
    (String::from_utf8(out.stdout).unwrap(), err)
}

/// The plain progress lines of `message` in `stderr`: `message: done/len (pct %), rate/s, ...`.
fn lines<'a>(stderr: &'a str, message: &str) -> Vec<&'a str> {
    stderr.lines().filter(|l| l.starts_with(&format!("{message}: ")) && l.contains(" %), ") && l.contains("/s, ")).collect()
}

#[test]
fn piped_stderr_gets_plain_progress_lines_and_json_stays_clean() {
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    let (_, err) = run(&["synth", "--out", p(&data), "--places", "12", "--size", "160x120", "--query-condition", "night"]);
    let rendering = lines(&err, "rendering");
    assert_eq!(rendering.last().copied().map(|l| l.split(',').next().unwrap()), Some("rendering: 24/24 (100 %)"), "{err}");
    // one line per tenth at most (24 steps: 10 tenths), and the last says how long it took
    assert!(rendering.len() <= 10 && rendering.last().unwrap().contains(", in "), "{rendering:?}");
    assert!(!err.contains('\r') && !err.contains('\u{1b}'), "a terminal bar was drawn into a pipe: {err:?}");

    let map = dir.path().join("map");
    let (_, err) = run(&["map", "build", "--dataset", p(&data), "--map", p(&map), "--no-appearance"]);
    assert!(lines(&err, "images").last().is_some_and(|l| l.starts_with("images: 12/12 (100 %)")), "{err}");

    let (out, err) = run(&["eval", "--dataset", p(&data), "--setting", "global", "--json", "--no-appearance"]);
    let report: serde_json::Value = serde_json::from_str(&out).unwrap_or_else(|e| panic!("stdout is not JSON ({e}):\n{out}"));
    assert_eq!(report["results"].as_array().unwrap().len(), 1);
    for what in ["references", "queries night", "matching night"] {
        assert!(!lines(&err, what).is_empty(), "no {what:?} progress in:\n{err}");
    }

    let (out, err) = run(&["eval", "--dataset", p(&data), "--setting", "global", "--json", "--no-appearance", "-q"]);
    serde_json::from_str::<serde_json::Value>(&out).unwrap();
    assert!(!err.contains(" %), "), "--quiet still printed progress:\n{err}");
}
