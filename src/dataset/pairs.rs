//! Datasets given as a reference folder and a query folder of images, with ground truth from
//! - a CSV file of `query,reference` rows (paths relative to the CSV's folder, several rows per
//!   query allowed): the layout of `../shared/data/real-vpr` (`ref/`, `query/`, `ground_truth.csv`);
//! - VPR-Bench's `ground_truth_new.npy` (`query/`, `ref/`; rows `[query_index, [ref_indices]]`,
//!   indices into the sorted file lists);
//! - UTM coordinates in the file names of gmberton's VPR-datasets layout (`database/`,
//!   `queries/`, names `@UTM_east@UTM_north@zone@letter@...@.jpg`): references within a distance
//!   (default [`UTM_DEFAULT_DISTANCE`]) of a query are correct.

use super::frames::{image_files, Dataset, Frame, GroundTruthRule, Pose, Traversal};
use super::npy;
use crate::error::{Error, Result};
use crate::input::{FrameSource, LabelFormat};
use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

/// gmberton/VPR-datasets-downloader's positive radius (metres).
pub const UTM_DEFAULT_DISTANCE: f64 = 25.0;

/// Where the ground truth of a folder pair comes from.
#[derive(Debug, Clone, PartialEq)]
pub enum PairTruth {
    /// A CSV file of `query,reference` rows.
    Csv(PathBuf),
    /// VPR-Bench's `ground_truth_new.npy`.
    Npy(PathBuf),
    /// UTM positions in the file names; positives within this many metres.
    Utm(f64),
}

impl PairTruth {
    /// A ground-truth file by its extension.
    pub fn from_file(path: &Path) -> Result<PairTruth> {
        match path.extension().and_then(|e| e.to_str()).map(str::to_ascii_lowercase).as_deref() {
            Some("csv") => Ok(PairTruth::Csv(path.into())),
            Some("npy") => Ok(PairTruth::Npy(path.into())),
            _ => Err(Error::dataset(path, "ground truth must be a .csv file (query,reference rows) or VPR-Bench's .npy")),
        }
    }
}

/// The key paths are compared by: the canonical path, or (for a path that does not exist) its
/// components with `.` dropped and `..` applied.
fn key(p: &Path) -> PathBuf {
    std::fs::canonicalize(p).unwrap_or_else(|_| lexical(p))
}

fn lexical(p: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in p.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    out
}

/// A traversal of every image in `dir`, ids relative to `root` (forward slashes).
fn folder(root: &Path, dir: &Path) -> Result<Traversal> {
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_else(|| dir.display().to_string());
    let frames: Vec<Frame> = image_files(dir)?
        .into_iter()
        .map(|img| {
            let rel = img.strip_prefix(root).unwrap_or(&img);
            let id = rel.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect::<Vec<_>>().join("/");
            Frame { source: FrameSource { id, image: Some(img), labels: None }, pose: None }
        })
        .collect();
    if frames.is_empty() {
        return Err(Error::dataset(dir, "no png or jpeg images"));
    }
    Ok(Traversal { name, frames, ground_truth: None })
}

/// The dataset of images in `refs` (the map) and `queries`, with ground truth from `truth`.
pub fn from_folders(refs: &Path, queries: &Path, truth: &PairTruth) -> Result<Dataset> {
    let root = match truth {
        PairTruth::Csv(f) | PairTruth::Npy(f) => f.parent().map(Path::to_path_buf).unwrap_or_default(),
        PairTruth::Utm(_) => refs.parent().map(Path::to_path_buf).unwrap_or_default(),
    };
    let mut reference = folder(&root, refs)?;
    let mut query = folder(&root, queries)?;
    let mut rule = None;
    match truth {
        PairTruth::Csv(csv) => query.ground_truth = Some(read_csv(csv, &reference, &query)?),
        PairTruth::Npy(file) => query.ground_truth = Some(read_npy(file, reference.frames.len(), query.frames.len())?),
        PairTruth::Utm(d) => {
            for f in reference.frames.iter_mut().chain(query.frames.iter_mut()) {
                let path = f.source.image.clone().unwrap_or_default();
                let (east, north, zone) = utm_of_name(&path)?;
                f.pose = Some(Pose { position: [east, north, zone], forward: [0.0, 0.0, 1.0], orientation: None });
            }
            rule = Some(GroundTruthRule { max_distance: *d, max_angle_deg: None });
        }
    }
    let name = root.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let ds = Dataset { root, name, label_format: LabelFormat::Auto, label_ids: None, reference, queries: vec![query], rule };
    ds.ground_truth(&ds.queries[0])?;
    Ok(ds)
}

/// Per query frame, the reference indices the CSV names.
fn read_csv(csv: &Path, refs: &Traversal, queries: &Traversal) -> Result<Vec<Vec<u32>>> {
    let dir = csv.parent().unwrap_or(Path::new(""));
    let index = |t: &Traversal| -> HashMap<PathBuf, u32> {
        t.frames.iter().enumerate().filter_map(|(i, f)| f.source.image.as_ref().map(|p| (key(p), i as u32))).collect()
    };
    let (ref_index, query_index) = (index(refs), index(queries));
    let mut reader = csv::ReaderBuilder::new().trim(csv::Trim::All).from_path(csv).map_err(|e| Error::dataset(csv, e.to_string()))?;
    let headers = reader.headers().map_err(|e| Error::dataset(csv, e.to_string()))?.clone();
    let col = |name: &str| {
        headers
            .iter()
            .position(|h| h.eq_ignore_ascii_case(name))
            .ok_or_else(|| Error::dataset(csv, format!("no {name:?} column (the header must name query and reference)")))
    };
    let (qc, rc) = (col("query")?, col("reference")?);
    // a name that is no image says where names are looked for, with one that would be found
    let base = if dir.as_os_str().is_empty() { Path::new(".") } else { dir };
    let not_found = |line: usize, what: &str, name: &str, t: &Traversal| {
        let example =
            t.frames.first().and_then(|f| f.source.image.as_deref()).and_then(|p| key(p).strip_prefix(key(base)).ok().map(Path::to_path_buf));
        let example = example.map_or(String::new(), |e| format!(", e.g. {:?}", e.to_string_lossy()));
        Error::dataset(
            csv,
            format!(
                "line {line}: {what} {name:?} is not an image of {}: names in the ground truth are paths relative to the CSV's folder {}{example} (this one is {})",
                t.name,
                base.display(),
                base.join(name).display()
            ),
        )
    };
    let mut gt = vec![Vec::new(); queries.frames.len()];
    for (line, row) in reader.records().enumerate() {
        let line = line + 2;
        let row = row.map_err(|e| Error::dataset(csv, format!("line {line}: {e}")))?;
        let (q, r) = (row.get(qc).unwrap_or(""), row.get(rc).unwrap_or(""));
        let qi = query_index.get(&key(&dir.join(q))).ok_or_else(|| not_found(line, "query", q, queries))?;
        let ri = ref_index.get(&key(&dir.join(r))).ok_or_else(|| not_found(line, "reference", r, refs))?;
        let list = &mut gt[*qi as usize];
        if !list.contains(ri) {
            list.push(*ri);
        }
    }
    for l in &mut gt {
        l.sort_unstable();
    }
    some_truth(gt, csv)
}

/// `gt` unless no query has a valid reference: every metric would be 0 without saying why.
fn some_truth(gt: Vec<Vec<u32>>, file: &Path) -> Result<Vec<Vec<u32>>> {
    if !gt.is_empty() && gt.iter().all(Vec::is_empty) {
        return Err(Error::dataset(file, "no query has a valid reference (no rows after the header?): nothing to evaluate"));
    }
    Ok(gt)
}

/// VPR-Bench's rows, checked against the folder sizes.
fn read_npy(file: &Path, n_refs: usize, n_queries: usize) -> Result<Vec<Vec<u32>>> {
    let bytes = std::fs::read(file).map_err(|e| Error::io(file, e))?;
    parse_npy_ground_truth(&bytes, file, n_refs, n_queries)
}

/// Per query, the valid reference indices of a VPR-Bench `ground_truth_new.npy` held in `bytes`
/// (`file` names it in errors), checked against the folder sizes.
pub fn parse_npy_ground_truth(bytes: &[u8], file: &Path, n_refs: usize, n_queries: usize) -> Result<Vec<Vec<u32>>> {
    let rows = npy::read_ground_truth(bytes).map_err(|e| e.named(|r| Error::dataset(file, r)))?;
    let mut gt = vec![Vec::new(); n_queries];
    for (q, refs) in rows {
        let slot = usize::try_from(q)
            .ok()
            .and_then(|q| gt.get_mut(q))
            .ok_or_else(|| Error::dataset(file, format!("query index {q}, there are {n_queries} query images")))?;
        for r in refs {
            if r >= n_refs as u64 {
                return Err(Error::dataset(file, format!("query {q}: reference index {r}, there are {n_refs} reference images")));
            }
            if !slot.contains(&(r as u32)) {
                slot.push(r as u32);
            }
        }
        slot.sort_unstable();
    }
    some_truth(gt, file)
}

/// (east, north, zone number) from a gmberton file name `@east@north@zone@letter@...`.
pub fn utm_of_name(path: &Path) -> Result<(f64, f64, f64)> {
    let name = path.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    let fields: Vec<&str> = name.split('@').collect();
    let num = |i: usize| fields.get(i).and_then(|s| s.parse::<f64>().ok()).filter(|v| v.is_finite());
    match (fields.first(), num(1), num(2)) {
        (Some(&""), Some(e), Some(n)) => {
            // a different zone must never count as near: offset zones far apart
            let zone = num(3).unwrap_or(0.0);
            Ok((e, n, zone * 1e7))
        }
        _ => Err(Error::dataset(path, "file name is not @UTM_east@UTM_north@zone@...: no position for ground truth")),
    }
}

/// The reference and query folders of a gmberton dataset root: `database/` and `queries/`,
/// directly or under `images/test/`.
pub fn gmberton_folders(root: &Path) -> Option<(PathBuf, PathBuf)> {
    [root.to_path_buf(), root.join("images/test")]
        .into_iter()
        .map(|b| (b.join("database"), b.join("queries")))
        .find(|(d, q)| d.is_dir() && q.is_dir())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn utm_names() {
        let (e, n, z) = utm_of_name(Path::new("x/@0543256.96@4178906.93@10@S@37.75@-122.50@abc@@@@@@201311@@.jpg")).unwrap();
        assert_eq!((e, n, z), (543256.96, 4178906.93, 1e8));
        assert!(utm_of_name(Path::new("x/000123.jpg")).is_err());
        assert!(utm_of_name(Path::new("x/@nan@1@.jpg")).is_err());
    }

    #[test]
    fn lexical_paths() {
        assert_eq!(lexical(Path::new("a/./b/../c.jpg")), PathBuf::from("a/c.jpg"));
    }
}
