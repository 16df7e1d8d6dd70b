//! Stage 3: the map of places. A map directory holds
//! - `manifest.json`: format version, the encoding config, the image list, and per segment file
//!   its name, image count, byte size and SHA-256;
//! - `segment-NNNNNN.safetensors`: the descriptors of at most [`SEGMENT_IMAGES`] images.
//!
//! In memory a map stays a list of segments (no allocation grows with the whole map); matching
//! reads it through [`GlobalSource`] tiles and [`RefSource`] look-ups.
//!
//! Writes are atomic: a segment is written to a temporary file, synced and renamed, and only then
//! is the manifest replaced the same way, so a crash or a bad input at any point leaves the
//! previous map intact. `map add` appends a segment and never rewrites stored ones. Loading
//! checks sizes, checksums, tensor layouts and values, so a truncated or altered file is
//! reported, never read as data.

mod descriptor_set;
mod segment;

pub use descriptor_set::DescriptorSet;

use crate::classes::ClassTable;
use crate::config::{first_difference, EncodingConfig};
use crate::error::{Error, Result};
use crate::appearance::vlad::Codebook;
use crate::global::ssim::SsimParams;
use crate::local::ForestRef;
use crate::matching::source::{GlobalSource, RefSource, TileBuf};
use serde::{Deserialize, Serialize};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "semlook-map";
/// Most images per segment file (about 130 MB of descriptors without appearance).
pub const SEGMENT_IMAGES: usize = 4096;
/// Version 2 added per-tree descriptor counts, whole-image appearance and HOG.
pub const VERSION: u32 = 2;
const MANIFEST: &str = "manifest.json";
const CODEBOOK: &str = "codebook.safetensors";
const LOCK: &str = ".lock";

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmentEntry {
    pub file: String,
    pub images: usize,
    pub trees: usize,
    pub bytes: u64,
    pub sha256: String,
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    pub format: String,
    pub version: u32,
    pub created_by: String,
    pub config: EncodingConfig,
    pub neighbour_slots: usize,
    pub appearance_dim: usize,
    /// Values of each image's HOG baseline descriptor (0: the map holds none).
    #[serde(default)]
    pub hog_dim: usize,
    pub segments: Vec<SegmentEntry>,
    /// Image ids in storage order (segment by segment).
    pub images: Vec<String>,
    /// The VLAD codebook file, when trees carry appearance.
    #[serde(default)]
    pub codebook: Option<SegmentEntry>,
    /// SHA-256 of the keypoint network's weights the appearance was computed with.
    #[serde(default)]
    pub appearance_model: Option<String>,
}

/// A loaded map: its manifest and its descriptors, segment by segment.
#[derive(Debug, Clone)]
pub struct Map {
    pub path: PathBuf,
    pub manifest: Manifest,
    segments: Vec<DescriptorSet>,
    /// First image index of each segment, then the total.
    starts: Vec<usize>,
    codebook: Option<Codebook>,
}

use crate::util::sha256_hex;

/// Writes `bytes` to `dir/name` atomically: temporary file, fsync, rename, directory fsync.
fn write_atomic(dir: &Path, name: &str, bytes: &[u8]) -> Result<()> {
    let tmp = dir.join(format!(".{name}.tmp"));
    let dst = dir.join(name);
    let mut f = std::fs::File::create(&tmp).map_err(|e| Error::io(&tmp, e))?;
    f.write_all(bytes).map_err(|e| Error::io(&tmp, e))?;
    f.sync_all().map_err(|e| Error::io(&tmp, e))?;
    drop(f);
    std::fs::rename(&tmp, &dst).map_err(|e| Error::io(&dst, e))?;
    if let Ok(d) = std::fs::File::open(dir) {
        let _ = d.sync_all();
    }
    Ok(())
}

/// Exclusive writer lock on a map directory, released on drop.
struct WriteLock(PathBuf);

impl WriteLock {
    fn take(dir: &Path) -> Result<WriteLock> {
        let p = dir.join(LOCK);
        match std::fs::OpenOptions::new().write(true).create_new(true).open(&p) {
            Ok(mut f) => {
                let _ = writeln!(f, "{}", std::process::id());
                Ok(WriteLock(p))
            }
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => Err(Error::invalid(
                format!("map {}", dir.display()),
                format!("another writer holds {} (delete it if no semlook process is running)", p.display()),
            )),
            Err(e) => Err(Error::io(&p, e)),
        }
    }
}

impl Drop for WriteLock {
    fn drop(&mut self) {
        let _ = std::fs::remove_file(&self.0);
    }
}

impl Map {
    /// An empty, unsaved map for descriptors encoded with `cfg`.
    pub fn new(path: &Path, cfg: &EncodingConfig, appearance_dim: usize, hog_dim: usize) -> Map {
        Map {
            path: path.to_path_buf(),
            manifest: Manifest {
                format: FORMAT.into(),
                version: VERSION,
                created_by: format!("semlook {}", env!("CARGO_PKG_VERSION")),
                config: cfg.clone(),
                neighbour_slots: cfg.local.neighbours,
                appearance_dim,
                hog_dim,
                segments: vec![],
                images: vec![],
                codebook: None,
                appearance_model: None,
            },
            segments: vec![],
            starts: vec![0],
            codebook: None,
        }
    }

    /// The VLAD codebook of the map's appearance vectors.
    pub fn codebook(&self) -> Option<&Codebook> {
        self.codebook.as_ref()
    }

    pub fn len(&self) -> usize {
        *self.starts.last().unwrap()
    }
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    pub fn n_trees(&self) -> usize {
        self.segments.iter().map(|s| s.n_trees()).sum()
    }
    pub fn segments(&self) -> &[DescriptorSet] {
        &self.segments
    }
    /// (segment, index inside it) of image `i`.
    fn locate(&self, i: usize) -> (usize, usize) {
        let s = self.starts.partition_point(|&st| st <= i) - 1;
        (s, i - self.starts[s])
    }
    /// All descriptors in one set (one allocation of the whole map: for small maps and tests).
    pub fn to_descriptor_set(&self) -> DescriptorSet {
        let g = &self.manifest.config.global;
        let ssim = SsimParams::new(g);
        let mut set = DescriptorSet::new(&ssim, self.manifest.neighbour_slots, self.manifest.appearance_dim, self.manifest.hog_dim);
        for s in &self.segments {
            set.append(s);
        }
        set
    }
    fn push_segment(&mut self, set: DescriptorSet) {
        self.starts.push(self.len() + set.len());
        self.segments.push(set);
    }

    /// Creates a new map directory holding `set`. With appearance, `appearance` gives the VLAD
    /// codebook and the SHA-256 of the keypoint network, both recorded in the map. Fails if `dir`
    /// exists and is not empty.
    pub fn create(dir: &Path, cfg: &EncodingConfig, set: &DescriptorSet, appearance: Option<(&Codebook, &str)>) -> Result<Map> {
        if dir.exists() && std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.next().is_some() {
            return Err(Error::invalid(format!("map {}", dir.display()), "directory exists and is not empty (use map add, or --force)"));
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let mut map = Map::new(dir, cfg, set.appearance_dim, set.hog_dim);
        if let Some((cb, sha)) = appearance {
            if cb.k * cb.dim != set.appearance_dim {
                return Err(Error::invalid(format!("map {}", dir.display()), "codebook size differs from the appearance vectors"));
            }
            let centres = safetensors::tensor::TensorView::new(safetensors::tensor::Dtype::F32, vec![cb.k, cb.dim], bytemuck::cast_slice(&cb.centres)).expect("shape matches");
            let bytes = safetensors::serialize([("centres", centres)], None).expect("serialises");
            write_atomic(dir, CODEBOOK, &bytes)?;
            map.manifest.codebook = Some(SegmentEntry { file: CODEBOOK.into(), images: 0, trees: 0, bytes: bytes.len() as u64, sha256: sha256_hex(&bytes) });
            map.manifest.appearance_model = Some(sha.to_string());
            map.codebook = Some(cb.clone());
        } else if set.appearance_dim != 0 {
            return Err(Error::invalid(format!("map {}", dir.display()), "appearance vectors without a codebook"));
        }
        map.add(set)?;
        Ok(map)
    }

    /// Fails naming the difference if images encoded with `model_sha256` (the keypoint network's
    /// checksum, or none without appearance) cannot be matched against this map.
    pub fn check_model(&self, model_sha256: Option<&str>) -> Result<()> {
        if self.manifest.appearance_model.as_deref() != model_sha256 {
            let show = |v: Option<&str>| v.map_or("none".to_string(), |s| format!("sha256 {}", &s[..12.min(s.len())]));
            return Err(Error::IncompatibleConfig {
                map: self.path.clone(),
                field: "appearance keypoint network".into(),
                map_value: show(self.manifest.appearance_model.as_deref()),
                given_value: show(model_sha256),
            });
        }
        Ok(())
    }

    /// Appends `set` as new segments (of at most [`SEGMENT_IMAGES`] images) and then rewrites the
    /// manifest, atomically. Ids already stored are refused before anything is written.
    pub fn add(&mut self, set: &DescriptorSet) -> Result<()> {
        self.add_in_segments(set, SEGMENT_IMAGES)
    }

    /// [`Map::add`] with at most `per_segment` images per segment file.
    pub fn add_in_segments(&mut self, set: &DescriptorSet, per_segment: usize) -> Result<()> {
        let per_segment = per_segment.max(1);
        let _lock = WriteLock::take(&self.path)?;
        let mut seen: std::collections::HashSet<&str> = self.manifest.images.iter().map(|s| s.as_str()).collect();
        for id in &set.ids {
            if !seen.insert(id) {
                return Err(Error::DuplicateImageId { map: self.path.clone(), id: id.clone() });
            }
        }
        if set.appearance_dim != self.manifest.appearance_dim || set.neighbour_slots != self.manifest.neighbour_slots || set.hog_dim != self.manifest.hog_dim {
            return Err(Error::invalid(
                format!("map {}", self.path.display()),
                format!(
                    "new images have appearance dim {} / {} neighbour slots / HOG dim {}, the map {} / {} / {}",
                    set.appearance_dim, set.neighbour_slots, set.hog_dim, self.manifest.appearance_dim, self.manifest.neighbour_slots, self.manifest.hog_dim
                ),
            ));
        }
        let g = &self.manifest.config.global;
        let mut manifest = self.manifest.clone();
        let mut parts = Vec::new();
        for start in (0..set.len()).step_by(per_segment) {
            let part = set.slice(start, (start + per_segment).min(set.len()));
            let bytes = segment::to_bytes(&part, g.width, g.height);
            let file = format!("segment-{:06}.safetensors", manifest.segments.len());
            write_atomic(&self.path, &file, &bytes)?;
            manifest.segments.push(SegmentEntry { file, images: part.len(), trees: part.n_trees(), bytes: bytes.len() as u64, sha256: sha256_hex(&bytes) });
            parts.push(part);
        }
        manifest.images.extend(set.ids.iter().cloned());
        let json = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
        write_atomic(&self.path, MANIFEST, &json)?;
        self.manifest = manifest;
        for part in parts {
            self.push_segment(part);
        }
        Ok(())
    }

    /// Opens a map directory, verifying every file.
    pub fn open(dir: &Path) -> Result<Map> {
        let mpath = dir.join(MANIFEST);
        let text = std::fs::read(&mpath).map_err(|e| Error::io(&mpath, e))?;
        let value: serde_json::Value =
            serde_json::from_slice(&text).map_err(|e| Error::corrupt(&mpath, format!("manifest is not valid JSON: {e}")))?;
        if value.get("format").and_then(|f| f.as_str()) != Some(FORMAT) {
            return Err(Error::corrupt(&mpath, format!("not a {FORMAT} manifest")));
        }
        let version = value.get("version").and_then(|v| v.as_u64()).unwrap_or(0) as u32;
        if version != VERSION {
            return Err(Error::MapVersion { path: dir.into(), found: version, supported: VERSION });
        }
        let manifest: Manifest =
            serde_json::from_value(value).map_err(|e| Error::corrupt(&mpath, format!("manifest fields: {e}")))?;
        let cfg = &manifest.config;
        crate::config::Config::default().with_encoding(cfg).validate(&mpath.display().to_string())?;
        if manifest.neighbour_slots != cfg.local.neighbours {
            return Err(Error::corrupt(&mpath, "neighbour slots differ from the config"));
        }
        let table = ClassTable::from_config(&cfg.classes)?;
        let ssim = SsimParams::new(&cfg.global);
        let codebook = match &manifest.codebook {
            Some(entry) => Some(read_codebook(dir, entry, manifest.appearance_dim)?),
            None if manifest.appearance_dim != 0 => return Err(Error::corrupt(&mpath, "appearance vectors but no codebook")),
            None => None,
        };
        let mut map = Map { path: dir.into(), manifest: manifest.clone(), segments: vec![], starts: vec![0], codebook };
        let mut ids_seen = std::collections::HashSet::new();
        for seg in &manifest.segments {
            if seg.file.contains('/') || seg.file.contains("..") {
                return Err(Error::corrupt(&mpath, format!("segment name {:?} leaves the map directory", seg.file)));
            }
            let p = dir.join(&seg.file);
            let bytes = std::fs::read(&p).map_err(|e| Error::io(&p, e))?;
            if bytes.len() as u64 != seg.bytes {
                return Err(Error::corrupt(&p, format!("file is {} bytes, the manifest says {} (truncated or replaced)", bytes.len(), seg.bytes)));
            }
            if sha256_hex(&bytes) != seg.sha256 {
                return Err(Error::corrupt(&p, "SHA-256 differs from the manifest (file altered)"));
            }
            let part = segment::from_bytes(&bytes, cfg.global.width, cfg.global.height, ssim.stats_len(), manifest.neighbour_slots, manifest.appearance_dim, manifest.hog_dim)
                .map_err(|r| Error::corrupt(&p, r))?;
            if part.len() != seg.images || part.n_trees() != seg.trees {
                return Err(Error::corrupt(&p, "image or tree count differs from the manifest"));
            }
            part.validate(table.len()).map_err(|r| Error::corrupt(&p, r))?;
            if let Some(dup) = part.ids.iter().find(|id| !ids_seen.insert(id.to_string())) {
                return Err(Error::corrupt(&p, format!("image id {dup:?} is stored twice")));
            }
            map.push_segment(part);
        }
        let listed = map.segments.iter().flat_map(|s| s.ids.iter());
        if map.len() != manifest.images.len() || !listed.zip(&manifest.images).all(|(a, b)| a == b) {
            return Err(Error::corrupt(&mpath, "image list differs from the segments' ids"));
        }
        Ok(map)
    }

    /// Fails with the first differing field if queries encoded with `cfg` cannot be matched here.
    pub fn check_compatible(&self, cfg: &EncodingConfig) -> Result<()> {
        match first_difference(&self.manifest.config, cfg) {
            None => Ok(()),
            Some((field, map_value, given_value)) => {
                Err(Error::IncompatibleConfig { map: self.path.clone(), field, map_value, given_value })
            }
        }
    }
}

/// Reads and checks the codebook file.
fn read_codebook(dir: &Path, entry: &SegmentEntry, appearance_dim: usize) -> Result<Codebook> {
    let p = dir.join(&entry.file);
    if entry.file != CODEBOOK {
        return Err(Error::corrupt(&p, "unexpected codebook file name"));
    }
    let bytes = std::fs::read(&p).map_err(|e| Error::io(&p, e))?;
    if bytes.len() as u64 != entry.bytes || sha256_hex(&bytes) != entry.sha256 {
        return Err(Error::corrupt(&p, "size or SHA-256 differs from the manifest"));
    }
    let st = safetensors::SafeTensors::deserialize(&bytes).map_err(|e| Error::corrupt(&p, e.to_string()))?;
    let t = st.tensor("centres").map_err(|_| Error::corrupt(&p, "no centres tensor"))?;
    let shape = t.shape().to_vec();
    if t.dtype() != safetensors::tensor::Dtype::F32 || shape.len() != 2 || shape[0] * shape[1] != appearance_dim || shape[0] == 0 {
        return Err(Error::corrupt(&p, format!("centres are {:?} {shape:?}; the map's appearance vectors have {appearance_dim} values", t.dtype())));
    }
    let centres: Vec<f32> = bytemuck::pod_collect_to_vec(t.data());
    if centres.iter().any(|v| !v.is_finite()) {
        return Err(Error::corrupt(&p, "centres hold NaN or infinity"));
    }
    Ok(Codebook { k: shape[0], dim: shape[1], centres })
}

impl GlobalSource for Map {
    fn len(&self) -> usize {
        Map::len(self)
    }
    /// Borrowed from one segment when the tile lies inside it, else assembled in `buf`.
    fn tile<'a>(&'a self, start: usize, end: usize, buf: &'a mut TileBuf) -> (&'a [f32], &'a [f32]) {
        let (s, i) = self.locate(start);
        if end - self.starts[s] <= self.segments[s].len() {
            return self.segments[s].tile(i, i + end - start, buf);
        }
        buf.globals.clear();
        buf.stats.clear();
        let mut at = start;
        while at < end {
            let (s, i) = self.locate(at);
            let stop = (self.starts[s + 1]).min(end);
            let seg = &self.segments[s];
            let n = stop - at;
            buf.globals.extend_from_slice(&seg.globals[i * seg.global_len..(i + n) * seg.global_len]);
            buf.stats.extend_from_slice(&seg.global_stats[i * seg.stats_len..(i + n) * seg.stats_len]);
            at = stop;
        }
        (&buf.globals, &buf.stats)
    }
}

impl RefSource for Map {
    fn id(&self, i: usize) -> &str {
        let (s, j) = self.locate(i);
        &self.segments[s].ids[j]
    }
    fn forest(&self, i: usize) -> ForestRef<'_> {
        let (s, j) = self.locate(i);
        self.segments[s].forest(j)
    }
    fn neighbour_slots(&self) -> usize {
        self.manifest.neighbour_slots
    }
    fn appearance_dim(&self) -> usize {
        self.manifest.appearance_dim
    }
    fn image_appearance(&self, i: usize) -> &[f32] {
        let (s, j) = self.locate(i);
        self.segments[s].image_appearance(j)
    }
    fn hog_dim(&self) -> usize {
        self.manifest.hog_dim
    }
    fn image_hog(&self, i: usize) -> &[f32] {
        let (s, j) = self.locate(i);
        self.segments[s].image_hog(j)
    }
}
