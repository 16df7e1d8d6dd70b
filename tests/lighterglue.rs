//! The crate's LighterGlue (src/networks/lighterglue/mod.rs) held to the authors' PyTorch model (kornia's
//! `LightGlue` with XFeat's configuration and `xfeat-lighterglue.pt`) on real pairs: the reference
//! outputs are committed in tests/data/lighterglue_pairs.json, written once by
//! scripts/make_lighterglue_fixtures.py from XFeat keypoints of real photos stored as the map stores
//! them (u16 positions, int8 descriptors).
//!
//! Tolerance: the matches (index pairs) identical, with and without point pruning; each match's
//! probability within 1e-3 of the reference's (float32 on both sides, other summation orders; the
//! largest difference seen is printed).

mod common;

use common::glue::{fixtures, network, reference_matches, Stored};

use semlook::config::Config;
use semlook::descriptors::keypoints::KeypointsRef;
use semlook::networks::lighterglue::GlueParams;
use semlook::verify::{verify_pairs_cpu, VerifyParams};

const PROBABILITY_TOLERANCE: f32 = 1e-3;

#[test]
fn matches_the_reference_on_real_pairs() {
    let Some(net) = network() else { return };
    let fx = fixtures();
    let mut worst = 0.0f32;
    let mut compared = 0;
    for pair in fx["pairs"].as_array().unwrap() {
        let (a, b) = (Stored::of(pair, "image0"), Stored::of(pair, "image1"));
        for run in ["pruned", "full"] {
            let r = &pair[run];
            let p = GlueParams { width_confidence: r["width_confidence"].as_f64().unwrap() as f32, ..GlueParams::default() };
            let ours = net.match_keypoints(&p, a.as_ref(), b.as_ref());
            let want = reference_matches(pair, run);
            let name = format!("{} ({run})", pair["name"].as_str().unwrap());
            let pairs = |v: &[(u32, u32, f32)]| v.iter().map(|&(i, j, _)| (i, j)).collect::<Vec<_>>();
            assert_eq!(pairs(&ours), pairs(&want), "{name}: matches differ from the reference");
            for (o, w) in ours.iter().zip(&want) {
                let d = (o.2 - w.2).abs();
                worst = worst.max(d);
                assert!(d <= PROBABILITY_TOLERANCE, "{name}: match {:?} probability {} vs reference {}", (o.0, o.1), o.2, w.2);
            }
            assert!(!want.is_empty(), "{name}: the fixture should have matches");
            compared += want.len();
        }
    }
    eprintln!("{compared} matches identical; largest probability difference {worst:.2e} (tolerance {PROBABILITY_TOLERANCE:.0e})");
}

#[test]
fn a_side_without_keypoints_has_no_matches() {
    let Some(net) = network() else { return };
    let fx = fixtures();
    let a = Stored::of(&fx["pairs"][0], "image0");
    let p = GlueParams::default();
    assert!(net.match_keypoints(&p, a.as_ref(), KeypointsRef::EMPTY).is_empty());
    assert!(net.match_keypoints(&p, KeypointsRef::EMPTY, a.as_ref()).is_empty());
    // one keypoint each side: runs, matches at most once
    let one = KeypointsRef { descriptors: &a.descriptors[..64], xy: &a.xy[..2], classes: &a.classes[..1], dim: 64 };
    assert!(net.match_keypoints(&p, one, one).len() <= 1);
}

#[test]
fn early_exit_and_pruning_are_honoured() {
    let Some(net) = network() else { return };
    let fx = fixtures();
    let pair = &fx["pairs"][1];
    let (a, b) = (Stored::of(pair, "image0"), Stored::of(pair, "image1"));
    let full = net.match_keypoints(&GlueParams { width_confidence: -1.0, ..GlueParams::default() }, a.as_ref(), b.as_ref());
    // an early exit after the first layer (any share of confident points beats 0+) gives other matches
    let early = net.match_keypoints(&GlueParams { width_confidence: -1.0, depth_confidence: 1e-6, ..GlueParams::default() }, a.as_ref(), b.as_ref());
    assert_ne!(full, early);
    // a stricter threshold keeps a subset
    let strict = net.match_keypoints(&GlueParams { filter_threshold: 0.5, width_confidence: -1.0, ..GlueParams::default() }, a.as_ref(), b.as_ref());
    assert!(strict.len() < full.len() && strict.iter().all(|m| full.iter().any(|f| (f.0, f.1) == (m.0, m.1))));
}

/// `verification.matcher = "lighterglue"` reaches verification: the pair is verified on the
/// learned matcher's matches (the reference's count, without pruning), not on mutual nearest
/// neighbours, and RANSAC keeps part of them.
#[test]
fn verification_with_the_learned_matcher_counts_its_matches() {
    let Some(_) = network() else { return };
    let fx = fixtures();
    let pair = &fx["pairs"][1];
    let (a, b) = (Stored::of(pair, "image0"), Stored::of(pair, "image1"));
    let reference = pair["full"]["matches0"].as_array().unwrap().iter().filter(|j| j.as_i64().unwrap() >= 0).count() as u32;
    let cfg = Config::from_toml("[verification]\nmatcher = \"lighterglue\"\nglue_width_confidence = -1\n", "glue.toml").unwrap();
    let verify = |cfg: &Config| verify_pairs_cpu(&VerifyParams::new(&cfg.verification), &|_| a.as_ref(), &|_| b.as_ref(), &[(0, 0), (0, 0)]).unwrap();
    let glue = verify(&cfg);
    assert_eq!(glue[0], glue[1]);
    assert_eq!(glue[0].matches, reference);
    assert!(glue[0].inliers >= 10 && glue[0].inliers <= glue[0].matches, "{:?}", glue[0]);
    let mnn = verify(&Config::default());
    assert_ne!(mnn[0].matches, glue[0].matches, "mutual nearest neighbours give other matches");
}

/// Many pairs in one call (each query's side prepared once for all its pairs, a block of queries
/// at a time) verify as each pair alone, whatever their order: more queries than one block, a
/// query's pairs scattered through the list, a pair twice, a query without keypoints.
#[test]
fn a_batch_of_pairs_verifies_as_each_pair_alone() {
    let Some(_) = network() else { return };
    let fx = fixtures();
    let images: Vec<Stored> = (0..3).flat_map(|k| ["image0", "image1"].map(|side| Stored::of(&fx["pairs"][k], side))).collect();
    let cfg = Config::from_toml("[verification]\nmatcher = \"lighterglue\"\nglue_threshold = 0.5\n", "glue.toml").unwrap();
    let p = VerifyParams::new(&cfg.verification);
    // 13 query indices over the 6 images, each its own keypoints (indices 6-11 without their
    // image's last 11; index 12: none), 3 references each, interleaved
    let q = |a: u32| match a {
        12 => KeypointsRef::EMPTY,
        _ => {
            let k = images[a as usize % 6].as_ref();
            let n = k.xy.len() / 2 - 11 * (a as usize / 6);
            KeypointsRef { descriptors: &k.descriptors[..n * 64], xy: &k.xy[..2 * n], classes: &k.classes[..n], dim: 64 }
        }
    };
    let r = |b: u32| images[(b as usize + 1) % 6].as_ref();
    let mut pairs: Vec<(u32, u32)> = (0..3).flat_map(|b| (0..13).rev().map(move |a| (a, (a + 2 * b) % 6))).collect();
    pairs.push(pairs[5]);
    let batch = verify_pairs_cpu(&p, &q, &r, &pairs).unwrap();
    let mut found = 0;
    for (k, &pair) in pairs.iter().enumerate() {
        let alone = verify_pairs_cpu(&p, &q, &r, &[pair]).unwrap()[0];
        assert_eq!(batch[k], alone, "pair {k} {pair:?}");
        found += (alone.inliers > 0) as usize;
    }
    assert!(found >= 3, "pairs with inliers among the batch: {found}");
    assert!(pairs.iter().zip(&batch).all(|(p, v)| p.0 != 12 || *v == Default::default()), "the query without keypoints matches nothing");
}

/// A descriptor set of stored keypoints alone (global descriptors all equal, no trees or
/// appearance), so that the verified score is the inlier terms plus a constant.
fn keypoint_set(cfg: &Config, images: &[&Stored]) -> semlook::descriptors::DescriptorSet {
    let p = cfg.global.ssim_params();
    let mut set = semlook::descriptors::DescriptorSet::new(&p, cfg.local.neighbours, 0, 0).with_keypoint_dim(64);
    for (i, s) in images.iter().enumerate() {
        let img = semlook::descriptors::EncodedImage {
            id: format!("{i}"),
            width: 640,
            height: 480,
            global: vec![0.5; p.len()],
            global_stats: vec![0.0; p.stats_len()],
            forest: semlook::local::Forest { neighbour_slots: cfg.local.neighbours, ..Default::default() },
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: semlook::descriptors::keypoints::ImageKeypoints {
                descriptors: s.descriptors.clone(),
                xy: s.xy.clone(),
                classes: s.classes.clone(),
                dim: 64,
            },
            pose: None,
        };
        set.push(&img).unwrap();
    }
    set
}

/// `verification.w_glue` > 0 with the MNN matcher: LighterGlue verifies every candidate too and
/// w_glue ln(1 + its inliers) is added to each score, exactly (MNN's part unchanged); a pair scores
/// the same whatever other pairs are scored with it.
#[test]
fn w_glue_adds_the_learned_matchers_inliers_to_every_candidate() {
    let Some(_) = network() else { return };
    let fx = fixtures();
    let img = |k: usize, side: &str| Stored::of(&fx["pairs"][k], side);
    let (q0, q1) = (img(0, "image0"), img(1, "image0"));
    let r = [img(0, "image1"), img(1, "image1"), img(2, "image1"), img(2, "image0")];
    let base = Config::from_toml("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\n", "t.toml").unwrap();
    let queries = keypoint_set(&base, &[&q0, &q1]);
    let refs = keypoint_set(&base, &r.iter().collect::<Vec<_>>());
    let with = Config::from_toml("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\nw_glue = 0.5\n", "t.toml").unwrap();
    let (plain, _) = semlook::matching::match_batch(&refs, &queries, semlook::matching::Setting::Verified, &base).unwrap();
    let (fused, _) = semlook::matching::match_batch(&refs, &queries, semlook::matching::Setting::Verified, &with).unwrap();
    let glue_cfg = Config::from_toml("[verification]\nmatcher = \"lighterglue\"\nglue_threshold = 0.7\n", "t.toml").unwrap();
    let mut raised = 0;
    for (qi, (p, f)) in plain.iter().zip(&fused).enumerate() {
        assert_eq!(p.ranked.len(), r.len());
        for c in &p.ranked {
            let after = f.ranked.iter().find(|x| x.reference == c.reference).unwrap();
            let glue = verify_pairs_cpu(
                &VerifyParams::new(&glue_cfg.verification),
                &|_| queries.keypoints(qi),
                &|_| refs.keypoints(c.reference as usize),
                &[(0, 0)],
            )
            .unwrap()[0]
                .inliers;
            let want = 0.5 * (glue as f64).ln_1p();
            assert!(
                ((after.score - c.score) as f64 - want).abs() < 1e-4,
                "query {qi} reference {}: {} -> {} (glue inliers {glue})",
                c.reference,
                c.score,
                after.score
            );
            raised += (want > 0.0) as usize;
        }
    }
    assert!(raised >= 2, "LighterGlue found inliers on some pairs");
    // one pair scored alone (as a shard or a sequence neighbour would score it) scores as in the batch
    // (weighed against its query's candidates, as the batch weighed it)
    let evidence: Vec<_> = fused.iter().map(|m| m.evidence).collect();
    let alone = semlook::matching::score_pairs(
        &mut semlook::matching::CpuStages,
        &refs,
        &queries,
        semlook::matching::Setting::Verified,
        &with,
        &[(1, 2)],
        Some(&evidence),
    )
    .unwrap();
    let in_batch = fused[1].ranked.iter().find(|c| c.reference == 2).unwrap();
    assert_eq!(alone[0].score, in_batch.score);
}

/// `glue_min_inliers`: LighterGlue's term only on the pairs whose MNN inliers reach the floor,
/// the others scored as without `w_glue`; a floor between the pairs' MNN inliers, so that both
/// sides of it hold pairs where LighterGlue finds inliers.
#[test]
fn glue_min_inliers_runs_the_learned_matcher_only_where_mnn_found_enough() {
    let Some(_) = network() else { return };
    let fx = fixtures();
    let img = |k: usize, side: &str| Stored::of(&fx["pairs"][k], side);
    let qs = [img(0, "image0"), img(1, "image0"), img(2, "image0")];
    let r = [img(0, "image1"), img(1, "image1"), img(2, "image1"), img(2, "image0"), img(0, "image0")];
    let base = Config::from_toml("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\n", "t.toml").unwrap();
    let queries = keypoint_set(&base, &qs.iter().collect::<Vec<_>>());
    let refs = keypoint_set(&base, &r.iter().collect::<Vec<_>>());
    let run = |toml: &str| {
        let cfg = Config::from_toml(toml, "t.toml").unwrap();
        semlook::matching::match_batch(&refs, &queries, semlook::matching::Setting::Verified, &cfg).unwrap().0
    };
    let plain = run("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\n");
    let all = run("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\nw_glue = 0.5\n");
    // the floor: the median MNN inliers of the pairs where LighterGlue adds something
    let find = |lists: &Vec<semlook::matching::QueryMatch>, q: usize, r: u32| *lists[q].ranked.iter().find(|c| c.reference == r).unwrap();
    let mut lifted: Vec<u32> = Vec::new();
    for (q, p) in plain.iter().enumerate() {
        for c in &p.ranked {
            if find(&all, q, c.reference).score > c.score {
                lifted.push(c.inliers.unwrap());
            }
        }
    }
    lifted.sort();
    let floor = lifted[lifted.len() / 2].max(1);
    let gated_toml = format!("[verification]\ninliers = \"count\"\nglue_threshold = 0.7\nw_glue = 0.5\nglue_min_inliers = {floor}\n");
    let gated = run(&gated_toml);
    let (mut kept, mut dropped) = (0, 0);
    for (q, p) in plain.iter().enumerate() {
        for c in &p.ranked {
            let (a, g) = (find(&all, q, c.reference), find(&gated, q, c.reference));
            let want = match c.inliers.unwrap() >= floor {
                true => a.score,
                false => c.score,
            };
            assert_eq!(g.score, want, "query {q} reference {}: MNN inliers {:?}, floor {floor}", c.reference, c.inliers);
            kept += (c.inliers.unwrap() >= floor && a.score > c.score) as usize;
            dropped += (c.inliers.unwrap() < floor && a.score > c.score) as usize;
        }
    }
    assert!(kept > 0 && dropped > 0, "pairs with LighterGlue inliers on both sides of the floor {floor}: {kept} kept, {dropped} dropped");
    // a pair scored alone scores as in the batch
    let cfg = Config::from_toml(&gated_toml, "t.toml").unwrap();
    let evidence: Vec<_> = gated.iter().map(|m| m.evidence).collect();
    for (q, p) in gated.iter().enumerate() {
        for c in &p.ranked {
            let alone = semlook::matching::score_pairs(
                &mut semlook::matching::CpuStages,
                &refs,
                &queries,
                semlook::matching::Setting::Verified,
                &cfg,
                &[(q as u32, c.reference)],
                Some(&evidence),
            )
            .unwrap();
            assert_eq!(alone[0].score, c.score);
        }
    }
}

/// The device executor's forward pass run on the CPU twins of `lighterglue.wgsl`
/// (`networks::lighterglue::forward_on_twins`: the same passes the device runs, the online softmax,
/// erf by a polynomial) held to the authors' model like the crate's CPU matcher: matches
/// identical with and without pruning, probabilities within 1e-3; all pairs in one batch, with
/// an empty pair among them. What the device is then held to (tests/gpu/lighterglue.rs).
#[test]
fn the_device_plan_on_the_twins_matches_the_reference() {
    let Some(net) = network() else { return };
    let fx = fixtures();
    let stored: Vec<(Stored, Stored)> = fx["pairs"].as_array().unwrap().iter().map(|p| (Stored::of(p, "image0"), Stored::of(p, "image1"))).collect();
    let mut worst = 0.0f32;
    for run in ["pruned", "full"] {
        let mut pairs: Vec<(KeypointsRef, KeypointsRef)> = stored.iter().map(|(a, b)| (a.as_ref(), b.as_ref())).collect();
        pairs.insert(1, (stored[0].0.as_ref(), KeypointsRef::EMPTY));
        let width = fx["pairs"][0][run]["width_confidence"].as_f64().unwrap() as f32;
        let p = GlueParams { width_confidence: width, ..GlueParams::default() };
        let got = semlook::networks::lighterglue::forward_on_twins(&net, &p, &pairs);
        assert_eq!(got.len(), pairs.len());
        assert!(got[1].is_empty(), "a side without keypoints has no matches");
        let got: Vec<_> = got.into_iter().enumerate().filter(|&(k, _)| k != 1).map(|x| x.1).collect();
        for (pair, ours) in fx["pairs"].as_array().unwrap().iter().zip(&got) {
            let want = reference_matches(pair, run);
            let name = format!("{} ({run})", pair["name"].as_str().unwrap());
            let ij = |v: &[(u32, u32, f32)]| v.iter().map(|&(i, j, _)| (i, j)).collect::<Vec<_>>();
            assert_eq!(ij(ours), ij(&want), "{name}: the twins' matches differ from the reference");
            for (o, w) in ours.iter().zip(&want) {
                worst = worst.max((o.2 - w.2).abs());
            }
        }
    }
    assert!(worst <= PROBABILITY_TOLERANCE, "largest probability difference {worst}");
    eprintln!("twins: matches identical; largest probability difference {worst:.2e}");
    // early exit (per pair) and pruning to an empty side, which the fixtures do not cover: the
    // twins' plan against the crate's CPU matcher, which is held to the reference above
    let pairs: Vec<(KeypointsRef, KeypointsRef)> = stored.iter().map(|(a, b)| (a.as_ref(), b.as_ref())).collect();
    let full = semlook::networks::lighterglue::forward_on_twins(&net, &GlueParams { width_confidence: -1.0, ..GlueParams::default() }, &pairs);
    for (what, p) in [
        ("early exit after the first layer", GlueParams { width_confidence: -1.0, depth_confidence: 1e-6, ..GlueParams::default() }),
        ("early exit 0.95 with pruning", GlueParams { depth_confidence: 0.95, ..GlueParams::default() }),
        ("pruning nearly every point", GlueParams { width_confidence: 1e-6, ..GlueParams::default() }),
    ] {
        let twins = semlook::networks::lighterglue::forward_on_twins(&net, &p, &pairs);
        for (k, (a, b)) in pairs.iter().enumerate() {
            let cpu = net.match_keypoints(&p, *a, *b);
            let ij = |v: &[(u32, u32, f32)]| v.iter().map(|&(i, j, _)| (i, j)).collect::<Vec<_>>();
            assert_eq!(ij(&twins[k]), ij(&cpu), "{what}, pair {k}: the twins' plan differs from the CPU matcher");
            assert!(twins[k].iter().zip(&cpu).all(|(t, c)| (t.2 - c.2).abs() <= PROBABILITY_TOLERANCE), "{what}, pair {k}");
        }
        if what.starts_with("early exit after") {
            assert!(twins.iter().zip(&full).all(|(e, f)| e != f), "an exit after the first layer gives other matches on every pair");
        }
    }
}
