//! The module layering the map store relies on, read from the sources: the shared bottom layer
//! (`descriptors`) imports none of the stages; encoding, the map store, matching and appearance
//! import each other in no circle; and building a map never passes through evaluation (batch
//! encoding and codebook training live outside `eval`).
//!
//! A module's imports are the `crate::NAME` paths in its files (comments left out; `super::NAME`
//! in a file directly under `src/` is `crate::NAME`). No module is exempt, `error` included.
//!
//! And no cycle anywhere: among the top-level modules of the library, and among the files of every
//! folder of it, of the kernels crate (`kernels/src`), of the command line's crate (`cli/src`) and
//! of the Python package (`python/src`). What the crates may import of each other is Cargo's to
//! say; this test reads their manifests only to hold that the library needs none of the command
//! line's dependencies. Within a folder,
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

/// Every `.rs` file under the folders `roots`, at any depth.
fn rs_files(roots: &[std::path::PathBuf]) -> Vec<std::path::PathBuf> {
    let mut out = vec![];
    let mut stack = roots.to_vec();
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            if p.is_dir() {
                stack.push(p);
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out
}

/// Module (first path component under `src/`, a `NAME_tests.rs` file counted with `NAME`) ->
/// the crate modules it imports.
fn import_graph() -> BTreeMap<String, BTreeSet<String>> {
    let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for p in rs_files(std::slice::from_ref(&src)) {
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

/// Text of a file, comments and `#[cfg(test)]` items left out (a `mod x;` line, or an item to
/// its closing brace; the rest of the file is kept).
fn source(path: &Path) -> String {
    let mut text = strip_comments(&std::fs::read_to_string(path).unwrap());
    while let Some(k) = text.find("#[cfg(test)]") {
        let rest = &text[k..];
        let end = match (rest.find(';'), rest.find('{')) {
            (Some(semi), Some(open)) if semi < open => semi + 1,
            (_, Some(open)) => {
                let mut depth = 0;
                let close = rest[open..].char_indices().find(|&(_, c)| {
                    depth += (c == '{') as i32 - (c == '}') as i32;
                    depth == 0
                });
                open + close.map_or(rest.len() - open, |(i, _)| i + 1)
            }
            (Some(semi), None) => semi + 1,
            (None, None) => rest.len(),
        };
        text.replace_range(k..k + end, "");
    }
    text
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
        // attributes (`#[doc(hidden)]` on a re-export) are not part of the item's path
        let mut t = line.trim();
        while let Some(rest) = t.strip_prefix("#[").and_then(|r| r.split_once(']')) {
            t = rest.1.trim_start();
        }
        let is_pub = t.starts_with("pub");
        let t = t.strip_prefix("pub(crate) ").or_else(|| t.strip_prefix("pub ")).unwrap_or(t);
        if let Some(rest) = t.strip_prefix("use ").and_then(|r| r.strip_prefix("self::").or(Some(r))) {
            let child: String = rest.chars().take_while(|c| c.is_ascii_alphanumeric() || *c == '_').collect();
            if texts.contains_key(&child) && is_pub {
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
    for src in [root.join("src"), root.join("kernels/src"), root.join("cli/src"), root.join("python/src")] {
        for (dir, path, parent) in folders(&src) {
            seen += 1;
            for c in cycles(&folder_graph(&dir, &path, &parent)) {
                problems.push(format!("{}: {c:?}", dir.strip_prefix(root).unwrap().display()));
            }
        }
    }
    // the root folders of the Python package, the kernels crate and the command line's crate:
    // their files import each other as `crate::NAME` (the root's subfolders are walked above)
    for (dir, least) in [("python/src", 5), ("kernels/src", 15), ("cli/src", 1)] {
        let top = root.join(dir);
        let mut g: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
        for e in std::fs::read_dir(&top).unwrap().flatten() {
            let p = e.path();
            let stem = p.file_stem().unwrap().to_string_lossy().into_owned();
            if p.extension().is_some_and(|x| x == "rs") && stem != "lib" && stem != "main" {
                let refs = named_after(&source(&p), "crate::");
                g.entry(stem.clone()).or_default().extend(refs.into_iter().filter(|r| *r != stem && top.join(format!("{r}.rs")).exists()));
            }
        }
        assert!(g.len() >= least, "{dir}'s files were not read: {:?}", g.keys().collect::<Vec<_>>());
        for c in cycles(&g) {
            problems.push(format!("{dir}: {c:?}"));
        }
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

/// The network runtime (`nn`: convolutions, ONNX Runtime, the weight readers) sits under every
/// network that runs on it (`networks`: XFeat, the segmenter, the embedding, LighterGlue) and the
/// stages that handle their tensors: it reads errors and helpers, no stage and no configuration.
#[test]
fn the_network_runtime_imports_no_stage() {
    let g = import_graph();
    let below = reachable(&g, "nn");
    let allowed = ["error", "util"];
    let extra: Vec<&String> = below.iter().filter(|m| !allowed.contains(&m.as_str())).collect();
    assert!(extra.is_empty(), "nn reaches {extra:?} (allowed: {allowed:?})");
    for user in ["appearance", "networks", "verify"] {
        assert!(g[user].contains("nn"), "the graph lacks nn's user {user}: {:?}", g[user]);
    }
}

/// The whole-image descriptors (`global`: semantic SSIM, VLAD, embedding, HOG) are computed from
/// one image: they reach no stage after them (objects and forests, the map, matching, encoding,
/// streams, evaluation), so any of them can be computed, stored or compared by whoever needs it.
#[test]
fn the_whole_image_descriptors_reach_no_later_stage() {
    let g = import_graph();
    let below = reachable(&g, "global");
    for later in ["objects", "local", "descriptors", "map", "matching", "encode", "batch", "stream", "eval", "engine", "gpu", "verify"] {
        assert!(!below.contains(later), "global reaches {later}: {:?}", g["global"]);
    }
    assert!(g["encode"].contains("global") && g["matching"].contains("global"), "the graph lacks global's users");
}

/// The library's dependencies, read from its manifest (`[dependencies]` and the target-specific
/// ones): none of the command line's (its parser, its charts, its progress bars, its crate), so an application that
/// embeds the engine builds none of them; and the kernels crate depends on no part of semlook.
/// (What a crate may import is then Cargo's to enforce: no test reads the tools' imports.)
#[test]
fn the_library_depends_on_no_command_line_crate() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    // `[dependencies]` and every `[target.CFG.dependencies]`, read with the crate's TOML parser
    let deps = |manifest: &str| -> Vec<String> {
        let text = std::fs::read_to_string(root.join(manifest)).unwrap();
        let m: toml::Table = toml::from_str(&text).unwrap_or_else(|e| panic!("{manifest}: {e}"));
        let targets = m.get("target").and_then(toml::Value::as_table).into_iter().flat_map(|t| t.values());
        let tables = m.get("dependencies").into_iter().chain(targets.filter_map(|t| t.get("dependencies")));
        tables.filter_map(toml::Value::as_table).flat_map(|t| t.keys().cloned()).collect()
    };
    let lib = deps("Cargo.toml");
    assert!(lib.iter().any(|d| d == "wgpu") && lib.iter().any(|d| d == "semlook-kernels"), "the library's dependencies were not read: {lib:?}");
    for cli_only in ["clap", "plotters", "indicatif", "semlook-cli", "signal-hook"] {
        assert!(!lib.iter().any(|d| d == cli_only), "the library depends on {cli_only}, the command line's");
    }
    let kernels = deps("kernels/Cargo.toml");
    assert!(kernels.iter().any(|d| d == "bytemuck"), "the kernels' dependencies were not read: {kernels:?}");
    assert!(!kernels.iter().any(|d| d.starts_with("semlook")), "the kernels crate depends on {kernels:?}");
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
    let cli = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("cli/src/cli/commands/map_cmd.rs")).unwrap();
    let cli = strip_comments(&cli);
    assert!(!cli.contains("eval::"), "map commands call into eval");
}

/// The engine's messages speak of the API, not of the command line's flags (a Python caller has
/// none): no string literal of the library names a `--flag`; the command line adds its flags
/// through `cli::hint`.
#[test]
fn library_messages_name_no_command_line_flag() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    let mut found = vec![];
    let mut stack = vec![root.clone()];
    while let Some(d) = stack.pop() {
        for e in std::fs::read_dir(&d).unwrap().flatten() {
            let p = e.path();
            let rel = p.strip_prefix(&root).unwrap().to_string_lossy().into_owned();
            if p.is_dir() {
                if rel != "cli" {
                    stack.push(p);
                }
                continue;
            }
            if rel == "main.rs" || !rel.ends_with(".rs") {
                continue;
            }
            let text = source(&p);
            // string literals: text between unescaped quotes
            let mut in_str = false;
            let mut lit = String::new();
            let mut prev = ' ';
            for c in text.chars() {
                if c == '"' && prev != '\\' {
                    if in_str
                        && lit
                            .split(|c: char| c.is_whitespace() || "(`'".contains(c))
                            .any(|w| w.starts_with("--") && w[2..].starts_with(|c: char| c.is_ascii_lowercase()))
                    {
                        found.push(format!("src/{rel}: {lit:?}"));
                    }
                    in_str = !in_str;
                    lit.clear();
                } else if in_str {
                    lit.push(c);
                }
                prev = if prev == '\\' && c == '\\' { ' ' } else { c };
            }
        }
    }
    assert!(found.is_empty(), "library messages that name command-line flags:\n{}", found.join("\n"));
}

/// The crate's top-level modules: those a library user may rely on, and those public only for the
/// command line and the tests (each `#[doc(hidden)]` with a reason on the line above). A new
/// `pub mod` is one or the other by decision, never by default.
const PUBLIC_MODULES: [&str; 26] = [
    "appearance",
    "batch",
    "choice",
    "classes",
    "config",
    "dataset",
    "descriptors",
    "encode",
    "engine",
    "error",
    "eval",
    "global",
    "gpu",
    "hloc",
    "index",
    "input",
    "local",
    "map",
    "matching",
    "models",
    "networks",
    "nn",
    "objects",
    "progress",
    "stream",
    "verify",
];
const INTERNAL_MODULES: [&str; 1] = ["util"];

/// `pub mod NAME` items of `text` (comments kept out), each with whether `#[doc(hidden)]` and a
/// reason (a `///` or `//` comment) come before it.
fn pub_mods(raw: &str) -> Vec<(String, bool)> {
    let lines: Vec<&str> = raw.lines().map(str::trim).collect();
    let mut out = vec![];
    for (i, l) in lines.iter().enumerate() {
        let Some(name) = l.strip_prefix("pub mod ").and_then(|r| r.strip_suffix(';')) else { continue };
        // the attributes and doc lines directly above
        // the reason may be a plain comment: a `///` line would join the module's own `//!` docs
        // and resolve their links from the parent
        let above: Vec<&str> = lines[..i].iter().rev().take_while(|a| a.starts_with("#[") || a.starts_with("//")).copied().collect();
        let hidden = above.contains(&"#[doc(hidden)]") && above.iter().any(|a| a.starts_with("//") && a.len() > 20);
        out.push((name.to_string(), hidden));
    }
    out
}

/// What a library user sees is decided: every public module of `lib.rs` is on the API list, or is
/// hidden with a reason and on the internal list.
#[test]
fn the_public_surface_is_decided() {
    let lib = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/lib.rs")).unwrap();
    let mods = pub_mods(&lib);
    assert!(mods.len() >= 20, "lib.rs's modules were not read: {mods:?}");
    let mut problems = vec![];
    for (name, hidden) in &mods {
        match (PUBLIC_MODULES.contains(&name.as_str()), INTERNAL_MODULES.contains(&name.as_str())) {
            (true, _) if *hidden => problems.push(format!("{name}: on the API list but hidden")),
            (true, _) => {}
            (false, true) if *hidden => {}
            (false, true) => problems.push(format!("{name}: internal, but public without `#[doc(hidden)]` and a reason")),
            (false, false) => problems
                .push(format!("{name}: a new public module: put it on the API list, or hide it (pub(crate), or #[doc(hidden)] with a reason)")),
        }
    }
    for name in PUBLIC_MODULES.iter().chain(&INTERNAL_MODULES) {
        if !mods.iter().any(|(m, _)| m == name) {
            problems.push(format!("{name}: listed here but not a public module of lib.rs"));
        }
    }
    // the value views are the kernels crate's, shown where the stages read them
    if !lib.lines().any(|l| l.trim() == "pub use semlook_kernels::values;") {
        problems.push("values: no longer re-exported from the kernels crate".into());
    }
    assert!(problems.is_empty(), "the public surface:\n{}", problems.join("\n"));
}

/// The GPU module shows a host its context types (`GpuContext`, `GpuOptions`, `GpuError`,
/// `GpuStages`) and the stage executors `GpuStages` composes (each usable alone on a host's
/// context), re-exported at its top; its submodules are private, but for the reference kernels
/// the equivalence tests reach (`#[doc(hidden)]` with a reason; issue 58 part 1).
#[test]
fn the_gpu_module_shows_its_context_and_executor_types() {
    let gpu = std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("src/gpu/mod.rs")).unwrap();
    let mods = pub_mods(&gpu);
    let shown: Vec<&String> = mods.iter().filter(|(_, hidden)| !hidden).map(|(m, _)| m).collect();
    assert!(shown.is_empty(), "gpu's public submodules not hidden with a reason: {shown:?}");
    assert!(mods.len() <= 1, "gpu's executors are reached through their re-exports, not their modules: {mods:?}");
    assert!(gpu.lines().filter(|l| l.starts_with("mod ")).count() >= 8, "gpu/mod.rs's private modules were not read");
    for ty in ["GpuContext", "GpuError", "GpuOptions", "GpuStages", "CoarseMatcherGpu", "FineMatcherGpu", "GlobalEncoderGpu", "MnnGpu", "VladGpu"] {
        assert!(gpu.lines().any(|l| l.starts_with("pub use") && l.contains(ty)), "gpu no longer re-exports {ty}");
    }
}

/// Each setting's name has one definition (`Setting::name`, src/matching/setting.rs): no other
/// file pairs a setting's name with a `Setting::` variant (a second table of names), in the
/// library, the Python package or the ROS 2 node.
#[test]
fn setting_names_are_defined_once() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let setting = source(&root.join("src/matching/setting.rs"));
    // the names, read from `Setting::name`'s arms: `Setting::X => "name",`
    let names: Vec<String> = setting
        .lines()
        .filter_map(|l| {
            l.trim()
                .strip_prefix("Setting::")
                .and_then(|r| r.split_once(" => \""))
                .and_then(|(_, r)| r.strip_suffix("\","))
                .filter(|n| n.chars().all(|c| c.is_ascii_lowercase() || c == '-'))
                .map(str::to_string)
        })
        .collect();
    assert!(names.len() >= 9 && names.iter().any(|n| n == "global-forest"), "the setting names were not read: {names:?}");
    let mut found = vec![];
    for p in rs_files(&[root.join("src"), root.join("python/src"), root.join("ros2/src")]) {
        if p.ends_with("src/matching/setting.rs") {
            continue;
        }
        for (n, line) in source(&p).lines().enumerate() {
            if line.contains("Setting::") && names.iter().any(|name| line.contains(&format!("\"{name}\""))) {
                found.push(format!("{}:{}: {}", p.strip_prefix(root).unwrap().display(), n + 1, line.trim()));
            }
        }
    }
    assert!(found.is_empty(), "setting names defined a second time (use Setting::name / Setting::from_name):\n{}", found.join("\n"));
}
