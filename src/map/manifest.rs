//! `manifest.json`, the one file that says what a map holds: format version, generation, the
//! encoding config, storage layout, and per segment its file, sizes, SHA-256 and removed rows.
//! It is replaced atomically by every commit; readers see one generation or the next, never a mix.

use crate::config::EncodingConfig;
use crate::error::{Error, Result};
use crate::values::ValueType;
use serde::{Deserialize, Serialize};
use std::path::Path;

/// The manifest's `format`.
pub const FORMAT: &str = "semlook-map";
/// Version 4: version 3 (memory-mapped segments with ids as tensors and no SSIM statistics, f16
/// option, generations, tombstones, content-named segment files) with the verification keypoints
/// of every image.
pub const VERSION: u32 = 4;
/// File name of the manifest, in the map folder.
pub const MANIFEST: &str = "manifest.json";
/// File name of the VLAD codebook, in the map folder.
pub const CODEBOOK: &str = "codebook.safetensors";
/// ENOENT on Unix, ERROR_FILE_NOT_FOUND on Windows: the same number.
const NO_SUCH_FILE: i32 = 2;
/// Largest manifest read: a million-image map has a few hundred segment entries (about 100 kB),
/// so anything near this bound is not a manifest.
const MAX_MANIFEST_BYTES: u64 = 256 << 20;

/// A file of the map with its size and checksum.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FileEntry {
    /// File name, in the map folder.
    pub file: String,
    /// File size in bytes.
    pub bytes: u64,
    /// SHA-256 of the file's content.
    pub sha256: String,
}

/// One segment file.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SegmentEntry {
    /// File name, in the map folder.
    pub file: String,
    /// Images stored in the file (removed ones included).
    pub images: usize,
    /// Trees stored in the file (those of removed images included).
    pub trees: usize,
    /// Verification keypoints stored in the file.
    pub keypoints: usize,
    /// File size in bytes.
    pub bytes: u64,
    /// SHA-256 of the file's content.
    pub sha256: String,
    /// Rows of removed images (tombstones), ascending; `map compact` drops them from the file.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub removed: Vec<u32>,
    /// The traversal (a run of frames in order, [`Manifest::traversals`]) the file's images
    /// belong to; its images follow the traversal's earlier files, in row order. Absent (0) in
    /// the manifests of maps that hold one traversal, so their checksums are those of before the
    /// field existed.
    #[serde(default, skip_serializing_if = "is_zero")]
    pub traversal: u32,
    /// The file of the segment's index codes ([`crate::index::codes`]), when the map has an
    /// index ([`Manifest::index`]). Absent in maps without one.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index: Option<FileEntry>,
}

/// A map's index: the model file, the parameters it was built with, and what was measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct IndexEntry {
    /// The model file (`index-model-<sha>.safetensors`).
    pub model: FileEntry,
    /// How it was built.
    pub params: crate::index::IndexParams,
    /// Values per reduced vector and lists of the model as trained (at most the parameters').
    pub dims: usize,
    /// Lists of the model as trained.
    pub lists: usize,
    /// Live images when it was trained.
    pub trained_on: usize,
    /// Recall@30 of the index's shortlist against the exact appearance ranking, measured when it
    /// was built on queries drawn from the map (each left out of its own ranking): the exact
    /// top-30 references the shortlists held, of `recall_of` (integers, so that the manifest's
    /// checksum survives a JSON round trip; floats may not). The recall against the fused score
    /// is measured by `eval` and `dev index-bench`.
    pub recall_hits: u64,
    /// See `recall_hits`.
    pub recall_of: u64,
    /// The probe and shortlist the recall was measured with.
    pub recall_probe: usize,
    /// See `recall_probe`.
    pub recall_shortlist: usize,
    /// Milliseconds the build took.
    pub build_ms: u64,
}

impl IndexEntry {
    /// The thumbnails this index keeps for a map whose global descriptors are `g`'s (none: built
    /// without them, or before them).
    pub fn thumb(&self, g: &crate::config::GlobalConfig) -> crate::index::thumb::ThumbSpec {
        crate::index::thumb::ThumbSpec::new(g, self.params.thumbnail)
    }
    /// `recall_hits / recall_of` (1 where nothing was measured).
    pub fn recall(&self) -> f64 {
        if self.recall_of == 0 {
            1.0
        } else {
            self.recall_hits as f64 / self.recall_of as f64
        }
    }
}

fn is_zero(v: &u32) -> bool {
    *v == 0
}

fn is_zero_usize(v: &usize) -> bool {
    *v == 0
}

impl SegmentEntry {
    /// Images of the file that are not removed.
    pub fn live(&self) -> usize {
        self.images - self.removed.len()
    }
    /// Whether row `j` is not removed.
    pub fn is_live(&self, j: usize) -> bool {
        self.removed.binary_search(&(j as u32)).is_err()
    }
}

/// The content of `manifest.json`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Manifest {
    /// Always [`FORMAT`].
    pub format: String,
    /// Format version ([`VERSION`] for maps this build writes).
    pub version: u32,
    /// Number of commits so far: every build, add, remove or compact step writes the next one.
    pub generation: u64,
    /// Random id given at creation. A writer that finds another id under its lock knows the map
    /// was replaced (`build --force`) while it worked, and stops.
    pub uid: String,
    /// The program that created the map (`semlook` and its version).
    pub created_by: String,
    /// The encoding configuration every image of the map was encoded with.
    pub config: EncodingConfig,
    /// Neighbour slots per tree.
    pub neighbour_slots: usize,
    /// Values per appearance vector (0: no appearance).
    pub appearance_dim: usize,
    /// Values of each image's HOG baseline descriptor (0: the map holds none).
    pub hog_dim: usize,
    /// Values of each image's compact HOG ([`crate::global::hog::compact_hog`]; 0: the map holds none).
    /// Maps of small frames hold them (`input.compact_hog_long_side`); absent (0) in the
    /// manifests of the others, so their checksums are those of before the field existed.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub compact_hog_dim: usize,
    /// Values per verification keypoint descriptor (0: the map stores no keypoints).
    pub keypoint_dim: usize,
    /// Values per stored block of the appearance vectors (the keypoint network's descriptor
    /// width, one block per VLAD centre; 0 without appearance).
    pub appearance_block: usize,
    /// How global descriptors and appearance vectors are stored.
    pub values: ValueType,
    /// The segment files, in the order of the map's image indices.
    pub segments: Vec<SegmentEntry>,
    /// The VLAD codebook file, when trees carry appearance.
    pub codebook: Option<FileEntry>,
    /// SHA-256 of the keypoint network's weights the appearance was computed with.
    pub appearance_model: Option<String>,
    /// The images were encoded without semantic labels (photos with neither label maps nor a
    /// segmenter, void label maps): only the settings that need no labels can be matched
    /// against the map. Absent (false) in the manifests of labelled maps, so their checksums
    /// are those of before the field existed.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub without_labels: bool,
    /// Names of the traversals the map holds (each `map build` or `map add` of a new run of
    /// frames starts one), indexed by [`SegmentEntry::traversal`]. Sequence matching never lets
    /// a trajectory cross from one traversal into another. Absent (empty) in the manifests of
    /// maps of one unnamed traversal.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub traversals: Vec<String>,
    /// Seconds between consecutive frames of a traversal (the median step of its images'
    /// timestamps, `map build/add --timestamps`), by traversal: a stream with timestamps derives
    /// its sequence velocity range from it (`sequence.velocity_scale`). Absent in maps without
    /// timed traversals, so their checksums are those of before the field existed.
    #[serde(default, skip_serializing_if = "std::collections::BTreeMap::is_empty")]
    pub frame_intervals: std::collections::BTreeMap<u32, f64>,
    /// The approximate index of the coarse stage ([`crate::index`]): its model file, how it was
    /// built and the recall measured then; every segment then names its codes. Absent in maps
    /// without one, so their checksums are those of before the field existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub index: Option<IndexEntry>,
    /// The network that made the images' whole-image embeddings ([`crate::networks::embedding`]); queries
    /// are embedded by the same file (same SHA-256). Absent in maps without embeddings (and in
    /// those built before them), so their checksums are those of before the field existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub embedding: Option<crate::descriptors::EmbeddingRecord>,
    /// The null of `verified`'s evidence measured when the map was built
    /// ([`crate::descriptors::null::StoredNull`], `map build`): what every process and every
    /// shard of the map tests candidates against under the config it was measured with. A commit
    /// that takes the map past double or half the size it was measured at drops it ([`write()`]).
    /// Absent in maps built without one, so their checksums are those of before the field existed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub null: Option<crate::descriptors::null::StoredNull>,
    /// The query sections of the config the map was built with, where they differ from the
    /// defaults ([`crate::config::QueryProfile`]): queries and streams without a `--config` take
    /// them ([`query_config`]). Absent in maps built with the defaults (and before the field
    /// existed), so their checksums are those of before.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub profile: Option<crate::config::QueryProfile>,
    /// SHA-256 of this manifest's content ([`Manifest::content_sha256`]): an edit by hand or a
    /// damaged byte anywhere in the file (a removed row, a config value, a model hash) is refused
    /// at open, never served.
    #[serde(default)]
    pub checksum: String,
}

/// The names of `m`'s traversals, indexed by [`SegmentEntry::traversal`]: its list, or for a map
/// of one unnamed traversal (no list) `["0"]` when it holds segments.
pub fn traversal_names(m: &Manifest) -> Vec<String> {
    let listed = m.traversals.len();
    let used = m.segments.iter().map(|s| s.traversal as usize + 1).max().unwrap_or(0);
    (0..listed.max(used)).map(|t| m.traversals.get(t).cloned().unwrap_or_else(|| t.to_string())).collect()
}

impl Manifest {
    /// Images the map serves (removed ones left out).
    pub fn live_images(&self) -> usize {
        self.segments.iter().map(SegmentEntry::live).sum()
    }
    /// Images stored in segment files, removed ones included.
    pub fn stored_images(&self) -> usize {
        self.segments.iter().map(|s| s.images).sum()
    }
    /// The file's bytes: pretty JSON with the checksum of the content.
    pub fn to_json(&self) -> serde_json::Result<Vec<u8>> {
        let m = Manifest { checksum: self.content_sha256()?, ..self.clone() };
        serde_json::to_vec_pretty(&m)
    }
    /// SHA-256 of the manifest's values without its checksum, as compact JSON (fields in their
    /// declared order, so the same values always give the same bytes).
    pub fn content_sha256(&self) -> serde_json::Result<String> {
        let m = Manifest { checksum: String::new(), ..self.clone() };
        Ok(crate::util::sha256_hex(&serde_json::to_vec(&m)?))
    }
}

/// Whether `name` is a file name the store itself writes (segments, codebook, temporary files,
/// lock, manifest): what a directory may hold for `--resume` or `--force` to treat it as a map.
pub fn is_store_file(name: &str) -> bool {
    name == MANIFEST
        || name == super::files::LOCK
        || name == CODEBOOK
        || (name.starts_with("segment-") && name.ends_with(".safetensors"))
        || (name.starts_with("index-") && name.ends_with(".safetensors"))
        || (name.starts_with('.') && name.ends_with(".tmp"))
}

/// Whether `name` is the name of a file of a map's approximate index (its model, a segment's
/// codes: `index-*.safetensors`).
pub fn is_index_file(name: &str) -> bool {
    name.starts_with("index-") && name.ends_with(".safetensors")
}

/// The files of its folder that `m` references: every segment and its index codes, the codebook,
/// the index model, and the manifest and lock themselves.
pub fn referenced_files(m: &Manifest) -> std::collections::HashSet<&str> {
    m.segments
        .iter()
        .flat_map(|s| std::iter::once(s.file.as_str()).chain(s.index.as_ref().map(|f| f.file.as_str())))
        .chain(m.codebook.as_ref().map(|c| c.file.as_str()))
        .chain(m.index.as_ref().map(|i| i.model.file.as_str()))
        .chain([MANIFEST, super::files::LOCK])
        .collect()
}

/// A segment file name for `content_name` (named by its content's hash) that no entry of
/// `segments` holds: the same images removed and added again make the same bytes, and a second
/// entry of one file would share its rows and tombstones. A taken name gets the generation that
/// commits it (new to this manifest, so not taken).
pub fn unique_segment_name(segments: &[SegmentEntry], content_name: &str, generation: u64) -> String {
    if !segments.iter().any(|s| s.file == content_name) {
        return content_name.to_string();
    }
    let stem = content_name.strip_suffix(".safetensors").unwrap_or(content_name);
    format!("{stem}-g{generation}.safetensors")
}

/// Reads and checks `dir/manifest.json`; `Ok(None)` when there is none.
pub fn read(dir: &Path) -> Result<Option<Manifest>> {
    let path = dir.join(MANIFEST);
    let f = match std::fs::File::open(&path) {
        Ok(f) => f,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(Error::io(&path, e)),
    };
    let len = f.metadata().map_err(|e| Error::io(&path, e))?.len();
    if len > MAX_MANIFEST_BYTES {
        return Err(Error::corrupt(&path, format!("manifest is {len} bytes, more than any map needs")));
    }
    let text = std::fs::read(&path).map_err(|e| Error::io(&path, e))?;
    let value: serde_json::Value = serde_json::from_slice(&text).map_err(|e| Error::corrupt(&path, format!("manifest is not valid JSON: {e}")))?;
    if value.get("format").and_then(|f| f.as_str()) != Some(FORMAT) {
        return Err(Error::corrupt(&path, format!("not a {FORMAT} manifest")));
    }
    let version = value.get("version").and_then(|v| v.as_u64()).and_then(|v| u32::try_from(v).ok()).unwrap_or(0);
    if version != VERSION {
        return Err(Error::MapVersion { path: dir.into(), found: version, supported: VERSION });
    }
    let m: Manifest = serde_json::from_value(value).map_err(|e| Error::corrupt(&path, format!("manifest fields: {e}")))?;
    match m.content_sha256() {
        Ok(sha) if sha == m.checksum => {}
        _ => {
            return Err(Error::corrupt(
                &path,
                "the manifest's checksum does not match its content (edited by hand, or damaged): restore it, or build the map again",
            ))
        }
    }
    check(&m).map_err(|e| e.named(|r| Error::corrupt(&path, r)))?;
    // the values a query is encoded and matched with, in the ranges a config file is held to
    // (a resealed edit such as `ssim_window = 0` is refused here, by open and verify alike)
    query_config(&m).validate(&path.display().to_string())?;
    Ok(Some(m))
}

/// Internal consistency of a manifest's fields.
fn check(m: &Manifest) -> Result<()> {
    if m.neighbour_slots != m.config.local.neighbours {
        return Err(Error::check("neighbour slots differ from the config"));
    }
    if m.generation == u64::MAX {
        return Err(Error::check("the generation count is at its maximum (no further commit could be numbered)"));
    }
    let names = m
        .segments
        .iter()
        .flat_map(|s| std::iter::once(s.file.as_str()).chain(s.index.as_ref().map(|i| i.file.as_str())))
        .chain(m.codebook.as_ref().map(|c| c.file.as_str()))
        .chain(m.index.as_ref().map(|i| i.model.file.as_str()));
    for name in names {
        if name.contains('/') || name.contains('\\') || name.contains("..") || !is_store_file(name) {
            return Err(Error::check(format!("file name {name:?} is not one the store writes (or leaves the map directory)")));
        }
    }
    let mut seen = std::collections::HashSet::new();
    for s in &m.segments {
        if !seen.insert(&s.file) {
            return Err(Error::check(format!("segment {} is listed twice", s.file)));
        }
        // forest and id offsets are u32
        if s.images > u32::MAX as usize - 1 || s.trees > u32::MAX as usize || s.keypoints > u32::MAX as usize {
            return Err(Error::check(format!(
                "segment {}: {} images and {} trees are more than a segment file can index",
                s.file, s.images, s.trees
            )));
        }
        if s.images == 0
            || s.removed.len() > s.images
            || !s.removed.windows(2).all(|w| w[0] < w[1])
            || s.removed.last().is_some_and(|&r| r as usize >= s.images)
        {
            return Err(Error::check(format!("segment {}: image count or removed rows are inconsistent", s.file)));
        }
        if s.sha256.len() != 64 || !s.sha256.bytes().all(|b| b.is_ascii_hexdigit()) {
            return Err(Error::check(format!("segment {}: the SHA-256 is not 64 hex digits", s.file)));
        }
    }
    match &m.index {
        Some(ix) => {
            if m.appearance_dim == 0 {
                return Err(Error::check("an index but no appearance vectors to index"));
            }
            if ix.dims == 0 || ix.dims > m.appearance_dim || ix.lists == 0 || ix.lists > u16::MAX as usize + 1 {
                return Err(Error::check(format!("index of {} dimensions and {} lists does not fit the map", ix.dims, ix.lists)));
            }
            if let Some(s) = m.segments.iter().find(|s| s.index.is_none()) {
                return Err(Error::check(format!("segment {} has no index codes, the map has an index", s.file)));
            }
        }
        None => {
            if let Some(s) = m.segments.iter().find(|s| s.index.is_some()) {
                return Err(Error::check(format!("segment {} names index codes, the map has no index", s.file)));
            }
        }
    }
    if m.appearance_dim != 0 && m.codebook.is_none() {
        return Err(Error::check("appearance vectors but no codebook"));
    }
    if (m.appearance_dim == 0) != (m.appearance_block == 0)
        || (m.appearance_block > 0 && (!m.appearance_dim.is_multiple_of(m.appearance_block) || m.appearance_dim / m.appearance_block > 256))
    {
        return Err(Error::check(format!(
            "appearance vectors of {} values do not split into blocks of {} (at most 256)",
            m.appearance_dim, m.appearance_block
        )));
    }
    Ok(())
}

/// [`read`] for a directory that must hold a map: no manifest is a not-found error naming it.
pub fn read_existing(dir: &Path) -> Result<Manifest> {
    match read(dir)? {
        Some(m) => Ok(m),
        // a folder that is there but holds no map says so, rather than "manifest.json: not found"
        None if dir.is_dir() => Err(not_a_map(dir)),
        // the OS's own "No such file or directory" (a bare ErrorKind says "entity not found")
        None => Err(Error::io(dir, std::io::Error::from_raw_os_error(NO_SUCH_FILE))),
    }
}

/// The refusal of folder `dir`, which holds no manifest, as a map: a build another process runs
/// there has committed nothing yet ([`being_built`]), or it is no map (build it, or go on with
/// its interrupted build).
pub fn not_a_map(dir: &Path) -> Error {
    match super::files::is_locked(dir) {
        true => being_built(dir),
        false => Error::refused(format!("{}", dir.display()), format!("is not a map (no {MANIFEST} in it)"), crate::error::Remedy::BuildOrResume),
    }
}

/// The refusal of map `dir` while another process builds it: the build holds the write lock and
/// has committed nothing yet (its first commit writes the manifest).
pub fn being_built(dir: &Path) -> Error {
    Error::refused(
        format!("map {}", dir.display()),
        "the map is being built by another process (nothing committed yet); wait for it to finish",
        crate::error::Remedy::WaitForBuild,
    )
}

/// The configuration queries of a map are encoded and matched with when none is given: the map's
/// encoding (appearance network included) and default matching parameters.
pub fn query_config(m: &Manifest) -> crate::config::Config {
    let cfg = crate::config::Config::default().with_encoding(&m.config);
    match &m.profile {
        Some(p) => cfg.with_profile(p),
        None => cfg,
    }
}

/// Writes the manifest atomically (the caller holds the write lock). A stored null the commit
/// takes past double or half the size it was measured at is dropped.
pub fn write(dir: &Path, m: &Manifest) -> Result<()> {
    // a null measured at another size no longer stands for the map's look-alikes
    let stale = m.null.as_ref().is_some_and(|n| !n.evidence.serves_size(n.images, m.live_images()));
    let kept;
    let m = match stale {
        true => {
            kept = Manifest { null: None, ..m.clone() };
            &kept
        }
        false => m,
    };
    let bytes = m.to_json().map_err(|e| Error::invalid(format!("map {}", dir.display()), format!("the manifest does not serialise: {e}")))?;
    super::files::write_atomic(dir, MANIFEST, &bytes)
}
