//! The map store: bit-exact round trips (f32 and f16), appends, removal and compaction with exact
//! top-K, refusal of bad values before writing, damaged files named, the advisory lock, and
//! readers that never see a partial state.

mod common;

use semlook::config::Config;
use semlook::descriptors::source::{GlobalSource, RefSource, TileBuf};
use semlook::descriptors::DescriptorSet;
use semlook::error::Error;
use semlook::map::{edit, Map, MapWriter, StoreOptions};
use semlook::matching::{match_batch, match_with, CpuStages, Setting};
use semlook::values::ValueType;
use std::path::Path;

fn built(dir: &Path) -> (Config, Map) {
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(6, 96, 72), "ref");
    (cfg.clone(), Map::create(dir, &cfg.encoding(), &set, None).unwrap())
}

/// A map of `n` images in segments of `per` images.
fn segmented(dir: &Path, n: usize, per: usize, values: ValueType) -> (Config, DescriptorSet, Map) {
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(n, 80, 60), "r");
    let map = Map::create_with(dir, &cfg.encoding(), &set, None, StoreOptions { values, segment_images: per, ..Default::default() }).unwrap();
    (cfg, set, map)
}

fn bits(v: &[f32]) -> Vec<u32> {
    v.iter().map(|x| x.to_bits()).collect()
}

#[test]
fn round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(6, 96, 72), "ref");
    let map = Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    let back = Map::open(&path).unwrap();
    assert_eq!(back.manifest, map.manifest);
    assert_eq!(back.manifest.generation, 1);
    let b = back.to_descriptor_set().unwrap();
    assert_eq!(bits(&set.globals), bits(&b.globals));
    // statistics are not stored: recomputed on read, they equal the encoder's bit for bit
    assert_eq!(bits(&set.global_stats), bits(&b.global_stats));
    assert_eq!(bits(&set.tree_areas), bits(&b.tree_areas));
    assert_eq!(set, b);
    assert!(b.n_trees() > 6, "label maps should give several objects each");
}

#[test]
fn f16_maps_round_values_and_keep_everything_else() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, set, map) = segmented(&dir.path().join("m"), 8, 3, ValueType::F16);
    assert_eq!(map.manifest.values, ValueType::F16);
    let back = Map::open(&dir.path().join("m")).unwrap().to_descriptor_set().unwrap();
    let mut rounded = set.globals.clone();
    semlook::values::round_through_f16(&mut rounded);
    assert_eq!(bits(&back.globals), bits(&rounded));
    assert_ne!(bits(&back.globals), bits(&set.globals), "f16 should round some values");
    assert_eq!((&back.ids, &back.tree_areas, &back.tree_neighbours), (&set.ids, &set.tree_areas, &set.tree_neighbours));
    // half the bytes of the global descriptors
    let f32_dir = dir.path().join("m32");
    segmented(&f32_dir, 8, 3, ValueType::F32);
    let size = |m: &Map| m.manifest.segments.iter().map(|s| s.bytes).sum::<u64>();
    let (a, b) = (size(&Map::open(&f32_dir).unwrap()), size(&map));
    assert!((b as f64) < 0.6 * a as f64, "f16 {b} bytes, f32 {a}");
    let queries = common::encode(&cfg, &common::label_maps(3, 80, 60), "q");
    let (m, _) = match_batch(&map, &queries, Setting::Semlook, &cfg).unwrap();
    assert_eq!(m.len(), 3);
}

#[test]
fn add_appends_a_segment_and_keeps_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, mut map) = built(&path);
    let first = map.manifest.segments[0].file.clone();
    let seg0 = std::fs::read(path.join(&first)).unwrap();
    let more = common::encode(&cfg, &common::label_maps(3, 80, 60), "new");
    map.add(&more).unwrap();
    assert_eq!(std::fs::read(path.join(&first)).unwrap(), seg0, "stored segment rewritten");
    let back = Map::open(&path).unwrap();
    assert_eq!((back.len(), back.manifest.generation, back.manifest.segments.len()), (9, 2, 2));
    assert_eq!(back.to_descriptor_set().unwrap(), map.to_descriptor_set().unwrap());
    assert_eq!(back.id(6), "new0");
}

/// One id given to two images of a new map or of an add is refused naming both positions, not
/// as "already stored" (which the map never held; before, create and add both said so); the
/// map is not created, or left as it was.
#[test]
fn an_id_given_twice_names_both_images() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let mut set = common::encode(&cfg, &common::label_maps(3, 96, 72), "ref");
    set.ids[2] = "ref0".into();
    let path = dir.path().join("new");
    let err = Map::create(&path, &cfg.encoding(), &set, None).unwrap_err();
    assert!(matches!(err, Error::RepeatedImageId { ref id, first: 0, second: 2, .. } if id == "ref0"), "{err}");
    assert!(err.to_string().contains("given twice") && !err.to_string().contains("already stored"), "{err}");
    assert!(!path.join("manifest.json").exists());
    let (_, mut map) = built(&dir.path().join("m"));
    let before = common::snapshot(&dir.path().join("m"));
    set.ids = vec!["new0".into(), "new1".into(), "new0".into()];
    let err = map.add(&set).unwrap_err();
    assert!(matches!(err, Error::RepeatedImageId { ref id, first: 0, second: 2, .. } if id == "new0"), "{err}");
    assert_eq!(common::snapshot(&dir.path().join("m")), before);
}

#[test]
fn duplicate_ids_are_refused_before_writing() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, mut map) = built(&path);
    let before = common::snapshot(&path);
    let again = common::encode(&cfg, &common::label_maps(2, 96, 72), "ref");
    let err = map.add(&again).unwrap_err();
    assert!(matches!(err, Error::DuplicateImageId { ref id, .. } if id == "ref0"), "{err}");
    assert_eq!(common::snapshot(&path), before, "a refused add changed the map");
}

#[test]
fn bad_values_are_refused_naming_the_image_before_anything_is_written() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let good = common::encode(&cfg, &common::label_maps(4, 64, 48), "g");
    type Spoil = fn(&mut DescriptorSet);
    let spoils: [(&str, Spoil); 5] = [
        ("NaN global value", |s| s.globals[s.global_len * 2 + 5] = f32::NAN),
        ("infinite tree area", |s| s.tree_areas[s.forest_offsets[2] as usize] = f32::INFINITY),
        ("global value above 1", |s| s.globals[s.global_len * 2] = 1.5),
        ("class outside the table", |s| s.tree_classes[s.forest_offsets[2] as usize] = 200),
        ("neighbour outside the forest", |s| s.tree_neighbours[s.forest_offsets[2] as usize * s.neighbour_slots] = 999),
    ];
    let path = dir.path().join("m");
    let mut map = Map::create(&path, &cfg.encoding(), &good.slice(0, 2), None).unwrap();
    let before = common::snapshot(&path);
    for (what, spoil) in spoils {
        let mut bad = good.clone();
        spoil(&mut bad);
        // a new map: nothing created
        let fresh = dir.path().join("fresh");
        let err = Map::create(&fresh, &cfg.encoding(), &bad, None).unwrap_err();
        assert!(matches!(&err, Error::InvalidImage { id, .. } if id == "g2"), "{what}: {err}");
        assert!(!fresh.exists(), "{what}: a refused map was created");
        // an existing map: nothing changed
        let err = map.add(&bad.slice(2, 4)).unwrap_err();
        assert!(matches!(&err, Error::InvalidImage { id, .. } if id == "g2"), "{what}: {err}");
        assert_eq!(common::snapshot(&path), before, "{what}: a refused add changed the map");
    }
    // the streaming writer refuses the image and keeps the others
    let mut w = MapWriter::append(&path, StoreOptions::default()).unwrap();
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let maps = common::label_maps(2, 64, 48);
    let mut img = enc.encode_labels("nan", &maps[0], &mut Default::default()).unwrap().0;
    img.global[0] = f32::NAN;
    assert!(matches!(w.push(&img), Err(Error::InvalidImage { id, .. }) if id == "nan"));
    let ok = enc.encode_labels("fine", &maps[1], &mut Default::default()).unwrap().0;
    w.push(&ok).unwrap();
    let map = w.finish().unwrap();
    assert_eq!((map.len(), map.id(2)), (3, "fine"));
}

fn expect_corrupt_at_open(path: &Path, what: &str) {
    match Map::open(path) {
        Err(Error::CorruptMap { reason, .. }) => eprintln!("{what}: refused ({reason})"),
        Err(other) => panic!("{what}: expected CorruptMap, got {other}"),
        Ok(_) => panic!("{what}: a damaged map was accepted"),
    }
}

#[test]
fn damaged_maps_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, map) = built(&path);
    let seg = path.join(&map.manifest.segments[0].file);
    drop(map);
    let manifest = path.join("manifest.json");
    let good_seg = std::fs::read(&seg).unwrap();
    let good_manifest = std::fs::read_to_string(&manifest).unwrap();
    let restore = || {
        std::fs::write(&seg, &good_seg).unwrap();
        std::fs::write(&manifest, &good_manifest).unwrap();
    };

    std::fs::write(&seg, &good_seg[..good_seg.len() - 100]).unwrap();
    expect_corrupt_at_open(&path, "truncated segment");
    restore();

    // a flipped data byte: opening stays cheap (no hashing); the first use finds it and names the file
    let mut flipped = good_seg.clone();
    let k = flipped.len() / 2;
    flipped[k] ^= 0x40;
    std::fs::write(&seg, &flipped).unwrap();
    let m = Map::open(&path).unwrap();
    let queries = common::encode(&cfg, &common::label_maps(2, 96, 72), "q");
    match match_with(&mut CpuStages, &m, &queries, Setting::Semlook, &cfg) {
        Err(Error::CorruptMap { path: p, .. }) => assert_eq!(p, seg),
        other => panic!("matching a damaged map: {:?}", other.map(|_| ())),
    }
    assert!(matches!(m.to_descriptor_set(), Err(Error::CorruptMap { .. })));
    drop(m);
    restore();

    std::fs::write(&manifest, &good_manifest[..good_manifest.len() / 2]).unwrap();
    expect_corrupt_at_open(&path, "truncated manifest");
    restore();

    std::fs::write(&manifest, good_manifest.replace("semlook-map", "something-else")).unwrap();
    expect_corrupt_at_open(&path, "foreign manifest");
    restore();

    std::fs::write(&manifest, good_manifest.replace("segment-", "../segment-")).unwrap();
    expect_corrupt_at_open(&path, "segment outside the map folder");
    restore();

    std::fs::remove_file(&seg).unwrap();
    assert!(matches!(Map::open(&path), Err(Error::Io { .. })), "missing segment");
    restore();
    Map::open(&path).unwrap().check_all().unwrap();
}

#[test]
fn a_flipped_byte_anywhere_in_a_segment_is_named_by_verify() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (_, _, map) = segmented(&path, 9, 3, ValueType::F32);
    let files: Vec<String> = map.manifest.segments.iter().map(|s| s.file.clone()).collect();
    drop(map);
    assert_eq!(files.len(), 3);
    let mut rng = semlook::util::SplitMix64::new(11);
    for f in &files {
        let p = path.join(f);
        let good = std::fs::read(&p).unwrap();
        // the length field, the header, the data, the last byte, and random places
        let mut at = vec![0, 3, 8, 40, good.len() / 2, good.len() - 1];
        at.extend((0..30).map(|_| rng.below(good.len())));
        for k in at {
            let mut bad = good.clone();
            bad[k] ^= 1 << rng.below(8);
            std::fs::write(&p, &bad).unwrap();
            let report = edit::verify(&path).unwrap();
            let damaged: Vec<&str> = report.damaged().map(|d| d.file.as_str()).collect();
            assert_eq!(damaged, vec![f.as_str()], "byte {k} of {f}");
        }
        std::fs::write(&p, &good).unwrap();
    }
    assert_eq!(edit::verify(&path).unwrap().damaged().count(), 0);
}

/// A stream that commits to a large map every few frames moves to each new generation: the
/// reopened map takes over the checks of the segment files it shares with the generation before
/// (they never change once in place) and checks only what the commit added; `prepare` runs the
/// checks before a stream's first frame (at 100,000 places they took 6 s of the first frame)
/// and fails naming a damaged file.
#[test]
fn a_reopened_map_checks_only_what_the_commit_added_and_prepare_names_damage() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, _, mut map) = segmented(&path, 6, 3, ValueType::F32);
    assert_eq!((map.manifest.segments.len(), map.unchecked()), (2, 2));
    map.prepare(true).unwrap();
    assert_eq!(map.unchecked(), 0);
    // this map's own add
    map.add(&common::encode(&cfg, &common::label_maps(2, 80, 60), "mine")).unwrap();
    assert_eq!((map.manifest.segments.len(), map.unchecked()), (3, 1), "an add checks again what the map had checked");
    map.prepare(true).unwrap();
    // another writer's add
    Map::open(&path).unwrap().add(&common::encode(&cfg, &common::label_maps(2, 80, 60), "theirs")).unwrap();
    let next = map.reopen().unwrap();
    assert_eq!(next.manifest.segments.len(), 4);
    assert_eq!(next.unchecked(), 1, "the reopened map checks again what the generation before checked");
    // a fresh open checks everything again
    assert_eq!(Map::open(&path).unwrap().unchecked(), 4);
    // the added segment damaged before its check: prepare names it
    let added = path.join(&next.manifest.segments[3].file);
    common::damage(&added, 1, 1);
    let reopened = next.reopen().unwrap();
    let e = reopened.prepare(true).unwrap_err();
    assert!(matches!(&e, Error::CorruptMap { path, .. } if path == &added), "{e:?}");
    assert_eq!(reopened.unchecked(), 0);
    // a generation of another map in the same folder (a rebuild: another uid) takes nothing over
    let again = Map::open(&path).unwrap();
    again.inherit_checks(&reopened);
    assert_eq!(again.unchecked(), 0);
    let mut rebuilt = Map::open(&path).unwrap();
    rebuilt.manifest.uid.push_str("-rebuilt");
    let fresh = Map::open(&path).unwrap();
    fresh.inherit_checks(&reopened);
    rebuilt.inherit_checks(&reopened);
    assert_eq!((fresh.unchecked(), rebuilt.unchecked()), (0, 4), "checks taken over from another map's generation");
}

#[test]
fn misaligned_tensors_are_refused_with_a_typed_error() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (_, map) = built(&path);
    let entry = map.manifest.segments[0].clone();
    drop(map);
    // rewrite the file with a one-byte tensor first: every tensor after it starts one byte late
    let bytes = std::fs::read(path.join(&entry.file)).unwrap();
    let n = u64::from_le_bytes(bytes[..8].try_into().unwrap()) as usize;
    let mut header: serde_json::Map<String, serde_json::Value> = serde_json::from_slice(&bytes[8..8 + n]).unwrap();
    for (name, t) in header.iter_mut() {
        if name != "__metadata__" {
            for k in 0..2 {
                let v = t["data_offsets"][k].as_u64().unwrap();
                t["data_offsets"][k] = (v + 1).into();
            }
        }
    }
    header.insert("a_pad".into(), serde_json::json!({"dtype": "U8", "shape": [1], "data_offsets": [0, 1]}));
    let mut h = serde_json::to_vec(&header).unwrap();
    h.resize(h.len().next_multiple_of(8), b' ');
    let mut out = (h.len() as u64).to_le_bytes().to_vec();
    out.extend_from_slice(&h);
    out.push(0);
    out.extend_from_slice(&bytes[8 + n..]);
    std::fs::write(path.join(&entry.file), &out).unwrap();
    common::edit_sealed_manifest(&path, |m| {
        m.replace(&format!("\"bytes\": {}", entry.bytes), &format!("\"bytes\": {}", out.len()))
            .replace(&entry.sha256, &semlook::util::sha256_hex(&out))
    });
    match Map::open(&path) {
        Err(Error::CorruptMap { reason, .. }) => assert!(reason.contains("not a multiple"), "{reason}"),
        other => panic!("misaligned file: {:?}", other.map(|_| ())),
    }
}

#[test]
fn version_and_config_mismatches_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, map) = built(&path);
    let manifest = path.join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, text.replace(&format!("\"version\": {}", semlook::map::VERSION), "\"version\": 2")).unwrap();
    assert!(matches!(Map::open(&path), Err(Error::MapVersion { found: 2, .. })));
    let mut other = cfg.encoding();
    other.objects.min_area_fraction = 0.01;
    let err = map.check_compatible(&other).unwrap_err();
    assert!(err.to_string().contains("objects.min_area_fraction"), "{err}");
    let mut matching_only = cfg.clone();
    matching_only.matching.top_k = 3;
    map.check_compatible(&matching_only.encoding()).unwrap();
    // the keypoint network's checksum is any string in the file: shown by characters, not bytes
    std::fs::write(&manifest, &text).unwrap();
    common::edit_sealed_manifest(&path, |m| {
        m.replace("\"appearance_model\": null", "\"appearance_model\": \"\u{e9}t\u{e9}-\u{1f6a6}-\u{5730}\u{56fe}\"")
    });
    let err = Map::open(&path).unwrap().check_model(None).unwrap_err();
    assert!(err.to_string().contains("sha256 \u{e9}t\u{e9}-\u{1f6a6}-\u{5730}\u{56fe}"), "{err}");
}

#[test]
fn a_stale_lock_file_does_not_block_and_a_held_lock_makes_writers_wait() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, mut map) = built(&path);
    let set = common::encode(&cfg, &common::label_maps(2, 64, 48), "x");
    assert!(Map::create(&path, &cfg.encoding(), &set, None).is_err(), "created over a map");
    // a lock file left by a dead process is just a file
    std::fs::write(path.join(".lock"), "12345").unwrap();
    map.add(&set.slice(0, 1)).unwrap();
    // a live holder (another open file description: flock excludes it like another process)
    let held = semlook::map::files::WriteLock::take(&path).unwrap();
    let t = std::time::Instant::now();
    let releaser = std::thread::spawn(move || {
        std::thread::sleep(std::time::Duration::from_millis(400));
        drop(held);
    });
    map.add(&set.slice(1, 2)).unwrap();
    assert!(t.elapsed().as_millis() >= 350, "the add did not wait for the lock ({:?})", t.elapsed());
    releaser.join().unwrap();
    assert_eq!(Map::open(&path).unwrap().len(), 8);
}

#[test]
fn segmented_maps_stream_and_match_like_one_set() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, set, back) = segmented(&dir.path().join("m"), 10, 3, ValueType::F32);
    assert_eq!(back.segments().len(), 4);
    assert_eq!(back.to_descriptor_set().unwrap(), set);
    // a tile across segment boundaries equals the same rows of the whole set
    let (mut b1, mut b2) = (TileBuf::default(), TileBuf::default());
    let (g, s) = back.tile(2, 8, &mut b1);
    let (g2, s2) = set.tile(2, 8, &mut b2);
    assert!(g == g2 && s == s2);
    assert_eq!(back.id(7), "r7");
    assert_eq!(back.forest(7).classes, set.forest(7).classes);
    let queries = common::encode(&cfg, &common::label_maps(4, 80, 60), "q");
    for setting in Setting::SEMLOOK {
        assert_eq!(match_batch(&back, &queries, setting, &cfg).unwrap().0, match_batch(&set, &queries, setting, &cfg).unwrap().0, "{setting}");
    }
}

/// `set` with synthetic appearance: unit vectors of `dim` values per tree (every fifth tree
/// without) and per image.
fn with_appearance(mut set: DescriptorSet, dim: usize, seed: u64) -> DescriptorSet {
    let mut rng = semlook::util::SplitMix64::new(seed);
    let mut unit = |n: usize| -> Vec<f32> {
        let v: Vec<f32> = (0..n).map(|_| rng.range(-1.0, 1.0) as f32).collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter().map(|x| x / norm).collect()
    };
    let t = set.n_trees();
    set.appearance_dim = dim;
    set.tree_appearance = (0..t).flat_map(|_| unit(dim)).collect();
    set.tree_has_appearance = (0..t).map(|k| u8::from(k % 5 != 4)).collect();
    set.image_appearance = (0..set.len()).flat_map(|_| unit(dim)).collect();
    set
}

#[test]
fn an_f16_map_with_appearance_matches_like_its_widened_set() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let cfg = Config::without_appearance();
    // 300 values: more than one block of the f16 dot product; blocks of 100 (3 "centres")
    let mut set = with_appearance(common::encode(&cfg, &common::label_maps(8, 80, 60), "r"), 300, 1);
    let queries = with_appearance(common::encode(&cfg, &common::label_maps(8, 80, 60)[2..5], "q"), 300, 2);
    let codebook = semlook::global::vlad::Codebook { k: 3, dim: 100, centres: vec![0.0; 300] };
    set.codebook = Some(codebook.sha256().unwrap());
    let map = Map::create_with(
        &path,
        &cfg.encoding(),
        &set,
        Some((&codebook, "test-network")),
        StoreOptions { values: ValueType::F16, segment_images: 3, ..Default::default() },
    )
    .unwrap();
    let wide = map.to_descriptor_set().unwrap();
    // global descriptors in f16; appearance vectors on the grid of int8 blocks
    let mut globals = set.globals.clone();
    semlook::values::round_through_f16(&mut globals);
    assert_eq!(bits(&wide.globals), bits(&globals));
    let mut rounded = set.tree_appearance.clone();
    semlook::values::round_to_blocks(&mut rounded, 100);
    assert_eq!(bits(&wide.tree_appearance), bits(&rounded));
    assert_ne!(bits(&wide.tree_appearance), bits(&set.tree_appearance), "int8 blocks should round appearance values");
    // rounded values are stored exactly: a second map of the widened set reads back the same bits
    let again = Map::create_with(
        &dir.path().join("again"),
        &cfg.encoding(),
        &wide,
        Some((&codebook, "test-network")),
        StoreOptions { values: ValueType::F16, ..Default::default() },
    )
    .unwrap();
    assert_eq!(bits(&again.to_descriptor_set().unwrap().tree_appearance), bits(&rounded));
    // matching reads the blocks straight from the mapped files: the same scores, bit for bit, as
    // the widened f32 set
    for setting in [Setting::Local, Setting::Semlook, Setting::Appearance, Setting::Fused] {
        let (a, b) = (ranked(&map, &queries, setting, &cfg), ranked(&wide, &queries, setting, &cfg));
        assert!(a.iter().all(|l| !l.is_empty()));
        assert_eq!(a, b, "{setting}");
    }
}

#[test]
fn device_cache_keys_follow_the_map_and_its_generation() {
    use semlook::descriptors::source::SourceKey;
    let dir = tempfile::tempdir().unwrap();
    let (cfg, set, mut a) = segmented(&dir.path().join("a"), 6, 4, ValueType::F16);
    let (_, _, b) = segmented(&dir.path().join("b"), 6, 4, ValueType::F16);
    let key = SourceKey::of(&a);
    assert_eq!(key, SourceKey::of(&a), "one open map, one key (f16 tiles are assembled in buffers that move)");
    assert_eq!(key, SourceKey::of(&Map::open(&dir.path().join("a")).unwrap()), "reopened at the same generation");
    assert_ne!(key, SourceKey::of(&b), "another map with the same contents, size and generation");
    a.add(&common::encode(&cfg, &common::label_maps(1, 80, 60), "new")).unwrap();
    assert_ne!(key, SourceKey::of(&a), "after a commit");
    let after_add = SourceKey::of(&a);
    edit::remove(&dir.path().join("a"), &[set.ids[0].clone()]).unwrap();
    let removed = Map::open(&dir.path().join("a")).unwrap();
    assert_ne!(after_add, SourceKey::of(&removed), "after a removal");
}

/// Ids and scores of every query's ranked list.
fn ranked(refs: &dyn RefSource, queries: &DescriptorSet, setting: Setting, cfg: &Config) -> Vec<Vec<(String, u32)>> {
    match_batch(refs, queries, setting, cfg)
        .unwrap()
        .0
        .iter()
        .map(|m| m.ranked.iter().map(|c| (refs.id(c.reference as usize).to_string(), c.score.to_bits())).collect())
        .collect()
}

#[test]
fn removed_images_never_come_back_and_compaction_keeps_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, set, map) = segmented(&path, 14, 4, ValueType::F32);
    let queries = common::encode(&cfg, &common::label_maps(3, 80, 60), "q");
    // remove a spread of images, then every image a query's best match was
    let best: Vec<String> = ranked(&map, &queries, Setting::Global, &cfg).iter().map(|l| l[0].0.clone()).collect();
    let mut gone: Vec<String> = vec!["r1".into(), "r4".into(), "r5".into(), "r13".into()];
    gone.extend(best);
    gone.sort();
    gone.dedup();
    drop(map);
    assert!(edit::remove(&path, &["r1".into(), "nope".into()]).is_err(), "an unknown id was accepted");
    assert_eq!(Map::open(&path).unwrap().len(), 14, "a refused removal changed the map");
    assert_eq!(edit::remove(&path, &gone).unwrap(), gone.len());
    // what the map serves now equals a set without the removed images, K live results each
    let keep: Vec<usize> = (0..set.len()).filter(|&i| !gone.contains(&set.ids[i])).collect();
    let mut live = set.empty_like();
    for &i in &keep {
        live.append_range(&set, i, i + 1).unwrap();
    }
    let map = Map::open(&path).unwrap();
    assert_eq!(map.len(), keep.len());
    for setting in Setting::SEMLOOK {
        let got = ranked(&map, &queries, setting, &cfg);
        assert_eq!(got, ranked(&live, &queries, setting, &cfg), "{setting}");
        assert!(got.iter().flatten().all(|(id, _)| !gone.contains(id)), "{setting}: a removed image came back");
    }
    let expected = ranked(&map, &queries, Setting::Semlook, &cfg);
    drop(map);
    // compaction drops them from the files and changes no result
    let before: u64 = Map::open(&path).unwrap().manifest.segments.iter().map(|s| s.bytes).sum();
    std::fs::write(path.join("segment-0000000000000000.safetensors"), b"stray").unwrap();
    let r = edit::compact(&path, StoreOptions { segment_images: 4, ..Default::default() }).unwrap();
    assert_eq!((r.dropped, r.stray_files), (gone.len(), 1));
    let map = Map::open(&path).unwrap();
    assert!(map.manifest.segments.iter().all(|s| s.removed.is_empty()));
    assert!(map.manifest.segments.iter().map(|s| s.bytes).sum::<u64>() < before);
    assert_eq!(ranked(&map, &queries, Setting::Semlook, &cfg), expected);
    assert_eq!(map.to_descriptor_set().unwrap(), live);
    assert!(!path.join("segment-0000000000000000.safetensors").exists());
    let listed: std::collections::HashSet<String> = map.manifest.segments.iter().map(|s| s.file.clone()).collect();
    for e in std::fs::read_dir(&path).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        assert!(!name.starts_with("segment-") || listed.contains(&name), "{name} left behind");
    }
}

#[test]
fn readers_see_whole_generations_while_a_writer_commits() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, _) = built(&path);
    let more = common::encode(&cfg, &common::label_maps(20, 64, 48), "w");
    let p2 = path.clone();
    let writer = std::thread::spawn(move || {
        let mut w = MapWriter::append(&p2, StoreOptions { segment_images: 1, ..Default::default() }).unwrap();
        w.push_set(&more).unwrap();
        w.finish().unwrap().manifest.generation
    });
    let mut seen = std::collections::BTreeSet::new();
    while !writer.is_finished() {
        let m = Map::open(&path).unwrap();
        assert_eq!(m.len(), 6 + m.manifest.segments.len() - 1, "generation {}", m.manifest.generation);
        m.check_all().unwrap();
        seen.insert(m.manifest.generation);
    }
    assert_eq!(writer.join().unwrap(), 21);
    eprintln!("generations seen while writing: {seen:?}");
}

#[test]
fn two_writers_committing_in_turn_both_land_and_a_raced_id_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, _) = built(&path);
    let enc = semlook::encode::Encoder::new(&cfg).unwrap();
    let maps = common::label_maps(12, 64, 48);
    let img = |id: &str, k: usize| enc.encode_labels(id, &maps[k], &mut Default::default()).unwrap().0;
    let one = StoreOptions { segment_images: 1, ..Default::default() };
    // two writers that opened the same generation: each commit must re-read the manifest under
    // the lock and append to what the other committed
    let (mut w1, mut w2) = (MapWriter::append(&path, one).unwrap(), MapWriter::append(&path, one).unwrap());
    for k in 0..5 {
        w1.push(&img(&format!("a{k}"), k)).unwrap();
        w2.push(&img(&format!("b{k}"), k + 5)).unwrap();
    }
    // both buffer the same id; the second to commit learns of the first's segment and refuses
    w2.push(&img("same", 10)).unwrap();
    assert!(matches!(w1.push(&img("same", 11)), Err(Error::DuplicateImageId { id, .. }) if id == "same"));
    drop(w1);
    let map = w2.finish().unwrap();
    assert_eq!((map.len(), map.manifest.generation), (6 + 11, 1 + 11));
    let ids: Vec<String> = (0..map.len()).map(|i| map.id(i).to_string()).collect();
    let expect: Vec<String> =
        (0..6).map(|i| format!("ref{i}")).chain((0..5).flat_map(|k| [format!("a{k}"), format!("b{k}")])).chain(["same".to_string()]).collect();
    assert_eq!(ids, expect);
    map.check_all().unwrap();
}

/// An image removed and added again makes a segment of the same bytes as the one that held it
/// (files are named by their content). The new one gets a name of its own: before, the manifest
/// listed one file twice (its rows and tombstones shared), and every open then failed with
/// "segment ... is listed twice" (found by the soak test, `cli/tests/soak.rs`).
#[test]
fn an_image_removed_and_added_again_gets_a_segment_of_its_own() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(2, 64, 48), "r");
    let path = dir.path().join("m");
    Map::create_with(&path, &cfg.encoding(), &set, None, StoreOptions { segment_images: 1, ..Default::default() }).unwrap();
    assert_eq!(edit::remove(&path, &["r1".to_string()]).unwrap(), 1);
    let mut map = Map::open(&path).unwrap();
    map.add_in_segments(&set.slice(1, 2), 1).unwrap();
    let reopened = Map::open(&path).expect("the map opens after the image came back");
    let ids = reopened.to_descriptor_set().unwrap().ids;
    assert_eq!(ids, ["r0", "r1"]);
    let files: Vec<&str> = reopened.manifest.segments.iter().map(|s| s.file.as_str()).collect();
    assert_eq!(files.len(), 3, "{files:?}");
    assert!(edit::verify(&path).unwrap().damaged().next().is_none());
    // compaction drops the tombstoned copy and keeps the image once
    edit::compact(&path, StoreOptions::default()).unwrap();
    assert_eq!(Map::open(&path).unwrap().to_descriptor_set().unwrap().ids, ["r0", "r1"]);
}

/// Poses stored with places: round trip (with and without orientation, and images without one),
/// segments without poses beside segments with them, removal and compaction keeping them, a bad
/// pose refused before writing, and a stored pose row broken under a valid checksum named by verify.
#[test]
fn poses_are_stored_with_their_places_and_bad_ones_are_refused() {
    use semlook::descriptors::PlacePose;
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let mut set = common::encode(&cfg, &common::label_maps(9, 64, 48), "p");
    let h = std::f64::consts::FRAC_1_SQRT_2;
    let pose = |i: usize| match i % 3 {
        0 => Some(PlacePose { position: [i as f64, -2.0, 0.5], orientation: Some([0.0, h, 0.0, h]) }),
        1 => Some(PlacePose { position: [500_000.25 + i as f64, 6_000_000.5, 0.0], orientation: None }),
        _ => None,
    };
    // images 0..3 without poses: their segment stores none, as maps from before poses
    for i in 3..9 {
        set.poses[i] = pose(i);
    }
    let path = dir.path().join("m");
    let map = Map::create_with(&path, &cfg.encoding(), &set, None, StoreOptions { segment_images: 3, ..Default::default() }).unwrap();
    assert!(!map.segments()[0].has_poses() && map.segments()[1].has_poses());
    for i in 0..9 {
        assert_eq!(map.pose(i), if i < 3 { None } else { pose(i) }, "image {i}");
    }
    assert_eq!(map.pose_counts(), (4, 2));
    assert_eq!(map.to_descriptor_set().unwrap().poses, set.poses);
    drop(map);
    // removal and compaction keep every other image's pose
    edit::remove(&path, &["p3".into(), "p7".into()]).unwrap();
    edit::compact(&path, StoreOptions { segment_images: 4, ..Default::default() }).unwrap();
    let map = Map::open(&path).unwrap();
    let kept: Vec<Option<PlacePose>> = (0..9).filter(|i| ![3, 7].contains(i)).map(|i| set.poses[i]).collect();
    assert_eq!((0..map.len()).map(|i| map.pose(i)).collect::<Vec<_>>(), kept);
    let before = common::snapshot(&path);
    drop(map);
    // a pose that is not one is refused, naming the image, and nothing is written
    let mut map = Map::open(&path).unwrap();
    for bad in [
        PlacePose { position: [f64::NAN, 0.0, 0.0], orientation: None },
        PlacePose { position: [0.0; 3], orientation: Some([0.0, 0.0, 0.0, 2.0]) },
        PlacePose { position: [0.0; 3], orientation: Some([0.0, f64::NAN, 0.0, 1.0]) },
    ] {
        let mut more = common::encode(&cfg, &common::label_maps(2, 64, 48), "n");
        more.poses[1] = Some(bad);
        let err = map.add(&more).unwrap_err();
        assert!(matches!(&err, Error::InvalidImage { id, .. } if id == "n1"), "{bad:?}: {err}");
        assert_eq!(common::snapshot(&path), before, "{bad:?}: a refused add changed the map");
        // the streaming writer (`map build`/`add`) refuses it too
        let mut w = MapWriter::append(&path, StoreOptions::default()).unwrap();
        let enc = semlook::encode::Encoder::new(&cfg).unwrap();
        let mut img = enc.encode_labels("w", &common::label_maps(1, 64, 48)[0], &mut Default::default()).unwrap().0;
        img.pose = Some(bad);
        assert!(matches!(w.push(&img), Err(Error::InvalidImage { id, .. }) if id == "w"), "{bad:?}");
        assert_eq!(w.finish().unwrap().len(), 7, "{bad:?}: the refused image was stored");
    }
    drop(map);
    // a pose row broken under a valid checksum (a writer bug, a hand edit that rehashed)
    let (s, j, id) = {
        let map = Map::open(&path).unwrap();
        let (s, seg) = map.segments().iter().enumerate().find(|(_, g)| g.has_poses()).unwrap();
        let j = (0..seg.len()).find(|&j| seg.pose(j).is_some_and(|p| p.orientation.is_some())).unwrap();
        (s, j, seg.id(j).to_string())
    };
    let mut m: semlook::map::Manifest = serde_json::from_slice(&std::fs::read(path.join("manifest.json")).unwrap()).unwrap();
    let entry = &mut m.segments[s];
    let file = path.join(&entry.file);
    let mut bytes = std::fs::read(&file).unwrap();
    let (header, meta) = safetensors::SafeTensors::read_metadata(&bytes).unwrap();
    let (a, _) = meta.info("place_pose").unwrap().data_offsets;
    // row j's qw becomes 3
    let at = 8 + header + a + (7 * j + 6) * 8;
    bytes[at..at + 8].copy_from_slice(&3.0f64.to_le_bytes());
    std::fs::write(&file, &bytes).unwrap();
    (entry.bytes, entry.sha256) = (bytes.len() as u64, semlook::util::sha256_hex(&bytes));
    std::fs::write(path.join("manifest.json"), m.to_json().unwrap()).unwrap();
    let map = Map::open(&path).unwrap();
    let report = map.verify_all();
    let err = report.iter().find_map(|(_, r)| r.as_ref().err()).expect("verify names the broken pose").to_string();
    assert!(err.contains(&format!("{id:?}")) && err.contains("unit quaternion"), "{err}");
    let i = (0..map.len()).find(|&i| map.locate(i) == (s, j)).unwrap();
    assert_eq!(map.pose(i), None, "a segment that failed its checks serves no pose");
}
