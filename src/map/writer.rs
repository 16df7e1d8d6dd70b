//! Streaming writes: [`MapWriter`] takes encoded images one at a time, checks each before it is
//! buffered, and commits a segment whenever the buffer is full, so memory stays that of one
//! segment whatever the map's size, and a crash loses at most the segment in progress.
//!
//! A commit: take the directory's advisory lock; re-read the manifest; check that the map is still
//! the one this writer started on (its uid) and that no other writer committed one of the buffered
//! ids meanwhile; write the segment file (atomic rename); write the manifest of the next
//! generation (atomic rename); release. Files are only ever added by renames, and the manifest is
//! replaced last, so every reader sees a whole generation.

use super::files::{write_atomic, WriteLock};
use super::manifest::{self, FileEntry, Manifest, SegmentEntry, CODEBOOK, FORMAT, VERSION};
use super::segment::{self, Layout, Mapped};
use super::Map;
use crate::classes::ClassTable;
use crate::config::EncodingConfig;
use crate::descriptors::{validate, DescriptorSet, EncodedImage};
use crate::error::{Error, Remedy, Result};
use crate::global::vlad::Codebook;
use crate::util::sha256_hex;
use crate::values::{ValueType, Values};
use std::collections::{HashMap, HashSet};
use std::hash::{Hash, Hasher};
use std::path::{Path, PathBuf};

/// Most images per segment file: a few thousand keeps the manifest short (a few hundred entries
/// for a million images) and one segment's buffer small (about 50 MB of f32 global descriptors).
pub const SEGMENT_IMAGES: usize = 4096;
/// Largest segment buffer: with appearance (4 kB per tree) or HOG (140 kB per image), fewer
/// images than [`SEGMENT_IMAGES`] fill a segment, so memory stays bounded either way.
pub const SEGMENT_BYTES: usize = 64 << 20;

/// How a writer stores what it is given.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StoreOptions {
    /// Storage type of global descriptors and appearance vectors (new maps; an existing map keeps
    /// its own).
    pub values: ValueType,
    /// Most images per segment file.
    pub segment_images: usize,
    /// Most bytes per segment file (approximately: the buffer is committed once it exceeds it).
    pub segment_bytes: usize,
}

impl Default for StoreOptions {
    fn default() -> Self {
        StoreOptions { values: ValueType::F32, segment_images: SEGMENT_IMAGES, segment_bytes: SEGMENT_BYTES }
    }
}

/// Values per image of the map's vector columns: its trees' and image's appearance, its HOG
/// descriptor and its verification keypoints' descriptors (0: none of that column).
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct ColumnDims {
    /// Values per appearance vector (trees' and image's).
    pub appearance: usize,
    /// Values per HOG descriptor.
    pub hog: usize,
    /// Values per verification keypoint descriptor.
    pub keypoints: usize,
    /// Values per compact HOG (maps of small frames; [`crate::global::hog::COMPACT_HOG_DIM`]).
    pub compact_hog: usize,
}

/// Which traversal (a run of frames in order, `Manifest::traversals`) a writer's images join.
/// Resolved against the manifest under the lock of the writer's first commit, so that two writers
/// starting at once each get their own.
#[derive(Debug, Clone, PartialEq, Eq, Default)]
pub enum TraversalPlan {
    /// A new traversal, named by its number (what `map build` and `map add` start).
    #[default]
    New,
    /// The traversal of this name: continued if the map holds it, else started under the name.
    Named(String),
    /// The map's last traversal (an interrupted add resumed; a stream that keeps adding frames).
    Last,
}

/// Hash of an id for the set of known ids (8 bytes per image instead of the id itself; a hit is
/// confirmed against the stored ids before it counts).
fn id_hash(id: &str) -> u64 {
    let mut h = std::hash::DefaultHasher::new();
    id.hash(&mut h);
    h.finish()
}

/// Writes images into a new or an existing map, segment by segment.
pub struct MapWriter {
    dir: PathBuf,
    layout: Layout,
    /// The last manifest this writer committed or read (for a new map: the one it will commit).
    manifest: Manifest,
    /// For a map not committed yet: the codebook file to write with the first commit.
    first: Option<Option<(Vec<u8>, FileEntry)>>,
    /// Hashes of the live ids stored or buffered.
    known: HashSet<u64>,
    /// Segment files whose ids are in `known`.
    seen: HashSet<String>,
    pending: DescriptorSet,
    opts: StoreOptions,
    committed: usize,
    plan: TraversalPlan,
    /// The traversal this writer's segments join, once its first commit resolved `plan`.
    traversal: Option<u32>,
    /// The index model of the map (its SHA-256 and the model), once a commit needed it.
    index_model: Option<(String, crate::index::Model)>,
    /// A new map's write lock, held from its creation to its first commit: a reader of the
    /// folder meanwhile is told that a build is running there (`manifest::read_existing`).
    held: Option<WriteLock>,
    /// Seconds between this writer's frames, stored for its traversal at each commit.
    frame_interval: Option<f64>,
}

impl MapWriter {
    /// A writer for a new map in `dir`, which must not exist, or be empty, or (with `resume`) hold
    /// only files an interrupted build left (no manifest). With appearance, `appearance` gives the
    /// VLAD codebook and the keypoint network's SHA-256, both stored with the first commit. Holds
    /// the folder's write lock until its first commit (a build another process runs in `dir` is
    /// refused, and readers of `dir` are told one runs there).
    pub fn create(
        dir: &Path,
        cfg: &EncodingConfig,
        dims: ColumnDims,
        appearance: Option<(&Codebook, &str)>,
        opts: StoreOptions,
        resume: bool,
    ) -> Result<MapWriter> {
        let ColumnDims { appearance: appearance_dim, hog: hog_dim, keypoints: keypoint_dim, compact_hog: compact_hog_dim } = dims;
        let what = || format!("map {}", dir.display());
        MapWriter::check_new_dir(dir, resume)?;
        let codebook = match (appearance, appearance_dim) {
            (Some((cb, _)), d) if cb.k * cb.dim != d => return Err(Error::invalid(what(), "codebook size differs from the appearance vectors")),
            (None, d) if d != 0 => return Err(Error::invalid(what(), "appearance vectors without a codebook")),
            (Some((cb, _)), _) => {
                let bytes = cb.file_bytes().map_err(|e| e.named(|r| Error::invalid(what(), r)))?;
                let entry = FileEntry { file: CODEBOOK.into(), bytes: bytes.len() as u64, sha256: sha256_hex(&bytes) };
                Some((bytes, entry))
            }
            (None, _) => None,
        };
        std::fs::create_dir_all(dir).map_err(|e| Error::io(dir, e))?;
        let held = WriteLock::try_take(dir)?.ok_or_else(|| manifest::being_built(dir))?;
        let n_classes = ClassTable::from_config(&cfg.classes)?.len();
        let manifest = Manifest {
            format: FORMAT.into(),
            version: VERSION,
            generation: 0,
            uid: sha256_hex(super::files::unique_suffix().as_bytes())[..16].to_string(),
            created_by: format!("semlook {}", env!("CARGO_PKG_VERSION")),
            config: cfg.clone(),
            neighbour_slots: cfg.local.neighbours,
            appearance_dim,
            hog_dim,
            compact_hog_dim,
            keypoint_dim,
            appearance_block: appearance.map_or(0, |(cb, _)| cb.dim),
            values: opts.values,
            segments: vec![],
            codebook: None,
            appearance_model: appearance.map(|(_, sha)| sha.to_string()),
            without_labels: false,
            traversals: vec![],
            frame_intervals: Default::default(),
            index: None,
            embedding: None,
            null: None,
            profile: None,
            checksum: String::new(),
        };
        let layout = super::layout_of(&manifest, n_classes);
        let pending = layout.storage_set();
        Ok(MapWriter {
            dir: dir.into(),
            layout,
            manifest,
            first: Some(codebook),
            known: HashSet::new(),
            seen: HashSet::new(),
            pending,
            opts,
            committed: 0,
            plan: TraversalPlan::New,
            traversal: None,
            index_model: None,
            held: Some(held),
            frame_interval: None,
        })
    }

    /// Which traversal the images written join (default: a new one). Before the first commit; a
    /// name must be 1 to 200 characters, none of them a control character.
    pub fn with_traversal(mut self, plan: TraversalPlan) -> Result<MapWriter> {
        if let TraversalPlan::Named(n) = &plan {
            if n.is_empty() || n.chars().count() > 200 || n.chars().any(char::is_control) {
                return Err(Error::invalid(format!("traversal name {n:?}"), "must be 1 to 200 characters, none of them a control character"));
            }
        }
        if self.traversal.is_some() {
            return Err(Error::invalid(format!("map {}", self.dir.display()), "the traversal is chosen before the first commit"));
        }
        self.plan = plan;
        Ok(self)
    }

    /// The seconds between consecutive frames of the traversal the images join (the median step
    /// of their timestamps), stored in the manifest with each commit
    /// ([`Manifest::frame_intervals`]); it replaces what the traversal had.
    pub fn with_frame_interval(mut self, seconds: f64) -> Result<MapWriter> {
        self.set_frame_interval(seconds)?;
        Ok(self)
    }

    /// [`MapWriter::with_frame_interval`] on a writer in use (a stream that measures its rate as
    /// it goes): from the next commit on.
    pub fn set_frame_interval(&mut self, seconds: f64) -> Result<()> {
        if !(seconds > 0.0 && seconds.is_finite()) {
            return Err(Error::invalid(format!("map {}", self.dir.display()), format!("a frame interval of {seconds} s (must be positive)")));
        }
        self.frame_interval = Some(seconds);
        Ok(())
    }

    /// The traversal the committed images joined (after the first commit).
    pub fn traversal(&self) -> Option<u32> {
        self.traversal
    }

    /// The id of the traversal `self.plan` names in `m`, adding it to `m`'s names when new; the
    /// same id for every later commit of this writer.
    fn resolve_traversal(&mut self, m: &mut Manifest) -> u32 {
        if let Some(t) = self.traversal {
            return t;
        }
        // a map of one unnamed traversal lists no names: its images are traversal "0"
        let mut names = manifest::traversal_names(m);
        let t = match &self.plan {
            TraversalPlan::Last if !names.is_empty() => names.len() - 1,
            TraversalPlan::Named(n) => names.iter().position(|x| x == n).unwrap_or_else(|| {
                names.push(n.clone());
                names.len() - 1
            }),
            _ => {
                let name = (names.len()..).map(|k| k.to_string()).find(|c| !names.contains(c)).unwrap_or_default();
                names.push(name);
                names.len() - 1
            }
        };
        m.traversals = if names.len() == 1 && names[0] == "0" { vec![] } else { names };
        self.traversal = Some(t as u32);
        t as u32
    }

    /// Marks a new map as encoded without semantic labels ([`Manifest::without_labels`]): its
    /// frames had neither label maps nor a segmenter. Only before the first commit.
    pub fn without_labels(mut self) -> Result<MapWriter> {
        if self.first.is_none() {
            return Err(Error::invalid(format!("map {}", self.dir.display()), "a stored map's labels cannot be changed"));
        }
        self.manifest.without_labels = true;
        Ok(self)
    }

    /// A new map whose images carry whole-image embeddings made by the network `rec` records
    /// (none: without embeddings). Only before the first commit.
    pub fn with_embedding(mut self, rec: Option<super::EmbeddingRecord>) -> Result<MapWriter> {
        if self.first.is_none() {
            return Err(Error::invalid(format!("map {}", self.dir.display()), "a stored map's embeddings cannot be changed"));
        }
        if rec.as_ref().is_some_and(|r| r.dim == 0) {
            return Err(Error::invalid(format!("map {}", self.dir.display()), "an embedding network of width 0"));
        }
        self.manifest.embedding = rec;
        self.layout.emb = self.manifest.embedding.as_ref().map_or(0, |e| e.dim);
        self.pending = self.layout.storage_set();
        Ok(self)
    }

    /// A new map that keeps `cfg`'s query sections where they differ from the defaults
    /// ([`crate::config::Config::profile`]): its queries and streams take them as their defaults.
    /// Only before the first commit.
    pub fn with_profile(mut self, cfg: &crate::config::Config) -> Result<MapWriter> {
        if self.first.is_none() {
            return Err(Error::invalid(format!("map {}", self.dir.display()), "a stored map's profile cannot be changed"));
        }
        self.manifest.profile = cfg.profile();
        Ok(self)
    }

    /// Fails unless a new map may be created in `dir`: it does not exist, or is empty, or (with
    /// `resume`) holds only files an interrupted build left and no manifest.
    pub fn check_new_dir(dir: &Path, resume: bool) -> Result<()> {
        let what = || format!("map {}", dir.display());
        if manifest::read(dir)?.is_some() {
            return Err(Error::refused(what(), "a map already exists there", Remedy::AddResumeOrReplace));
        }
        // the files there are a running build's, not an interrupted one's
        if super::files::is_locked(dir) {
            return Err(manifest::being_built(dir));
        }
        if dir.exists() {
            let entries: Vec<String> =
                std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
            if let Some(other) = entries.iter().find(|n| !manifest::is_store_file(n)) {
                return Err(Error::invalid(what(), format!("directory exists and holds {other:?}, which is not a map file")));
            }
            if !entries.is_empty() && !resume {
                return Err(Error::refused(what(), "directory exists and is not empty (an interrupted build?)", Remedy::ResumeOrReplace));
            }
        }
        Ok(())
    }

    /// A writer that appends to the map in `dir` (its storage type applies; `opts.values` is
    /// ignored). Reads the ids of every stored segment (not their checksums).
    pub fn append(dir: &Path, opts: StoreOptions) -> Result<MapWriter> {
        if manifest::read(dir)?.is_none() {
            return Err(manifest::not_a_map(dir));
        }
        // read without the lock: a compaction may delete a listed segment meanwhile
        super::with_current_manifest(dir, |manifest| {
            let n_classes = ClassTable::from_config(&manifest.config.classes)?.len();
            let layout = super::layout_of(&manifest, n_classes);
            let pending = layout.storage_set();
            let mut w = MapWriter {
                dir: dir.into(),
                layout,
                first: None,
                known: HashSet::new(),
                seen: HashSet::new(),
                pending,
                opts: StoreOptions { values: manifest.values, ..opts },
                committed: 0,
                plan: TraversalPlan::New,
                traversal: None,
                index_model: None,
                held: None,
                frame_interval: None,
                manifest,
            };
            let segments = w.manifest.segments.clone();
            w.learn(&segments, &HashSet::new())?;
            Ok(w)
        })
    }

    /// Adds the live ids of `segments` not seen yet to the known ids; fails if one of them is in
    /// `buffered` (another writer committed it meanwhile).
    fn learn(&mut self, segments: &[SegmentEntry], buffered: &HashSet<&str>) -> Result<()> {
        for entry in segments {
            if self.seen.contains(&entry.file) {
                continue;
            }
            let seg = Mapped::open(&self.dir, entry, self.layout)?;
            for j in 0..seg.len() {
                if !entry.is_live(j) {
                    continue;
                }
                let id = seg.id(j);
                if buffered.contains(id) {
                    return Err(Error::DuplicateImageId { map: self.dir.clone(), id: id.to_string() });
                }
                self.known.insert(id_hash(id));
            }
            self.seen.insert(entry.file.clone());
        }
        Ok(())
    }

    /// The map directory.
    pub fn dir(&self) -> &Path {
        &self.dir
    }
    /// Sizes of the map's columns.
    pub fn layout(&self) -> Layout {
        self.layout
    }
    /// The last manifest this writer committed or read (for a new map: the one it will commit).
    pub fn manifest(&self) -> &Manifest {
        &self.manifest
    }
    /// Images committed by this writer so far.
    pub fn committed(&self) -> usize {
        self.committed
    }
    /// Images per segment this writer aims at.
    pub fn segment_images(&self) -> usize {
        self.opts.segment_images.max(1)
    }

    /// Whether image `id` is stored (and not removed) or buffered.
    pub fn contains(&self, id: &str) -> bool {
        self.known.contains(&id_hash(id)) && (self.pending.ids.iter().any(|p| p == id) || self.stored(id))
    }

    /// The ids among `ids` that are stored and not removed, exactly (one pass over the stored
    /// ids when any hash matches): what `--resume` skips.
    pub fn stored_among<'a>(&self, ids: impl IntoIterator<Item = &'a str>) -> HashSet<String> {
        let candidates: HashSet<&str> = ids.into_iter().filter(|id| self.known.contains(&id_hash(id))).collect();
        let mut found: HashSet<String> = self.pending.ids.iter().filter(|id| candidates.contains(id.as_str())).cloned().collect();
        if candidates.is_empty() {
            return found;
        }
        for e in self.manifest.segments.iter().filter(|e| self.seen.contains(&e.file)) {
            if let Ok(seg) = Mapped::open(&self.dir, e, self.layout) {
                for j in 0..seg.len() {
                    if e.is_live(j) && candidates.contains(seg.id(j)) {
                        found.insert(seg.id(j).to_string());
                    }
                }
            }
        }
        found
    }

    /// Whether a committed segment this writer knows holds live image `id` (the slow, exact check
    /// behind a hash hit).
    fn stored(&self, id: &str) -> bool {
        self.manifest.segments.iter().filter(|e| self.seen.contains(&e.file)).any(|e| match Mapped::open(&self.dir, e, self.layout) {
            Ok(seg) => (0..seg.len()).any(|j| seg.id(j) == id && e.is_live(j)),
            Err(_) => false,
        })
    }

    /// Checks an image and buffers it; commits a segment when the buffer is full. An image with a
    /// bad value (NaN, infinity, out of range) or a stored id is refused, naming it, before it
    /// joins the buffer.
    pub fn push(&mut self, img: &EncodedImage) -> Result<()> {
        let f = img.forest.as_ref();
        let app = if img.appearance.is_empty() { Values::F32(&[]) } else { Values::F32(&img.appearance) };
        validate::image(&img.id, [img.width, img.height], Values::F32(&img.global), f, app, &img.hog, self.layout.n_classes, self.opts.values)
            .and_then(|()| validate::keypoints(img.keypoints.as_ref(), self.layout.n_classes))
            .and_then(|()| validate::embedding(Values::F32(&img.embedding)))
            .and_then(|()| match img.embedding.len() == self.layout.emb {
                true => Ok(()),
                false => Err(Error::check(format!("an embedding of {} values, the map's have {}", img.embedding.len(), self.layout.emb))),
            })
            .and_then(|()| validate::compact_hog(Values::F32(&img.compact_hog)))
            .and_then(|()| match img.compact_hog.len() == self.layout.chog {
                true => Ok(()),
                false => Err(Error::check(format!("a compact HOG of {} values, the map's have {}", img.compact_hog.len(), self.layout.chog))),
            })
            .and_then(|()| img.pose.map_or(Ok(()), |p| validate::pose_row(&p.to_row())))
            .map_err(|e| e.named(|reason| Error::InvalidImage { id: img.id.clone(), reason }))?;
        if self.contains(&img.id) {
            return Err(Error::DuplicateImageId { map: self.dir.clone(), id: img.id.clone() });
        }
        self.pending.push(img).map_err(|e| e.named(|r| Error::invalid(format!("map {}", self.dir.display()), r)))?;
        self.known.insert(id_hash(&img.id));
        self.flush_if_full()
    }

    /// Adds every image of `set` (same layout): all are checked first (values, ids), so a refused
    /// set writes nothing.
    pub fn push_set(&mut self, set: &DescriptorSet) -> Result<()> {
        let l = &self.layout;
        if set.global_len != l.global_len()
            || set.neighbour_slots != l.slots
            || set.appearance_dim != l.dim
            || set.hog_dim != l.hog
            || set.keypoint_dim != l.kdim
            || set.embedding_dim != l.emb
            || set.compact_hog_dim != l.chog
        {
            return Err(Error::invalid(
                format!("map {}", self.dir.display()),
                format!(
                    "new images have {} global values / {} neighbour slots / appearance dim {} / HOG dim {} / keypoint dim {} / embedding dim {} / compact HOG dim {}, the map {} / {} / {} / {} / {} / {} / {}",
                    set.global_len,
                    set.neighbour_slots,
                    set.appearance_dim,
                    set.hog_dim,
                    set.keypoint_dim,
                    set.embedding_dim,
                    set.compact_hog_dim,
                    l.global_len(),
                    l.slots,
                    l.dim,
                    l.hog,
                    l.kdim,
                    l.emb,
                    l.chog
                ),
            ));
        }
        let map_codebook = self
            .manifest
            .codebook
            .as_ref()
            .map(|c| c.sha256.clone())
            .or_else(|| self.first.as_ref().and_then(|f| f.as_ref().map(|(_, e)| e.sha256.clone())));
        if set.appearance_dim > 0 && set.codebook != map_codebook {
            let show = |v: &Option<String>| v.clone().map_or("none".into(), |s| format!("sha256 {s}"));
            return Err(Error::IncompatibleConfig {
                map: self.dir.clone(),
                field: "VLAD codebook of the appearance vectors".into(),
                map_value: show(&map_codebook),
                given_value: show(&set.codebook),
            });
        }
        if let (Some(map), true) = (&self.manifest.embedding, set.embedding_dim > 0) {
            if !set.embedding.as_ref().is_some_and(|given| given.same_network(map)) {
                let show = |r: &crate::descriptors::EmbeddingRecord| {
                    format!("{} sha256 {} ({} values, long side {})", r.network, r.sha256, r.dim, r.long_side)
                };
                return Err(Error::IncompatibleConfig {
                    map: self.dir.clone(),
                    field: "embedding network".into(),
                    map_value: show(map),
                    given_value: set.embedding.as_ref().map_or_else(|| "embeddings of no recorded network".into(), show),
                });
            }
        }
        let mut ids = HashMap::new();
        for i in 0..set.len() {
            set.check_image(i, l.n_classes, self.opts.values)
                .map_err(|e| e.named(|reason| Error::InvalidImage { id: set.ids[i].clone(), reason }))?;
            if let Some(first) = ids.insert(set.ids[i].as_str(), i) {
                return Err(Error::RepeatedImageId { map: self.dir.clone(), id: set.ids[i].clone(), first, second: i });
            }
            if self.contains(&set.ids[i]) {
                return Err(Error::DuplicateImageId { map: self.dir.clone(), id: set.ids[i].clone() });
            }
        }
        for i in 0..set.len() {
            self.pending.extend_from(set, i, i + 1);
            self.known.insert(id_hash(&set.ids[i]));
            self.flush_if_full()?;
        }
        Ok(())
    }

    fn flush_if_full(&mut self) -> Result<()> {
        let bytes = self.pending.len() * self.layout.image_bytes()
            + self.pending.n_trees() * self.layout.tree_bytes()
            + self.pending.n_keypoints() * self.layout.keypoint_bytes();
        if self.pending.len() >= self.segment_images() || bytes >= self.opts.segment_bytes {
            self.flush()?;
        }
        Ok(())
    }

    /// Commits the buffered images as one segment (nothing when the buffer is empty).
    pub fn flush(&mut self) -> Result<()> {
        if self.pending.is_empty() {
            return Ok(());
        }
        let (bytes, entry) =
            segment::encode(&self.pending, &self.layout).map_err(|e| e.named(|r| Error::invalid(format!("map {}", self.dir.display()), r)))?;
        let ids: Vec<String> = self.pending.ids.clone();
        let (dir, layout) = (self.dir.clone(), self.layout);
        let mut cache = self.index_model.take();
        let file = self.commit(
            |m, file, traversal| {
                if let Some(file) = file {
                    let mut e = SegmentEntry { file: file.to_string(), traversal, ..entry.clone() };
                    // a map with an index: the segment's codes, under the model the manifest
                    // names now (another writer may have rebuilt it meanwhile)
                    if let Some(ix) = m.index.clone() {
                        e.index = Some(super::index_files::write_segment_codes(&dir, m, &ix, &e, layout, &mut cache)?);
                    }
                    m.segments.push(e);
                }
                Ok(())
            },
            Some((&entry.file, &bytes)),
            &ids,
        );
        self.index_model = cache;
        let file = file?;
        self.seen.extend(file);
        self.committed += self.pending.len();
        self.pending = self.pending.empty_like();
        Ok(())
    }

    /// One commit under the lock: `file` (content name, bytes) written first under a name no
    /// listed segment holds, then `change` applied to the current manifest with that name, which
    /// is returned.
    fn commit(
        &mut self,
        change: impl FnOnce(&mut Manifest, Option<&str>, u32) -> Result<()>,
        file: Option<(&str, &[u8])>,
        buffered: &[String],
    ) -> Result<Option<String>> {
        // a new map's first commit under the lock it holds since its creation
        let _lock = match self.held.take() {
            Some(held) => held,
            None => WriteLock::take(&self.dir)?,
        };
        let what = || format!("map {}", self.dir.display());
        let mut m = match (manifest::read(&self.dir)?, &self.first) {
            (None, Some(codebook)) => {
                let mut m = self.manifest.clone();
                if let Some((bytes, entry)) = codebook {
                    write_atomic(&self.dir, &entry.file, bytes)?;
                    m.codebook = Some(entry.clone());
                }
                m
            }
            (Some(_), Some(_)) => return Err(Error::invalid(what(), "another process created a map there while this build ran")),
            (None, None) => return Err(Error::invalid(what(), "the map's manifest is gone (removed or replaced while writing)")),
            (Some(m), None) if m.uid != self.manifest.uid => {
                return Err(Error::invalid(what(), "the map was replaced (rebuilt) while this writer ran"))
            }
            (Some(m), None) => m,
        };
        let buffered: HashSet<&str> = buffered.iter().map(|s| s.as_str()).collect();
        let others = m.segments.clone();
        self.learn(&others, &buffered)?;
        let name = file.map(|(content_name, _)| manifest::unique_segment_name(&m.segments, content_name, m.generation + 1));
        if let (Some(name), Some((_, bytes))) = (&name, file) {
            write_atomic(&self.dir, name, bytes)?;
        }
        let traversal = self.resolve_traversal(&mut m);
        if let Some(s) = self.frame_interval {
            m.frame_intervals.insert(traversal, s);
        }
        change(&mut m, name.as_deref(), traversal)?;
        m.generation += 1;
        manifest::write(&self.dir, &m)?;
        self.manifest = m;
        self.first = None;
        Ok(name)
    }

    /// Commits what is buffered and opens the map. A new map that received no image is committed
    /// empty (with its codebook), so that it exists.
    pub fn finish(mut self) -> Result<Map> {
        self.flush()?;
        if self.first.is_some() {
            self.commit(|_, _, _| Ok(()), None, &[])?;
        }
        Map::open(&self.dir)
    }
}

impl Map {
    /// Creates a new map directory holding `set` (f32, default segments). With appearance,
    /// `appearance` gives the VLAD codebook and the SHA-256 of the keypoint network, both recorded
    /// in the map. Fails if `dir` exists and is not empty; every image is checked first, so a
    /// refused set creates nothing.
    pub fn create(dir: &Path, cfg: &EncodingConfig, set: &DescriptorSet, appearance: Option<(&Codebook, &str)>) -> Result<Map> {
        Map::create_with(dir, cfg, set, appearance, StoreOptions::default())
    }

    /// [`Map::create`] with storage options.
    pub fn create_with(
        dir: &Path,
        cfg: &EncodingConfig,
        set: &DescriptorSet,
        appearance: Option<(&Codebook, &str)>,
        opts: StoreOptions,
    ) -> Result<Map> {
        let n_classes = ClassTable::from_config(&cfg.classes)?.len();
        let mut ids = HashMap::new();
        for i in 0..set.len() {
            set.check_image(i, n_classes, opts.values).map_err(|e| e.named(|reason| Error::InvalidImage { id: set.ids[i].clone(), reason }))?;
            if let Some(first) = ids.insert(&set.ids[i], i) {
                return Err(Error::RepeatedImageId { map: dir.into(), id: set.ids[i].clone(), first, second: i });
            }
        }
        let mut w = MapWriter::create(
            dir,
            cfg,
            ColumnDims { appearance: set.appearance_dim, hog: set.hog_dim, keypoints: set.keypoint_dim, compact_hog: set.compact_hog_dim },
            appearance,
            opts,
            false,
        )?
        .with_embedding(set.embedding.clone())?;
        w.push_set(set)?;
        w.finish()
    }

    /// Appends `set` as new segments and reopens the map. Every image is checked and every id
    /// compared with the stored ones before anything is written.
    pub fn add(&mut self, set: &DescriptorSet) -> Result<()> {
        self.add_in_segments(set, SEGMENT_IMAGES)
    }

    /// [`Map::add`] with at most `per_segment` images per segment file.
    pub fn add_in_segments(&mut self, set: &DescriptorSet, per_segment: usize) -> Result<()> {
        let mut w = MapWriter::append(&self.path, StoreOptions { segment_images: per_segment.max(1), ..StoreOptions::default() })?;
        w.push_set(set)?;
        let new = w.finish()?;
        new.inherit_checks(self);
        *self = new;
        Ok(())
    }
}
