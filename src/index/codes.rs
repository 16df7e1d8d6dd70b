//! The codes of one segment's images, written beside the segment as
//! `index-<sha>.safetensors`: tensors `list` `[n]` u16, `code` `[n, dims]` i8, `scale` `[n]` f32,
//! with thumbnails ([`super::thumb`]) `thumb` `[n, thumb_len]` u8 (format 2; format 1, written
//! where the index keeps none, is the file of before thumbnails byte for byte), and in the header
//! the SHA-256 of the segment they describe and of the model that made them, so
//! that codes of another segment, another map or another model are refused at open. Rows follow
//! the segment's rows, removed ones included (the map leaves those out of the index space).

use super::CodeRows;
use crate::error::{Error, Result};
use memmap2::Mmap;
use safetensors::tensor::{Dtype, TensorView};
use std::ops::Range;
use std::path::{Path, PathBuf};
use std::sync::OnceLock;

/// The header's format tag without thumbnails, and with them.
const FORMAT: &str = "semlook-map-index 1";
const FORMAT_THUMBS: &str = "semlook-map-index 2";

/// The format tag of codes with thumbnails of `thumb_len` bytes (0: none).
fn format_of(thumb_len: usize) -> &'static str {
    if thumb_len > 0 {
        FORMAT_THUMBS
    } else {
        FORMAT
    }
}

/// Codes in memory.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Codes {
    /// Reduced dimensions.
    pub dims: usize,
    /// Per row, its list.
    pub lists: Vec<u16>,
    /// Per row, `dims` int8 values.
    pub codes: Vec<i8>,
    /// Per row, the scale of its values.
    pub scales: Vec<f32>,
    /// Bytes of a row's thumbnail (0: none).
    pub thumb_len: usize,
    /// Per row, `thumb_len` bytes.
    pub thumbs: Vec<u8>,
}

impl Codes {
    /// Empty codes of `dims` values, room for `n` rows.
    pub fn with_capacity(n: usize, dims: usize) -> Codes {
        Codes { dims, lists: Vec::with_capacity(n), codes: Vec::with_capacity(n * dims), scales: Vec::with_capacity(n), thumb_len: 0, thumbs: vec![] }
    }
    /// Rows held.
    pub fn len(&self) -> usize {
        self.lists.len()
    }
    /// Whether no row is held.
    pub fn is_empty(&self) -> bool {
        self.lists.is_empty()
    }
    /// Adds a row: its list and its reduced vector `y`, quantised to int8 with one scale (the
    /// largest magnitude over 127; 1 for a zero vector).
    pub fn push(&mut self, list: u16, y: &[f32]) {
        let m = y.iter().fold(0.0f32, |a, v| a.max(v.abs()));
        let scale = if m > 0.0 { m / 127.0 } else { 1.0 };
        self.lists.push(list);
        self.codes.extend(y.iter().map(|v| (v / scale).round().clamp(-127.0, 127.0) as i8));
        self.scales.push(scale);
    }

    /// The file's bytes, naming the segment (`segment_sha`) and the model (`model_sha`).
    pub fn to_bytes(&self, segment_sha: &str, model_sha: &str) -> Result<Vec<u8>> {
        let n = self.len();
        if self.thumbs.len() != n * self.thumb_len {
            return Err(Error::check(format!("{} thumbnail bytes for {n} rows of {}", self.thumbs.len(), self.thumb_len)));
        }
        let mut parts = vec![
            ("list", Dtype::U16, vec![n], bytemuck::cast_slice::<u16, u8>(&self.lists)),
            ("code", Dtype::I8, vec![n, self.dims], bytemuck::cast_slice::<i8, u8>(&self.codes)),
            ("scale", Dtype::F32, vec![n], bytemuck::cast_slice::<f32, u8>(&self.scales)),
        ];
        if self.thumb_len > 0 {
            parts.push(("thumb", Dtype::U8, vec![n, self.thumb_len], &self.thumbs));
        }
        let tensors = parts
            .into_iter()
            .map(|(name, dt, shape, bytes)| {
                TensorView::new(dt, shape, bytes).map(|v| (name, v)).map_err(|e| Error::check(format!("tensor {name:?}: {e}")))
            })
            .collect::<Result<Vec<_>>>()?;
        let meta = std::collections::HashMap::from([
            ("format".to_string(), format_of(self.thumb_len).to_string()),
            ("segment".to_string(), segment_sha.to_string()),
            ("model".to_string(), model_sha.to_string()),
        ]);
        safetensors::serialize(tensors, Some(meta)).map_err(|e| Error::check(format!("index codes do not serialise: {e}")))
    }
}

impl CodeRows for Codes {
    fn list(&self, j: usize) -> u16 {
        self.lists[j]
    }
    fn code(&self, j: usize) -> &[i8] {
        &self.codes[j * self.dims..(j + 1) * self.dims]
    }
    fn scale(&self, j: usize) -> f32 {
        self.scales[j]
    }
    fn thumb(&self, j: usize) -> &[u8] {
        &self.thumbs[j * self.thumb_len..(j + 1) * self.thumb_len]
    }
}

/// A segment's codes, memory-mapped.
#[derive(Debug)]
pub struct MappedCodes {
    /// Path of the file.
    pub path: PathBuf,
    sha256: String,
    mmap: Mmap,
    n: usize,
    dims: usize,
    lists: usize,
    list: Range<usize>,
    code: Range<usize>,
    scale: Range<usize>,
    thumb_len: usize,
    thumb: Range<usize>,
    checked: OnceLock<Option<String>>,
    by_list: OnceLock<Inverted>,
}

/// A segment's rows grouped by list (the inverted lists proper): list `l`'s rows are
/// `rows[starts[l]..starts[l + 1]]`, ascending.
#[derive(Debug, Default)]
pub struct Inverted {
    starts: Vec<u32>,
    rows: Vec<u32>,
}

impl Inverted {
    /// Groups rows `0..n` by `list(j)` (< `lists`) by a counting sort.
    fn new(n: usize, lists: usize, list: impl Fn(usize) -> usize) -> Inverted {
        let mut starts = vec![0u32; lists + 1];
        for j in 0..n {
            starts[list(j).min(lists - 1) + 1] += 1;
        }
        for l in 0..lists {
            starts[l + 1] += starts[l];
        }
        let mut next = starts.clone();
        let mut rows = vec![0u32; n];
        for j in 0..n {
            let l = list(j).min(lists - 1);
            rows[next[l] as usize] = j as u32;
            next[l] += 1;
        }
        Inverted { starts, rows }
    }
    /// The rows of list `l` (none past the model's lists).
    pub fn rows(&self, l: usize) -> &[u32] {
        match (self.starts.get(l), l.checked_add(1).and_then(|e| self.starts.get(e))) {
            (Some(&a), Some(&b)) => &self.rows[a as usize..b as usize],
            _ => &[],
        }
    }
}

impl MappedCodes {
    /// Maps `dir/file` and checks its size, header, shapes and alignment, and that it describes
    /// the segment `segment_sha` (with `n` rows) with the model `model_sha` (`dims`, `lists`,
    /// thumbnails of `thumb_len` bytes: 0, none).
    /// Its SHA-256 (`sha256`) and values are checked on first use ([`MappedCodes::check`]).
    #[allow(clippy::too_many_arguments)]
    pub fn open(
        dir: &Path,
        file: &str,
        bytes: u64,
        sha256: &str,
        segment_sha: &str,
        model_sha: &str,
        n: usize,
        dims: usize,
        lists: usize,
        thumb_len: usize,
    ) -> Result<MappedCodes> {
        let path = dir.join(file);
        let f = std::fs::File::open(&path).map_err(|e| Error::io(&path, e))?;
        let len = f.metadata().map_err(|e| Error::io(&path, e))?.len();
        if len != bytes {
            return Err(Error::corrupt(&path, format!("index codes are {len} bytes, the manifest says {bytes} (truncated or replaced)")));
        }
        // SAFETY: the store never changes a file after renaming it into place (new contents
        // always go to new, content-named files), so the mapped bytes do not change.
        let mmap = unsafe { Mmap::map(&f) }.map_err(|e| Error::io(&path, e))?;
        let [list, code, scale, thumb] =
            header(&mmap, segment_sha, model_sha, n, dims, thumb_len).map_err(|e| e.named(|r| Error::corrupt(&path, r)))?;
        Ok(MappedCodes {
            path,
            sha256: sha256.to_string(),
            mmap,
            n,
            dims,
            lists,
            list,
            code,
            scale,
            thumb_len,
            thumb,
            checked: OnceLock::new(),
            by_list: OnceLock::new(),
        })
    }

    /// Rows of the file.
    pub fn len(&self) -> usize {
        self.n
    }
    /// Whether the file holds no rows.
    pub fn is_empty(&self) -> bool {
        self.n == 0
    }

    /// The rows grouped by list, made on first use (one pass over the lists; after [`Self::check`]).
    pub fn inverted(&self) -> &Inverted {
        self.by_list.get_or_init(|| Inverted::new(self.n, self.lists.max(1), |j| self.list(j) as usize))
    }

    /// Whether [`Self::check`] has run (here or, inherited, on an earlier generation).
    pub fn checked(&self) -> bool {
        self.checked.get().is_some()
    }
    /// Takes over `prev`'s [`Self::check`] result where `prev` maps the same file with the same
    /// checksum (codes files never change once in place), so a reopened map does not check it again.
    pub fn inherit(&self, prev: &MappedCodes) {
        crate::util::take_over_check(&self.checked, &prev.checked, prev.path == self.path && prev.sha256 == self.sha256);
    }

    /// The SHA-256 against the manifest, and every value: lists below the model's, finite positive
    /// scales. Once; later calls give the first answer.
    pub fn check(&self) -> Result<()> {
        let found = self.checked.get_or_init(|| {
            if crate::util::sha256_hex(&self.mmap) != self.sha256 {
                return Some("SHA-256 differs from the manifest (damaged or replaced)".into());
            }
            let lists: &[u16] = bytemuck::cast_slice(&self.mmap[self.list.clone()]);
            if let Some(j) = lists.iter().position(|&l| l as usize >= self.lists) {
                return Some(format!("row {j}: list {} of a model of {} lists", lists[j], self.lists));
            }
            let scales: &[f32] = bytemuck::cast_slice(&self.mmap[self.scale.clone()]);
            if let Some(j) = scales.iter().position(|s| !(s.is_finite() && *s > 0.0)) {
                return Some(format!("row {j}: scale {} is not a finite positive number", scales[j]));
            }
            None
        });
        match found {
            None => Ok(()),
            Some(r) => Err(Error::corrupt(&self.path, r.clone())),
        }
    }
}

impl CodeRows for MappedCodes {
    fn list(&self, j: usize) -> u16 {
        bytemuck::cast_slice::<u8, u16>(&self.mmap[self.list.clone()])[j]
    }
    fn code(&self, j: usize) -> &[i8] {
        let all: &[i8] = bytemuck::cast_slice(&self.mmap[self.code.clone()]);
        &all[j * self.dims..(j + 1) * self.dims]
    }
    fn scale(&self, j: usize) -> f32 {
        bytemuck::cast_slice::<u8, f32>(&self.mmap[self.scale.clone()])[j]
    }
    fn thumb(&self, j: usize) -> &[u8] {
        &self.mmap[self.thumb.clone()][j * self.thumb_len..(j + 1) * self.thumb_len]
    }
}

/// The tensors' byte ranges (list, code, scale, thumb: empty without thumbnails), checked against
/// what the manifest expects.
fn header(bytes: &[u8], segment_sha: &str, model_sha: &str, n: usize, dims: usize, thumb_len: usize) -> Result<[Range<usize>; 4]> {
    let (hlen, meta) = safetensors::SafeTensors::read_metadata(bytes).map_err(|e| Error::check(format!("not an index codes file: {e}")))?;
    let tags = meta.metadata().clone().unwrap_or_default();
    let tag = |k: &str| tags.get(k).map(String::as_str).unwrap_or("");
    let format = format_of(thumb_len);
    if tag("format") != format {
        return Err(Error::check(format!(
            "format {:?}, not {format:?} (the manifest's index {} thumbnails)",
            tag("format"),
            if thumb_len > 0 { "keeps" } else { "keeps no" }
        )));
    }
    if tag("segment") != segment_sha {
        return Err(Error::check(format!(
            "codes of segment sha256 {}, not of this segment ({segment_sha}): from another segment or map",
            tag("segment")
        )));
    }
    if tag("model") != model_sha {
        return Err(Error::check(format!("codes of index model sha256 {}, the map's model is {model_sha}", tag("model"))));
    }
    let start = 8 + hlen;
    let get = |name: &str, dt: Dtype, shape: Vec<usize>, align: usize| -> Result<Range<usize>> {
        let info = meta.info(name).ok_or_else(|| Error::check(format!("no {name} tensor")))?;
        if info.dtype != dt || info.shape != shape {
            return Err(Error::check(format!("{name} is {:?} {:?}, expected {dt:?} {shape:?}", info.dtype, info.shape)));
        }
        let r = start + info.data_offsets.0..start + info.data_offsets.1;
        if r.end > bytes.len() || r.start % align != 0 {
            return Err(Error::check(format!("{name} lies outside the file or is not aligned")));
        }
        Ok(r)
    };
    let thumb = if thumb_len > 0 { get("thumb", Dtype::U8, vec![n, thumb_len], 1)? } else { start..start };
    Ok([get("list", Dtype::U16, vec![n], 2)?, get("code", Dtype::I8, vec![n, dims], 1)?, get("scale", Dtype::F32, vec![n], 4)?, thumb])
}

#[cfg(test)]
mod tests {
    use super::*;

    fn codes() -> Codes {
        let mut c = Codes::with_capacity(3, 4);
        c.push(1, &[0.5, -1.0, 0.25, 0.0]);
        c.push(0, &[0.0; 4]);
        c.push(2, &[3.0, 3.0, -3.0, 1.5]);
        c
    }

    #[test]
    fn quantisation_error_is_at_most_half_a_scale() {
        let c = codes();
        let y = [0.5f32, -1.0, 0.25, 0.0];
        for (k, v) in y.iter().enumerate() {
            assert!((c.code(0)[k] as f32 * c.scale(0) - v).abs() <= c.scale(0) / 2.0 + 1e-7);
        }
        assert_eq!((c.code(1), c.scale(1)), (&[0i8; 4][..], 1.0));
    }

    #[test]
    fn a_file_is_read_back_and_refused_for_another_segment_model_or_size() {
        let dir = tempfile::tempdir().unwrap();
        let c = codes();
        let bytes = c.to_bytes("seg", "mod").unwrap();
        std::fs::write(dir.path().join("index-x.safetensors"), &bytes).unwrap();
        let sha = crate::util::sha256_hex(&bytes);
        let open =
            |seg: &str, model: &str, n: usize, len: u64| MappedCodes::open(dir.path(), "index-x.safetensors", len, &sha, seg, model, n, 4, 3, 0);
        let m = open("seg", "mod", 3, bytes.len() as u64).unwrap();
        m.check().unwrap();
        for j in 0..3 {
            assert_eq!((m.list(j), m.code(j), m.scale(j)), (c.list(j), c.code(j), c.scale(j)));
        }
        assert!(open("other", "mod", 3, bytes.len() as u64).unwrap_err().to_string().contains("another segment"));
        assert!(open("seg", "other", 3, bytes.len() as u64).is_err());
        assert!(open("seg", "mod", 4, bytes.len() as u64).is_err());
        assert!(open("seg", "mod", 3, bytes.len() as u64 - 1).unwrap_err().to_string().contains("truncated"));
        // a flipped bit in the values: the header opens, the first use refuses it
        let mut bad = bytes.clone();
        let last = bad.len() - 1;
        bad[last] ^= 0x10;
        std::fs::write(dir.path().join("index-x.safetensors"), &bad).unwrap();
        let m = open("seg", "mod", 3, bytes.len() as u64).unwrap();
        assert!(m.check().unwrap_err().to_string().contains("SHA-256"));
        // no rows
        let empty = Codes::with_capacity(0, 4).to_bytes("seg", "mod").unwrap();
        std::fs::write(dir.path().join("index-e.safetensors"), &empty).unwrap();
        let e = MappedCodes::open(dir.path(), "index-e.safetensors", empty.len() as u64, &crate::util::sha256_hex(&empty), "seg", "mod", 0, 4, 3, 0)
            .unwrap();
        e.check().unwrap();
        assert!(e.is_empty());
    }

    #[test]
    fn thumbnails_are_read_back_and_a_file_without_them_is_refused_where_they_are_expected() {
        let dir = tempfile::tempdir().unwrap();
        let plain = codes();
        let mut c = codes();
        c.thumb_len = 2;
        c.thumbs = vec![1, 2, 3, 4, 5, 6];
        let bytes = c.to_bytes("seg", "mod").unwrap();
        let old = plain.to_bytes("seg", "mod").unwrap();
        std::fs::write(dir.path().join("t.safetensors"), &bytes).unwrap();
        std::fs::write(dir.path().join("p.safetensors"), &old).unwrap();
        let open = |f: &str, b: &[u8], thumb: usize| {
            MappedCodes::open(dir.path(), f, b.len() as u64, &crate::util::sha256_hex(b), "seg", "mod", 3, 4, 3, thumb)
        };
        let m = open("t.safetensors", &bytes, 2).unwrap();
        m.check().unwrap();
        for j in 0..3 {
            assert_eq!((m.list(j), m.code(j), m.scale(j), m.thumb(j)), (c.list(j), c.code(j), c.scale(j), c.thumb(j)));
        }
        assert!(open("t.safetensors", &bytes, 3).is_err(), "another thumbnail size");
        assert!(open("t.safetensors", &bytes, 0).unwrap_err().to_string().contains("keeps no thumbnails"));
        assert!(open("p.safetensors", &old, 2).unwrap_err().to_string().contains("keeps thumbnails"));
        assert!(open("p.safetensors", &old, 0).unwrap().thumb(1).is_empty());
        // rows and thumbnails that disagree do not serialise
        c.thumbs.pop();
        assert!(c.to_bytes("seg", "mod").is_err());
    }

    #[test]
    fn inverted_lists_hold_every_row_once_under_its_list_in_order() {
        let lists = [2usize, 0, 2, 1, 2, 0];
        let inv = Inverted::new(lists.len(), 4, |j| lists[j]);
        assert_eq!((inv.rows(0), inv.rows(1), inv.rows(2), inv.rows(3)), (&[1u32, 5][..], &[3u32][..], &[0u32, 2, 4][..], &[][..]));
        assert!(inv.rows(4).is_empty() && inv.rows(usize::MAX).is_empty(), "past the model's lists: none");
        assert!(Inverted::new(0, 4, |_| 0).rows(0).is_empty());
    }
}
