//! Changing a stored map as a whole: removing images (tombstones in the manifest), compacting
//! (rewriting the segments that hold removed images or are too small), verifying every file, and
//! replacing a map by one built beside it (`build --force`). Each change is one commit under the
//! map's write lock.

use super::files::{self, write_atomic, WriteLock};
use super::manifest::{self, SegmentEntry};
use super::segment::{self, Mapped};
use super::{layout_of, writer::StoreOptions};
use crate::classes::ClassTable;
use crate::descriptors::DescriptorSet;
use crate::error::{Error, Result};
use rayon::prelude::*;
use serde::Serialize;
use std::collections::HashSet;
use std::path::Path;

/// Unknown ids named in a refused removal (the rest are counted).
const SHOW_UNKNOWN: usize = 5;

/// Removes the images `ids` (tombstones: their rows are marked in the manifest and left out of
/// every query; `compact` drops them from the files). Every id must be in the map, or nothing is
/// changed. Returns the number removed.
pub fn remove(dir: &Path, ids: &[String]) -> Result<usize> {
    let _lock = WriteLock::take(dir)?;
    let mut m = manifest::read_existing(dir)?;
    let layout = layout_of(&m, ClassTable::from_config(&m.config.classes)?.len());
    let wanted: HashSet<&str> = ids.iter().map(|s| s.as_str()).collect();
    let mut found: HashSet<String> = HashSet::new();
    let mut marks: Vec<Vec<u32>> = vec![vec![]; m.segments.len()];
    for (k, entry) in m.segments.iter().enumerate() {
        let seg = Mapped::open(dir, entry, layout)?;
        for j in 0..seg.len() {
            let id = seg.id(j);
            if wanted.contains(id) && entry.is_live(j) {
                marks[k].push(j as u32);
                found.insert(id.to_string());
            }
        }
    }
    let unknown: Vec<&str> = ids.iter().map(|s| s.as_str()).filter(|id| !found.contains(*id)).collect();
    if !unknown.is_empty() {
        let shown: Vec<String> = unknown.iter().take(SHOW_UNKNOWN).map(|s| format!("{s:?}")).collect();
        let more = unknown.len().saturating_sub(SHOW_UNKNOWN);
        let tail = if more > 0 { format!(" and {more} more") } else { String::new() };
        return Err(Error::invalid(
            format!("map {}", dir.display()),
            format!("not in the map (or removed already), nothing removed: {}{tail}", shown.join(", ")),
        ));
    }
    for (entry, new) in m.segments.iter_mut().zip(marks) {
        entry.removed.extend(new);
        entry.removed.sort_unstable();
    }
    m.generation += 1;
    manifest::write(dir, &m)?;
    Ok(found.len())
}

/// Stores `null`, measured on the map's generation `generation`, in its manifest (one commit).
/// Returns false, storing nothing, where the map has had another commit since: the null was
/// measured on references it no longer holds.
pub fn store_null(dir: &Path, generation: u64, null: crate::descriptors::null::NullEvidence) -> Result<bool> {
    let _lock = WriteLock::take(dir)?;
    let mut m = manifest::read_existing(dir)?;
    if m.generation != generation {
        return Ok(false);
    }
    m.null = Some(crate::descriptors::null::StoredNull { images: m.live_images(), evidence: null });
    m.generation += 1;
    manifest::write(dir, &m)?;
    Ok(true)
}

/// What `compact` did.
#[derive(Debug, Clone, Serialize)]
pub struct CompactReport {
    /// Segment files before compacting.
    pub segments_before: usize,
    /// Segment files after compacting.
    pub segments_after: usize,
    /// Removed images dropped from the files.
    pub dropped: usize,
    /// Bytes of the segment files before compacting.
    pub bytes_before: u64,
    /// Bytes of the segment files after compacting.
    pub bytes_after: u64,
    /// Files deleted that no manifest referenced (left by interrupted writers).
    pub stray_files: usize,
}

/// Rewrites the segments that hold removed images, merging runs of small segments (below half of
/// `opts`' segment size) into full ones, in order; leaves the others as they are. Every rewritten
/// segment is verified first: a damaged one stops the compaction, naming it, before anything is
/// committed. Then deletes the replaced files and any store file no manifest references. Holds the
/// write lock throughout (writers wait, see [`files::LOCK_WAIT`]).
pub fn compact(dir: &Path, opts: StoreOptions) -> Result<CompactReport> {
    let _lock = WriteLock::take(dir)?;
    let old = manifest::read_existing(dir)?;
    let layout = layout_of(&old, ClassTable::from_config(&old.config.classes)?.len());
    let small = |e: &SegmentEntry| e.live() * 2 < opts.segment_images && (e.bytes as usize) * 2 < opts.segment_bytes;
    let mut out: Vec<SegmentEntry> = Vec::new();
    let mut buf = layout.storage_set();
    let mut run: Vec<&SegmentEntry> = Vec::new();
    let model = std::cell::RefCell::new(None);
    let flush = |buf: &mut DescriptorSet, out: &mut Vec<SegmentEntry>, traversal: u32| -> Result<()> {
        if buf.is_empty() {
            return Ok(());
        }
        let (bytes, mut entry) = segment::encode(buf, &layout).map_err(|e| e.named(|r| Error::invalid(format!("map {}", dir.display()), r)))?;
        // unique among the files kept, written, and replaced (deleted after the commit)
        let listed: Vec<SegmentEntry> = out.iter().chain(&old.segments).cloned().collect();
        entry.file = manifest::unique_segment_name(&listed, &entry.file, old.generation + 1);
        entry.traversal = traversal;
        write_atomic(dir, &entry.file, &bytes)?;
        // a map with an index: the new segment's codes under the same model
        if let Some(ix) = &old.index {
            entry.index = Some(super::index_files::write_segment_codes(dir, &old, ix, &entry, layout, &mut model.borrow_mut())?);
        }
        out.push(entry);
        *buf = buf.empty_like();
        Ok(())
    };
    // a run of segments of one traversal to rewrite, flushed when a segment to keep or another
    // traversal's follows (order is kept, and no segment mixes traversals)
    let rewrite = |run: &mut Vec<&SegmentEntry>, buf: &mut DescriptorSet, out: &mut Vec<SegmentEntry>| -> Result<()> {
        let Some(traversal) = run.first().map(|e| e.traversal) else { return Ok(()) };
        if run.len() == 1 && run[0].removed.is_empty() {
            out.push(run[0].clone());
        } else {
            for entry in run.iter() {
                let seg = Mapped::open(dir, entry, layout)?;
                seg.ensure()?;
                for j in 0..seg.len() {
                    if entry.is_live(j) {
                        seg.append_row(j, buf);
                        if buf.len() >= opts.segment_images
                            || buf.len() * layout.image_bytes() + buf.n_trees() * layout.tree_bytes() >= opts.segment_bytes
                        {
                            flush(buf, out, traversal)?;
                        }
                    }
                }
            }
            flush(buf, out, traversal)?;
        }
        run.clear();
        Ok(())
    };
    for entry in &old.segments {
        if run.first().is_some_and(|r| r.traversal != entry.traversal) {
            rewrite(&mut run, &mut buf, &mut out)?;
        }
        if entry.removed.is_empty() && !small(entry) {
            rewrite(&mut run, &mut buf, &mut out)?;
            out.push(entry.clone());
        } else {
            run.push(entry);
        }
    }
    rewrite(&mut run, &mut buf, &mut out)?;
    let mut m = old.clone();
    // nothing rewritten: the same generation (readers' caches stay valid)
    if out != old.segments {
        m.segments = out;
        m.generation += 1;
        manifest::write(dir, &m)?;
    }
    // delete what the new manifest does not reference: replaced segments and strays
    let keep: HashSet<&str> = manifest::referenced_files(&m);
    let replaced: HashSet<&str> =
        old.segments.iter().flat_map(|s| std::iter::once(s.file.as_str()).chain(s.index.as_ref().map(|f| f.file.as_str()))).collect();
    let mut stray = 0;
    for e in std::fs::read_dir(dir).map_err(|e| Error::io(dir, e))?.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        if manifest::is_store_file(&name) && !keep.contains(name.as_str()) {
            stray += usize::from(!replaced.contains(name.as_str()));
            std::fs::remove_file(e.path()).map_err(|err| Error::io(e.path(), err))?;
        }
    }
    files::sync_dir(dir);
    Ok(CompactReport {
        segments_before: old.segments.len(),
        segments_after: m.segments.len(),
        dropped: old.segments.iter().map(|s| s.removed.len()).sum(),
        bytes_before: old.segments.iter().map(|s| s.bytes).sum(),
        bytes_after: m.segments.iter().map(|s| s.bytes).sum(),
        stray_files: stray,
    })
}

/// The check of one file.
#[derive(Debug, Clone, Serialize)]
pub struct FileCheck {
    /// File name, in the map folder.
    pub file: String,
    /// What is wrong with it; `None` when sound.
    pub problem: Option<String>,
}

/// What `verify` found.
#[derive(Debug, Clone, Serialize)]
pub struct VerifyReport {
    /// The manifest's generation.
    pub generation: u64,
    /// Images of the map, removed ones left out.
    pub images: usize,
    /// The check of every segment file, then of the codebook.
    pub files: Vec<FileCheck>,
    /// Temporary files and staging folders interrupted writers left ([`files::leftovers`]); the
    /// next writer removes them under the lock.
    pub leftovers: Vec<String>,
    /// Store files in the map folder (segments, index files, a codebook) that the manifest does
    /// not reference: left by a write that failed after writing them (a writer commits them
    /// under the lock, so one committing while `verify` runs may be listed too); `compact`
    /// deletes them.
    pub unreferenced: Vec<String>,
    /// SHA-256 of the keypoint network the map's appearance was computed with (queries must use
    /// the same), and how it is configured.
    pub appearance_model: Option<String>,
    /// The kind of keypoint network the map's configuration names.
    pub appearance_kind: crate::config::AppearanceModelKind,
    /// The network that made the map's whole-image embeddings (queries must use the same file).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub embedding: Option<crate::descriptors::EmbeddingRecord>,
}

impl VerifyReport {
    /// The files found damaged.
    pub fn damaged(&self) -> impl Iterator<Item = &FileCheck> {
        self.files.iter().filter(|f| f.problem.is_some())
    }
    /// Whether files are damaged and every one of them belongs to the map's approximate index
    /// (building the index again or dropping it mends the map).
    pub fn only_index_damaged(&self) -> bool {
        self.damaged().count() > 0 && self.damaged().all(|f| manifest::is_index_file(&f.file) || f.file == INDEX_ENTRY)
    }
}

/// The report's name for the index as a whole, where it fails to open and no file of it names why.
pub const INDEX_ENTRY: &str = "index";

/// What is wrong with a file, without the "map X: corrupt:" the report adds once.
fn reason_of(e: Error) -> String {
    match e {
        Error::CorruptMap { reason, .. } | Error::DamagedIndex { reason, .. } => reason,
        other => other.to_string(),
    }
}

/// The store files (segments, index files, a codebook) in `dir` that neither `m` nor the manifest
/// there now references, sorted.
fn unreferenced(dir: &Path, m: &manifest::Manifest) -> Result<Vec<String>> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map_err(|e| Error::io(dir, e))?
        .flatten()
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| manifest::is_store_file(n) && !n.starts_with('.'))
        .collect();
    // a writer that committed since `m` was read references its new files in the manifest now
    let now = manifest::read(dir).ok().flatten();
    let (then, now) = (manifest::referenced_files(m), now.as_ref().map(manifest::referenced_files).unwrap_or_default());
    names.retain(|n| !then.contains(n.as_str()) && !now.contains(n.as_str()));
    names.sort();
    Ok(names)
}

/// Checks every file of the map in full (in parallel): the codebook, and each segment's header,
/// size, SHA-256 and values, the index's model and codes. Reports every damaged file, not just
/// the first, and lists what interrupted or failed writes left (leftovers, unreferenced files).
pub fn verify(dir: &Path) -> Result<VerifyReport> {
    let m = manifest::read_existing(dir)?;
    let layout = layout_of(&m, ClassTable::from_config(&m.config.classes)?.len());
    let mut files: Vec<FileCheck> = m
        .segments
        .par_iter()
        .map(|entry| {
            let problem = match Mapped::open(dir, entry, layout) {
                Ok(seg) => seg.verify().err().map(reason_of),
                Err(e) => Some(reason_of(e)),
            };
            FileCheck { file: entry.file.clone(), problem }
        })
        .collect();
    if let Some(entry) = &m.codebook {
        let problem = super::read_codebook(dir, entry, m.appearance_dim).err().map(reason_of);
        files.push(FileCheck { file: entry.file.clone(), problem });
    }
    if let Some(ix) = &m.index {
        // the model, then each segment's codes (header, segment and model named, SHA-256, values)
        match super::index_files::MapIndex::open(dir, &m) {
            Ok(Some(index)) => {
                files.push(FileCheck { file: ix.model.file.clone(), problem: None });
                for (path, r) in index.verify_all() {
                    files.push(FileCheck {
                        file: path.file_name().map_or(String::new(), |f| f.to_string_lossy().into_owned()),
                        problem: r.err().map(reason_of),
                    });
                }
            }
            Ok(None) => {}
            Err(e) => {
                // name the file that failed to open, then check the others one by one
                let why = reason_of(e);
                files.push(FileCheck { file: ix.model.file.clone(), problem: super::index_files::model_problem(dir, &m).err().map(reason_of) });
                for s in &m.segments {
                    if let Some(f) = &s.index {
                        let p = super::index_files::codes_problem(dir, &m, s).err().map(reason_of);
                        files.push(FileCheck { file: f.file.clone(), problem: p });
                    }
                }
                if files.iter().all(|f| f.problem.is_none()) {
                    files.push(FileCheck { file: INDEX_ENTRY.into(), problem: Some(why) });
                }
            }
        }
    }
    let leftovers = files::leftovers(dir).iter().map(|p| p.display().to_string()).collect();
    let unreferenced = unreferenced(dir, &m)?;
    Ok(VerifyReport {
        generation: m.generation,
        images: m.live_images(),
        files,
        leftovers,
        unreferenced,
        appearance_model: m.appearance_model.clone(),
        appearance_kind: m.config.appearance.model,
        embedding: m.embedding.clone(),
    })
}

/// Builds a map with `build` into a new directory beside `out` (same folder, unique name) and,
/// once it is complete, swaps it with `out` (atomically on Linux) and deletes the old one. `out`
/// must be a map (or a folder holding only map files) or not exist; no other path is touched. A
/// failed build leaves `out` as it was.
pub fn build_replacing<T>(out: &Path, build: impl FnOnce(&Path) -> Result<T>) -> Result<T> {
    if out.exists() {
        let entries: Vec<String> =
            std::fs::read_dir(out).map_err(|e| Error::io(out, e))?.flatten().map(|e| e.file_name().to_string_lossy().into_owned()).collect();
        if let Some(other) = entries.iter().find(|n| !manifest::is_store_file(n)) {
            return Err(Error::invalid(format!("map {}", out.display()), format!("a rebuild replaces only a map, and this folder holds {other:?}")));
        }
    }
    let staging = files::sibling(out, "building")?;
    let result = build(&staging);
    let value = match result {
        Ok(v) => v,
        Err(e) => {
            let _ = std::fs::remove_dir_all(&staging);
            return Err(e);
        }
    };
    if !out.exists() {
        std::fs::rename(&staging, out).map_err(|e| Error::io(out, e))?;
        return Ok(value);
    }
    {
        // no writer of the old map is between reading and committing while the two swap
        let _old = WriteLock::take(out)?;
        files::exchange(&staging, out)?;
    }
    std::fs::remove_dir_all(&staging).map_err(|e| Error::io(&staging, e))?;
    Ok(value)
}
