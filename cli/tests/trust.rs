//! A map that cannot be silently altered, and inputs that cannot poison it (issue 20): each test
//! names the wrong result it guards against.

mod common;

use semlook::config::Config;
use semlook::global::vlad::Codebook;
use semlook::map::{edit, Map};
use std::path::Path;

/// A small map of label maps with one image removed.
fn map_with_a_removal(dir: &Path) -> (Config, std::path::PathBuf) {
    let cfg = Config::without_appearance();
    let set = common::encode(&cfg, &common::label_maps(4, 64, 48), "r");
    let path = dir.join("m");
    Map::create(&path, &cfg.encoding(), &set, None).unwrap();
    assert_eq!(edit::remove(&path, &["r1".to_string()]).unwrap(), 1);
    (cfg, path)
}

/// Edits of manifest.json that keep it valid JSON and valid values (a removed row brought back, a
/// config value changed, a model hash flipped) are refused at open and by verify, naming the
/// manifest; before, each was served (a removed image back, scores moved by up to 0.84).
#[test]
fn an_edited_manifest_is_refused_not_served() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = map_with_a_removal(dir.path());
    let manifest = path.join("manifest.json");
    let original = std::fs::read_to_string(&manifest).unwrap();
    assert_eq!(Map::open(&path).unwrap().len(), 3);
    let edits: [(&str, &str, &str); 3] = [
        ("a removed row", "\"removed\": [\n        1\n      ]", "\"removed\": [\n        0\n      ]"),
        ("ssim_k1", "\"ssim_k1\": 0.01", "\"ssim_k1\": 0.21"),
        ("brighten_dark", "\"brighten_dark\": 0.35", "\"brighten_dark\": 0.95"),
    ];
    for (what, from, to) in edits {
        assert!(original.contains(from), "{what}: {from:?} not in\n{original}");
        std::fs::write(&manifest, original.replacen(from, to, 1)).unwrap();
        let err = Map::open(&path).unwrap_err().to_string();
        assert!(err.contains("manifest.json") && err.contains("checksum"), "{what}: {err}");
        assert!(edit::verify(&path).is_err(), "{what}: verify passed an edited manifest");
    }
    std::fs::write(&manifest, &original).unwrap();
    assert_eq!(Map::open(&path).unwrap().len(), 3, "the original manifest opens again");
}

/// Rewrites the map's manifest with `edit` applied and a checksum that matches (a deliberate
/// edit, not a damaged byte).
fn reseal(path: &Path, edit: impl FnOnce(&mut semlook::map::Manifest)) {
    common::edit_sealed_manifest(path, |text| {
        let mut m: semlook::map::Manifest = serde_json::from_str(text).unwrap();
        edit(&mut m);
        serde_json::to_string(&m).unwrap()
    });
}

/// A resealed manifest (checksum recomputed) with a config value out of range is refused by open
/// and by verify alike, naming the manifest and the field; before, verify passed what the query
/// then refused.
#[test]
fn verify_refuses_a_resealed_manifest_with_values_a_query_refuses() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = map_with_a_removal(dir.path());
    reseal(&path, |m| m.config.global.ssim_window = 0);
    let open = Map::open(&path).unwrap_err().to_string();
    let verify = edit::verify(&path).unwrap_err().to_string();
    for msg in [&open, &verify] {
        assert!(msg.contains("manifest.json") && msg.contains("ssim_window"), "{msg}");
    }
}

/// `map verify` checks the keypoint network as a query does: the installed one must be the one
/// the map was built with. A map resealed to another network's SHA-256 fails verify naming the
/// manifest and both hashes in full (the query's message used to show two equal 12-character
/// prefixes); the matching network passes and is named.
#[test]
fn verify_checks_the_installed_keypoint_network() {
    let dir = tempfile::tempdir().unwrap();
    let (_, path) = map_with_a_removal(dir.path());
    let models = dir.path().join("models");
    std::fs::create_dir(&models).unwrap();
    std::fs::write(models.join(semlook::networks::xfeat::XFEAT_WEIGHTS), b"installed weights").unwrap();
    let installed = semlook::util::sha256_hex(b"installed weights");
    let other = format!("{}0", &installed[..63]);
    let run = |sha: &str| {
        reseal(&path, |m| {
            m.config.appearance.model = semlook::config::AppearanceModelKind::Xfeat;
            m.appearance_model = Some(sha.to_string());
        });
        std::process::Command::new(env!("CARGO_BIN_EXE_semlook"))
            .args(["map", "verify", "--map", common::p(&path)])
            .env("SEMLOOK_MODELS", &models)
            .output()
            .unwrap()
    };
    let bad = run(&other);
    let text = String::from_utf8_lossy(&bad.stdout).to_string() + &String::from_utf8_lossy(&bad.stderr);
    assert!(!bad.status.success() && text.contains("manifest.json") && text.contains(&other) && text.contains(&installed), "{text}");
    let good = run(&installed);
    let text = String::from_utf8_lossy(&good.stdout).to_string();
    assert!(
        good.status.success() && text.contains("ok       keypoint network") && text.contains(&installed),
        "{text}\n{}",
        String::from_utf8_lossy(&good.stderr)
    );
}

/// `set` with unit appearance vectors of 2 x 3 values (codebook of 2 centres of 3 values) tagged
/// with `codebook`'s SHA-256.
fn with_appearance(mut set: semlook::descriptors::DescriptorSet, codebook: &Codebook) -> semlook::descriptors::DescriptorSet {
    let unit = |n: usize| (0..n).flat_map(|i| (0..6).map(move |j| f32::from(u8::from(j == i % 6)))).collect::<Vec<f32>>();
    set.appearance_dim = 6;
    set.tree_appearance = unit(set.n_trees());
    set.tree_has_appearance = vec![1; set.n_trees()];
    set.image_appearance = unit(set.len());
    set.codebook = Some(codebook.sha256().unwrap());
    set
}

fn codebook(shift: f32) -> Codebook {
    Codebook { k: 2, dim: 3, centres: vec![0.5 + shift, -1.0, 2.0, 0.25, 0.0, -3.5] }
}

/// Descriptors aggregated with another map's codebook are refused by `Map::add` with a typed error
/// naming both codebooks, and the map is left as it was; before, they were stored and no longer
/// found their own originals.
#[test]
fn descriptors_of_another_codebook_do_not_enter_a_map() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let (ours, theirs) = (codebook(0.0), codebook(0.125));
    let set = with_appearance(common::encode(&cfg, &common::label_maps(4, 64, 48), "r"), &ours);
    let path = dir.path().join("m");
    let mut map = Map::create(&path, &cfg.encoding(), &set, Some((&ours, "net"))).unwrap();
    let before = common::snapshot(&path);
    let foreign = with_appearance(common::encode(&cfg, &common::label_maps(2, 64, 48), "x"), &theirs);
    match map.add(&foreign) {
        Err(semlook::Error::IncompatibleConfig { map_value, given_value, .. }) => {
            assert!(map_value.contains(&ours.sha256().unwrap()) && given_value.contains(&theirs.sha256().unwrap()), "{map_value} / {given_value}");
        }
        other => panic!("another codebook's descriptors: {other:?}"),
    }
    let untagged = semlook::descriptors::DescriptorSet { codebook: None, ..foreign.clone() };
    assert!(map.add(&untagged).is_err(), "descriptors naming no codebook entered a map with one");
    assert_eq!(common::snapshot(&path), before, "a refused add changed the map");
    // the same codebook is accepted
    let own = with_appearance(common::encode(&cfg, &common::label_maps(2, 64, 48), "y"), &ours);
    map.add(&own).unwrap();
    assert_eq!(map.len(), 6);
}

/// Appearance vectors longer than the encoder's unit vectors (a value of 100, or 3e38) are refused
/// at write, naming the image; before, the poisoned image became top-1 for 29 of 30 queries.
#[test]
fn a_poisoned_appearance_vector_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cfg = Config::without_appearance();
    let cb = codebook(0.0);
    let set = with_appearance(common::encode(&cfg, &common::label_maps(4, 64, 48), "r"), &cb);
    let mut map = Map::create(&dir.path().join("m"), &cfg.encoding(), &set, Some((&cb, "net"))).unwrap();
    for (column, value) in [("tree", 100.0f32), ("tree", 3e38), ("image", 1.5)] {
        let mut bad = with_appearance(common::encode(&cfg, &common::label_maps(2, 64, 48), "p"), &cb);
        if column == "tree" {
            bad.tree_appearance[0] = value
        } else {
            bad.image_appearance[1] = value
        }
        match map.add(&bad) {
            Err(semlook::Error::InvalidImage { id, reason }) => assert!(id == "p0" && reason.contains("appearance"), "{id}: {reason}"),
            other => panic!("{column} appearance {value}: {other:?}"),
        }
        assert_eq!(Map::open(&dir.path().join("m")).unwrap().len(), 4);
    }
}

/// Temporary files a killed or out-of-space writer left (`.segment-*.tmp`, `.manifest.json.tmp`)
/// and the staging folder of a killed `build --force` are reported by verify and removed by the
/// next writer under the lock; a staging folder of a live process is left alone. Before, they
/// survived every add and resume, and verify did not mention them.
#[test]
fn leftovers_of_interrupted_writers_are_reported_and_removed() {
    let dir = tempfile::tempdir().unwrap();
    let (cfg, path) = map_with_a_removal(dir.path());
    let tmp_files = [".segment-7.safetensors.tmp", ".manifest.json.tmp"];
    for f in tmp_files {
        std::fs::write(path.join(f), vec![0u8; 4096]).unwrap();
    }
    // pids above the kernel's limit (4194304) never run; our own pid does
    let dead = dir.path().join(".m.building-4194999-1a2b-0");
    let live = dir.path().join(format!(".m.building-{}-1a2b-0", std::process::id()));
    for d in [&dead, &live] {
        std::fs::create_dir(d).unwrap();
        std::fs::write(d.join("segment-0.safetensors"), b"partial").unwrap();
    }
    let report = edit::verify(&path).unwrap();
    let mut expected: Vec<String> = tmp_files.iter().map(|f| path.join(f).display().to_string()).collect();
    expected.push(dead.display().to_string());
    expected.sort();
    let mut listed = report.leftovers.clone();
    listed.sort();
    assert_eq!(listed, expected);
    assert_eq!(report.damaged().count(), 0, "leftovers are not damage");
    // the next writer removes them
    let mut map = Map::open(&path).unwrap();
    map.add(&common::encode(&cfg, &common::label_maps(1, 64, 48), "n")).unwrap();
    assert!(tmp_files.iter().all(|f| !path.join(f).exists()) && !dead.exists(), "leftovers survived a writer");
    assert!(live.exists(), "a running build's staging folder was removed");
    assert!(edit::verify(&path).unwrap().leftovers.is_empty());
    assert_eq!(Map::open(&path).unwrap().len(), 4);
}
