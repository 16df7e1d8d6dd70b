//! Stage 3: the map of places. A map directory holds
//! - `manifest.json`: format version, the encoding config, the image list, and per segment file
//!   its name, image count, byte size and SHA-256;
//! - `segment-NNNNNN.safetensors`: the descriptors of the images added in one build or add.
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
use crate::global::ssim::SsimParams;
use serde::{Deserialize, Serialize};
use sha2::{Digest, Sha256};
use std::io::Write;
use std::path::{Path, PathBuf};

pub const FORMAT: &str = "semlook-map";
pub const VERSION: u32 = 1;
const MANIFEST: &str = "manifest.json";
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
    pub segments: Vec<SegmentEntry>,
    /// Image ids in storage order (segment by segment).
    pub images: Vec<String>,
}

/// A loaded map: its manifest and all its descriptors in memory.
#[derive(Debug, Clone)]
pub struct Map {
    pub path: PathBuf,
    pub manifest: Manifest,
    pub descriptors: DescriptorSet,
}

fn sha256_hex(bytes: &[u8]) -> String {
    Sha256::digest(bytes).iter().map(|b| format!("{b:02x}")).collect()
}

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
    pub fn new(path: &Path, cfg: &EncodingConfig, appearance_dim: usize) -> Map {
        let ssim = SsimParams::new(&cfg.global);
        Map {
            path: path.to_path_buf(),
            manifest: Manifest {
                format: FORMAT.into(),
                version: VERSION,
                created_by: format!("semlook {}", env!("CARGO_PKG_VERSION")),
                config: cfg.clone(),
                neighbour_slots: cfg.local.neighbours,
                appearance_dim,
                segments: vec![],
                images: vec![],
            },
            descriptors: DescriptorSet::new(&ssim, cfg.local.neighbours, appearance_dim),
        }
    }

    pub fn len(&self) -> usize {
        self.descriptors.len()
    }
    pub fn is_empty(&self) -> bool {
        self.descriptors.is_empty()
    }

    /// Creates a new map directory holding `set` as its first segment. Fails if `dir` exists and
    /// is not empty.
    pub fn create(dir: &Path, cfg: &EncodingConfig, set: &DescriptorSet) -> Result<Map> {
        if dir.exists() && std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.next().is_some() {
            return Err(Error::invalid(format!("map {}", dir.display()), "directory exists and is not empty (use map add, or --force)"));
        }
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let mut map = Map::new(dir, cfg, set.appearance_dim);
        map.add(set)?;
        Ok(map)
    }

    /// Appends `set` as a new segment and rewrites the manifest, atomically. Ids already stored
    /// are refused before anything is written.
    pub fn add(&mut self, set: &DescriptorSet) -> Result<()> {
        let _lock = WriteLock::take(&self.path)?;
        let mut seen: std::collections::HashSet<&str> = self.manifest.images.iter().map(|s| s.as_str()).collect();
        for id in &set.ids {
            if !seen.insert(id) {
                return Err(Error::DuplicateImageId { map: self.path.clone(), id: id.clone() });
            }
        }
        if set.appearance_dim != self.manifest.appearance_dim || set.neighbour_slots != self.manifest.neighbour_slots {
            return Err(Error::invalid(
                format!("map {}", self.path.display()),
                format!(
                    "new images have appearance dim {} / {} neighbour slots, the map {} / {}",
                    set.appearance_dim, set.neighbour_slots, self.manifest.appearance_dim, self.manifest.neighbour_slots
                ),
            ));
        }
        let g = &self.manifest.config.global;
        let bytes = segment::to_bytes(set, g.width, g.height);
        let file = format!("segment-{:06}.safetensors", self.manifest.segments.len());
        write_atomic(&self.path, &file, &bytes)?;
        let mut manifest = self.manifest.clone();
        manifest.segments.push(SegmentEntry {
            file,
            images: set.len(),
            trees: set.n_trees(),
            bytes: bytes.len() as u64,
            sha256: sha256_hex(&bytes),
        });
        manifest.images.extend(set.ids.iter().cloned());
        let json = serde_json::to_vec_pretty(&manifest).expect("manifest serialises");
        write_atomic(&self.path, MANIFEST, &json)?;
        self.manifest = manifest;
        self.descriptors.append(set);
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
        let mut set = DescriptorSet::new(&ssim, manifest.neighbour_slots, manifest.appearance_dim);
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
            let part = segment::from_bytes(&bytes, cfg.global.width, cfg.global.height, ssim.stats_len(), manifest.neighbour_slots, manifest.appearance_dim)
                .map_err(|r| Error::corrupt(&p, r))?;
            if part.len() != seg.images || part.n_trees() != seg.trees {
                return Err(Error::corrupt(&p, "image or tree count differs from the manifest"));
            }
            part.validate(table.len()).map_err(|r| Error::corrupt(&p, r))?;
            set.append(&part);
        }
        if set.ids != manifest.images {
            return Err(Error::corrupt(&mpath, "image list differs from the segments' ids"));
        }
        set.validate(table.len()).map_err(|r| Error::corrupt(&mpath, r))?;
        Ok(Map { path: dir.into(), manifest, descriptors: set })
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
