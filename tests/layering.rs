//! The module layering the map store relies on, read from the sources: the shared bottom layer
//! (`descriptors`) imports none of the stages; encoding, the map store, matching and appearance
//! import each other in no circle; and building a map never passes through evaluation (batch
//! encoding and codebook training live outside `eval`).
//!
//! A module's imports are the `crate::NAME` paths in its files (comments left out; `super::NAME`
//! in a file directly under `src/` is `crate::NAME`). `error` is left out of the graph: the one
//! error enum names every stage's error type, and every stage returns it.

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
            names.retain(|n| n.starts_with(|c: char| c.is_ascii_lowercase()) && *n != module && n != "error");
            graph.entry(module).or_default().extend(names);
        }
    }
    graph
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
        assert!(!r.contains(stage), "{stage} imports itself through a circle: it reaches {:?}", r.iter().filter(|m| reachable(&g, m).contains(stage)).collect::<Vec<_>>());
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
