//! End to end on the library: synthetic data, encoding, matching, evaluation.

mod common;

use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions};
use semlook::eval::{evaluate, EvalOptions};
use semlook::global::ssim::SsimParams;
use semlook::matching::{coarse_topk, match_batch, Setting};

#[test]
fn synth_is_deterministic_and_seed_dependent() {
    let (a, b, c) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
    common::tiny_synth(a.path(), 3, 11);
    common::tiny_synth(b.path(), 3, 11);
    common::tiny_synth(c.path(), 3, 12);
    let (sa, sb, sc) = (common::snapshot(a.path()), common::snapshot(b.path()), common::snapshot(c.path()));
    assert_eq!(sa.len(), 3 * 3 * 3 + 2, "3 traversals x 3 frames x (rgb, labels, pose) + 2 manifests");
    assert!(sa == sb, "same seed, different bytes");
    assert!(sa != sc, "different seeds, same bytes");
}

#[test]
fn synth_layout_is_read_with_and_without_the_manifest() {
    let dir = tempfile::tempdir().unwrap();
    common::tiny_synth(dir.path(), 4, 3);
    let with = Dataset::open(dir.path(), &DatasetOptions::default()).unwrap();
    assert_eq!(with.reference.name, "day");
    assert_eq!(with.queries.iter().map(|q| q.name.as_str()).collect::<Vec<_>>(), ["overcast", "night"]);
    std::fs::remove_file(dir.path().join("semlook-dataset.json")).unwrap();
    assert!(Dataset::open(dir.path(), &DatasetOptions::default()).is_err(), "no manifest and no --reference");
    let opts = DatasetOptions { reference: Some("day".into()), max_distance: Some(7.0), ..Default::default() };
    let without = Dataset::open(dir.path(), &opts).unwrap();
    assert_eq!(without.reference, with.reference);
    assert_eq!(without.queries.len(), 2);
    for q in &with.queries {
        let gt = with.ground_truth(q).unwrap();
        assert!(gt.iter().all(|g| !g.is_empty()), "every query has a reference within 7 m");
    }
}

#[test]
fn a_map_queried_with_itself_finds_itself_in_every_setting() {
    let cfg = Config::without_appearance();
    let refs = common::encode(&cfg, &common::label_maps(12, 120, 90), "r");
    for setting in Setting::SEMLOOK {
        let (m, _) = match_batch(&refs, &refs, setting, &cfg);
        for (q, qm) in m.iter().enumerate() {
            let best = qm.best().unwrap();
            assert_eq!(best.reference as usize, q, "{setting}: query {q}");
            if setting.uses_coarse() {
                assert!((best.coarse.unwrap() - 1.0).abs() < 1e-5);
            }
            if setting == Setting::Forest || setting == Setting::GlobalForest {
                assert!((best.fine.unwrap() - 1.0).abs() < 1e-5, "identical forests score 1");
            }
            assert!(qm.ranked.windows(2).all(|w| w[0].score >= w[1].score), "ranked best first");
        }
    }
}

#[test]
fn streaming_top_k_does_not_depend_on_the_tile_size() {
    let cfg = Config::without_appearance();
    let refs = common::encode(&cfg, &common::label_maps(23, 80, 60), "r");
    let queries = common::encode(&cfg, &common::label_maps(5, 80, 60), "q");
    let p = SsimParams::new(&cfg.global);
    let whole = coarse_topk(&refs, &queries, &p, 7, 1_000_000);
    for tile in [1, 2, 5, 22] {
        assert_eq!(coarse_topk(&refs, &queries, &p, 7, tile), whole, "tile {tile}");
    }
    assert!(whole.iter().all(|l| l.len() == 7));
}

#[test]
fn evaluation_on_a_tiny_benchmark_reports_every_setting() {
    let dir = tempfile::tempdir().unwrap();
    common::tiny_synth(dir.path(), 12, 5);
    let ds = Dataset::open(dir.path(), &DatasetOptions::default()).unwrap();
    let cfg = Config::without_appearance();
    let report = evaluate(&ds, &cfg, &EvalOptions { settings: Setting::ALL.to_vec(), map: None, skip_invalid: false, quiet: true }, &mut semlook::engine::Engine::cpu()).unwrap();
    // without appearance the `appearance` baseline cannot run, and the report says so
    assert_eq!(report.skipped.iter().map(|s| s.0).collect::<Vec<_>>(), vec![Setting::Appearance]);
    assert_eq!(report.results.len(), 2 * (Setting::ALL.len() - 1));
    assert_eq!(report.references, 12);
    for r in &report.results {
        assert_eq!(r.queries, 12);
        for v in [r.pr.auc, r.pr.recall_at_100_precision, r.pr.precision_at_100_recall] {
            assert!((0.0..=1.0).contains(&v), "{} {}: {v}", r.query_set, r.setting);
        }
        // Recall@N never decreases with N, and Recall@1 is the share of correct top-1s
        assert!(r.recall_at.windows(2).all(|w| w[0].1 <= w[1].1));
        let correct = r.outcomes.iter().filter(|o| o.correct).count() as f64 / 12.0;
        assert!((r.recall_at[0].1 - correct).abs() < 1e-12);
    }
    let overcast_r1 = report.results.iter().find(|r| r.query_set == "overcast" && r.setting == Setting::GlobalForest).unwrap().recall_at[0].1;
    assert!(overcast_r1 > 0.3, "the easy condition should mostly match: {overcast_r1}");
    assert!(report.to_table().contains("global-forest"));
}
