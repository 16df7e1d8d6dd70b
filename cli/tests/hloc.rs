//! hloc interop: `query --pairs` writes hloc's retrieval pairs (names relative to the image root,
//! each query's top K in rank order), and names hloc could not read back are refused.

mod common;

use common::{cli, cli_ok as ok, p};
use semlook::hloc::{common_root, image_name, reference_names};
use std::path::{Path, PathBuf};

/// hloc's `parse_retrieval`: `q r` lines split on whitespace, references per query in order.
fn parse_retrieval(text: &str) -> Vec<(String, Vec<String>)> {
    let mut out: Vec<(String, Vec<String>)> = Vec::new();
    for line in text.lines().filter(|l| !l.is_empty()) {
        let parts: Vec<&str> = line.split_whitespace().collect();
        assert_eq!(parts.len(), 2, "line {line:?}");
        match out.iter_mut().find(|(q, _)| q == parts[0]) {
            Some((_, refs)) => refs.push(parts[1].into()),
            None => out.push((parts[0].into(), vec![parts[1].into()])),
        }
    }
    out
}

/// A synthetic set: (root, day images, day labels, night images, night labels).
fn synth(dir: &Path) -> [PathBuf; 5] {
    let data = dir.join("data");
    ok(&["synth", "--out", p(&data), "--places", "6", "--size", "160x120", "--query-condition", "night", "-q"]);
    let f = |t: &str, kind: &str| data.join(t).join(kind).join("Stereo_Left/Omni_F");
    [data.clone(), f("day", "RGB"), f("day", "GT/LABELS"), f("night", "RGB"), f("night", "GT/LABELS")]
}

#[test]
fn pairs_are_each_querys_top_k_named_under_the_image_root() {
    let dir = tempfile::tempdir().unwrap();
    let [data, day, day_labels, night, night_labels] = synth(dir.path());
    let map = dir.path().join("map");
    ok(&["map", "build", "--images", p(&day), "--labels", p(&day_labels), "--map", p(&map), "--no-appearance", "-q"]);
    let pairs = dir.path().join("pairs.txt");
    let query = ["query", "--map", p(&map), "--images", p(&night), "--labels", p(&night_labels), "--no-appearance", "--json", "-q"];
    let json: serde_json::Value =
        serde_json::from_str(&ok(&[&query[..], &["--pairs", p(&pairs), "--references", p(&day), "--pairs-k", "3"]].concat())).unwrap();
    let parsed = parse_retrieval(&std::fs::read_to_string(&pairs).unwrap());
    // one entry per query, K = 3 references each, in the order of the query's own top-K
    assert_eq!(parsed.len(), 6);
    for ((q, refs), row) in parsed.iter().zip(json["queries"].as_array().unwrap()) {
        assert_eq!(q, &format!("night/RGB/Stereo_Left/Omni_F/{}.png", row["query"].as_str().unwrap()));
        let top: Vec<String> = row["top_k"]
            .as_array()
            .unwrap()
            .iter()
            .take(3)
            .map(|t| format!("day/RGB/Stereo_Left/Omni_F/{}.png", t["reference"].as_str().unwrap()))
            .collect();
        assert_eq!(refs, &top);
        assert!(refs.iter().chain([q]).all(|n| data.join(n).is_file()), "{q}: {refs:?}");
    }
    // a root that does not hold the references is refused; the query folder itself as the root
    // (its own references) gives bare file names
    let out = cli(&[&query[..], &["--pairs", p(&pairs), "--references", p(&day), "--pairs-root", p(&night)]].concat());
    assert!(!out.status.success() && String::from_utf8_lossy(&out.stderr).contains("is not inside the image root"));
    let out = ok(&[&query[..], &["--pairs", p(&pairs), "--references", p(&night), "--pairs-root", p(&night)]].concat());
    assert!(out.contains("\"queries\""));
    let parsed = parse_retrieval(&std::fs::read_to_string(&pairs).unwrap());
    assert_eq!(parsed[0].0, "000000.png");
    assert!(parsed.iter().all(|(_, refs)| refs.len() == 6 && !refs[0].contains('/')), "the whole list (6 of top_k 20): {parsed:?}");
}

#[test]
fn names_hloc_cannot_read_back_are_refused_before_encoding() {
    let dir = tempfile::tempdir().unwrap();
    let [_, day, day_labels, night, night_labels] = synth(dir.path());
    let map = dir.path().join("map");
    ok(&["map", "build", "--images", p(&day), "--labels", p(&day_labels), "--map", p(&map), "--no-appearance", "-q"]);
    let pairs = dir.path().join("pairs.txt");
    let run = |images: &Path, labels: &Path, refs: &Path| {
        let out = cli(&[
            "query",
            "--map",
            p(&map),
            "--images",
            p(images),
            "--labels",
            p(labels),
            "--no-appearance",
            "-q",
            "--pairs",
            p(&pairs),
            "--references",
            p(refs),
        ]);
        assert_eq!(out.status.code(), Some(1));
        assert!(!pairs.exists());
        String::from_utf8(out.stderr).unwrap()
    };
    // a query file name with a space: hloc would split the line there
    let spaced = dir.path().join("spaced");
    std::fs::create_dir(&spaced).unwrap();
    std::fs::copy(night.join("000001.png"), spaced.join("a b.png")).unwrap();
    let err = run(&spaced, &night_labels, &day);
    assert!(err.contains("a b.png") && err.contains("whitespace"), "{err}");
    // a map image missing from the reference folder is named
    std::fs::remove_file(spaced.join("a b.png")).unwrap();
    std::fs::copy(day.join("000002.png"), spaced.join("000002.png")).unwrap();
    let err = run(&night, &night_labels, &spaced);
    assert!(err.contains("map image \"000000\"") && err.contains("no image file"), "{err}");
}

#[test]
fn reference_names_refuse_what_they_cannot_tell_apart() {
    let dir = tempfile::tempdir().unwrap();
    let (a, b) = (dir.path().join("db/a"), dir.path().join("db/b"));
    for d in [&a, &b] {
        std::fs::create_dir_all(d).unwrap();
    }
    for f in [a.join("x.jpg"), a.join("y.png"), a.join("y.jpg"), b.join("x.png"), b.join("z.png")] {
        std::fs::write(f, b"").unwrap();
    }
    let root = dir.path().join("db");
    let names = reference_names(&["z", "a/x.jpg", "b/x.png"], &[a.clone(), b.clone()], &root).unwrap();
    assert_eq!(names, ["b/z.png", "a/x.jpg", "b/x.png"]);
    let err = |ids: &[&str], folders: &[PathBuf]| reference_names(ids, folders, &root).unwrap_err().to_string();
    assert!(err(&["y"], std::slice::from_ref(&a)).contains("more than one image file"));
    assert!(err(&["x"], &[a.clone(), b.clone()]).contains("more than one image file"));
    assert!(err(&["t1/z", "t2/z"], std::slice::from_ref(&b)).contains("also map image \"t1/z\""));
    assert!(err(&["w"], std::slice::from_ref(&a)).contains("no image file w.*"));
    // names: relative, `/`-separated, `..` applied; outside the root refused
    assert_eq!(image_name(&root, &root.join("a/../b/z.png")).unwrap(), "b/z.png");
    // the engine names the remedy; the command line words it as --pairs-root (cli::hint)
    let outside = image_name(&a, &b.join("z.png")).unwrap_err();
    assert!(outside.to_string().contains("is not inside the image root"), "{outside}");
    assert_eq!(outside.remedy(), Some(semlook::error::Remedy::NameImageRoot));
    assert_eq!(common_root(&[a.clone(), b.join("."), a.join("deeper")]).unwrap(), semlook::hloc::absolute(&root).unwrap());
}
