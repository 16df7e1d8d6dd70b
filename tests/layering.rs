//! The module layering the map store relies on, read from the sources: the shared bottom layer
//! (`descriptors`) imports none of the stages; encoding, the map store, matching and appearance
//! import each other in no circle; and building a map never passes through evaluation (batch
//! encoding and codebook training live outside `eval`).
//!
//! A module's imports are the `crate::NAME` paths in its files (comments left out; `super::NAME`
//! in a file directly under `src/` is `crate::NAME`). No module is exempt, `error` included.
//!
//! And no cycle anywhere: among the top-level modules of the library, and among the files of every
//! folder of it, of the command line and of the Python package (`python/src`). Within a folder,
//! a file's imports are its `super::NAME` and `crate::PATH::NAME` paths, NAME resolved to the
//! sibling file that defines it (directly, or through the parent's `pub use`) or else to the
//! parent (`mod.rs`, or `X.rs` for folder `X/`); the parent's own imports are its `child::`
//! paths outside its `mod` and `pub use` lines (the wiring).

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

/// Stages among which no import circle may exist.
const STAGES: [&str; 5] = ["descriptors", "map", "encode", "matching", "appearance"];

fn strip_comments(src: &str) -> String {
    let mut out = String::with_capacity(src.len());
    let mut rest = src;
    while !rest.is_empty() {
        if let Some(r) = rest.strip_prefix("//") {
            rest = r.find('\n').map_or("", |k| &r[k..]);
        } else if let Some(r) = rest.strip_prefix("/*") {
            rest = r.find("*/").map_or("", |k| &r[k + 2..]);
        } else {
            let c = rest.chars().next().unwrap();
            out.push(c);
            rest = &rest[c.len_utf8()..];
        }
    }
    out
}

/// Identifiers following `prefix` in `text` (also each top-level name of `prefix{a, b::c}`).
fn paths_after(text: &str, prefix: &str, out: &mut BTreeSet<String>) {
    let ident = |s: &str| s.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect::<String>();
    for (k, _) in text.match_indices(prefix) {
        let before = text[..k].chars().next_back();
        if before.is_some_and(|c| c.is_ascii_alphanumeric() || c == '_' || c == ':') {
            continue;
        }
        let rest = &text[k + prefix.len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let (mut depth, mut item_start) = (0usize, true);
            for (i, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => break,
                    '}' => depth -= 1,
                    ',' if depth == 0 => item_start = true,
                    c if item_start && !c.is_whitespace() => {
                        out.insert(ident(&group[i..]));
                        item_start = false;
                    }
                    _ => {}
                }
            }
        } else {
            out.insert(ident(rest));
        }
    }
}

/// Module (first path component under `src/`, a `NAME_tests.rs` file counted with `NAME`) ->
/// the crate modules it imports.
fn import_graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let mut stack = vec![src.clone()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
                continue;
            }
            if p.extension().is_none_or(|x| x != "rs") {
                continue;
            }
            let rel = p.strip_prefix(&src).unwrap();
            let first = rel.components().next().unwrap().as_os_str().to_string_lossy().into_owned();
            let module = first.trim_end_matches(".rs").trim_end_matches("_tests").to_string();
            if module == "lib" || module == "main" {
                continue;
            }
            let text = strip_comments(&std::fs::read_to_string(&p).unwrap());
            let mut names = BTreeSet::new();
            paths_after(&text, "crate::", &mut names);
            if rel.components().count() == 1 {
                paths_after(&text, "super::", &mut names);
            }
            names.retain(|n| n.starts_with(|c: char| c.is_ascii_lowercase()) && *n != module);
            graph.entry(module).or_default().extend(names);
        }
    }
    graph
}

/// The cycles of `graph` (its strongly connected parts of more than one node), each sorted.
fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    let nodes: BTreeSet<&String> = graph.keys().chain(graph.values().flatten()).collect();
    let mut out: Vec<Vec<String>> = Vec::new();
    let mut placed = BTreeSet::new();
    for n in nodes {
        if placed.contains(n.as_str()) {
            continue;
        }
        let r = reachable(graph, n);
        if !r.contains(n.as_str()) {
            continue;
        }
        let mut part: Vec<String> = r.iter().filter(|m| reachable(graph, m).contains(n.as_str())).cloned().collect();
        part.sort();
        placed.extend(part.iter().cloned());
        out.push(part);
    }
    out
}

/// Top-level names a `prefix::{a, b::c}` group or a `prefix::a` path names, each once.
fn named_after(text: &str, prefix: &str) -> BTreeSet<String> {
    let mut out = BTreeSet::new();
    paths_after(text, prefix, &mut out);
    out.retain(|n| !n.is_empty());
    out
}

/// Text of a file, comments and `#[cfg(test)]` code (to the end of the file) left out.
fn source(path: &Path) -> String {
    let text = strip_comments(&std::fs::read_to_string(path).unwrap());
    match text.find("#[cfg(test)]") {
        Some(k) => text[..k].to_string(),
        None => text,
    }
}

/// Every `.rs` file under `dir`, concatenated.
fn all_text(dir: &Path) -> String {
    let mut out = String::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        if p.is_dir() {
            out += &all_text(&p);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out += &source(&p);
        }
    }
    out
}

/// The import graph among the files of folder `dir` (module path `path` from the crate root),
/// with `parent` the file that declares them, as the module comment says.
fn folder_graph(dir: &Path, path: &str, parent: &Path) -> BTreeMap<String, BTreeSet<String>> {
    // each sibling's own text (where `super::` is this folder) and, for a sibling folder, the text
    // of the files inside it (where only `crate::PATH::` paths name this folder's files)
    let mut texts: BTreeMap<String, String> = BTreeMap::new();
    let mut inner: BTreeMap<String, String> = BTreeMap::new();
    for e in std::fs::read_dir(dir).unwrap().flatten() {
        let p = e.path();
        let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
        if p.is_dir() {
            inner.insert(stem.clone(), all_text(&p));
            texts.entry(stem).or_default();
        } else if p.extension().is_some_and(|x| x == "rs") && p != parent {
            texts.entry(stem).or_default().push_str(&source(&p));
        }
    }
    let parent_name = "(parent)".to_string();
    let parent_text = source(parent);
    // NAME -> the child it comes from, for the parent's `pub use child::NAME` / `child::{A, B}`
    let mut reexported: BTreeMap<String, String> = BTreeMap::new();
    let mut wiring_free = String::new();
    for line in parent_text.split_inclusive(';') {
        let t = line.trim();
        let t = t.strip_prefix("pub(crate) ").or_else(|| t.strip_prefix("pub ")).unwrap_or(t);
        if let Some(rest) = t.strip_prefix("use ").and_then(|r| r.strip_prefix("self::").or(Some(r))) {
            let child: String = rest.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
            if texts.contains_key(&child) && line.trim_start().starts_with("pub") {
                for name in named_after(rest, &format!("{child}::")) {
                    reexported.insert(name, child.clone());
                }
                continue;
            }
        }
        if t.starts_with("mod ") {
            continue;
        }
        wiring_free.push_str(line);
    }
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    let resolve = |name: &str| -> String {
        if texts.contains_key(name) {
            name.to_string()
        } else {
            reexported.get(name).cloned().unwrap_or_else(|| parent_name.clone())
        }
    };
    for (name, text) in &texts {
        let mut refs = named_after(text, "super::");
        if !path.is_empty() {
            let deeper = inner.get(name).map_or("", String::as_str);
            refs.extend(named_after(&format!("{text}\n{deeper}"), &format!("crate::{path}::")));
        }
        let edges = graph.entry(name.clone()).or_default();
        edges.extend(refs.iter().map(|r| resolve(r)).filter(|r| r != name));
    }
    let parent_edges: BTreeSet<String> = texts.keys().filter(|child| !named_after(&wiring_free, &format!("{child}::")).is_empty()).cloned().collect();
    graph.insert(parent_name, parent_edges);
    graph
}

/// Every folder of the crate rooted at `src` (its own parent file, or none for the root, whose
/// graph is the top-level one), with its module path.
fn folders(src: &Path) -> Vec<(std::path::PathBuf, String, std::path::PathBuf)> {
    let mut out = vec![];
    let mut stack = vec![(src.to_path_buf(), String::new())];
    while let Some((d, path)) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if !p.is_dir() {
                continue;
            }
            let name = p.file_name().unwrap().to_string_lossy().into_owned();
            let sub = if path.is_empty() { name.clone() } else { format!("{path}::{name}") };
            let parent = if p.join("mod.rs").exists() { p.join("mod.rs") } else { d.join(format!("{name}.rs")) };
            assert!(parent.exists(), "{}: no mod.rs and no {name}.rs beside it", p.display());
            out.push((p.clone(), sub.clone(), parent));
            stack.push((p, sub));
        }
    }
    out
}

#[test]
fn no_module_imports_itself_through_a_cycle() {
    let g = import_graph();
    assert!(g.contains_key("error") && g.contains_key("gpu"), "the graph lacks modules: {:?}", g.keys().collect::<Vec<_>>());
    let found = cycles(&g);
    assert!(found.is_empty(), "top-level modules in cycles: {found:?}");
}

#[test]
fn no_file_imports_itself_through_a_cycle() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut problems = vec![];
    let mut seen = 0;
    for src in [root.join("src"), root.join("python/src")] {
        for (dir, path, parent) in folders(&src) {
            seen += 1;
            for c in cycles(&folder_graph(&dir, &path, &parent)) {
                problems.push(format!("{}: {c:?}", dir.strip_prefix(root).unwrap().display()));
            }
        }
    }
    // the Python package's root folder: its files import each other as `crate::NAME`
    let py = root.join("python/src");
    let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for e in std::fs::read_dir(&py).unwrap().flatten() {
        let p = e.path();
        let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
        if p.extension().is_some_and(|x| x == "rs") && stem != "lib" {
            let refs = named_after(&source(&p), "crate::");
            g.entry(stem.clone()).or_default().extend(refs.into_iter().filter(|r| *r != stem && py.join(format!("{r}.rs")).exists()));
        }
    }
    assert!(g.len() >= 5, "the Python package's files were not read: {:?}", g.keys().collect::<Vec<_>>());
    for c in cycles(&g) {
        problems.push(format!("python/src: {c:?}"));
    }
    assert!(seen >= 10, "only {seen} folders read");
    assert!(problems.is_empty(), "files in cycles:\n{}", problems.join("\n"));
}

/// Modules reachable from `from` (not counting `from` itself unless a path returns to it).
fn reachable(graph: &BTreeMap<String, BTreeSet<String>>, from: &str) -> BTreeSet<String> {
    let mut seen = BTreeSet::new();
    let mut todo: Vec<&str> = graph.get(from).map_or(vec![], |s| s.iter().map(|x| x.as_str()).collect());
    while let Some(m) = todo.pop() {
        if seen.insert(m.to_string()) {
            todo.extend(graph.get(m).into_iter().flatten().map(|x| x.as_str()));
        }
    }
    seen
}

#[test]
fn the_graph_is_read() {
    let g = import_graph();
    for (m, needs) in [("map", "descriptors"), ("encode", "descriptors"), ("matching", "descriptors"), ("batch", "encode"), ("eval", "batch")] {
        assert!(g[m].contains(needs), "{m} should import {needs}; read {:?}", g[m]);
    }
}

#[test]
fn descriptors_import_no_stage() {
    let g = import_graph();
    let below = reachable(&g, "descriptors");
    for stage in STAGES.iter().filter(|s| **s != "descriptors").chain(&["eval", "batch", "engine", "gpu", "cli"]) {
        assert!(!below.contains(*stage), "descriptors (the shared bottom layer) reaches {stage}: {:?}", g["descriptors"]);
    }
}

#[test]
fn no_stage_imports_another_in_a_circle() {
    let g = import_graph();
    for stage in STAGES {
        let r = reachable(&g, stage);
        assert!(
            !r.contains(stage),
            "{stage} imports itself through a circle: it reaches {:?}",
            r.iter().filter(|m| reachable(&g, m).contains(stage)).collect::<Vec<_>>()
        );
    }
}

#[test]
fn building_a_map_never_passes_through_evaluation() {
    let g = import_graph();
    for m in ["batch", "map", "encode", "matching", "appearance", "descriptors"] {
        assert!(!reachable(&g, m).contains("eval"), "{m} reaches eval");
    }
    // the map commands of the command line
    let cli = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/cli/commands/map_cmd.rs")).unwrap();
    let cli = strip_comments(&cli);
    assert!(!cli.contains("eval::"), "map commands call into eval");
}

#[test]
fn the_kernel_twins_import_neither_the_gpu_nor_a_stage() {
    let g = import_graph();
    assert!(g.contains_key("kernels"), "the graph lacks kernels: {:?}", g.keys().collect::<Vec<_>>());
    let below = reachable(&g, "kernels");
    for m in STAGES.iter().chain(&["gpu", "engine", "eval", "batch", "cli"]) {
        assert!(!below.contains(*m), "kernels (the CPU twins) reach {m}: {:?}", g["kernels"]);
    }
}
