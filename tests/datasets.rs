//! Dataset layouts other than the synthetic one, on small fixtures laid out like the real datasets.

use image::{GrayImage, Luma};
use semlook::dataset::pairs::{from_folders, PairTruth};
use semlook::dataset::{Dataset, DatasetOptions};
use std::path::Path;

fn label(path: &Path, class: u8) {
    std::fs::create_dir_all(path.parent().unwrap()).unwrap();
    let mut g = GrayImage::from_pixel(64, 48, Luma([0]));
    for y in 0..20 {
        for x in 10..30 {
            g.put_pixel(x, y, Luma([class]));
        }
    }
    g.save(path).unwrap();
}

#[test]
fn folders_layout_like_extended_cmu_seasons() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    // images in slice6/database and slice6/query; labels computed beforehand in labels/...
    for (sub, names) in [("database", ["img_00001_c0_100us", "img_00002_c0_200us"]), ("query", ["img_00101_c0_900us", "img_00102_c0_950us"])] {
        for (k, n) in names.iter().enumerate() {
            label(&root.join("slice6").join(sub).join(format!("{n}.jpg")), 2);
            label(&root.join("labels/slice6").join(sub).join(format!("{n}.png")), 2 + k as u8);
        }
    }
    std::fs::write(root.join("slice6/gt-db.txt"), "img_00001_c0_100us.jpg 1 0 0 0 0 0 0\nimg_00002_c0_200us.jpg 1 0 0 0 0 0 10\n").unwrap();
    std::fs::write(root.join("slice6/gt-q.txt"), "img_00101_c0_900us.jpg 1 0 0 0 0.5 0 1\nimg_00102_c0_950us.jpg 0 0 1 0 0 0 9\n").unwrap();
    let manifest = r#"{ "format": "semlook-dataset", "version": 1, "layout": "folders",
      "reference": { "name": "database", "images": "slice6/database", "labels": "labels/slice6/database",
                     "poses": "slice6/gt-db.txt", "pose_format": "quat_center" },
      "queries": [ { "name": "query", "images": "slice6/query", "labels": "labels/slice6/query",
                     "poses": "slice6/gt-q.txt", "pose_format": "quat_center" } ],
      "ground_truth": { "max_distance": 5.0, "max_angle_deg": 30 } }"#;
    std::fs::write(root.join("semlook-dataset.json"), manifest).unwrap();
    let ds = Dataset::open(root, &DatasetOptions::default()).unwrap();
    assert_eq!(ds.reference.frames.len(), 2);
    assert_eq!(ds.reference.frames[1].source.id, "database/img_00002_c0_200us");
    assert!(ds.reference.frames[0].source.labels.as_ref().unwrap().ends_with("labels/slice6/database/img_00001_c0_100us.png"));
    // query 0 is near reference 0 facing the same way; query 1 is near reference 1 but turned 180 degrees
    let gt = ds.ground_truth(&ds.queries[0]).unwrap();
    assert_eq!(gt, vec![vec![0], vec![]]);
    let loose = Dataset::open(root, &DatasetOptions { max_distance: Some(5.0), ..Default::default() }).unwrap();
    assert_eq!(loose.ground_truth(&loose.queries[0]).unwrap(), vec![vec![0], vec![1]]);
    // the pipeline runs on it
    let cfg = semlook::config::Config::without_appearance();
    let rep = semlook::eval::evaluate(
        &ds,
        &cfg,
        &semlook::eval::EvalOptions {
            settings: vec![semlook::matching::Setting::Semlook],
            map: None,
            skip_invalid: false,
            quiet: true,
            sequence: false,
            label_cache: None,
        },
        &mut semlook::engine::Engine::cpu(),
    )
    .unwrap();
    assert_eq!(rep.results[0].queries_without_ground_truth, 1);
}

#[test]
fn explicit_layout_with_listed_ground_truth_and_a_missing_pose_line() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    label(&root.join("r0.png"), 2);
    label(&root.join("r1.png"), 8);
    label(&root.join("q0.png"), 8);
    let manifest = r#"{ "format": "semlook-dataset", "version": 1, "layout": "explicit",
      "reference": { "name": "refs", "frames": [ { "id": "r0", "labels": "r0.png" }, { "id": "r1", "labels": "r1.png" } ] },
      "queries": [ { "name": "q", "frames": [ { "id": "q0", "labels": "q0.png", "ground_truth": [1] } ] } ] }"#;
    std::fs::write(root.join("semlook-dataset.json"), manifest).unwrap();
    let ds = Dataset::open(root, &DatasetOptions::default()).unwrap();
    assert_eq!(ds.ground_truth(&ds.queries[0]).unwrap(), vec![vec![1]]);
    let bad = manifest.replace("\"ground_truth\": [1]", "\"ground_truth\": [7]");
    std::fs::write(root.join("semlook-dataset.json"), bad).unwrap();
    let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("names reference 7"), "{err}");
    // folders layout whose pose list lacks an image
    std::fs::create_dir_all(root.join("imgs")).unwrap();
    label(&root.join("imgs/a.png"), 2);
    std::fs::write(root.join("poses.txt"), "b.png 1 0 0 0 0 0 0\n").unwrap();
    let m = r#"{ "format": "semlook-dataset", "version": 1, "layout": "folders",
      "reference": { "name": "r", "images": "imgs", "poses": "poses.txt" }, "queries": [ { "name": "r2", "images": "imgs" } ] }"#;
    std::fs::write(root.join("semlook-dataset.json"), m).unwrap();
    let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("a.png"), "{err}");
}

/// Writes label images (usable as frames) `dir/names[i]`.
fn frames(dir: &Path, names: &[&str]) {
    for (k, n) in names.iter().enumerate() {
        label(&dir.join(n), 2 + k as u8);
    }
}

#[test]
fn real_vpr_layout_with_a_csv_of_query_reference_rows() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path();
    frames(&root.join("ref"), &["00.png", "01.png", "02.png"]);
    frames(&root.join("query"), &["00.png", "01.png", "02.png"]);
    // several rows per query, paths relative to the CSV's folder, one query without a row
    std::fs::write(root.join("ground_truth.csv"), "query,reference\nquery/00.png,ref/00.png\nquery/00.png,ref/01.png\nquery/01.png,./ref/02.png\n")
        .unwrap();
    let ds = Dataset::open(root, &DatasetOptions::default()).unwrap();
    assert_eq!((ds.reference.name.as_str(), ds.queries[0].name.as_str()), ("ref", "query"));
    assert_eq!(ds.reference.frames[1].source.id, "ref/01.png");
    assert_eq!(ds.ground_truth(&ds.queries[0]).unwrap(), vec![vec![0, 1], vec![2], vec![]]);
    // the same through explicit folders and file (what `eval --references --queries --ground-truth` does)
    let truth = PairTruth::from_file(&root.join("ground_truth.csv")).unwrap();
    let same = from_folders(&root.join("ref"), &root.join("query"), &truth).unwrap();
    assert_eq!(same.ground_truth(&same.queries[0]).unwrap(), ds.ground_truth(&ds.queries[0]).unwrap());
    // a row naming an image that is not there is an error naming the CSV and the line
    std::fs::write(root.join("ground_truth.csv"), "query,reference\nquery/00.png,ref/07.png\n").unwrap();
    let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("ground_truth.csv") && err.contains("line 2") && err.contains("ref/07.png"), "{err}");
    // a header and no rows: refused (before, eval printed AUC 0.000 without a word)
    std::fs::write(root.join("ground_truth.csv"), "query,reference\n").unwrap();
    let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("ground_truth.csv") && err.contains("no query has a valid reference"), "{err}");
    std::fs::write(root.join("ground_truth.csv"), "q,r\nquery/00.png,ref/00.png\n").unwrap();
    let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("\"query\" column"), "{err}");
}

#[test]
fn vpr_bench_layout_reads_every_numpy_variant() {
    let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data");
    for name in ["vprbench_lists.npy", "vprbench_arrays_p2.npy", "vprbench_rows.npy"] {
        let dir = tempfile::tempdir().unwrap();
        let root = dir.path();
        frames(&root.join("ref"), &["a.png", "b.png", "c.png", "d.png"]);
        frames(&root.join("query"), &["x.png", "y.png", "z.png"]);
        std::fs::copy(fixtures.join(name), root.join("ground_truth_new.npy")).unwrap();
        let ds = Dataset::open(root, &DatasetOptions::default()).unwrap();
        assert_eq!(ds.ground_truth(&ds.queries[0]).unwrap(), vec![vec![0, 1], vec![1, 2], vec![3]], "{name}");
        // one reference fewer: index 3 is out of range, and the error says so
        std::fs::remove_file(root.join("ref/d.png")).unwrap();
        let err = Dataset::open(root, &DatasetOptions::default()).unwrap_err().to_string();
        assert!(err.contains("ground_truth_new.npy") && err.contains("reference index 3"), "{name}: {err}");
    }
    // truncated files are errors, never panics
    let bytes = std::fs::read(fixtures.join("vprbench_arrays_p2.npy")).unwrap();
    let dir = tempfile::tempdir().unwrap();
    frames(&dir.path().join("ref"), &["a.png", "b.png", "c.png", "d.png"]);
    frames(&dir.path().join("query"), &["x.png", "y.png", "z.png"]);
    for cut in (0..bytes.len()).step_by(7) {
        std::fs::write(dir.path().join("ground_truth_new.npy"), &bytes[..cut]).unwrap();
        assert!(Dataset::open(dir.path(), &DatasetOptions::default()).is_err(), "cut at {cut}");
    }
}

#[test]
fn gmberton_layout_takes_positives_from_utm_names() {
    let dir = tempfile::tempdir().unwrap();
    let root = dir.path().join("images/test");
    let utm = |e: f64, n: f64| format!("@{e:.2}@{n:.2}@10@S@37.7@-122.5@@@@@@@@.png");
    frames(&root.join("database"), &[&utm(1000.0, 5000.0), &utm(1020.0, 5000.0), &utm(1100.0, 5000.0)]);
    frames(&root.join("queries"), &[&utm(1010.0, 5000.0), &utm(1095.0, 5003.0)]);
    let ds = Dataset::open(dir.path(), &DatasetOptions::default()).unwrap();
    // default radius 25 m
    let mut gt = ds.ground_truth(&ds.queries[0]).unwrap();
    gt.iter_mut().for_each(|g| g.sort());
    // database files sort by name: @1000, @1020, @1100
    assert_eq!(gt, vec![vec![0, 1], vec![2]]);
    let tight = Dataset::open(dir.path(), &DatasetOptions { max_distance: Some(5.0), ..Default::default() }).unwrap();
    assert_eq!(tight.ground_truth(&tight.queries[0]).unwrap(), vec![Vec::<u32>::new(), vec![]]);
    let err = Dataset::open(dir.path(), &DatasetOptions { max_angle_deg: Some(30.0), ..Default::default() }).unwrap_err().to_string();
    assert!(err.contains("ground-truth angle"), "{err}");
    // a file without a position is named
    label(&root.join("queries/plain.png"), 2);
    let err = Dataset::open(dir.path(), &DatasetOptions::default()).unwrap_err().to_string();
    assert!(err.contains("plain.png"), "{err}");
}
