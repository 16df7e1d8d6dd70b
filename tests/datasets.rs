//! Dataset layouts other than the synthetic one, on small fixtures laid out like the real datasets.

use image::{GrayImage, Luma};
use semlook::eval::dataset::{Dataset, DatasetOptions};
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
    std::fs::write(
        root.join("slice6/gt-db.txt"),
        "img_00001_c0_100us.jpg 1 0 0 0 0 0 0\nimg_00002_c0_200us.jpg 1 0 0 0 0 0 10\n",
    )
    .unwrap();
    std::fs::write(
        root.join("slice6/gt-q.txt"),
        "img_00101_c0_900us.jpg 1 0 0 0 0.5 0 1\nimg_00102_c0_950us.jpg 0 0 1 0 0 0 9\n",
    )
    .unwrap();
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
    let rep = semlook::eval::evaluate(&ds, &cfg, &semlook::eval::EvalOptions { settings: vec![semlook::matching::Setting::Semlook], map: None, skip_invalid: false, quiet: true }, &mut semlook::engine::Engine::cpu()).unwrap();
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
