//! The fine stage on the device: the map's packed forests resident across batches (counted to
//! the byte; a stored map keyed by its generation, no forest read after the first batch),
//! streamed through two slots beyond the budget, the CPU path's lists either way; several pairs
//! of small forests per workgroup (`tree_similarity_small`) equal to their twin on forests of
//! every size, every option, and a real scene.

use super::{assert_same_lists, gpu, gpu_with, random_forest_set};
use semlook::config::Config;
use semlook::descriptors::source::{GlobalSource, RefSource, TileBuf};
use semlook::descriptors::DescriptorSet;
use semlook::gpu::GpuOptions;
use semlook::gpu::GpuStages;
use semlook::local::Forest;
use semlook::matching::{CpuStages, Setting, Stages};
use semlook::util::SplitMix64;
use semlook_kernels::abi::TreeSimParams;
use semlook_kernels::tree_similarity::{fits_small, tree_similarity, tree_similarity_small, ForestRef, TreeSimScratch, PAIRS_PER_GROUP};
use std::sync::atomic::{AtomicUsize, Ordering};

/// The same batch twice against the same map: the second writes exactly the map's packed
/// forests less than the first (everything else it writes, queries, lookups, parameters, empty
/// lists, is the same). Listed pairs against the resident map then upload none of it; another
/// tree-weight rule (other packed weights) is another map, uploaded again.
#[test]
fn forests_are_uploaded_once_across_batches() {
    let Some(ctx) = gpu() else { return };
    let refs = random_forest_set(40, 16, 201);
    let q = random_forest_set(5, 16, 202);
    let sim = semlook::config::SimilarityConfig::default();
    let p = sim.tree_params(true, 3);
    let mut stages = GpuStages::new(ctx.clone());
    let b0 = ctx.bytes_uploaded();
    let l1 = stages.fine_topk(&p, &refs, &q, 6, 4096).unwrap();
    let b1 = ctx.bytes_uploaded();
    let l2 = stages.fine_topk(&p, &refs, &q, 6, 4096).unwrap();
    let b2 = ctx.bytes_uploaded();
    let map = stages.map_bytes().1;
    assert!(stages.fine_map_is_resident() && map > 0);
    assert_eq!((b1 - b0) - (b2 - b1), map, "first batch {} bytes, second {}, forests {map}", b1 - b0, b2 - b1);
    assert_eq!(l1, l2);
    assert_same_lists(&l1, &CpuStages.fine_topk(&p, &refs, &q, 6, 4096).unwrap(), 1e-5, "resident forests");
    let pairs: Vec<(u32, u32)> = (0..5).flat_map(|qi| (0..40).step_by(3).map(move |r| (qi, r))).collect();
    let s = stages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
    let b3 = ctx.bytes_uploaded();
    assert!(b3 - b2 < map, "listed pairs re-uploaded the forests ({} bytes)", b3 - b2);
    let c = CpuStages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
    assert!(s.iter().zip(&c).all(|(a, b)| (a - b).abs() <= 1e-5));
    let other = (semlook::config::SimilarityConfig { tree_weight: semlook::config::TreeWeight::SqrtArea, ..sim }).tree_params(true, 3);
    stages.fine_topk(&other, &refs, &q, 6, 4096).unwrap();
    assert!(ctx.bytes_uploaded() - b3 >= map, "forests with other weights are another map");
}

/// A budget below the map's forests: they are streamed, uploaded with every batch, and the
/// lists are the CPU path's; several map chunks under a small binding limit.
#[test]
fn forests_beyond_the_budget_are_streamed() {
    let Some(ctx) = gpu_with(&GpuOptions { resident_budget: Some(20_000), max_binding_size: Some(64 * 1024), ..Default::default() }) else { return };
    let refs = random_forest_set(60, 16, 211);
    let q = random_forest_set(4, 16, 212);
    let p = semlook::config::SimilarityConfig::default().tree_params(true, 3);
    let mut stages = GpuStages::new(ctx.clone());
    let cpu = CpuStages.fine_topk(&p, &refs, &q, 7, 4096).unwrap();
    for batch in 0..2 {
        let b = ctx.bytes_uploaded();
        let l = stages.fine_topk(&p, &refs, &q, 7, 4096).unwrap();
        let map = stages.map_bytes().1;
        assert!(map > 20_000 && !stages.fine_map_is_resident(), "{map} bytes of forests over a 20 kB budget");
        assert!(ctx.bytes_uploaded() - b >= map, "batch {batch}: the streamed forests are uploaded");
        assert_same_lists(&l, &cpu, 1e-5, "streamed forests");
    }
}

/// Forests of the given sizes (trees over four classes, neighbours, unit appearance on four
/// fifths of the trees); every fourth forest `uniform`: all its trees alike, so that every
/// same-class cell of its pairs ties and the tie rule decides the assignment.
pub fn forests_of_sizes(sizes: &[usize], dim: usize, seed: u64) -> DescriptorSet {
    let p = Config::without_appearance().global.ssim_params();
    let mut set = DescriptorSet::new(&p, 3, dim, 0);
    let mut rng = SplitMix64::new(seed);
    for (i, &trees) in sizes.iter().enumerate() {
        let uniform = i % 4 == 3;
        let mut f = Forest { neighbour_slots: 3, ..Default::default() };
        let first = (rng.below(4) as u8, rng.range(0.001, 0.3) as f32, rng.next_f64() as f32, rng.next_f64() as f32);
        let v0: Vec<f32> = (0..dim).map(|_| rng.normal() as f32).collect();
        let mut app = vec![0.0f32; trees * dim];
        let mut counts = vec![0u32; trees];
        for t in 0..trees {
            let (c, a, x, y) =
                if uniform { first } else { (rng.below(4) as u8, rng.range(0.001, 0.3) as f32, rng.next_f64() as f32, rng.next_f64() as f32) };
            f.classes.push(c);
            f.areas.push(a);
            f.centroids.extend([x, y]);
            for _ in 0..3 {
                f.neighbours.push(if trees > 1 && rng.chance(0.8) { ((t + 1 + rng.below(trees - 1)) % trees) as i32 } else { -1 });
            }
            if dim > 0 && (uniform || rng.chance(0.8)) {
                // uniform: tied scores, unequal weights (descriptor counts), so the tie rule shows
                counts[t] = if uniform { 1 + (t % 7) as u32 } else { 1 + rng.below(40) as u32 };
                let v: Vec<f32> = if uniform { v0.clone() } else { (0..dim).map(|_| rng.normal() as f32).collect() };
                let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
                app[t * dim..(t + 1) * dim].iter_mut().zip(&v).for_each(|(o, x)| *o = x / norm);
            }
        }
        f.set_appearance(dim, app, counts, 1).unwrap();
        let img = semlook::descriptors::EncodedImage {
            id: format!("s{i}"),
            width: 10,
            height: 10,
            global: vec![0.5; p.len()],
            global_stats: vec![0.0; p.stats_len()],
            forest: f,
            appearance: vec![],
            hog: vec![],
            embedding: vec![],
            compact_hog: vec![],
            keypoints: Default::default(),
            pose: None,
        };
        set.push(&img).unwrap();
    }
    set
}

/// The similarity options of `tree_similarity_matches_the_cpu_twin`, each with and without
/// appearance (the last pairing trees by Cityscapes category).
fn every_option() -> Vec<(String, TreeSimParams)> {
    use semlook::config::*;
    let variants = [
        SimilarityConfig::default(),
        SimilarityConfig { position: PositionSimilarity::Gaussian, missing_appearance: MissingAppearance::Drop, ..Default::default() },
        SimilarityConfig { assignment: Assignment::BestMatch, ..Default::default() },
        SimilarityConfig { tree_weight: TreeWeight::Descriptors, normalise: Normalise::GeometricMean, ..Default::default() },
        SimilarityConfig { tree_weight: TreeWeight::SqrtArea, assignment: Assignment::BestMatch, ..Default::default() },
        SimilarityConfig {
            tree_weight: TreeWeight::Area,
            w_area: 0.0,
            w_position: 0.0,
            missing_appearance: MissingAppearance::Drop,
            ..Default::default()
        },
        SimilarityConfig { class_match: ClassMatch::Category, ..Default::default() },
    ];
    let table = semlook::classes::ClassTable::cityscapes();
    variants
        .iter()
        .enumerate()
        .flat_map(|(v, sim)| [false, true].map(|app| (format!("option {v}, appearance {app}"), sim.tree_params_over(app, 3, &table.category_key()))))
        .collect()
}

/// Every (query, reference) pair in grid order (query-major), as a whole-map pass takes them.
fn grid(nq: usize, nr: usize) -> Vec<(u32, u32)> {
    (0..nq as u32).flat_map(|q| (0..nr as u32).map(move |r| (q, r))).collect()
}

/// Scores of `pairs` by the twins: `tree_similarity_small` in the order given (the pairs that
/// fit), `tree_similarity` for the rest; with the small twin's rounds.
fn twin_scores(
    p: &TreeSimParams,
    q: &DescriptorSet,
    r: &DescriptorSet,
    pairs: &[(u32, u32)],
) -> (Vec<f32>, semlook_kernels::tree_similarity::SmallRounds) {
    let qf: Vec<ForestRef> = (0..q.len()).map(|i| q.forest(i)).collect();
    let rf: Vec<ForestRef> = (0..r.len()).map(|i| r.forest(i)).collect();
    let list: Vec<[u32; 2]> = pairs.iter().map(|&(a, b)| [a, b]).collect();
    let mut out = vec![f32::NAN; pairs.len()];
    let mut scratch = TreeSimScratch::default();
    let rounds = tree_similarity_small(p, &qf, &rf, &list, &mut out, &mut scratch);
    for (o, &(a, b)) in out.iter_mut().zip(pairs) {
        if !fits_small(qf[a as usize].len(), rf[b as usize].len()) {
            *o = tree_similarity(p, qf[a as usize], rf[b as usize], &mut scratch);
        }
    }
    (out, rounds)
}

fn worst(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0f32, f32::max)
}

/// `tree_similarity_small` on the device equals its twin within 1e-5 (and the twin equals
/// `tree_similarity` bit for bit, `local::tree_similarity_tests`): forests of 0, 1, a few and
/// tens of trees, up to the round's limits and over them (64 x 24 fits, 65 x 24 and 130 x 0 do
/// not), uniform forests whose cells all tie, every similarity option. Listed pairs (the K
/// candidates) and the whole-map top-K, whose large pairs go to `tree_similarity` listed (a few
/// large references) or by the grid with `skip_small` (a query of 130 trees makes every pair of
/// its row large). The counters show several pairs per workgroup, and the twin's rounds that
/// several pairs share a round's workgroup memory.
#[test]
fn several_pairs_per_workgroup_equal_the_twin() {
    let Some(ctx) = gpu() else { return };
    let sizes = [0, 1, 2, 3, 5, 8, 12, 17, 24, 31, 40, 48, 64, 65, 100, 127, 128, 130];
    let refs = forests_of_sizes(&[&sizes[..], &[3, 9, 14, 20, 22, 25, 6, 11, 2, 27, 19, 24, 16, 1, 29, 33][..]].concat(), 16, 301);
    // queries: tens of trees, one small, one of 130 (no pair of its fits a round)
    let wide = forests_of_sizes(&[22, 7, 130, 40, 0, 18], 16, 302);
    let narrow = forests_of_sizes(&[22, 7, 13, 40, 0, 18], 16, 303);
    let mut stages = GpuStages::new(ctx.clone());
    let mut seen = (0f32, 0usize);
    for (what, p) in every_option() {
        for (qname, q) in [("a query of 130 trees", &wide), ("no query over 64 trees", &narrow)] {
            let pairs = grid(q.len(), refs.len());
            let before = stages.fine_counters();
            let got = stages.fine_pairs(&p, &refs, q, &pairs).unwrap();
            let c = stages.fine_counters();
            let (want, rounds) = twin_scores(&p, q, &refs, &pairs);
            let w = worst(&got, &want);
            assert!(w <= 1e-5, "{what}, {qname}: listed pairs differ from the twins by {w}");
            let (small, large) = (c.small_pairs - before.small_pairs, c.large_pairs - before.large_pairs);
            let fitting = pairs.iter().filter(|&&(a, b)| fits_small(q.forest(a as usize).len(), refs.forest(b as usize).len())).count() as u64;
            assert_eq!((small, large), (fitting, pairs.len() as u64 - fitting), "{what}: pairs per kernel");
            assert_eq!(
                c.small_workgroups - before.small_workgroups,
                small.div_ceil(PAIRS_PER_GROUP as u64),
                "{what}: {PAIRS_PER_GROUP} pairs a workgroup"
            );
            assert!(rounds.shared_rounds > 0 && rounds.most_pairs_in_a_round >= 4, "{what}: {rounds:?}");
            // the whole-map top-K through both kernels, against the CPU path
            let before = stages.fine_counters();
            let g = stages.fine_topk(&p, &refs, q, 10, 4096).unwrap();
            let c = stages.fine_counters();
            let cpu = CpuStages.fine_topk(&p, &refs, q, 10, 4096).unwrap();
            assert_same_lists(&g, &cpu, 1e-5, &format!("{what}, {qname}: whole-map top-K"));
            let (large, groups) = (c.large_pairs - before.large_pairs, c.large_workgroups - before.large_workgroups);
            assert_eq!(large, pairs.len() as u64 - fitting);
            if qname.starts_with('a') {
                assert!(groups == pairs.len() as u64, "{what}: many large pairs go by the grid with skip_small ({groups} workgroups)");
            } else {
                assert!(groups == large, "{what}: a few large pairs are listed ({groups} workgroups for {large})");
            }
            seen = (seen.0.max(w), seen.1.max(rounds.most_pairs_in_a_round));
        }
    }
    eprintln!("several pairs per workgroup: worst difference from the twins {:e}, up to {} pairs in a round", seen.0, seen.1);
}

/// A stored map is keyed by its identity and generation: after the first batch, a fine batch
/// against it reads none of its forests (nothing is hashed) and uploads none of them; adding to
/// it or removing from it (a new generation) uploads it again; the lists are the CPU path's.
#[test]
fn a_stored_maps_forests_are_keyed_by_its_generation() {
    let Some(ctx) = gpu() else { return };
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let cfg = Config::without_appearance();
    let set = crate::common::encode(&cfg, &crate::common::label_maps(12, 80, 60), "r");
    let queries = crate::common::encode(&cfg, &crate::common::label_maps(3, 80, 60), "q");
    let mut map = semlook::map::Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    let p = semlook::matching::tree_params(&cfg, Setting::Forest, map.neighbour_slots()).unwrap();
    let mut stages = GpuStages::new(ctx.clone());
    let batch = |stages: &mut GpuStages, map: &semlook::map::Map| {
        let counted = Counted { src: map, reads: AtomicUsize::new(0) };
        let b = ctx.bytes_uploaded();
        let lists = stages.fine_topk(&p, &counted, &queries, 5, 4096).unwrap();
        assert_same_lists(&lists, &CpuStages.fine_topk(&p, map, &queries, 5, 4096).unwrap(), 1e-5, "stored map");
        let s = stages.fine_pairs(&p, &counted, &queries, &grid(queries.len(), map.len())).unwrap();
        assert!(worst(&s, &CpuStages.fine_pairs(&p, map, &queries, &grid(queries.len(), map.len())).unwrap()) <= 1e-5);
        (counted.reads.load(Ordering::Relaxed), ctx.bytes_uploaded() - b)
    };
    let (reads, bytes) = batch(&mut stages, &map);
    let forests = stages.map_bytes().1;
    assert!(reads >= map.len() && bytes >= forests, "first batch: {reads} forest reads, {bytes} bytes");
    let (reads, bytes) = batch(&mut stages, &map);
    assert_eq!(reads, 0, "a batch against the same stored map read its forests (hashing them for a key)");
    assert!(bytes < forests, "the forests were uploaded again ({bytes} bytes)");
    map.add(&crate::common::encode(&cfg, &crate::common::label_maps(2, 70, 50), "new")).unwrap();
    let (reads, bytes) = batch(&mut stages, &map);
    assert!(reads >= map.len() && bytes >= stages.map_bytes().1, "after an add: {reads} reads, {bytes} bytes");
    drop(map);
    semlook::map::edit::remove(&path, &["r3".to_string()]).unwrap();
    let map = semlook::map::Map::open(&path).unwrap();
    let (reads, bytes) = batch(&mut stages, &map);
    assert!(reads >= map.len() && bytes >= stages.map_bytes().1, "after a removal: {reads} reads, {bytes} bytes");
}

/// A reference source that counts its forest reads (everything else as the source says, its
/// generation included).
struct Counted<'a> {
    src: &'a dyn RefSource,
    reads: AtomicUsize,
}

impl GlobalSource for Counted<'_> {
    fn len(&self) -> usize {
        self.src.len()
    }
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        self.src.tile(start, end, buf)
    }
    fn check(&self) -> semlook::Result<()> {
        self.src.check()
    }
    fn generation(&self) -> Option<u64> {
        self.src.generation()
    }
}

impl RefSource for Counted<'_> {
    fn id(&self, i: usize) -> &str {
        self.src.id(i)
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        self.reads.fetch_add(1, Ordering::Relaxed);
        self.src.forest(i)
    }
    fn neighbour_slots(&self) -> usize {
        self.src.neighbour_slots()
    }
    fn appearance_dim(&self) -> usize {
        self.src.appearance_dim()
    }
    fn image_appearance(&self, i: usize) -> semlook::values::Values<'_> {
        self.src.image_appearance(i)
    }
    fn hog_dim(&self) -> usize {
        self.src.hog_dim()
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        self.src.image_hog(i)
    }
    fn keypoint_dim(&self) -> usize {
        self.src.keypoint_dim()
    }
    fn keypoints(&self, i: usize) -> semlook::descriptors::keypoints::KeypointsRef<'_> {
        self.src.keypoints(i)
    }
}

/// A real scene: 52 CamVid test frames (`../shared/data/camvid-test`, skipped visibly when
/// absent), encoded from their real labels (and images: XFeat appearance, a codebook trained on
/// the references, where the weights are installed), 12 queries against 40 references, the
/// whole-map `forest` and `local` settings: every pair's score within 1e-5 of the twins, the
/// whole-map lists and the final ranking (`match_with`) the CPU path's.
#[test]
fn a_real_scene_through_several_pairs_per_workgroup() {
    let Some(dir) = crate::common::shared_or_required("data/camvid-test") else { return };
    let Some(ctx) = gpu() else { return };
    let mut names: Vec<String> =
        std::fs::read_dir(dir.join("labels")).unwrap().map(|e| e.unwrap().file_name().to_string_lossy().into_owned()).collect();
    names.sort();
    // both drives: every fourth frame, the first 40 the map, the next 12 the queries
    let names: Vec<&String> = names.iter().step_by(4).take(52).collect();
    let appearance = semlook::nn::onnx::find_model(semlook::networks::xfeat::XFEAT_WEIGHTS, None, "XFeat").is_ok();
    if !appearance {
        assert!(std::env::var_os("CI").is_none(), "setup.sh must provide the XFeat weights under CI");
        eprintln!("note: no XFeat weights, the real scene without appearance");
    }
    let cfg = match appearance {
        true => Config::camvid(),
        false => Config {
            appearance: semlook::config::AppearanceConfig { model: semlook::config::AppearanceModelKind::None, ..Default::default() },
            ..Config::camvid()
        },
    };
    let sources: Vec<semlook::input::FrameSource> = names
        .iter()
        .map(|n| semlook::input::FrameSource { id: n.to_string(), image: Some(dir.join("images").join(n)), labels: Some(dir.join("labels").join(n)) })
        .collect();
    let mut enc = semlook::encode::Encoder::new(&cfg).unwrap();
    if appearance {
        enc.train_codebook(&sources[..40], &|| {}).unwrap();
    }
    let encoded = enc.encode_all(&sources, Default::default(), &|| {});
    let (mut refs, mut q) = (enc.descriptor_set(), enc.descriptor_set());
    for (i, e) in encoded.into_iter().enumerate() {
        let img = e.unwrap().0;
        let pushed = if i < 40 { refs.push(&img) } else { q.push(&img) };
        pushed.unwrap();
    }
    let mut stages = GpuStages::new(ctx.clone());
    for setting in [Setting::Forest, Setting::Local] {
        let p = semlook::matching::tree_params(&cfg, setting, refs.neighbour_slots()).unwrap();
        let pairs = grid(q.len(), refs.len());
        let t = std::time::Instant::now();
        let before = stages.fine_counters();
        let got = stages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
        let (secs, c) = (t.elapsed().as_secs_f64(), stages.fine_counters());
        let (want, rounds) = twin_scores(&p, &q, &refs, &pairs);
        let w = worst(&got, &want);
        assert!(w <= 1e-5, "{setting}: pair scores differ from the twins by {w}");
        let cpu = CpuStages.fine_pairs(&p, &refs, &q, &pairs).unwrap();
        assert!(worst(&got, &cpu) <= 1e-5, "{setting}: pair scores differ from the CPU path");
        let small = c.small_pairs - before.small_pairs;
        assert!(small * 10 >= pairs.len() as u64 * 9, "{setting}: only {small} of {} real pairs fit a round", pairs.len());
        assert!(rounds.shared_rounds * 2 >= rounds.rounds, "{setting}: {rounds:?}");
        // the whole-map setting end to end: lists and ranking as on the CPU
        let (g, _) = semlook::matching::match_with(&mut stages, &refs, &q, setting, &cfg).unwrap();
        let (cp, _) = semlook::matching::match_batch(&refs, &q, setting, &cfg).unwrap();
        let as_lists = |m: &[semlook::matching::QueryMatch]| {
            m.iter().map(|m| m.ranked.iter().map(|c| (c.score, c.reference)).collect()).collect::<Vec<Vec<_>>>()
        };
        assert_same_lists(&as_lists(&g), &as_lists(&cp), 1e-5, &format!("CamVid {setting}: ranking"));
        let same = g.iter().zip(&cp).filter(|(a, b)| a.ranked.iter().map(|c| c.reference).eq(b.ranked.iter().map(|c| c.reference))).count();
        let trees: Vec<usize> = (0..refs.len()).map(|i| refs.forest(i).len()).collect();
        eprintln!(
            "CamVid {setting} ({} x {} pairs, appearance dim {}, forests of {}..{} trees): worst {w:e}, {small} pairs in {} small workgroups, {} rounds of up to {} pairs, {same} of {} rankings identical, {secs:.2} s for the pairs on {}",
            q.len(),
            refs.len(),
            refs.appearance_dim,
            trees.iter().min().unwrap(),
            trees.iter().max().unwrap(),
            c.small_workgroups - before.small_workgroups,
            rounds.rounds,
            rounds.most_pairs_in_a_round,
            q.len(),
            ctx.describe()
        );
    }
}

/// Forests without a single tree (what a map built without labels holds), on the map's side, the
/// queries' or both: the device's scores and lists are the CPU path's, for listed pairs, for the
/// whole map, and through the `verified` pipeline (it crashed on the device: an empty tree array
/// was bound where the shader needs one record).
#[test]
fn forests_without_any_tree_match_on_both_paths() {
    let Some(ctx) = gpu() else { return };
    let p = semlook::config::SimilarityConfig::default().tree_params(true, 3);
    let (empty_refs, empty_q) = (forests_of_sizes(&[0; 12], 16, 301), forests_of_sizes(&[0; 3], 16, 302));
    let (refs, q) = (forests_of_sizes(&[3, 0, 7, 1, 0, 12], 16, 303), forests_of_sizes(&[0, 5], 16, 304));
    let mut stages = GpuStages::new(ctx.clone());
    for (r, qs, what) in [(&empty_refs, &empty_q, "both empty"), (&empty_refs, &q, "map empty"), (&refs, &empty_q, "queries empty")] {
        let pairs: Vec<(u32, u32)> = (0..qs.len() as u32).flat_map(|qi| (0..r.len() as u32).map(move |ri| (qi, ri))).collect();
        let g = stages.fine_pairs(&p, r, qs, &pairs).unwrap();
        let c = CpuStages.fine_pairs(&p, r, qs, &pairs).unwrap();
        assert!(g.iter().zip(&c).all(|(a, b)| (a - b).abs() <= 1e-5), "{what}: {g:?} against {c:?}");
        stages.forget_map();
        assert_same_lists(&stages.fine_topk(&p, r, qs, 4, 4096).unwrap(), &CpuStages.fine_topk(&p, r, qs, 4, 4096).unwrap(), 1e-5, what);
        stages.forget_map();
        let cfg = Config::default();
        let (gm, _) = semlook::matching::match_with(&mut stages, r, qs, Setting::Verified, &cfg).unwrap();
        let (cm, _) = semlook::matching::match_with(&mut CpuStages, r, qs, Setting::Verified, &cfg).unwrap();
        for (a, b) in gm.iter().zip(&cm) {
            let refs_of = |m: &semlook::matching::QueryMatch| m.ranked.iter().map(|c| c.reference).collect::<Vec<_>>();
            assert_eq!(refs_of(a), refs_of(b), "{what}: verified rankings");
        }
        stages.forget_map();
    }
}
