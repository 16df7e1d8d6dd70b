//! `scripts/device-check.sh --smoke`, the reduced form of the device check CI runs on lavapipe so
//! the script cannot rot (issue 19 part 4): it writes one JSON naming the GPU adapter, with a coarse
//! row on the CPU and on the GPU and an encoding row on the GPU backend.

mod common;

#[test]
fn the_device_check_smoke_run_writes_its_json() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("device-check.json");
    // the encoding row's photos are labelled by the real segmenter, named (never the installed one)
    let segmenter: Vec<String> = common::real_segmenter().map(|s| vec!["--segmenter".into(), s.display().to_string()]).unwrap_or_default();
    let run = std::process::Command::new("bash")
        .arg(common::repo().join("scripts/device-check.sh"))
        .args(["--smoke", "--bin", env!("CARGO_BIN_EXE_semlook"), "--out", common::p(&out)])
        .args(&segmenter)
        .output()
        .expect("bash runs");
    let log = String::from_utf8_lossy(&run.stderr);
    assert!(run.status.success(), "device-check --smoke failed:\n{log}");
    let report: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&out).unwrap()).unwrap();
    assert_eq!(report["smoke"], true);
    let rows = report["rows"].as_array().unwrap();
    let ran = |row: &str, backend: &str| rows.iter().any(|r| r["row"] == row && r["backend"] == backend && r["status"] == "ran");
    assert!(ran("coarse", "cpu"), "no CPU coarse row: {report}");
    if report["gpu_adapters"].as_array().is_none_or(|a| a.is_empty()) {
        return common::skip_unless_required("REQUIRE_GPU", format!("no GPU adapter for the device check's GPU rows:\n{log}"));
    }
    assert!(ran("coarse", "gpu"), "no GPU coarse row: {report}");
    let encode = rows.iter().find(|r| r["row"] == "encode").expect("an encoding row");
    match encode["result"]["frames"].as_u64() {
        Some(n) => assert_eq!(n, 4, "{encode}"),
        None => {
            assert!(encode["reason"].as_str().is_some_and(|r| !r.is_empty()), "{encode}");
            common::skip_unless_required("REQUIRE_MODELS", format!("the encoding row did not run: {encode}"));
        }
    }
    let stream = rows.iter().find(|r| r["row"] == "stream").expect("a stream row");
    match stream["result"]["frames"].as_u64() {
        Some(n) => assert_eq!(n, 8, "{stream}"),
        None => {
            assert!(stream["reason"].as_str().is_some_and(|r| !r.is_empty()), "{stream}");
            common::skip_unless_required("REQUIRE_MODELS", format!("the stream row did not run: {stream}"));
        }
    }
    let index = rows.iter().find(|r| r["row"] == "index").expect("an index row");
    match index["result"]["map_size"].as_u64() {
        Some(n) => {
            assert_eq!(n, 2000, "{index}");
            let recall = index["result"]["recall_at_30"].as_f64().unwrap_or(-1.0);
            assert!((0.0..=1.0).contains(&recall), "the index row measures its recall: {index}");
        }
        None => {
            assert!(index["reason"].as_str().is_some_and(|r| !r.is_empty()), "{index}");
            common::skip_unless_required("REQUIRE_MODELS", format!("the index row did not run: {index}"));
        }
    }
    for left_out in ["fine", "verify"] {
        assert!(
            rows.iter().any(|r| r["row"] == left_out && r["status"] == "not run"),
            "the smoke run names the rows it leaves out ({left_out}): {report}"
        );
    }
}
