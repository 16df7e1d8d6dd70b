//! hloc interop (github.com/cvg/Hierarchical-Localization). hloc names an image by its path
//! relative to an image root (`query/001.jpg`, `/`-separated) and reads retrieval pairs as lines
//! `query_name reference_name`, split on whitespace (`parse_retrieval`). A map stores ids (file
//! stems, or a dataset's ids such as `ref/001.jpg`), not file names: [`reference_names`] finds
//! each map image's file in the folders it was built from, and refuses what it cannot tell apart.

use crate::dataset::image_files;
use crate::error::{Error, Result};
use std::collections::HashMap;
use std::path::{Component, Path, PathBuf};

/// `path` made absolute against the working folder, `.` dropped and `..` applied, symbolic
/// links kept (the names a user sees).
pub fn absolute(path: &Path) -> Result<PathBuf> {
    let abs = std::path::absolute(path).map_err(|e| Error::io(path, e))?;
    let mut out = PathBuf::new();
    for c in abs.components() {
        match c {
            Component::CurDir => {}
            Component::ParentDir => {
                out.pop();
            }
            other => out.push(other),
        }
    }
    Ok(out)
}

/// The deepest folder holding every folder of `dirs`: hloc's image root when none is given.
pub fn common_root(dirs: &[PathBuf]) -> Result<PathBuf> {
    let mut root: Option<PathBuf> = None;
    for d in dirs {
        let d = absolute(d)?;
        root = Some(match root {
            None => d,
            Some(r) => r.components().zip(d.components()).take_while(|(a, b)| a == b).map(|(a, _)| a).collect(),
        });
    }
    root.ok_or_else(|| Error::invalid("image root", "no folders to find it from"))
}

/// The image root names are relative to when none is given: the deepest folder holding the
/// *parents* of every folder of `dirs`, so a name keeps the folder its image is in
/// (`ref/00.jpg`, `query/00.jpg` under `G` for the folders `G/ref` and `G/query`), and the map's
/// export (`python -m semlook.hloc --images G/ref`) and `query --pairs` (references `G/ref`,
/// queries `G/query`) name one image alike without a `--root`.
pub fn default_root(dirs: &[PathBuf]) -> Result<PathBuf> {
    let parents: Vec<PathBuf> = dirs.iter().map(|d| absolute(d).map(|a| a.parent().map(Path::to_path_buf).unwrap_or(a))).collect::<Result<_>>()?;
    common_root(&parents)
}

/// hloc's name of `file` under `root`: its relative path, `/`-separated. Refused when the file
/// is not under `root`, or its name is not UTF-8 or holds whitespace (pairs split on it).
pub fn image_name(root: &Path, file: &Path) -> Result<String> {
    let (root_abs, abs) = (absolute(root)?, absolute(file)?);
    let what = || file.display().to_string();
    let rel = abs
        .strip_prefix(&root_abs)
        .map_err(|_| Error::refused(what(), format!("is not inside the image root {}", root_abs.display()), crate::error::Remedy::NameImageRoot))?;
    let parts: Vec<&str> = rel
        .components()
        .map(|c| c.as_os_str().to_str().ok_or_else(|| Error::invalid(what(), "the file name is not UTF-8, which hloc's names must be")))
        .collect::<Result<_>>()?;
    let name = parts.join("/");
    if name.is_empty() {
        return Err(Error::invalid(what(), "is the image root itself, not an image under it"));
    }
    if name.chars().any(char::is_whitespace) {
        return Err(Error::invalid(what(), format!("hloc name {name:?} holds whitespace, on which hloc splits a pairs line: rename the file")));
    }
    Ok(name)
}

/// hloc names of the map images `ids`, in order: each id's file in `folders` (the last
/// `/`-part of the id equal to a file's name or stem), named under `root`. An id with no file,
/// with two, or with the file of another id is refused.
pub fn reference_names(ids: &[&str], folders: &[PathBuf], root: &Path) -> Result<Vec<String>> {
    let mut files: HashMap<String, Vec<PathBuf>> = HashMap::new();
    for dir in folders {
        for f in image_files(dir)? {
            let name = f.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            let stem = f.file_stem().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            files.entry(name).or_default().push(f.clone());
            files.entry(stem).or_default().push(f);
        }
    }
    let listed = || folders.iter().map(|d| d.display().to_string()).collect::<Vec<_>>().join(", ");
    let mut owner: HashMap<&Path, &str> = HashMap::new();
    let mut names = Vec::with_capacity(ids.len());
    for &id in ids {
        let key = id.rsplit('/').next().unwrap_or(id);
        let what = || format!("map image {id:?}");
        let file = match files.get(key).map(Vec::as_slice) {
            Some([one]) => one,
            None | Some([]) => {
                return Err(Error::invalid(what(), format!("no image file {key}.* in {} (the folders the map was built from?)", listed())))
            }
            Some(many) => {
                let all: Vec<String> = many.iter().map(|f| f.display().to_string()).collect();
                return Err(Error::invalid(what(), format!("more than one image file could be it: {}", all.join(", "))));
            }
        };
        if let Some(other) = owner.insert(file, id) {
            return Err(Error::invalid(
                what(),
                format!("its file {} is also map image {other:?}'s: give the folder each was built from", file.display()),
            ));
        }
        names.push(image_name(root, file)?);
    }
    Ok(names)
}

/// The text of a pairs file: per query, a line `query reference` for each of its references.
pub fn pairs_text(rows: &[(String, Vec<String>)]) -> String {
    let mut out = String::new();
    for (q, refs) in rows {
        for r in refs {
            out += &format!("{q} {r}\n");
        }
    }
    out
}
