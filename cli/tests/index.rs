//! The approximate index of the coarse stage on real photos (CamVid's drive, its real labels, the
//! XFeat appearance): with every list probed and a shortlist of the whole map it answers exactly
//! as the exact scan (bit for bit); its recall against the exact ranking is measured; `map add`,
//! `remove` and `compact` keep it current; damaged, truncated or foreign index files are refused
//! by open, by the first query and by `map verify`; SIGKILL during `map index`, `map add` and
//! `map compact` of an indexed map never breaks it, and finishing the command gives the answers
//! of an uninterrupted run.

mod common;

use common::{cli, cli_ok, p};
use semlook::config::IndexSearch;
use semlook::descriptors::DescriptorSet;
use semlook::engine::Engine;
use semlook::index::CodeRows;
use semlook::map::{edit, Map};
use semlook::matching::{candidates, CpuStages, Setting};
use semlook_cli::tools::synth::camvid::{self, Change};
use std::collections::HashSet;
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

/// CamVid's drive every `step`-th frame and its night copy under `dir` (reference/, night/), or
/// `None` (the test skips) without the shared data or the XFeat weights.
fn drive(dir: &Path, step: usize) -> Option<(PathBuf, PathBuf)> {
    let src = common::shared_or_required("data/camvid-test")?;
    if !common::has_xfeat() {
        return None;
    }
    camvid::generate(&src, dir, &[Change::Night], step, &|| {}).unwrap();
    Some((dir.join("reference"), dir.join("night")))
}

/// `map build` of `frames` (images and real labels) into `map`, segments of `per` images, no index.
fn build(frames: &Path, map: &Path, per: usize) {
    let per = per.to_string();
    cli_ok(&[
        "map",
        "build",
        "--images",
        p(&frames.join("images")),
        "--labels",
        p(&frames.join("labels")),
        "--map",
        p(map),
        "--segment-images",
        &per,
        "--index",
        "none",
        "-q",
    ]);
}

/// The frames of `from` (images/, labels/) copied into `to` under ids prefixed `n-`, so that they
/// can join a map of the frames they were made from.
fn renamed(from: &Path, to: &Path) -> PathBuf {
    for sub in ["images", "labels"] {
        std::fs::create_dir_all(to.join(sub)).unwrap();
        for e in std::fs::read_dir(from.join(sub)).unwrap().flatten() {
            std::fs::copy(e.path(), to.join(sub).join(format!("n-{}", e.file_name().to_string_lossy()))).unwrap();
        }
    }
    to.to_path_buf()
}

/// A config file in `dir` with `[index]` values.
fn index_config(dir: &Path, name: &str, body: &str) -> PathBuf {
    let f = dir.join(name);
    std::fs::write(&f, format!("[index]\n{body}\n")).unwrap();
    f
}

/// The queries of `frames`, encoded for `map`.
fn queries(map: &Map, frames: &Path) -> DescriptorSet {
    let cfg = map.query_config();
    let enc = semlook::encode::Encoder::for_map(&cfg, map).unwrap();
    let files: Vec<_> = semlook::dataset::image_files(&frames.join("images")).unwrap();
    let sources: Vec<semlook::input::FrameSource> = files
        .iter()
        .map(|f| {
            let stem = f.file_stem().unwrap().to_string_lossy().into_owned();
            semlook::input::FrameSource { id: stem.clone(), image: Some(f.clone()), labels: Some(frames.join("labels").join(format!("{stem}.png"))) }
        })
        .collect();
    semlook::batch::encode_frames(&mut Engine::cpu(), &enc, &sources, Default::default(), "queries", false, true).unwrap().set
}

/// The fused coarse lists (top `k`) of `q` against `map`, exact or through the index.
fn coarse(map: &Map, q: &DescriptorSet, search: IndexSearch, probe: usize, shortlist: usize, k: usize) -> Vec<Vec<(u32, u32)>> {
    coarse_weighted(map, q, search, probe, shortlist, k, map.query_config().matching.w_global)
}

/// [`coarse`] with the SSIM term weighted by `w_global`.
fn coarse_weighted(
    map: &Map,
    q: &DescriptorSet,
    search: IndexSearch,
    probe: usize,
    shortlist: usize,
    k: usize,
    w_global: f64,
) -> Vec<Vec<(u32, u32)>> {
    let mut cfg = map.query_config();
    cfg.matching.w_global = w_global;
    cfg.index.search = search;
    cfg.index.probe = probe;
    cfg.index.shortlist = shortlist;
    cfg.matching.top_k = k;
    let (lists, times) = candidates(&mut CpuStages, map, q, Setting::Fused, &cfg).unwrap();
    assert_eq!(times.approximate, search == IndexSearch::Approximate, "the coarse stage ran the wrong way");
    // scores as bits: the index path must give the scan's scores, not close ones
    lists.into_iter().map(|l| l.into_iter().map(|(s, r)| (s.to_bits(), r)).collect()).collect()
}

/// The whole pipeline's answers (`verified`, best first) through the index at full probe.
fn answers(map: &Map, q: &DescriptorSet, search: IndexSearch) -> Vec<Vec<(u32, u32)>> {
    let mut cfg = map.query_config();
    cfg.index.search = search;
    cfg.index.probe = 1 << 16;
    cfg.index.shortlist = 1 << 20;
    let (m, _) = Engine::cpu().match_batch(map, q, Setting::Verified, &cfg).unwrap();
    m.into_iter().map(|m| m.ranked.into_iter().map(|c| (c.score.to_bits(), c.reference)).collect()).collect()
}

#[test]
fn the_index_at_full_probe_answers_as_the_exact_scan_and_its_recall_is_measured() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 2) else { return };
    let map = dir.path().join("map");
    build(&refs, &map, 32);
    let cfg = index_config(dir.path(), "ix.toml", "lists = 8\nprobe = 2\nshortlist = 20");
    let out = cli_ok(&["map", "index", "--map", p(&map), "--config", p(&cfg), "--json"]);
    let entry: serde_json::Value = serde_json::from_str(&out).unwrap();
    assert_eq!(entry["lists"], 8, "{out}");
    let m = Map::open(&map).unwrap();
    assert!(m.manifest.segments.iter().all(|s| s.index.is_some()));
    let info = cli_ok(&["map", "info", "--map", p(&map)]);
    assert!(info.contains("index: IVF over") && info.contains("8 lists"), "{info}");
    let q = queries(&m, &night);
    // every list probed, the whole map shortlisted: the scan's lists, bit for bit
    let exact = coarse(&m, &q, IndexSearch::Exact, 0, 1, 30);
    assert_eq!(coarse(&m, &q, IndexSearch::Approximate, 8, m.len(), 30), exact);
    assert_eq!(answers(&m, &q, IndexSearch::Approximate), answers(&m, &q, IndexSearch::Exact));
    // the SSIM weighted far above the cosine: the fused order leaves the cosine order the index
    // path scores in, so its early stop (no SSIM past the bound) is what keeps the lists equal
    for k in [1, 5, 30] {
        let heavy = coarse_weighted(&m, &q, IndexSearch::Approximate, 8, m.len(), k, 20.0);
        assert_eq!(heavy, coarse_weighted(&m, &q, IndexSearch::Exact, 0, 1, k, 20.0), "k = {k}, w_global 20");
    }
    // two lists of eight and a shortlist of 20: an approximation, measured
    let approx = coarse(&m, &q, IndexSearch::Approximate, 2, 20, 10);
    let exact10 = coarse(&m, &q, IndexSearch::Exact, 0, 1, 10);
    let hits: usize = approx.iter().zip(&exact10).map(|(a, e)| e.iter().filter(|x| a.iter().any(|y| y.1 == x.1)).count()).sum();
    let recall = hits as f64 / (10 * q.len()) as f64;
    eprintln!("recall@10 with 2 of 8 lists and a shortlist of 20: {recall:.3}");
    assert!(recall > 0.5 && recall < 1.0, "recall@10 {recall}: the small probe should approximate, not fail or be exact");
    // the recall the build recorded is the one its own queries measure: between 0 and 1
    let ix = m.index().unwrap();
    assert!(ix.entry.recall_of > 0 && ix.entry.recall_hits <= ix.entry.recall_of);
    // auto: a map below index.min_places is scanned exactly
    let mut auto = m.query_config();
    auto.index.search = IndexSearch::Auto;
    assert!(!candidates(&mut CpuStages, &m, &q, Setting::Fused, &auto).unwrap().1.approximate);
    auto.index.min_places = 1;
    assert!(candidates(&mut CpuStages, &m, &q, Setting::Fused, &auto).unwrap().1.approximate);
}

/// The codes of segment `s` of `m`'s index, opened as the map opens them.
fn segment_codes(m: &Map, s: usize) -> semlook::index::MappedCodes {
    let (ix, seg) = (m.manifest.index.as_ref().unwrap(), &m.manifest.segments[s]);
    semlook::map::index_files::open_codes(&m.path, &m.manifest, ix, seg, seg.index.as_ref().unwrap()).unwrap()
}

#[test]
fn the_pool_reranks_by_the_codes_plus_the_thumbnails_ssim_as_a_brute_force_does() {
    use semlook::index::thumb::widen;
    use semlook::index::{code_dot, IndexQuery, Probe, Shortlist};
    use semlook_kernels::ssim::{ssim_pair, ssim_stats, SsimScratch};
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 4) else { return };
    let map = dir.path().join("map");
    build(&refs, &map, 16);
    cli_ok(&["map", "index", "--map", p(&map), "--config", p(&index_config(dir.path(), "ix.toml", "lists = 8")), "-q"]);
    let m = Map::open(&map).unwrap();
    let info = cli_ok(&["map", "info", "--map", p(&map)]);
    assert!(info.contains("thumbnails 32x24"), "{info}");
    let ix = m.index().unwrap();
    let cfg = m.query_config();
    let q = queries(&m, &night);
    let codes: Vec<_> = (0..m.manifest.segments.len()).map(|s| segment_codes(&m, s)).collect();
    let tp = ix.thumb.ssim_params(&cfg.global);
    let mut sc = SsimScratch::default();
    let (mut xs, mut ys) = (vec![0.0; tp.stats_len()], vec![0.0; tp.stats_len()]);
    let (probe, pool, shortlist) = (3, 24, 8);
    let mut moved = 0;
    for i in 0..q.len() {
        let iq = IndexQuery {
            appearance: q.image_appearance(i),
            global: q.global(i),
            probe,
            pool,
            shortlist,
            at_least: 0,
            w_global: cfg.matching.w_global as f32,
            ssim: &cfg.global,
            embedding: &[],
            w_embedding: 0.0,
        };
        let got = m.index_shortlist(&iq, 0..m.len()).unwrap();
        // the brute force: the probed lists' pool by the codes, then codes + w x the twin's SSIM
        let pr = Probe::new(&ix.model, iq.appearance, probe);
        let mut by_codes = Shortlist::new(pool);
        for r in 0..m.len() {
            let (s, j) = m.locate(r);
            if pr.lists[codes[s].list(j) as usize] {
                by_codes.offer(code_dot(codes[s].code(j), codes[s].scale(j), &pr.reduced), r as u32);
            }
        }
        let mut qt = Vec::new();
        ix.thumb.thumbnail(iq.global, &mut qt);
        let (mut x, mut want) = (Vec::new(), Vec::new());
        widen(&qt, &mut x);
        ssim_stats(&tp, &x, &mut xs, &mut sc);
        let pooled = by_codes.into_sorted();
        for &(a, r) in &pooled {
            let (s, j) = m.locate(r as usize);
            let mut y = Vec::new();
            widen(codes[s].thumb(j), &mut y);
            ssim_stats(&tp, &y, &mut ys, &mut sc);
            want.push((a + iq.w_global * ssim_pair(&tp, &x, &xs, &y, &ys, &mut sc), r));
        }
        want.sort_by(|a, b| b.0.total_cmp(&a.0).then(a.1.cmp(&b.1)));
        assert_eq!(got.len(), shortlist.min(want.len()));
        // the same references with the same scores (1e-5: the fast path against the twin), a
        // near tie at the cut excepted
        let cut = want.get(shortlist).map_or(f32::NEG_INFINITY, |w| w.0);
        for (g, w) in got.iter().zip(&want) {
            assert!((g.0 - w.0).abs() <= 1e-5 || (w.0 - cut).abs() <= 1e-5, "query {i}: {g:?} vs the brute force's {w:?}");
            let brute = want.iter().find(|x| x.1 == g.1).expect("a reference of the pool");
            assert!((brute.0 - g.0).abs() <= 1e-5, "query {i}: reference {} scored {} vs {}", g.1, g.0, brute.0);
        }
        let codes_only: Vec<(f32, u32)> = pooled.iter().take(shortlist).copied().collect();
        moved += got.iter().filter(|g| !codes_only.iter().any(|c| c.1 == g.1)).count();
        // pool 0, no larger than the shortlist, or no SSIM weight: the codes' best, as before
        // thumbnails
        for plain in [IndexQuery { pool: 0, ..iq }, IndexQuery { pool: shortlist, ..iq }, IndexQuery { pool: 500, w_global: 0.0, ..iq }] {
            assert_eq!(m.index_shortlist(&plain, 0..m.len()).unwrap(), codes_only, "query {i}: pool {} w {}", plain.pool, plain.w_global);
        }
    }
    eprintln!("references the thumbnails brought into the shortlists of {} queries: {moved}", q.len());
    assert!(moved > 0, "the thumbnails never changed a shortlist: the test does not exercise them");
}

#[test]
fn an_index_without_thumbnails_is_the_index_of_before_them() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 8) else { return };
    let map = dir.path().join("map");
    build(&refs, &map, 16);
    // first with thumbnails, then rebuilt without: the same model (only the thumbnails differ), so
    // the codes must go to new files, never over the ones the committed manifest lists (a kill
    // between writing them and the commit would leave a map whose files differ from its manifest)
    let files =
        |m: &Path| -> HashSet<String> { Map::open(m).unwrap().manifest.segments.iter().map(|s| s.index.as_ref().unwrap().file.clone()).collect() };
    cli_ok(&["map", "index", "--map", p(&map), "--config", p(&index_config(dir.path(), "ix2.toml", "lists = 8")), "-q"]);
    let (with, model) = (files(&map), Map::open(&map).unwrap().manifest.index.unwrap().model.sha256);
    cli_ok(&["map", "index", "--map", p(&map), "--config", p(&index_config(dir.path(), "ix.toml", "lists = 8\nthumbnail = 0")), "-q"]);
    assert_eq!(Map::open(&map).unwrap().manifest.index.unwrap().model.sha256, model, "the same model");
    assert!(files(&map).is_disjoint(&with), "codes rewritten under the names of the committed ones: {with:?}");
    // the manifest has no thumbnail field (as a manifest of before it: same checksum rules), the
    // codes are format 1, and a pool changes nothing
    let manifest = std::fs::read_to_string(map.join("manifest.json")).unwrap();
    assert!(!manifest.contains("thumbnail"), "{manifest}");
    let m = Map::open(&map).unwrap();
    assert!(m.index().unwrap().thumb.is_empty());
    let codes = std::fs::read(m.path.join(&m.manifest.segments[0].index.as_ref().unwrap().file)).unwrap();
    // the safetensors header (its length, then JSON whose key order is not fixed) names the format
    let hlen = u64::from_le_bytes(codes[..8].try_into().unwrap()) as usize;
    let header = String::from_utf8_lossy(&codes[8..8 + hlen]);
    assert!(header.contains("\"semlook-map-index 1\""), "{header}");
    let info = cli_ok(&["map", "info", "--map", p(&map)]);
    assert!(info.contains("no thumbnails"), "{info}");
    // each query's shortlist is the scan of before thumbnails (every live row's codes, the
    // probed lists' best), whatever the pool
    use semlook::index::{IndexQuery, Probe, Shortlist};
    let q = queries(&m, &night);
    let ix = m.index().unwrap();
    let codes: Vec<_> = (0..m.manifest.segments.len()).map(|s| segment_codes(&m, s)).collect();
    let cfg = m.query_config();
    for i in 0..q.len() {
        let pr = Probe::new(&ix.model, q.image_appearance(i), 2);
        let mut before = Shortlist::new(10);
        for (s, c) in codes.iter().enumerate() {
            let first: usize = (0..s).map(|t| m.manifest.segments[t].live()).sum();
            pr.scan(c, m.live_rows(s).enumerate().map(|(k, j)| (j, (first + k) as u32)), &mut before);
        }
        let iq = IndexQuery {
            appearance: q.image_appearance(i),
            global: q.global(i),
            probe: 2,
            pool: 6000,
            shortlist: 10,
            at_least: 0,
            w_global: cfg.matching.w_global as f32,
            ssim: &cfg.global,
            embedding: &[],
            w_embedding: 0.0,
        };
        assert_eq!(m.index_shortlist(&iq, 0..m.len()).unwrap(), before.into_sorted(), "query {i}");
    }
}

#[test]
fn add_remove_and_compact_keep_the_index_current() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 3) else { return };
    let map = dir.path().join("map");
    build(&refs, &map, 40);
    let cfg = index_config(dir.path(), "ix.toml", "lists = 4");
    cli_ok(&["map", "index", "--map", p(&map), "--config", p(&cfg)]);
    let model_sha = Map::open(&map).unwrap().manifest.index.clone().unwrap().model.sha256;
    // the night copy added as a new traversal: its segments get codes under the same model
    let night_ids = renamed(&night, &dir.path().join("night-renamed"));
    cli_ok(&[
        "map",
        "add",
        "--images",
        p(&night_ids.join("images")),
        "--labels",
        p(&night_ids.join("labels")),
        "--map",
        p(&map),
        "--segment-images",
        "40",
        "-q",
    ]);
    let m = Map::open(&map).unwrap();
    let ix = m.index().unwrap();
    assert_eq!(ix.entry.model.sha256, model_sha, "an add keeps the model");
    assert!(m.manifest.segments.len() >= 4 && m.manifest.segments.iter().all(|s| s.index.is_some()));
    // the added segments' codes are the model's codes of the values the segments store
    for (s, seg) in m.segments().iter().enumerate() {
        let want = semlook::map::index_files::codes_for_segment(&ix.model, &ix.thumb, seg);
        let got = segment_codes(&m, s);
        assert!(!ix.thumb.is_empty(), "the default index keeps thumbnails");
        for j in 0..seg.len() {
            assert_eq!(
                (got.list(j), got.code(j), got.scale(j).to_bits(), got.thumb(j)),
                (want.list(j), want.code(j), want.scale(j).to_bits(), want.thumb(j)),
                "{}",
                seg.path.display()
            );
        }
    }
    let q = queries(&m, &night);
    assert_eq!(coarse(&m, &q, IndexSearch::Approximate, 4, m.len(), 30), coarse(&m, &q, IndexSearch::Exact, 0, 1, 30));
    // removal: the removed never come back through the index
    let gone: Vec<String> = (0..m.len()).step_by(3).map(|i| semlook::descriptors::source::RefSource::id(&m, i).to_string()).collect();
    drop(m);
    cli_ok(&["map", "remove", "--map", p(&map), "--ids"].into_iter().chain(gone.iter().map(String::as_str)).collect::<Vec<_>>());
    let m = Map::open(&map).unwrap();
    let ids: HashSet<&str> = gone.iter().map(String::as_str).collect();
    let approx = coarse(&m, &q, IndexSearch::Approximate, 4, m.len(), 30);
    for l in &approx {
        assert!(l.iter().all(|&(_, r)| !ids.contains(semlook::descriptors::source::RefSource::id(&m, r as usize))));
    }
    assert_eq!(approx, coarse(&m, &q, IndexSearch::Exact, 0, 1, 30));
    drop(m);
    // compaction rewrites segments: their codes follow, the old files go
    let before: HashSet<String> = std::fs::read_dir(&map).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    cli_ok(&["map", "compact", "--map", p(&map)]);
    let m = Map::open(&map).unwrap();
    assert!(m.manifest.segments.iter().all(|s| s.index.is_some() && s.removed.is_empty()));
    let listed: HashSet<String> = m
        .manifest
        .segments
        .iter()
        .flat_map(|s| [s.file.clone(), s.index.as_ref().unwrap().file.clone()])
        .chain([m.manifest.index.as_ref().unwrap().model.file.clone()])
        .collect();
    let now: HashSet<String> = std::fs::read_dir(&map).unwrap().flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
    let stray: Vec<&String> = now.iter().filter(|f| (f.starts_with("index-") || f.starts_with("segment-")) && !listed.contains(*f)).collect();
    assert!(stray.is_empty(), "compaction left {stray:?}");
    assert!(before.iter().any(|f| f.starts_with("index-") && !now.contains(f)), "no replaced codes were deleted");
    assert_eq!(coarse(&m, &q, IndexSearch::Approximate, 4, m.len(), 30), coarse(&m, &q, IndexSearch::Exact, 0, 1, 30));
    assert_eq!(edit::verify(&map).unwrap().damaged().count(), 0);
    // dropping it: one commit, its files gone, the map scanned exactly
    drop(m);
    cli_ok(&["map", "index", "--map", p(&map), "--drop"]);
    let m = Map::open(&map).unwrap();
    assert!(m.index().is_none() && m.manifest.segments.iter().all(|s| s.index.is_none()));
    assert!(std::fs::read_dir(&map).unwrap().flatten().all(|e| !e.file_name().to_string_lossy().starts_with("index-")));
}

/// The manifest's entry of the codes of segment `s` of the map in `dir`.
fn codes_file(dir: &Path, s: usize) -> PathBuf {
    let m = semlook::map::manifest::read_existing(dir).unwrap();
    dir.join(&m.segments[s].index.as_ref().unwrap().file)
}

#[test]
fn damaged_truncated_or_foreign_index_files_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 4) else { return };
    let clean = dir.path().join("clean");
    build(&refs, &clean, 20);
    let cfg = index_config(dir.path(), "ix.toml", "lists = 4");
    cli_ok(&["map", "index", "--map", p(&clean), "--config", p(&cfg)]);
    let q = queries(&Map::open(&clean).unwrap(), &night);
    let copy = |name: &str| -> PathBuf {
        let d = dir.path().join(name);
        std::fs::create_dir_all(&d).unwrap();
        for e in std::fs::read_dir(&clean).unwrap().flatten() {
            std::fs::copy(e.path(), d.join(e.file_name())).unwrap();
        }
        d
    };
    let verify_names = |d: &Path, file: &Path| {
        let out = cli(&["map", "verify", "--map", p(d)]);
        let text = String::from_utf8_lossy(&out.stdout);
        assert!(!out.status.success(), "verify passed a damaged index:\n{text}");
        let name = file.file_name().unwrap().to_string_lossy();
        assert!(text.lines().any(|l| l.starts_with("DAMAGED") && l.contains(name.as_ref())), "verify did not name {name}:\n{text}");
    };
    // a flipped bit in the codes: the map opens (headers are sound), the first query through
    // the index refuses it naming the file, verify names it
    let flipped = copy("flipped");
    let f = codes_file(&flipped, 1);
    let mut b = std::fs::read(&f).unwrap();
    let last = b.len() - 3;
    b[last] ^= 0x04;
    std::fs::write(&f, &b).unwrap();
    let m = Map::open(&flipped).unwrap();
    let mut c = m.query_config();
    c.index.search = IndexSearch::Approximate;
    let e = candidates(&mut CpuStages, &m, &q, Setting::Fused, &c).unwrap_err().to_string();
    assert!(e.contains(&*f.file_name().unwrap().to_string_lossy()) && e.contains("SHA-256"), "{e}");
    verify_names(&flipped, &f);
    // truncated: open refuses it
    let cut = copy("truncated");
    let f = codes_file(&cut, 0);
    let b = std::fs::read(&f).unwrap();
    std::fs::write(&f, &b[..b.len() - 10]).unwrap();
    let e = Map::open(&cut).unwrap_err().to_string();
    assert!(e.contains("truncated") && e.contains(&*f.file_name().unwrap().to_string_lossy()), "{e}");
    verify_names(&cut, &f);
    // another segment's codes in this one's place (same size): their header names the other
    let swapped = copy("swapped");
    let (f0, f1) = (codes_file(&swapped, 0), codes_file(&swapped, 1));
    assert_eq!(std::fs::metadata(&f0).unwrap().len(), std::fs::metadata(&f1).unwrap().len(), "the test needs equal segments");
    std::fs::copy(&f1, &f0).unwrap();
    let e = Map::open(&swapped).unwrap_err().to_string();
    assert!(e.contains("another segment or map"), "{e}");
    verify_names(&swapped, &f0);
    // the model damaged: open refuses it
    let model = copy("model");
    let mf = model.join(&semlook::map::manifest::read_existing(&model).unwrap().index.unwrap().model.file);
    let mut b = std::fs::read(&mf).unwrap();
    let mid = b.len() / 2;
    b[mid] ^= 0x01;
    std::fs::write(&mf, &b).unwrap();
    let e = Map::open(&model).unwrap_err().to_string();
    assert!(e.contains("SHA-256") && e.contains(&*mf.file_name().unwrap().to_string_lossy()), "{e}");
    verify_names(&model, &mf);
    // the clean map still answers
    assert!(Map::open(&clean).is_ok() && edit::verify(&clean).unwrap().damaged().count() == 0);
}

/// Copies the map folder `from` to `to` (files only).
/// A copy of the map at `from` in `to` (none where `from` does not exist: a build's start).
fn copy_map(from: &Path, to: &Path) {
    let _ = std::fs::remove_dir_all(to);
    if !from.exists() {
        return;
    }
    std::fs::create_dir_all(to).unwrap();
    for e in std::fs::read_dir(from).unwrap().flatten() {
        if e.path().is_file() {
            std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
        }
    }
}

/// SIGKILL at a random moment of each command, then: the map opens and verifies clean (leftovers
/// of the interrupted writer allowed), the command run again to its end gives the answers of an
/// uninterrupted run, bit for bit. 30 kills per command. One of them (issue 49) is `map index`
/// training a new model while this process compacts the map in a loop (each compaction another
/// segment size, so each rewrites the segments and cleans stale files): the interleaving that
/// once committed an index whose files the compaction had deleted.
#[test]
fn sigkill_during_index_build_add_and_compact_never_breaks_an_indexed_map() {
    const KILLS: usize = 30;
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 6) else { return };
    let base = dir.path().join("base");
    build(&refs, &base, 8);
    let cfg = index_config(dir.path(), "ix.toml", "lists = 4");
    // a rebuild that changes only the thumbnails trains the same model: its files must not
    // replace the ones the committed manifest lists
    let cfg0 = index_config(dir.path(), "ix0.toml", "lists = 4\nthumbnail = 0");
    // a new model (more lists): new file names, which a compaction must not take for stale ones
    let cfg6 = index_config(dir.path(), "ix6.toml", "lists = 6");
    let q = queries(&Map::open(&base).unwrap(), &night);
    // the three commands, each from its starting map
    let indexed = dir.path().join("indexed");
    copy_map(&base, &indexed);
    cli_ok(&["map", "index", "--map", p(&indexed), "--config", p(&cfg)]);
    let removed = dir.path().join("removed");
    copy_map(&indexed, &removed);
    let ids: Vec<String> = {
        let m = Map::open(&removed).unwrap();
        (0..m.len()).step_by(2).map(|i| semlook::descriptors::source::RefSource::id(&m, i).to_string()).collect()
    };
    cli_ok(&["map", "remove", "--map", p(&removed), "--ids"].into_iter().chain(ids.iter().map(String::as_str)).collect::<Vec<_>>());
    let night = renamed(&night, &dir.path().join("night-renamed"));
    let night_images = p(&night.join("images")).to_string();
    let night_labels = p(&night.join("labels")).to_string();
    let ref_images = p(&refs.join("images")).to_string();
    let ref_labels = p(&refs.join("labels")).to_string();
    type Cmd = (&'static str, PathBuf, Vec<String>, Vec<String>);
    let commands: Vec<Cmd> = vec![
        (
            "build",
            dir.path().join("no-map-yet"),
            ["map", "build", "--images", &ref_images, "--labels", &ref_labels, "--segment-images", "8", "--index", "ivf", "--config", p(&cfg), "-q"]
                .map(String::from)
                .to_vec(),
            vec!["--resume".into()],
        ),
        ("index", base.clone(), vec!["map".into(), "index".into(), "--config".into(), p(&cfg).into()], vec![]),
        ("reindex", indexed.clone(), vec!["map".into(), "index".into(), "--config".into(), p(&cfg0).into()], vec![]),
        (
            "add",
            indexed.clone(),
            ["map", "add", "--images", &night_images, "--labels", &night_labels, "--segment-images", "4", "-q"].map(String::from).to_vec(),
            vec!["--resume".into()],
        ),
        ("compact", removed.clone(), vec!["map".into(), "compact".into()], vec![]),
        ("index-while-compacting", removed.clone(), vec!["map".into(), "index".into(), "--config".into(), p(&cfg6).into()], vec![]),
    ];
    // compactions of `m` in a loop on a thread until the flag is set; how many committed
    let compacting = |m: &Path| {
        let stop = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
        let (m, flag) = (m.to_path_buf(), stop.clone());
        let worker = std::thread::spawn(move || {
            let mut done = 0usize;
            while !flag.load(std::sync::atomic::Ordering::Relaxed) {
                let opts = semlook::map::StoreOptions { segment_images: 3 + done % 3, ..Default::default() };
                match edit::compact(&m, opts) {
                    Ok(_) => done += 1,
                    Err(e) => panic!("compaction beside the index build: {e}"),
                }
            }
            done
        });
        move || {
            stop.store(true, std::sync::atomic::Ordering::Relaxed);
            worker.join().unwrap()
        }
    };
    let mut compactions = 0;
    let mut rng = semlook::util::SplitMix64::new(29);
    for (name, start, args, again) in commands {
        let run = |m: &Path, extra: &[String]| -> Command {
            let mut c = Command::new(common::bin());
            c.args(&args).arg("--map").arg(m).args(extra).stdout(Stdio::null()).stderr(Stdio::null());
            c
        };
        // the uninterrupted run: its answers, how long it takes, and when it commits (the
        // manifest's generation watched every 2 ms), so that most kills land around the commits
        let whole = dir.path().join(format!("{name}-whole"));
        copy_map(&start, &whole);
        let generation = |m: &Path| semlook::map::manifest::read(m).ok().flatten().map_or(0, |x| x.generation);
        let g_start = generation(&start);
        let beside = name == "index-while-compacting";
        let stop = beside.then(|| compacting(&whole));
        let t = Instant::now();
        let mut child = run(&whole, &[]).spawn().unwrap();
        let (mut first, mut last) = (None, 0.0f64);
        let status = loop {
            if let Ok(Some(m)) = semlook::map::manifest::read(&whole) {
                if m.generation > g_start {
                    let at = t.elapsed().as_secs_f64();
                    first.get_or_insert(at);
                    last = at;
                }
            }
            if let Some(st) = child.try_wait().unwrap() {
                break st;
            }
            std::thread::sleep(Duration::from_millis(2));
        };
        let full = t.elapsed().as_secs_f64();
        compactions += stop.map_or(0, |s| s());
        assert!(status.success(), "{name} failed uninterrupted");
        let first = first.unwrap_or(full);
        let want = answers(&Map::open(&whole).unwrap(), &q, IndexSearch::Approximate);
        let (g0, g1) = (g_start, generation(&whole));
        let (mut before, mut partial) = (0, 0);
        for k in 0..KILLS {
            let m = dir.path().join(format!("{name}-{k}"));
            copy_map(&start, &m);
            // a third anywhere in the run, a third around its commits, a third as soon as the
            // manifest shows a chosen commit (the command killed between two of its commits)
            let at = if k % 3 == 0 { rng.range(0.0, full * 1.1) } else { rng.range((first - 0.02).max(0.0), last + 0.02) };
            let target = g0 + 1 + (rng.next_u64() % (g1 - g0).max(1));
            let stop = beside.then(|| compacting(&m));
            let mut child = run(&m, &[]).spawn().unwrap();
            if k % 3 == 2 {
                let t = Instant::now();
                while child.try_wait().unwrap().is_none() && t.elapsed().as_secs_f64() < full * 2.0 {
                    if semlook::map::manifest::read(&m).ok().flatten().is_some_and(|x| x.generation >= target) {
                        break;
                    }
                    std::thread::sleep(Duration::from_micros(500));
                }
            } else {
                std::thread::sleep(Duration::from_secs_f64(at));
            }
            let _ = child.kill(); // SIGKILL
            let _ = child.wait();
            compactions += stop.map_or(0, |s| s());
            // a build killed before its first commit leaves no manifest: nothing to open yet
            let committed = semlook::map::manifest::read(&m).ok().flatten().is_some();
            assert!(committed || name == "build", "{name}, kill {k} at {at:.3} s: the manifest is gone");
            let g = if committed {
                let opened = Map::open(&m).unwrap_or_else(|e| panic!("{name}, kill {k} at {at:.3} s: the map does not open: {e}"));
                let v = edit::verify(&m).unwrap();
                assert_eq!(v.damaged().count(), 0, "{name}, kill {k} at {at:.3} s: {:?}", v.files);
                opened.manifest.generation
            } else {
                g0
            };
            before += usize::from(g == g0);
            partial += usize::from(g > g0 && g < g1);
            // finish the command
            let finished = match name {
                "index" | "reindex" | "index-while-compacting" => run(&m, &[]).status().unwrap(),
                _ => run(&m, &again).status().unwrap(),
            };
            assert!(finished.success(), "{name}, kill {k}: finishing failed");
            let got = answers(&Map::open(&m).unwrap(), &q, IndexSearch::Approximate);
            assert_eq!(got, want, "{name}, kill {k} at {at:.3} s: answers differ from an uninterrupted run");
            assert_eq!(edit::verify(&m).unwrap().damaged().count(), 0);
            std::fs::remove_dir_all(&m).unwrap();
        }
        eprintln!("{name}: {KILLS} kills over {full:.2} s (commits from {first:.3} to {last:.3} s, generation {g0} to {g1}): {before} before its first commit, {partial} between commits");
        // beside the compactions the map's generation moves without the command: no count of
        // where the kills landed, but compactions must have run beside them
        if beside {
            assert!(compactions >= KILLS, "{name}: only {compactions} compactions ran beside {KILLS} index builds");
            continue;
        }
        assert!(before >= 3, "{name}: only {before} kills landed before the command committed: the test did not interrupt it");
        if name == "add" || name == "build" {
            assert!(partial >= 3, "{name}: only {partial} kills landed between its commits");
        }
    }
}

/// Issue 49: `map compact` and `map remove` while `map index` rebuilds. The build is held (by
/// its test hook, no timing) between writing its model and codes and taking the lock for its
/// commit; a compaction and a removal run there; the build then commits. Before, the compaction
/// deleted the new model and codes as unlisted and the build committed a manifest naming them:
/// no command could open the map. Now the build's files are staged out of the other writers'
/// sight and moved in by its commit: the map opens, verifies, and its index answers as the
/// exact scan at full probe.
#[test]
fn compaction_and_removal_during_an_index_rebuild_leave_a_map_that_verifies() {
    let dir = tempfile::tempdir().unwrap();
    let Some((refs, night)) = drive(&dir.path().join("data"), 6) else { return };
    let map = dir.path().join("map");
    build(&refs, &map, 10);
    let cfg = index_config(dir.path(), "ix.toml", "lists = 4");
    cli_ok(&["map", "index", "--map", p(&map), "--config", p(&cfg)]);
    // removed images: the compaction below has segments to rewrite
    let ids: Vec<String> = {
        let m = Map::open(&map).unwrap();
        (0..m.len()).step_by(4).map(|i| semlook::descriptors::source::RefSource::id(&m, i).to_string()).collect()
    };
    edit::remove(&map, &ids[..ids.len() / 2]).unwrap();
    let (staged_tx, staged_rx) = std::sync::mpsc::channel::<()>();
    let (go_tx, go_rx) = std::sync::mpsc::channel::<()>();
    let go_rx = std::sync::Mutex::new(go_rx);
    let staged_tx = std::sync::Mutex::new(staged_tx);
    semlook::map::index::set_staged_hook(Some(Box::new(move || {
        staged_tx.lock().unwrap().send(()).unwrap();
        go_rx.lock().unwrap().recv().unwrap();
    })));
    let builder = {
        let map = map.clone();
        // another model than the one committed (more lists): new file names
        let params = semlook::index::IndexParams { lists: 6, ..semlook::index::IndexParams::from_config(&Default::default(), 100) };
        std::thread::spawn(move || semlook::map::index::build(&map, &params, 6, 0))
    };
    staged_rx.recv().unwrap();
    let report = edit::compact(&map, semlook::map::StoreOptions { segment_images: 10, ..Default::default() }).unwrap();
    assert!(report.segments_after < report.segments_before || report.dropped > 0, "the compaction had nothing to do: {report:?}");
    edit::remove(&map, &ids[ids.len() / 2..]).unwrap();
    go_tx.send(()).unwrap();
    let built = builder.join().unwrap();
    semlook::map::index::set_staged_hook(None);
    built.unwrap();
    let m = Map::open(&map).unwrap();
    assert_eq!(m.index().unwrap().entry.lists, 6, "the rebuilt index is committed");
    assert_eq!(edit::verify(&map).unwrap().damaged().count(), 0);
    assert!(
        std::fs::read_dir(&map).unwrap().flatten().all(|e| !e.file_name().to_string_lossy().starts_with(".index-staging-")),
        "the staging folder is gone"
    );
    let q = queries(&m, &night);
    assert_eq!(coarse(&m, &q, IndexSearch::Approximate, 6, m.len(), 30), coarse(&m, &q, IndexSearch::Exact, 0, 1, 30));
}
