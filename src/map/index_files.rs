//! A map's index files ([`crate::index`]) in the store: the model as a content-named file, each
//! segment's codes beside it (`index-<segment>-<model>.safetensors`), all listed in the manifest
//! with their sizes and SHA-256. Codes are computed from the values the segment stores (not from
//! those it was given), so codes written by `map add` equal those a rebuild computes. Opening,
//! checking and writing them; [`super::index`] builds and searches.

use super::files::{self, write_atomic};
use super::manifest::{self, FileEntry, IndexEntry, Manifest, SegmentEntry};
use super::segment::{Layout, Mapped};
use crate::error::{Error, Result};
use crate::index::thumb::ThumbSpec;
use crate::index::{Codes, MappedCodes, Model};
use crate::util::sha256_hex;
use rayon::prelude::*;
use std::collections::HashSet;
use std::path::Path;

/// Rows widened to f32 at a time while computing codes (4 MiB a thousand rows at 4,096 values).
const CHUNK: usize = 1024;
/// An open map's index: its manifest entry, model and every segment's codes.
#[derive(Debug)]
pub struct MapIndex {
    /// What the manifest says of it.
    pub entry: IndexEntry,
    /// The model.
    pub model: Model,
    /// What its thumbnails are (none: an index of before thumbnails, or built without).
    pub thumb: ThumbSpec,
    pub(super) codes: Vec<MappedCodes>,
}

/// Reads and checks a model file (small: read and hashed in full); a missing or damaged one is an
/// [`Error::DamagedIndex`].
pub(super) fn read_model(dir: &Path, m: &Manifest, ix: &IndexEntry) -> Result<Model> {
    let p = dir.join(&ix.model.file);
    let bytes = std::fs::read(&p).map_err(|e| Error::io(&p, e).in_index())?;
    if bytes.len() as u64 != ix.model.bytes || sha256_hex(&bytes) != ix.model.sha256 {
        return Err(Error::corrupt(&p, "size or SHA-256 differs from the manifest").in_index());
    }
    Model::from_bytes(&bytes, m.appearance_dim, ix.dims, ix.lists).map_err(|e| e.named(|r| Error::corrupt(&p, r)).in_index())
}

impl MapIndex {
    /// The index of manifest `m` in `dir`, if it has one: the model read and checked, every
    /// segment's codes mapped with their headers checked (the segment and model they name, sizes);
    /// checksums and values are checked on first use.
    pub(crate) fn open(dir: &Path, m: &Manifest) -> Result<Option<MapIndex>> {
        let Some(ix) = &m.index else { return Ok(None) };
        let model = read_model(dir, m, ix)?;
        let mut codes = Vec::with_capacity(m.segments.len());
        for s in &m.segments {
            let f = s.index.as_ref().ok_or_else(|| Error::corrupt(dir.join(manifest::MANIFEST), format!("segment {} has no index codes", s.file)))?;
            codes.push(open_codes(dir, m, ix, s, f)?);
        }
        Ok(Some(MapIndex { entry: ix.clone(), model, thumb: ix.thumb(&m.config.global), codes }))
    }

    /// Codes files not checked yet.
    pub(super) fn unchecked(&self) -> usize {
        self.codes.iter().filter(|c| !c.checked()).count()
    }

    /// Checks every segment's codes ([`MapIndex::verify_all`]) and groups their rows by list
    /// ([`super::Map::prepare`]): the first damaged file in manifest order fails.
    pub(super) fn prepare(&self) -> Result<()> {
        self.verify_all().into_iter().try_for_each(|(_, r)| r)?;
        self.codes.par_iter().for_each(|c| {
            c.inverted();
        });
        Ok(())
    }

    /// Checks every segment's codes in full (`map verify`), in parallel: the check of each, in manifest order
    /// (a damaged one's an [`Error::DamagedIndex`]).
    pub fn verify_all(&self) -> Vec<(&Path, Result<()>)> {
        self.codes.par_iter().map(|c| (c.path.as_path(), c.check().map_err(Error::in_index))).collect()
    }
}

/// Widens the appearance vectors of rows `a..b` of `seg` into `buf` (`width` values each).
fn segment_vectors(width: usize, seg: &Mapped, a: usize, b: usize, buf: &mut Vec<f32>) {
    buf.clear();
    buf.resize((b - a) * width, 0.0);
    for (j, dst) in (a..b).zip(buf.chunks_mut(width)) {
        seg.image_appearance(j).write_to(dst);
    }
}

/// The codes of every row of a stored segment (removed ones included), from the values it
/// stores, with the thumbnails `thumb` of its global descriptors.
pub fn codes_for_segment(model: &Model, thumb: &ThumbSpec, seg: &Mapped) -> Codes {
    let n = seg.len();
    let mut out = Codes::with_capacity(n, model.dims);
    out.thumb_len = thumb.len();
    out.thumbs.reserve(n * thumb.len());
    let mut buf = Vec::new();
    for a in (0..n).step_by(CHUNK) {
        let b = (a + CHUNK).min(n);
        segment_vectors(model.width, seg, a, b, &mut buf);
        let c = model.encode(&buf, b - a);
        out.lists.extend(c.lists);
        out.codes.extend(c.codes);
        out.scales.extend(c.scales);
    }
    if !thumb.is_empty() {
        let mut global = vec![0.0f32; thumb.width * thumb.height];
        for j in 0..n {
            seg.globals(j, j + 1).write_to(&mut global);
            thumb.thumbnail(&global, &mut out.thumbs);
        }
    }
    out
}

/// The file name of segment `segment`'s codes under the model `model_sha`, with thumbnails pooled
/// by `thumbnail` named in it (a rebuild that changes only the thumbnails trains the same model and
/// must not write over files the committed manifest lists); without thumbnails, the name of before.
pub(super) fn codes_name(segment: &str, model_sha: &str, thumbnail: usize) -> String {
    let stem = segment.strip_prefix("segment-").unwrap_or(segment).strip_suffix(".safetensors").unwrap_or(segment);
    let model = &model_sha[..16.min(model_sha.len())];
    match thumbnail {
        0 => format!("index-{stem}-{model}.safetensors"),
        t => format!("index-{stem}-{model}-t{t}.safetensors"),
    }
}

/// Whether the model file of `m`'s index opens (size, SHA-256, shapes, values): `map verify`.
pub(crate) fn model_problem(dir: &Path, m: &Manifest) -> Result<()> {
    match &m.index {
        Some(ix) => read_model(dir, m, ix).map(|_| ()),
        None => Ok(()),
    }
}

/// The codes file `f` of segment `s` under the index `ix` of manifest `m` in `dir`, mapped with its
/// header checked against what the manifest expects (the segment, the model, the shapes, the
/// thumbnails); a missing or damaged file is an [`Error::DamagedIndex`].
pub fn open_codes(dir: &Path, m: &Manifest, ix: &IndexEntry, s: &SegmentEntry, f: &FileEntry) -> Result<MappedCodes> {
    let thumb = ix.thumb(&m.config.global).len();
    MappedCodes::open(dir, &f.file, f.bytes, &f.sha256, &s.sha256, &ix.model.sha256, s.images, ix.dims, ix.lists, thumb).map_err(Error::in_index)
}

/// Whether the codes of segment `s` open and check in full: `map verify`.
pub(crate) fn codes_problem(dir: &Path, m: &Manifest, s: &SegmentEntry) -> Result<()> {
    let (Some(ix), Some(f)) = (&m.index, &s.index) else { return Ok(()) };
    open_codes(dir, m, ix, s, f)?.check().map_err(Error::in_index)
}

/// Writes the codes of segment `entry` (already written to `dir`) under the index `ix`, loading
/// the model into `cache` where it holds another; returns their manifest entry.
pub(crate) fn write_segment_codes(
    dir: &Path,
    m: &Manifest,
    ix: &IndexEntry,
    entry: &SegmentEntry,
    layout: Layout,
    cache: &mut Option<(String, Model)>,
) -> Result<FileEntry> {
    if cache.as_ref().is_none_or(|c| c.0 != ix.model.sha256) {
        *cache = Some((ix.model.sha256.clone(), read_model(dir, m, ix)?));
    }
    let model = &cache.as_ref().ok_or_else(|| Error::check("no index model"))?.1;
    let seg = Mapped::open(dir, entry, layout)?;
    let codes = codes_for_segment(model, &ix.thumb(&m.config.global), &seg);
    let bytes = codes.to_bytes(&entry.sha256, &ix.model.sha256)?;
    let name = codes_name(&entry.file, &ix.model.sha256, ix.params.thumbnail);
    write_atomic(dir, &name, &bytes)?;
    Ok(FileEntry { file: name, bytes: bytes.len() as u64, sha256: sha256_hex(&bytes) })
}

/// The index files `m` lists.
pub(super) fn index_files(m: &Manifest) -> Vec<String> {
    m.segments.iter().filter_map(|s| s.index.as_ref().map(|f| f.file.clone())).chain(m.index.as_ref().map(|i| i.model.file.clone())).collect()
}

/// Deletes the files of `old` that `m` does not list (best effort: a leftover is listed by
/// `map verify` and removed by the next compaction).
pub(super) fn delete_unreferenced(dir: &Path, m: &Manifest, old: &[String]) {
    let now: HashSet<String> = index_files(m).into_iter().collect();
    for f in old {
        if !now.contains(f) {
            let _ = std::fs::remove_file(dir.join(f));
        }
    }
    files::sync_dir(dir);
}
