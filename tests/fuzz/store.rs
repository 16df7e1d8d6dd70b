//! Targets for the map store: the manifest (its bytes, and its values with the structure kept),
//! segment files (mutated under the manifest's SHA-256, which refuses them, and rehashed into the
//! manifest, so that they reach the header and value checks behind the hash) and the codebook
//! (rehashed). Every input goes into a folder holding the files of two small maps (f32 without
//! appearance, with a removed image; f16 with appearance, a codebook and HOG), which is then
//! opened, checked in full as `map verify` does, read back, queried in every setting, and opened
//! for appending.

use crate::mutate::{json_mutate, random_seeds, Entropy};
use crate::{Target, Verdict};
use semlook::config::Config;
use semlook::descriptors::source::RefSource;
use semlook::descriptors::DescriptorSet;
use semlook::global::vlad::Codebook;
use semlook::map::{edit, Manifest, Map, MapWriter, StoreOptions};
use semlook::matching::{match_with, CpuStages, Setting};
use semlook::values::ValueType;
use semlook::Error;
use semlook_kernels::ssim::{ssim_stats, SsimScratch};
use std::path::{Path, PathBuf};

const MANIFEST: &str = "manifest.json";
const CODEBOOK: &str = "codebook.safetensors";

/// The fixture maps' config: small global descriptors, so that a segment's header is a good part
/// of its bytes.
fn config() -> Config {
    let mut cfg = Config::without_appearance();
    (cfg.global.width, cfg.global.height, cfg.global.ssim_window) = (16, 12, 5);
    cfg
}

/// `set` with appearance (unit vectors of 8 values, every third tree without) and 6 HOG values.
fn with_extras(mut set: DescriptorSet) -> DescriptorSet {
    let mut rng = semlook::util::SplitMix64::new(5);
    let mut unit = |n: usize| -> Vec<f32> {
        let v: Vec<f32> = (0..n).map(|_| rng.range(0.1, 1.0) as f32).collect();
        let norm = v.iter().map(|x| x * x).sum::<f32>().sqrt();
        v.iter().map(|x| x / norm).collect()
    };
    let (t, n) = (set.n_trees(), set.len());
    set.appearance_dim = 8;
    set.tree_appearance = (0..t).flat_map(|_| unit(8)).collect();
    set.tree_has_appearance = (0..t).map(|k| u8::from(k % 3 != 2)).collect();
    set.image_appearance = (0..n).flat_map(|_| unit(8)).collect();
    set.hog_dim = 6;
    set.image_hog = (0..n).flat_map(|_| unit(6)).collect();
    set
}

/// A work folder, the good files of both fixture maps (segment names are content hashes, so they
/// do not collide; only the f16 map has a codebook) and each map's manifest.
pub struct Store {
    _tmp: tempfile::TempDir,
    work: PathBuf,
    files: Vec<(String, Vec<u8>)>,
    manifests: Vec<Vec<u8>>,
    /// Every segment file: (its map, its name).
    segments: Vec<(usize, String)>,
}

impl Store {
    fn new() -> Store {
        let tmp = tempfile::tempdir().expect("temp dir");
        let cfg = config();
        let maps = crate::common::label_maps(5, 64, 48);
        let plain = crate::common::encode(&cfg, &maps, "a");
        let mut rich = with_extras(crate::common::encode(&cfg, &maps[..4], "b"));
        let codebook = Codebook { k: 2, dim: 4, centres: (0..8).map(|i| i as f32 / 8.0).collect() };
        rich.codebook = Some(codebook.sha256().expect("fixture codebook"));
        let (a, b) = (tmp.path().join("a"), tmp.path().join("b"));
        Map::create_with(&a, &cfg.encoding(), &plain, None, StoreOptions { segment_images: 2, ..Default::default() }).expect("fixture map");
        edit::remove(&a, &["a1".to_string()]).expect("fixture removal");
        let opts = StoreOptions { values: ValueType::F16, segment_images: 3, ..Default::default() };
        Map::create_with(&b, &cfg.encoding(), &rich, Some((&codebook, "fuzz-network")), opts).expect("fixture map");
        let (mut files, mut manifests, mut segments) = (Vec::new(), Vec::new(), Vec::new());
        for (m, dir) in [a, b].iter().enumerate() {
            let manifest = std::fs::read(dir.join(MANIFEST)).expect("fixture manifest");
            let parsed: Manifest = serde_json::from_slice(&manifest).expect("fixture manifest");
            segments.extend(parsed.segments.iter().map(|s| (m, s.file.clone())));
            for name in parsed.segments.iter().map(|s| s.file.clone()).chain(parsed.codebook.map(|c| c.file)) {
                let bytes = std::fs::read(dir.join(&name)).expect("fixture file");
                files.push((name, bytes));
            }
            manifests.push(manifest);
        }
        let work = tmp.path().join("work");
        std::fs::create_dir_all(&work).expect("work folder");
        Store { _tmp: tmp, work, files, manifests, segments }
    }

    /// Deletes what an earlier input left (compacted segments), then gives every good file, the
    /// manifest and `replaced` (a file's name and new content) their contents; files that hold
    /// them already are left alone (rewriting a file costs a flush on some file systems).
    fn restore(&self, manifest: &[u8], replaced: Option<(&str, &[u8])>) -> Result<(), Verdict> {
        let fail = |what: &str, e: std::io::Error| Verdict::Violation(format!("fixture {what}: {e}"));
        for entry in std::fs::read_dir(&self.work).map_err(|e| fail("folder", e))?.flatten() {
            let name = entry.file_name();
            if name != MANIFEST && !self.files.iter().any(|f| *f.0 == *name) {
                std::fs::remove_file(entry.path()).map_err(|e| fail("clean-up", e))?;
            }
        }
        let good = self.files.iter().map(|(n, b)| (n.as_str(), b.as_slice())).filter(|f| replaced.is_none_or(|r| r.0 != f.0));
        for (name, bytes) in good.chain([(MANIFEST, manifest)]).chain(replaced) {
            let path = self.work.join(name);
            if std::fs::read(&path).ok().as_deref() != Some(bytes) {
                std::fs::write(&path, bytes).map_err(|e| fail(name, e))?;
            }
        }
        Ok(())
    }

    /// Manifest `m` with the size and SHA-256 of file `name` (a segment, or the codebook) set to
    /// those of `bytes`.
    fn rehashed(&self, m: usize, name: &str, bytes: &[u8]) -> Vec<u8> {
        let mut parsed: Manifest = serde_json::from_slice(&self.manifests[m]).expect("fixture manifest");
        let (len, sha) = (bytes.len() as u64, semlook::util::sha256_hex(bytes));
        for s in parsed.segments.iter_mut().filter(|s| s.file == name) {
            (s.bytes, s.sha256) = (len, sha.clone());
        }
        if let Some(c) = parsed.codebook.as_mut().filter(|c| c.file == name) {
            (c.bytes, c.sha256) = (len, sha);
        }
        parsed.to_json().expect("a manifest serialises")
    }
}

/// Whether `e` is a typed map error naming `dir` or a file in it: the manifest, or a file it lists.
fn names_map_file(e: &Error, dir: &Path) -> bool {
    match e {
        Error::CorruptMap { path, .. } | Error::Io { path, .. } | Error::DamagedIndex { path, .. } => path == dir || path.parent() == Some(dir),
        Error::MapVersion { path, .. } => path == dir,
        Error::InvalidConfig { source_name, .. } => *source_name == dir.join(MANIFEST).display().to_string(),
        _ => false,
    }
}

/// Whether `e` is a typed map error naming file `name` of `dir`.
fn names_file(e: &Error, dir: &Path, name: &str) -> bool {
    matches!(e, Error::CorruptMap { path, .. } | Error::Io { path, .. } | Error::DamagedIndex { path, .. } if *path == dir.join(name))
}

fn verdict(e: &Error, named: &dyn Fn(&Error) -> bool) -> Verdict {
    match named(e) {
        true => Verdict::Refused,
        false => Verdict::Violation(format!("unexpected error (wrong kind, or not naming the file): {e:?}")),
    }
}

/// Opens `dir` as a map and uses it as the commands do; a refusal must satisfy `named`. A map that
/// opens must give the same answer from `map verify`, reading back and matching: sound in all
/// three, or a damaged segment named by all three. With `edit`, a sound map then loses its first
/// image to `map remove` and `map compact`.
fn use_map(dir: &Path, named: &dyn Fn(&Error) -> bool, edit: bool) -> Verdict {
    let map = match Map::open(dir) {
        Ok(m) => m,
        Err(e) => return verdict(&e, named),
    };
    let report = match edit::verify(dir) {
        Ok(r) => r,
        Err(e) => return Verdict::Violation(format!("map verify fails on a map that opens: {e}")),
    };
    let damaged: Vec<&str> = report.damaged().map(|f| f.file.as_str()).collect();
    let cfg = Config::default().with_encoding(&map.manifest.config);
    if let Err(e) = map.check_compatible(&cfg.encoding()) {
        return Verdict::Violation(format!("a map is incompatible with its own config: {e}"));
    }
    // the model check formats whatever the manifest holds
    let _ = (map.check_model(None), map.check_model(Some("another network")));
    let set = match map.to_descriptor_set() {
        Ok(set) => set,
        Err(e) => {
            let in_report = damaged.iter().any(|f| e.to_string().contains(f));
            if !matches!(e, Error::CorruptMap { .. }) || !in_report {
                return Verdict::Violation(format!("the map does not read back ({e}), map verify finds {damaged:?}"));
            }
            return damaged_queries(&map, &cfg, &e).unwrap_or_else(|| verdict(&e, named));
        }
    };
    if !damaged.is_empty() || set.len() != map.len() {
        return Verdict::Violation(format!("map verify finds {damaged:?}, yet {} of {} images read back", set.len(), map.len()));
    }
    let queries = set.slice(0, set.len().min(2));
    for setting in Setting::ALL {
        match match_with(&mut CpuStages, &map, &queries, setting, &cfg) {
            Ok((m, _)) if m.len() == queries.len() && m.iter().flat_map(|q| &q.ranked).all(|c| (c.reference as usize) < map.len()) => {}
            Ok(_) => return Verdict::Violation(format!("{setting}: rankings of the wrong length or out of the map")),
            // a baseline the map cannot serve (no HOG stored, no appearance) is refused by name
            Err(Error::InvalidInput { .. } | Error::Refused { .. }) if setting.is_baseline() => {}
            Err(e) => return Verdict::Violation(format!("{setting} on a sound map: {e}")),
        }
    }
    if let Err(e) = MapWriter::append(dir, StoreOptions::default()) {
        return Verdict::Violation(format!("a sound map does not open for appending: {e}"));
    }
    match (edit, set.ids.first()) {
        (true, Some(first)) => remove_and_compact(dir, first, set.len()),
        _ => Verdict::Accepted,
    }
}

/// Removes image `first` of a sound map of `n` images and compacts it: both succeed, and the map
/// then reads back without it.
fn remove_and_compact(dir: &Path, first: &str, n: usize) -> Verdict {
    match edit::remove(dir, &[first.to_string()]) {
        Ok(1) => {}
        other => return Verdict::Violation(format!("removing {first:?} from a sound map: {other:?}")),
    }
    if let Err(e) = edit::compact(dir, StoreOptions::default()) {
        return Verdict::Violation(format!("compacting a sound map: {e}"));
    }
    match Map::open(dir).and_then(|m| m.to_descriptor_set()) {
        Ok(set) if set.len() + 1 == n && !set.ids.iter().any(|id| id == first) => Verdict::Accepted,
        other => Verdict::Violation(format!("after removing {first:?} of {n} and compacting: {:?}", other.map(|s| s.ids))),
    }
}

/// Gives `rows` (read back from a map, which stores no SSIM statistics) the statistics an
/// encoder's query set has.
fn add_ssim_stats(rows: &mut DescriptorSet, cfg: &Config) {
    let p = cfg.global.ssim_params();
    rows.stats_len = p.stats_len();
    let mut scratch = SsimScratch::default();
    for i in 0..rows.len() {
        let mut stats = vec![0.0; rows.stats_len];
        ssim_stats(&p, rows.global(i), &mut stats, &mut scratch);
        rows.global_stats.extend(stats);
    }
}

/// Queries a map with a damaged segment, with queries of its own (the first live images of its
/// sound segments): every setting must refuse with the damage named, as `e` names it. `None`
/// when no sound image is left to query with.
fn damaged_queries(map: &Map, cfg: &Config, e: &Error) -> Option<Verdict> {
    let l = map.layout();
    let mut rows = DescriptorSet::for_storage(l.global_len(), l.slots, l.dim, l.hog);
    for (s, seg) in map.segments().iter().enumerate() {
        if seg.ensure().is_ok() {
            if let Some(j) = map.live_rows(s).next() {
                seg.append_row(j, &mut rows);
            }
        }
    }
    if rows.is_empty() {
        return None;
    }
    add_ssim_stats(&mut rows, cfg);
    for setting in Setting::ALL {
        match match_with(&mut CpuStages, map, &rows, setting, cfg) {
            Err(Error::CorruptMap { path, .. }) if e.to_string().contains(&path.display().to_string()) => {}
            // a baseline the map cannot serve (no HOG stored, no appearance) is refused by name
            Err(Error::InvalidInput { .. } | Error::Refused { .. }) if setting.is_baseline() => {}
            Ok(_) => return Some(Verdict::Violation(format!("{setting} ranks a map with a damaged segment ({e})"))),
            Err(other) => return Some(Verdict::Violation(format!("{setting} on a damaged map: {other}, expected {e}"))),
        }
    }
    None
}

pub fn map_manifest() -> Option<Target> {
    let st = Store::new();
    let seeds = st.manifests.clone();
    let run = move |b: &[u8]| match st.restore(b, None) {
        Ok(()) => use_map(&st.work, &|e| names_map_file(e, &st.work), b.len().is_multiple_of(4)),
        Err(v) => v,
    };
    Some(Target { name: "map_manifest", seeds, fixup: None, quick: 300, run: Box::new(run) })
}

/// Changes a damaged or hand-edited manifest would have: segment entries taken from the other
/// map, dropped, reordered, or with other removed rows; free-form strings (the uid, the writer,
/// the keypoint network's checksum) replaced by others, non-ASCII or long ones among them.
fn edit_manifest(e: &mut Entropy, v: &mut serde_json::Value, other: &serde_json::Value) {
    if e.chance(4) {
        let field = *e.pick(&["uid", "created_by", "appearance_model"]);
        let text = match e.below(4) {
            0 => String::new(),
            1 => "\u{e9}t\u{e9}-\u{1f6a6}-\u{5730}\u{56fe}".to_string(),
            2 => "0123456789abcdef".repeat(1 + e.below(300)),
            _ => "\u{fffd}".repeat(e.below(20)),
        };
        v[field] = serde_json::json!(text);
    }
    let Some(list) = v.get_mut("segments").and_then(|s| s.as_array_mut()) else { return };
    if e.chance(4) {
        if let Some(entry) = other["segments"].as_array().and_then(|o| o.get(e.below(o.len()))) {
            let at = e.below(list.len() + 1);
            list.insert(at, entry.clone());
        }
    }
    if e.chance(6) && !list.is_empty() {
        list.remove(e.below(list.len()));
    }
    if e.chance(6) {
        list.reverse();
    }
    if e.chance(4) && !list.is_empty() {
        let k = e.below(list.len());
        let rows: Vec<u32> = (0..e.below(4)).map(|_| e.below(5) as u32).collect();
        if let Some(entry) = list[k].as_object_mut() {
            entry.insert("removed".into(), serde_json::json!(rows));
        }
    }
}

/// Every query's ranked (id, score bits) in every label setting, for `queries` against the map in
/// `dir`; `None` when the map does not open or a setting fails.
fn rankings(dir: &Path, queries: &DescriptorSet) -> Option<Vec<Vec<Vec<(String, u32)>>>> {
    let map = Map::open(dir).ok()?;
    let cfg = Config::default().with_encoding(&map.manifest.config);
    Setting::SEMLOOK
        .iter()
        .map(|&s| {
            let (m, _) = match_with(&mut CpuStages, &map, queries, s, &cfg).ok()?;
            Some(m.iter().map(|q| q.ranked.iter().map(|c| (map.id(c.reference as usize).to_string(), c.score.to_bits())).collect()).collect())
        })
        .collect()
}

/// Fixed queries (the first two live images of map `which`, with SSIM statistics) and the
/// rankings the unedited map gives them.
fn baseline(st: &Store, which: usize) -> (DescriptorSet, Vec<Vec<Vec<(String, u32)>>>) {
    st.restore(&st.manifests[which], None).map_err(|_| ()).expect("fixture restore");
    let map = Map::open(&st.work).expect("fixture map opens");
    let mut q = map.to_descriptor_set().expect("fixture reads back").slice(0, 2);
    add_ssim_stats(&mut q, &Config::default().with_encoding(&map.manifest.config));
    let r = rankings(&st.work, &q).expect("fixture rankings");
    (q, r)
}

pub fn map_manifest_values() -> Option<Target> {
    let st = Store::new();
    let manifests: Vec<serde_json::Value> = st.manifests.iter().map(|m| serde_json::from_slice(m).expect("fixture manifest")).collect();
    // what the unedited maps answer: an edit that opens must not change it (issue 20: a flipped
    // removed row or config value was served with other results)
    let baselines: Vec<_> = (0..manifests.len()).map(|m| baseline(&st, m)).collect();
    let run = move |b: &[u8]| {
        // a short input repeated: the values past the segment list take choices too (truncated
        // inputs would otherwise leave every later value as it was)
        let long: Vec<u8> = b.iter().copied().cycle().take(b.len().max(1024)).collect();
        let mut e = Entropy::new(&long);
        let (which, edit, depth) = (e.below(manifests.len()), e.chance(3), e.below(3));
        let mut v = manifests[which].clone();
        edit_manifest(&mut e, &mut v, &manifests[1 - which]);
        // then (by depth) nothing more, the segment list's values, or every value
        if let Some(list) = v.get_mut("segments").filter(|_| depth >= 1) {
            json_mutate(&mut e, list);
        }
        if depth == 2 {
            json_mutate(&mut e, &mut v);
        }
        if let Err(v) = st.restore(v.to_string().as_bytes(), None) {
            return v;
        }
        // refused at open, or the same answers as the unedited map (before any remove/compact)
        if Map::open(&st.work).is_ok() && edit::verify(&st.work).is_ok_and(|r| r.damaged().count() == 0) {
            let (queries, expected) = &baselines[which];
            if let Some(got) = rankings(&st.work, queries) {
                if got != *expected {
                    return Verdict::Violation("an edited manifest opened and changed the answers to the same queries".into());
                }
            }
        }
        use_map(&st.work, &|e| names_map_file(e, &st.work), edit)
    };
    let mut seeds = vec![vec![0u8; 8], vec![1, 0, 0, 0, 0, 0, 0, 0], vec![0, 0, 0, 0, 2, 0, 0, 0], vec![1, 0, 0, 0, 2, 0, 0, 0]];
    seeds.extend(random_seeds(11, 12, 256));
    Some(Target { name: "map_manifest_values", seeds, fixup: None, quick: 300, run: Box::new(run) })
}

/// Segment files: the first byte picks one (of both maps; its high bit: edit the map if it is
/// sound), the rest is its new content. With `rehash`, the manifest takes the new size and SHA-256.
fn segment_target(name: &'static str, rehash: bool) -> Option<Target> {
    let st = Store::new();
    let seeds = (0..2 * st.segments.len())
        .map(|k| {
            let (s, edit) = (k % st.segments.len(), k >= st.segments.len());
            let bytes = &st.files.iter().find(|f| f.0 == st.segments[s].1).expect("fixture segment").1;
            [&[s as u8 | u8::from(edit) << 7][..], bytes].concat()
        })
        .collect();
    let run = move |b: &[u8]| {
        let (pick, bytes) = b.split_first().map_or((0, &[][..]), |(p, rest)| (*p as usize, rest));
        let (m, file) = &st.segments[(pick & 0x7f) % st.segments.len()];
        let manifest = if rehash { st.rehashed(*m, file, bytes) } else { st.manifests[*m].clone() };
        match st.restore(&manifest, Some((file, bytes))) {
            Ok(()) => use_map(&st.work, &|e| names_file(e, &st.work, file), pick & 0x80 != 0),
            Err(v) => v,
        }
    };
    Some(Target { name, seeds, fixup: None, quick: 300, run: Box::new(run) })
}

pub fn map_segment() -> Option<Target> {
    segment_target("map_segment", false)
}

pub fn map_segment_rehashed() -> Option<Target> {
    segment_target("map_segment_rehashed", true)
}

/// The codebook of the f16 map, rehashed into its manifest (a codebook under the old hash is
/// refused at open by its size or SHA-256, which `map_manifest` reaches).
pub fn map_codebook() -> Option<Target> {
    let st = Store::new();
    let seeds = st.files.iter().filter(|f| f.0 == CODEBOOK).map(|f| f.1.clone()).collect();
    let run = move |b: &[u8]| {
        let manifest = st.rehashed(1, CODEBOOK, b);
        match st.restore(&manifest, Some((CODEBOOK, b))) {
            Ok(()) => use_map(&st.work, &|e| names_file(e, &st.work, CODEBOOK), b.len().is_multiple_of(4)),
            Err(v) => v,
        }
    };
    Some(Target { name: "map_codebook", seeds, fixup: None, quick: 200, run: Box::new(run) })
}
