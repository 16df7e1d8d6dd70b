//! End to end on the library: synthetic data, encoding, matching, evaluation.

mod common;

use semlook::config::Config;
use semlook::dataset::{Dataset, DatasetOptions};
use semlook::eval::{evaluate, EvalOptions};
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
        let (m, _) = match_batch(&refs, &refs, setting, &cfg).unwrap();
        for (q, qm) in m.iter().enumerate() {
            let best = qm.best().unwrap();
            assert_eq!(best.reference as usize, q, "{setting}: query {q}");
            if setting.uses_coarse() {
                // SSIM 1 with itself; the fused coarse score without appearance is w_global x SSIM
                let expected = if setting.fuses_coarse(cfg.matching.coarse) { cfg.matching.w_global as f32 } else { 1.0 };
                assert!((best.coarse.unwrap() - expected).abs() < 1e-5, "{setting}: coarse {:?}", best.coarse);
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
    let p = cfg.global.ssim_params();
    let whole = coarse_topk(&refs, &queries, &p, 7, 1_000_000);
    for tile in [1, 2, 5, 22] {
        assert_eq!(coarse_topk(&refs, &queries, &p, 7, tile), whole, "tile {tile}");
    }
    assert!(whole.iter().all(|l| l.len() == 7));
}

/// R@1 of a matcher that picks a reference at random, on a query set with these ground-truth
/// lists: its mean (the share of the map that is correct, per query) and its standard deviation
/// (a mean of independent Bernoulli trials).
fn chance_r1(gt: &[Vec<u32>], refs: usize) -> (f64, f64) {
    let p: Vec<f64> = gt.iter().filter(|g| !g.is_empty()).map(|g| g.len() as f64 / refs as f64).collect();
    let n = p.len() as f64;
    (p.iter().sum::<f64>() / n, p.iter().map(|p| p * (1.0 - p)).sum::<f64>().sqrt() / n)
}

/// AUC, R@100P and P@100R from (score, correct) pairs, written out from the definitions
/// (scikit-learn's precision-recall curve, VPR-Bench's metrics) independently of `eval::metrics`.
fn pr_by_definition(outcomes: &[(f64, bool)]) -> (f64, f64, f64) {
    let positives = outcomes.iter().filter(|o| o.1).count() as f64;
    if positives == 0.0 {
        return (0.0, 0.0, 0.0);
    }
    let mut thresholds: Vec<f64> = outcomes.iter().map(|o| o.0).collect();
    thresholds.sort_by(|a, b| b.total_cmp(a));
    thresholds.dedup();
    // (recall, precision) from the highest threshold down, after the (0, 1) end point
    let mut curve = vec![(0.0, 1.0)];
    for t in &thresholds {
        let accepted: Vec<bool> = outcomes.iter().filter(|o| o.0 >= *t).map(|o| o.1).collect();
        let tp = accepted.iter().filter(|&&c| c).count() as f64;
        curve.push((tp / positives, tp / accepted.len() as f64));
    }
    let auc: f64 = curve.windows(2).map(|w| (w[1].0 - w[0].0) * (w[0].1 + w[1].1) / 2.0).sum();
    let r100p = if curve[1].1 < 1.0 { 0.0 } else { curve.iter().skip(1).filter(|c| c.1 == 1.0).map(|c| c.0).fold(0.0, f64::max) };
    let p100r = curve.iter().filter(|c| c.0 == 1.0).map(|c| c.1).fold(0.0, f64::max);
    (auc, r100p, p100r)
}

#[test]
fn evaluation_on_a_tiny_benchmark_reports_every_setting() {
    let dir = tempfile::tempdir().unwrap();
    let places = 24;
    common::tiny_synth(dir.path(), places, 5);
    let ds = Dataset::open(dir.path(), &DatasetOptions::default()).unwrap();
    let cfg = Config::without_appearance();
    let report = evaluate(
        &ds,
        &cfg,
        &EvalOptions { settings: Setting::ALL.to_vec(), map: None, skip_invalid: false, quiet: true, sequence: false, label_cache: None },
        &mut semlook::engine::Engine::cpu(),
    )
    .unwrap();
    // without appearance the `appearance` baseline cannot run, and the report says so
    assert_eq!(report.skipped.iter().map(|s| s.0).collect::<Vec<_>>(), vec![Setting::Appearance]);
    assert_eq!(report.results.len(), 2 * (Setting::ALL.len() - 1));
    assert_eq!(report.references, places);
    for r in &report.results {
        assert_eq!(r.queries, places);
        // the metrics are those of the report's own outcomes
        let scored: Vec<(f64, bool)> =
            r.outcomes.iter().filter(|o| o.valid_references > 0).map(|o| (o.score.map_or(f64::NEG_INFINITY, f64::from), o.correct)).collect();
        let (auc, r100p, p100r) = pr_by_definition(&scored);
        let what = format!("{} {}", r.query_set, r.setting);
        assert!(
            (r.pr.auc - auc).abs() < 1e-12 && r.pr.recall_at_100_precision == r100p && r.pr.precision_at_100_recall == p100r,
            "{what}: {:?} vs {auc} {r100p} {p100r}",
            r.pr
        );
        // Recall@N never decreases with N, and Recall@1 is the share of correct top-1s
        assert!(r.recall_at.windows(2).all(|w| w[0].1 <= w[1].1), "{what}");
        let correct = scored.iter().filter(|o| o.1).count() as f64 / scored.len() as f64;
        assert!((r.recall_at[0].1 - correct).abs() < 1e-12, "{what}");
    }
    // on the easy condition every setting beats a random matcher by four standard deviations
    let overcast = ds.queries.iter().find(|q| q.name == "overcast").unwrap();
    let (chance, sd) = chance_r1(&ds.ground_truth(overcast).unwrap(), places);
    let floor = chance + 4.0 * sd;
    for r in report.results.iter().filter(|r| r.query_set == "overcast") {
        eprintln!("overcast {}: R@1 {:.3} (chance {chance:.3}, floor {floor:.3})", r.setting, r.recall_at[0].1);
        assert!(r.recall_at[0].1 > floor, "{}: R@1 {} is not above chance {chance:.3} + 4 sd = {floor:.3}", r.setting, r.recall_at[0].1);
    }
    assert!(report.to_table().contains("global-forest"));
}
