//! The map store: bit-exact round trips, appends, and refusal of every kind of damaged map.

mod common;

use semlook::config::Config;
use semlook::error::Error;
use semlook::map::Map;

fn built(dir: &std::path::Path) -> (Config, Map) {
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(6, 96, 72), "ref");
    (cfg.clone(), Map::create(dir, &cfg.encoding(), &set, None).unwrap())
}

#[test]
fn round_trip_is_bit_exact() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (_, map) = built(&path);
    let back = Map::open(&path).unwrap();
    assert_eq!(back.manifest, map.manifest);
    let (a, b) = (&map.to_descriptor_set(), &back.to_descriptor_set());
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(&a.globals), bits(&b.globals));
    assert_eq!(bits(&a.global_stats), bits(&b.global_stats));
    assert_eq!(bits(&a.tree_areas), bits(&b.tree_areas));
    assert_eq!(bits(&a.tree_centroids), bits(&b.tree_centroids));
    assert_eq!(a, b);
    assert!(a.n_trees() > 6, "label maps should give several objects each");
}

#[test]
fn add_appends_a_segment_and_keeps_the_rest() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, mut map) = built(&path);
    let seg0 = std::fs::read(path.join("segment-000000.safetensors")).unwrap();
    let more = common::encode(&cfg, &common::label_maps(3, 80, 60), "new");
    map.add(&more).unwrap();
    assert_eq!(std::fs::read(path.join("segment-000000.safetensors")).unwrap(), seg0, "stored segment rewritten");
    let back = Map::open(&path).unwrap();
    assert_eq!(back.len(), 9);
    assert_eq!(back.to_descriptor_set(), map.to_descriptor_set());
    assert_eq!(back.to_descriptor_set().ids[6], "new0");
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

fn expect_corrupt(path: &std::path::Path, what: &str) {
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
    built(&path);
    let seg = path.join("segment-000000.safetensors");
    let manifest = path.join("manifest.json");
    let good_seg = std::fs::read(&seg).unwrap();
    let good_manifest = std::fs::read_to_string(&manifest).unwrap();
    let restore = || {
        std::fs::write(&seg, &good_seg).unwrap();
        std::fs::write(&manifest, &good_manifest).unwrap();
    };

    std::fs::write(&seg, &good_seg[..good_seg.len() - 100]).unwrap();
    expect_corrupt(&path, "truncated segment");
    restore();

    let mut flipped = good_seg.clone();
    let k = flipped.len() / 2;
    flipped[k] ^= 0x40;
    std::fs::write(&seg, &flipped).unwrap();
    expect_corrupt(&path, "flipped byte");
    restore();

    std::fs::write(&manifest, &good_manifest[..good_manifest.len() / 2]).unwrap();
    expect_corrupt(&path, "truncated manifest");
    restore();

    std::fs::write(&manifest, good_manifest.replace("semlook-map", "something-else")).unwrap();
    expect_corrupt(&path, "foreign manifest");
    restore();

    // a segment whose checksum matches but whose contents break the invariants
    let mut set = Map::open(&path).unwrap().to_descriptor_set();
    set.tree_neighbours[0] = 9999;
    let cfg = Config::without_appearance();
    let other = dir.path().join("other");
    Map::create(&other, &cfg.encoding(), &set, None).unwrap();
    expect_corrupt(&other, "neighbour index out of range");
    let mut set = Map::open(&path).unwrap().to_descriptor_set();
    set.globals[5] = f32::NAN;
    let nan = dir.path().join("nan");
    Map::create(&nan, &cfg.encoding(), &set, None).unwrap();
    expect_corrupt(&nan, "NaN descriptor");

    std::fs::remove_file(&seg).unwrap();
    assert!(matches!(Map::open(&path), Err(Error::Io { .. })), "missing segment");
    restore();
    assert!(Map::open(&path).is_ok(), "restored map opens again");
}

#[test]
fn version_and_config_mismatches_are_named() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, map) = built(&path);
    let manifest = path.join("manifest.json");
    let text = std::fs::read_to_string(&manifest).unwrap();
    std::fs::write(&manifest, text.replace(&format!("\"version\": {}", semlook::map::VERSION), "\"version\": 99")).unwrap();
    assert!(matches!(Map::open(&path), Err(Error::MapVersion { found: 99, .. })));
    let mut other = cfg.encoding();
    other.objects.min_area_fraction = 0.01;
    let err = map.check_compatible(&other).unwrap_err();
    assert!(err.to_string().contains("objects.min_area_fraction"), "{err}");
    let mut matching_only = cfg.clone();
    matching_only.matching.top_k = 3;
    map.check_compatible(&matching_only.encoding()).unwrap();
}

#[test]
fn create_refuses_a_non_empty_directory_and_a_held_lock() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("m");
    let (cfg, mut map) = built(&path);
    let set = common::encode(&cfg, &common::label_maps(1, 64, 48), "x");
    assert!(Map::create(&path, &cfg.encoding(), &set, None).is_err());
    std::fs::write(path.join(".lock"), "1").unwrap();
    let err = map.add(&set).unwrap_err();
    assert!(err.to_string().contains(".lock"), "{err}");
}

#[test]
fn segmented_maps_stream_and_match_like_one_set() {
    use semlook::matching::source::{GlobalSource, RefSource, TileBuf};
    use semlook::matching::{match_batch, Setting};
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(10, 80, 60), "r");
    let mut map = Map::new(&dir.path().join("m"), &cfg.encoding(), 0, 0);
    std::fs::create_dir_all(dir.path().join("m")).unwrap();
    map.add_in_segments(&set, 3).unwrap();
    assert_eq!(map.manifest.segments.len(), 4);
    let back = Map::open(&dir.path().join("m")).unwrap();
    assert_eq!(back.segments().len(), 4);
    assert_eq!(back.to_descriptor_set(), set);
    // a tile across segment boundaries equals the same rows of the whole set
    let (mut b1, mut b2) = (TileBuf::default(), TileBuf::default());
    let (g, s) = back.tile(2, 8, &mut b1);
    let (g2, s2) = set.tile(2, 8, &mut b2);
    assert!(g == g2 && s == s2);
    assert_eq!(back.id(7), "r7");
    assert_eq!(back.forest(7).classes, set.forest(7).classes);
    let queries = common::encode(&cfg, &common::label_maps(4, 80, 60), "q");
    for setting in Setting::SEMLOOK {
        assert_eq!(match_batch(&back, &queries, setting, &cfg).0, match_batch(&set, &queries, setting, &cfg).0, "{setting}");
    }
}
