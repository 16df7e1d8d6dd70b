//! `eval --report`: one self-contained page (every picture a data: URI, data escaped) with a row
//! per setting, two charts per query set and the worst queries' sheets; and, in headless
//! Chromium (Debian's `chromium`, installed by setup.sh), it renders: every image decodes, no
//! script error, a screenshot that is not blank.

mod common;

use common::{cli_ok as ok, p};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// A synthetic set in a folder whose name needs escaping, evaluated with `--report`: the
/// report folder and the evaluation's JSON.
fn report(dir: &Path) -> (PathBuf, serde_json::Value) {
    let data = dir.join("set <b>&\"'");
    ok(&["synth", "--out", p(&data), "--places", "6", "--size", "160x120", "--query-condition", "night", "-q"]);
    // and a dataset name that does
    let manifest = data.join("semlook-dataset.json");
    let mut m: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(&manifest).unwrap()).unwrap();
    m["name"] = "synth <b>&\"'".into();
    std::fs::write(&manifest, m.to_string()).unwrap();
    let out = dir.join("report");
    let json = ok(&["eval", "--dataset", p(&data), "--no-appearance", "--json", "--report", p(&out), "-q"]);
    (out, serde_json::from_str(&json).unwrap())
}

/// Images the page must hold: two charts per query set, a sheet per worst query (at most 6).
fn expected_images(json: &serde_json::Value) -> usize {
    let results = json["results"].as_array().unwrap();
    let sets: std::collections::BTreeSet<&str> = results.iter().map(|r| r["query_set"].as_str().unwrap()).collect();
    let verified = results.iter().filter(|r| r["setting"] == "verified").flat_map(|r| r["outcomes"].as_array().unwrap());
    2 * sets.len() + verified.filter(|o| o["valid_references"].as_u64().unwrap() > 0).count().min(6)
}

#[test]
fn the_report_is_one_self_contained_page_with_every_setting() {
    let dir = tempfile::tempdir().unwrap();
    let (out, json) = report(dir.path());
    let html = std::fs::read_to_string(out.join("index.html")).unwrap();
    let results = json["results"].as_array().unwrap();
    assert_eq!(html.matches(" data-setting=\"").count(), results.len(), "one row per result");
    for r in results {
        assert_eq!(html.matches(&format!("data-setting=\"{}\"><td>night</td>", r["setting"].as_str().unwrap())).count(), 1, "{}", r["setting"]);
    }
    assert!(html.contains("<tr class=\"rec\" data-setting=\"verified\">"), "the recommended setting stands out");
    // every picture inline, nothing fetched
    let srcs: Vec<&str> = html.split("src=\"").skip(1).collect();
    assert_eq!(srcs.len(), expected_images(&json));
    assert!(srcs.iter().all(|s| s.starts_with("data:image/svg+xml;base64,") || s.starts_with("data:image/jpeg;base64,")));
    assert!(!html.contains("<link") && !html.contains("url(") && !html.contains("@import"));
    // the dataset's name is escaped wherever it appears, the provenance is there
    assert!(!html.contains("<b>") && html.matches("synth &lt;b&gt;&amp;&quot;&#39;").count() == 2, "unescaped data");
    let run = &json["run"];
    assert!(
        html.contains(run["config_sha256"].as_str().unwrap())
            && html.contains(&semlook_cli::tools::viz::report::escape(run["backend"].as_str().unwrap()))
    );
}

#[test]
fn the_report_renders_in_headless_chromium() {
    let Some(chromium) = chromium() else {
        return common::skip_unless_required("REQUIRE_CHROMIUM", "no chromium on PATH (setup.sh installs Debian's chromium)");
    };
    let dir = tempfile::tempdir().unwrap();
    let (out, json) = report(dir.path());
    let page = out.join("index.html");
    let check = render_check(&chromium, &page, dir.path());
    let rows = json["results"].as_array().unwrap().len();
    assert_eq!(check, [("done", 1), ("images", expected_images(&json)), ("broken", 0), ("errors", 0), ("rows", rows)], "{}", page.display());

    let shot = dir.path().join("report.png");
    let profile = tempfile::tempdir().unwrap();
    let window = "--window-size=1200,1600";
    run(Command::new(&chromium).args(flags(profile.path())).args([window, &format!("--screenshot={}", p(&shot)), &url(&page)]));
    let img = image::open(&shot).unwrap_or_else(|e| panic!("{}: {e}", shot.display())).to_rgb8();
    assert_eq!(img.dimensions(), (1200, 1600));
    let colours: std::collections::HashSet<[u8; 3]> = img.pixels().map(|p| p.0).collect();
    let inked = img.pixels().filter(|p| p.0.iter().any(|&c| c < 200)).count() as f64 / (1200.0 * 1600.0);
    assert!(colours.len() > 500 && inked > 0.01, "a blank screenshot: {} colours, {:.1} % inked", colours.len(), inked * 100.0);

    // the check itself sees a broken image and a script error
    let html = std::fs::read_to_string(&page).unwrap();
    let broken = dir.path().join("broken.html");
    let bad = "<img src=\"data:image/png;base64,AAAA\" alt=\"broken\"><script>no_such_function();</script><p id=\"render-check\"";
    std::fs::write(&broken, html.replacen("<p id=\"render-check\"", bad, 1)).unwrap();
    let check = render_check(&chromium, &broken, dir.path());
    assert_eq!(&check[..4], [("done", 1), ("images", expected_images(&json) + 1), ("broken", 1), ("errors", 1)]);
}

/// Debian's chromium, if it runs.
fn chromium() -> Option<String> {
    ["chromium", "chromium-browser"]
        .into_iter()
        .find(|c| Command::new(c).arg("--version").stdout(Stdio::null()).stderr(Stdio::null()).status().is_ok_and(|s| s.success()))
        .map(String::from)
}

fn flags(profile: &Path) -> Vec<String> {
    let fixed = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run", "--disable-background-networking"];
    let more = ["--disable-component-update", "--disable-sync", "--hide-scrollbars"];
    fixed.iter().chain(&more).map(|s| s.to_string()).chain([format!("--user-data-dir={}", p(profile))]).collect()
}

fn url(page: &Path) -> String {
    // percent-encode what a file URL cannot hold as it is
    let path = page.canonicalize().unwrap().display().to_string();
    let enc: String =
        path.chars().map(|c| if c.is_ascii_alphanumeric() || "/-_.".contains(c) { c.to_string() } else { format!("%{:02X}", c as u32) }).collect();
    format!("file://{enc}")
}

/// The page's own verdict after its scripts ran: `#render-check`'s data attributes.
fn render_check(chromium: &str, page: &Path, tmp: &Path) -> [(&'static str, usize); 5] {
    let profile = tempfile::tempdir_in(tmp).unwrap();
    let dom = run(Command::new(chromium).args(flags(profile.path())).args(["--virtual-time-budget=10000", "--dump-dom", &url(page)]));
    let tag = dom.split("<p id=\"render-check\"").nth(1).and_then(|t| t.split('>').next()).unwrap_or_else(|| panic!("no #render-check in:\n{dom}"));
    ["done", "images", "broken", "errors", "rows"].map(|k| {
        let v = tag.split(&format!("data-{k}=\"")).nth(1).and_then(|v| v.split('"').next()).unwrap_or_else(|| panic!("no data-{k} in {tag}"));
        (k, v.parse().unwrap())
    })
}

/// stdout of a command that must succeed within 90 s.
fn run(cmd: &mut Command) -> String {
    let mut child = cmd.stdout(Stdio::piped()).stderr(Stdio::null()).spawn().unwrap();
    let mut stdout = child.stdout.take().unwrap();
    let reader = std::thread::spawn(move || {
        let mut s = String::new();
        std::io::Read::read_to_string(&mut stdout, &mut s).map(|_| s)
    });
    let start = Instant::now();
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > Duration::from_secs(90) {
            let _ = child.kill();
            panic!("{cmd:?} ran past 90 s");
        }
        std::thread::sleep(Duration::from_millis(50));
    };
    assert!(status.success(), "{cmd:?}: {status}");
    reader.join().unwrap().unwrap()
}
