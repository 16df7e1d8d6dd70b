//! A map split into shards ([`semlook::map::shard`]) matches exactly like the whole map: per-shard
//! candidates merged by `merge_lists`, fine scores from the owning shard, ranked by `rank`, equal
//! `match_with` bit for bit, with removed images and identical references straddling shards.

mod common;

use semlook::config::{Config, ScoreFusion};
use semlook::descriptors::DescriptorSet;
use semlook::map::{edit, shard, Map, StoreOptions};
use semlook::matching::merge_lists;
use semlook::matching::{candidates, fine_scores, list_len, match_with, pairs_of, rank, CpuStages, QueryMatch, Setting};
use std::path::Path;

/// The sharding protocol of the Python driver, in one process.
fn sharded(dir: &Path, n_shards: usize, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Vec<QueryMatch> {
    let m = Map::open(dir).unwrap().manifest;
    let shards: Vec<(Map, shard::ShardSpec)> =
        shard::plan(&m, n_shards).unwrap().iter().map(|s| Map::open_range(dir, s.segments.clone(), Some(s.generation)).unwrap()).collect();
    let parts: Vec<Vec<Vec<(f32, u32)>>> = shards
        .iter()
        .map(|(map, spec)| {
            let (lists, _) = candidates(&mut CpuStages, map, queries, setting, cfg).unwrap();
            lists.into_iter().map(|l| l.into_iter().map(|(s, r)| (s, r + spec.global_start as u32)).collect()).collect()
        })
        .collect();
    let views: Vec<&[Vec<(f32, u32)>]> = parts.iter().map(Vec::as_slice).collect();
    let lists = merge_lists(&views, list_len(setting, cfg)).unwrap();
    let fine = setting.reranks().then(|| {
        pairs_of(&lists)
            .into_iter()
            .map(|(q, r)| {
                let (map, spec) = shards.iter().find(|(_, s)| (s.global_start..s.global_start + s.len).contains(&(r as usize))).unwrap();
                fine_scores(&mut CpuStages, map, queries, setting, cfg, &[(q, r - spec.global_start as u32)]).unwrap()[0]
            })
            .collect::<Vec<_>>()
    });
    rank(setting, &lists, fine.as_deref(), cfg).unwrap()
}

fn bits(m: &[QueryMatch]) -> Vec<Vec<(u32, u32, Option<u32>, Option<u32>)>> {
    m.iter()
        .map(|q| q.ranked.iter().map(|c| (c.reference, c.score.to_bits(), c.coarse.map(f32::to_bits), c.fine.map(f32::to_bits))).collect())
        .collect()
}

#[test]
fn shards_give_exactly_the_lists_of_the_whole_map() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let mut cfg = Config::without_appearance();
    cfg.matching.top_k = 4;
    let maps = common::label_maps(9, 80, 60);
    // every image twice (ids a*, b*), 3 images per segment: identical references 9 apart, so
    // ties cross segment and shard boundaries
    let mut set = common::encode(&cfg, &maps, "a");
    set.append(&common::encode(&cfg, &maps, "b")).unwrap();
    Map::create_with(&path, &cfg.encoding(), &set, None, StoreOptions { segment_images: 3, ..Default::default() }).unwrap();
    edit::remove(&path, &["a1".into(), "b7".into()]).unwrap_or_else(|e| panic!("{e}"));
    let queries = common::encode(&cfg, &maps[2..7], "q");
    let whole = Map::open(&path).unwrap();
    assert_eq!(whole.len(), 16);
    let mut compared = 0;
    for fusion in [ScoreFusion::Fine, ScoreFusion::FineTimesGlobal] {
        cfg.matching.score = fusion;
        for setting in [Setting::Global, Setting::Forest, Setting::GlobalForest, Setting::Semlook] {
            let (single, _) = match_with(&mut CpuStages, &whole, &queries, setting, &cfg).unwrap();
            let ties = single.iter().filter(|q| q.ranked.windows(2).any(|w| w[0].score == w[1].score)).count();
            assert!(ties > 0 || setting != Setting::Global, "the fixture should make ties");
            for n in [1, 2, 3, 6] {
                assert_eq!(bits(&sharded(&path, n, &queries, setting, &cfg)), bits(&single), "{setting} {fusion:?} over {n} shards");
                compared += 1;
            }
        }
    }
    assert_eq!(compared, 32);
}

#[test]
fn a_shard_planned_before_a_change_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(6, 80, 60), "r");
    let map = Map::create_with(&path, &cfg.encoding(), &set, None, StoreOptions { segment_images: 2, ..Default::default() }).unwrap();
    let plan = shard::plan(&map.manifest, 3).unwrap();
    edit::remove(&path, &["r0".into()]).unwrap();
    let err = Map::open_range(&path, plan[1].segments.clone(), Some(plan[1].generation)).unwrap_err().to_string();
    assert!(err.contains("plan again") && err.contains("manifest.json"), "{err}");
    assert!(Map::open_range(&path, 2..9, None).is_err());
    let (part, spec) = Map::open_range(&path, 1..3, None).unwrap();
    assert_eq!((spec.global_start, part.len()), (1, 4));
}

#[test]
fn a_driver_needs_only_the_manifest_and_the_codebook() {
    let dir = tempfile::tempdir().unwrap();
    let (path, driver) = (dir.path().join("m"), dir.path().join("driver"));
    let cfg = Config::without_appearance();
    let mut set = common::encode(&cfg, &common::label_maps(6, 80, 60), "r");
    // appearance vectors of 2 x 3 values, as the codebook below makes
    let unit = |n: usize| (0..n).flat_map(|i| (0..6).map(move |j| f32::from(u8::from(j == i % 6)))).collect::<Vec<f32>>();
    set.appearance_dim = 6;
    set.tree_appearance = unit(set.n_trees());
    set.tree_has_appearance = vec![1; set.n_trees()];
    set.image_appearance = unit(set.len());
    let codebook = semlook::global::vlad::Codebook { k: 2, dim: 3, centres: vec![0.5, -1.0, 2.0, 0.25, 0.0, -3.5] };
    set.codebook = Some(codebook.sha256().unwrap());
    let whole =
        Map::create_with(&path, &cfg.encoding(), &set, Some((&codebook, "net-sha")), StoreOptions { segment_images: 2, ..Default::default() })
            .unwrap();
    // the driver's copy of the map directory: every file but the segments
    std::fs::create_dir(&driver).unwrap();
    for e in std::fs::read_dir(&path).unwrap().flatten() {
        let name = e.file_name().into_string().unwrap();
        if !name.starts_with("segment-") {
            std::fs::copy(e.path(), driver.join(&name)).unwrap();
        }
    }
    assert!(Map::open(&driver).is_err(), "the segments are missing: a full open must fail");
    let head = Map::open_header(&driver).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!((head.len(), head.segments().len()), (0, 0));
    let cb = head.codebook().expect("the codebook is read");
    assert_eq!((cb.k, cb.dim, &cb.centres), (codebook.k, codebook.dim, &codebook.centres));
    assert_eq!(head.query_config().to_toml().unwrap(), whole.query_config().to_toml().unwrap());
    assert!(head.check_model(Some("net-sha")).is_ok() && head.check_model(None).is_err());
    let mut other = cfg.encoding();
    other.global.width += 1;
    assert!(head.check_compatible(&cfg.encoding()).is_ok() && head.check_compatible(&other).is_err());
    // a damaged codebook is refused as by a full open, naming the file
    let cb_file = std::fs::read_dir(&driver)
        .unwrap()
        .flatten()
        .map(|e| e.path())
        .find(|p| p.file_name().unwrap().to_string_lossy().starts_with("codebook"))
        .expect("a codebook file");
    let mut bytes = std::fs::read(&cb_file).unwrap();
    let last = bytes.len() - 1;
    bytes[last] ^= 1;
    std::fs::write(&cb_file, bytes).unwrap();
    let err = Map::open_header(&driver).unwrap_err().to_string();
    assert!(err.contains(&*cb_file.file_name().unwrap().to_string_lossy()), "{err}");
}

/// Issue 60: `map build` measures the null of `verified`'s evidence and stores it in the manifest;
/// every shard of the map then tests its candidates against that one, so a sharded `verified`
/// equals the whole map's bit for bit (shards measuring their own nulls gave other tail
/// probabilities). `map add` keeps it until the map has doubled, then measures it again; a
/// removal that halves the map drops it; `map info` says which.
#[test]
fn the_null_is_stored_at_build_and_every_shard_tests_against_it() {
    use common::{cli_ok, p};
    use semlook::descriptors::source::{GlobalSource, RefSource};
    use semlook::matching::null;
    if !common::has_xfeat() {
        return;
    }
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    common::tiny_synth(&data, 40, 7);
    let cam = semlook::dataset::SYNTHIA_CAMERA;
    let f = |t: &str, k: &str| data.join(t).join(k).join(cam);
    let map = dir.path().join("map");
    let build = |out: &Path, t: &str| {
        let (rgb, lab) = (f(t, "RGB"), f(t, "GT/LABELS"));
        let args = ["--backend", "cpu", "map", "build", "--images", p(&rgb), "--labels", p(&lab), "--map", p(out)];
        cli_ok(&[&args[..], &["--segment-images", "7", "-q"]].concat())
    };
    build(&map, "day");
    let whole = Map::open(&map).unwrap();
    // the bonus uncapped, so that every candidate's score says how far in the null's tail its
    // inliers lie (the overcast frames' few inliers say nothing; the day frames' own many)
    let mut cfg = whole.query_config();
    cfg.verification.max_bonus = 1e6;
    let stored = whole.stored_null().expect("map build stores the null");
    assert_eq!(stored.key, null::key(&cfg), "measured under the config queries of the map use");
    assert!(stored.pairs as usize >= null::MIN_NULL_PAIRS && stored.sources == 40, "{stored:?}");
    // the compact HOGs' same-place sample (frames of 160x120 store compact HOGs): each of the 40
    // sources with its neighbours along the one traversal, 2 x 40 - 2 pairs, reference 0 with 1
    // among them; the look-alikes' cosines beside them, one a null pair
    assert!(whole.compact_hog_dim() > 0);
    assert_eq!((stored.compact_hog_near.len(), stored.compact_hog.len()), (78, stored.pairs as usize));
    let c01 = whole.image_compact_hog(0).dot(&whole.image_compact_hog(1));
    assert!(stored.compact_hog_near.iter().any(|&c| (c - c01).abs() < 1e-5), "{c01} not in {:?}", stored.compact_hog_near);
    let frames = semlook::dataset::frames_from_folders(Some(&f("overcast", "RGB")), Some(&f("overcast", "GT/LABELS"))).unwrap();
    let enc = semlook::encode::Encoder::for_map(&cfg, &whole).unwrap();
    let mut queries =
        semlook::batch::encode_frames(&mut semlook::engine::Engine::cpu(), &enc, &frames, Default::default(), "queries", false, true).unwrap().set;
    queries.append(&whole.gather(&[3, 17, 30]).unwrap()).unwrap();
    assert!(queries.keypoint_dim > 0);
    let (single, _) = match_with(&mut CpuStages, &whole, &queries, Setting::Verified, &cfg).unwrap();
    // evidence counted: the day frames' own references score above their coarse terms
    let bonus = |c: &semlook::matching::Candidate| c.score - cfg.verification.w_coarse as f32 * c.coarse.unwrap();
    assert!(single.iter().rev().take(3).all(|m| bonus(&m.ranked[0]) > 8.0), "no evidence counted: {:?}", &single[single.len() - 1].ranked[..3]);
    for n in [2, 3] {
        // a shard's own null would differ from the whole map's
        let m = Map::open(&map).unwrap().manifest;
        let s = &shard::plan(&m, n).unwrap()[0];
        let (part, _) = Map::open_range(&map, s.segments.clone(), Some(s.generation)).unwrap();
        assert_ne!(semlook::matching::measure_null(&mut CpuStages, &part, &cfg).unwrap(), *stored, "{n} shards");
        assert_eq!(bits(&sharded(&map, n, &queries, Setting::Verified, &cfg)), bits(&single), "verified over {n} shards");
    }
    let info = |m: &Path| -> serde_json::Value { serde_json::from_str(&cli_ok(&["map", "info", "--map", p(m), "--json"])).unwrap() };
    assert_eq!(info(&map)["null"]["images"], 40);
    // 80 images: the null of 40 still stands; 120: measured again
    let add = |t: &str, prefix: &str| {
        let (rgb, lab) = (f(t, "RGB"), f(t, "GT/LABELS"));
        let args = ["--backend", "cpu", "map", "add", "--images", p(&rgb), "--labels", p(&lab), "--map", p(&map)];
        cli_ok(&[&args[..], &["--id-prefix", prefix, "-q"]].concat())
    };
    add("night", "n");
    assert_eq!(info(&map)["null"]["images"], 40);
    add("day", "again");
    assert_eq!(info(&map)["null"]["images"], 120);
    // a removal below half: dropped (queries measure their own)
    let ids: Vec<String> = (0..40).map(|i| format!("again{i:06}")).collect();
    let ids: Vec<String> = ids.into_iter().chain((0..21).map(|i| format!("n{i:06}"))).collect();
    edit::remove(&map, &ids).unwrap();
    let after = info(&map);
    assert!(after["images"].as_u64().unwrap() < 60 && after["null"].is_null(), "{after}");
}
