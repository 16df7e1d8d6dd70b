//! The docs that restate code are held to it: docs/config.md's table names every key of every
//! section of `Config::default()` and no other, and where a row's default is a plain value (a
//! number, a boolean, a quoted string, a list of numbers) it is the code's default, key by key;
//! docs/library.md's example is the one src/lib.rs compiles (its doc test), line for line; every
//! figure README shows is on a measurement page it links to, beside `semlook` commands that exist.

use serde_json::Value;
use std::collections::{BTreeMap, BTreeSet};

/// The doc's rows: each `section.key` of the first column (`a.b`, `c` is `a.b` and `a.c`) with
/// its default cell, split on top-level commas where the row names several keys.
fn doc_rows() -> Vec<(Vec<String>, String)> {
    let text = std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/docs/config.md")).unwrap();
    let mut rows = vec![];
    for line in text.lines().filter(|l| l.starts_with("| `")) {
        let cells: Vec<&str> = line.split(" | ").collect();
        let (keys_cell, default) = (cells[0].trim_start_matches("| "), cells.get(1).copied().unwrap_or(""));
        let mut section = String::new();
        let mut keys = vec![];
        for item in keys_cell.split(',').map(|s| s.trim().trim_matches('`')) {
            match item.split_once('.') {
                Some((s, k)) => {
                    section = s.to_string();
                    keys.push(format!("{s}.{k}"));
                }
                None => keys.push(format!("{section}.{item}")),
            }
        }
        rows.push((keys, default.to_string()));
    }
    rows
}

/// Every `section.key` of the defaults, with its value. Keys written only when set (so that
/// manifests of maps built before them keep their checksums) are read from a config that sets
/// them, with the default's value.
fn code_keys() -> BTreeMap<String, Value> {
    let mut v = serde_json::to_value(semlook::config::Config::default()).unwrap();
    let mut set = semlook::config::Config::default();
    set.appearance.ignore_classes = vec!["sky".into()];
    set.sequence.velocity_scale = Some(1.0);
    let set = serde_json::to_value(set).unwrap();
    for (section, body) in set.as_object().unwrap() {
        for k in body.as_object().into_iter().flat_map(|b| b.keys()) {
            if v[section].get(k).is_none() {
                v[section][k] = Value::Array(vec![]);
            }
        }
    }
    let mut out = BTreeMap::new();
    for (section, body) in v.as_object().unwrap() {
        match body.as_object() {
            Some(keys) => {
                for (k, val) in keys {
                    out.insert(format!("{section}.{k}"), val.clone());
                }
            }
            None => {
                out.insert(section.clone(), body.clone());
            }
        }
    }
    out
}

/// A doc cell's value when it is plain: `64`, `0.5`, `true`, `"fused"`, `[1, 5, 10]`.
fn plain(cell: &str) -> Option<Value> {
    let c = cell.trim().trim_matches('`');
    serde_json::from_str::<Value>(c).ok()
}

/// The cell of a row naming `n` keys, split into `n` values (top-level commas, outside brackets).
fn split(cell: &str, n: usize) -> Option<Vec<String>> {
    if n == 1 {
        return Some(vec![cell.to_string()]);
    }
    let mut parts = vec![String::new()];
    let mut depth = 0;
    for c in cell.chars() {
        match c {
            '[' => depth += 1,
            ']' => depth -= 1,
            ',' if depth == 0 => {
                parts.push(String::new());
                continue;
            }
            _ => {}
        }
        parts.last_mut().unwrap().push(c);
    }
    (parts.len() == n).then_some(parts)
}

/// Equal values, numbers by value (`1` is `1.0`), lists item by item.
fn same(doc: &Value, code: &Value) -> bool {
    match (doc, code) {
        (Value::Array(a), Value::Array(b)) => a.len() == b.len() && a.iter().zip(b).all(|(x, y)| same(x, y)),
        _ => match (doc.as_f64(), code.as_f64()) {
            (Some(a), Some(b)) => (a - b).abs() <= 1e-12 * b.abs().max(1.0),
            _ => doc == code,
        },
    }
}

#[test]
fn the_config_doc_names_every_key_and_its_default() {
    let code = code_keys();
    let rows = doc_rows();
    assert!(rows.len() >= 40 && code.len() >= 60, "read {} rows, {} keys", rows.len(), code.len());
    let documented: BTreeSet<String> = rows.iter().flat_map(|(k, _)| k.iter().cloned()).collect();
    let undocumented: Vec<&String> = code.keys().filter(|k| !documented.contains(*k)).collect();
    let unknown: Vec<&String> = documented.iter().filter(|k| !code.contains_key(*k)).collect();
    assert!(undocumented.is_empty(), "keys of the code that docs/config.md does not name: {undocumented:?}");
    assert!(unknown.is_empty(), "keys docs/config.md names that the code does not have: {unknown:?}");
    let (mut checked, mut wrong) = (0, vec![]);
    for (keys, cell) in &rows {
        let Some(parts) = split(cell, keys.len()) else { continue };
        for (k, part) in keys.iter().zip(parts) {
            if let Some(doc) = plain(&part) {
                checked += 1;
                if !same(&doc, &code[k]) {
                    wrong.push(format!("{k}: docs/config.md says {doc}, the code {}", code[k]));
                }
            }
        }
    }
    assert!(checked >= 40, "only {checked} plain defaults read");
    assert!(wrong.is_empty(), "defaults docs/config.md misstates:\n{}", wrong.join("\n"));
}

/// The library example of docs/library.md (the first `rust` block under "## Library") is the doc
/// test of src/lib.rs (the `no_run` block of its crate docs, hidden `# ` lines left out), so the
/// example a reader copies is one the tests compile.
#[test]
fn the_library_example_is_the_compiled_one() {
    let root = env!("CARGO_MANIFEST_DIR");
    let md = std::fs::read_to_string(format!("{root}/docs/library.md")).unwrap();
    let after = &md[md.find("## Library").expect("docs/library.md has a ## Library section")..];
    let start = after.find("```rust\n").expect("a rust block under ## Library") + "```rust\n".len();
    let doc_example: Vec<&str> = after[start..].split("\n```").next().unwrap().lines().collect();
    let lib = std::fs::read_to_string(format!("{root}/src/lib.rs")).unwrap();
    let crate_doc: Vec<&str> = lib.lines().filter_map(|l| l.strip_prefix("//!")).map(|l| l.strip_prefix(' ').unwrap_or(l)).collect();
    let open = crate_doc.iter().position(|l| *l == "```no_run").expect("src/lib.rs has a no_run example");
    let close = open + 1 + crate_doc[open + 1..].iter().position(|l| *l == "```").expect("the example ends");
    let compiled: Vec<&str> = crate_doc[open + 1..close].iter().copied().filter(|l| !l.starts_with("# ") && *l != "#").collect();
    assert!(compiled.len() >= 10, "the compiled example was not read: {compiled:?}");
    assert_eq!(doc_example, compiled, "docs/library.md's example differs from src/lib.rs's doc test");
}

/// The profiles in configs/ load and pass validation (a key renamed or a value out of range in the
/// code fails here, not in a user's run).
#[test]
fn the_config_profiles_load() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("configs");
    let mut n = 0;
    for e in std::fs::read_dir(&dir).unwrap() {
        let path = e.unwrap().path();
        if path.extension().is_some_and(|x| x == "toml") {
            semlook::config::Config::load(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            n += 1;
        }
    }
    assert!(n >= 2, "profiles found in {}: {n}", dir.display());
}

/// README's two commands are the ones `.ci/run` runs (issue 50): the main job (`bash setup.sh && ...`)
/// and the test command (`bash setup.sh --tests && ...`), character for character, so a newcomer
/// runs what CI checks.
#[test]
fn readme_commands_are_the_ones_ci_runs() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let ci = std::fs::read_to_string(root.join(".ci/run")).unwrap();
    let commands: Vec<&str> =
        readme.lines().filter(|l| l.starts_with("bash setup.sh") && l.contains(" && ")).map(|l| l.split("  #").next().unwrap().trim()).collect();
    assert_eq!(commands.len(), 2, "README names two commands that start with `bash setup.sh`: {commands:?}");
    for c in &commands {
        assert!(ci.contains(&format!("bash -c '{c}'")) || ci.contains(&format!("{c} ||")), ".ci/run does not run README's `{c}`");
    }
}

/// Every relative link of README and of the docs' pages points at a file or folder of the
/// repository (anchors and web addresses aside).
#[test]
fn readme_and_docs_links_resolve() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let mut pages = vec![root.join("README.md"), root.join("sweeps/README.md")];
    for e in std::fs::read_dir(root.join("docs")).unwrap().flatten() {
        if e.path().extension().is_some_and(|x| x == "md") {
            pages.push(e.path());
        }
    }
    let mut broken = vec![];
    for page in &pages {
        let text = std::fs::read_to_string(page).unwrap();
        let mut rest = text.as_str();
        while let Some(i) = rest.find("](") {
            rest = &rest[i + 2..];
            let Some(end) = rest.find(')') else { break };
            let target = rest[..end].split('#').next().unwrap().trim();
            rest = &rest[end..];
            if target.is_empty() || target.contains("://") || target.starts_with("mailto:") || target.contains(' ') {
                continue;
            }
            if !page.parent().unwrap().join(target).exists() {
                broken.push(format!("{}: {target}", page.strip_prefix(root).unwrap().display()));
            }
        }
    }
    assert!(broken.is_empty(), "links to nothing: {broken:?}");
}

/// The numbers with a decimal point in `text` (`0.709`, `16.1`, `1,392.5`), each whole: a number
/// that a letter, digit, `.` or `_` touches (a commit hash, a version `1.2.3`, `v0.8`) is none.
fn decimal_figures(text: &str) -> BTreeSet<String> {
    let b = text.as_bytes();
    let word = |c: u8| c.is_ascii_alphanumeric() || c == b'_';
    let mut found = BTreeSet::new();
    let mut i = 0;
    while i < b.len() {
        if !b[i].is_ascii_digit() || (i > 0 && (word(b[i - 1]) || b[i - 1] == b'.')) {
            i += 1;
            continue;
        }
        let start = i;
        // the whole part, thousands commas included
        while i < b.len() && (b[i].is_ascii_digit() || (b[i] == b',' && b.get(i + 1).is_some_and(u8::is_ascii_digit))) {
            i += 1;
        }
        if b.get(i) != Some(&b'.') || !b.get(i + 1).is_some_and(u8::is_ascii_digit) {
            // an integer, or part of a word: skip the rest of it
            while i < b.len() && (word(b[i]) || b[i] == b'.') {
                i += 1;
            }
            continue;
        }
        i += 1;
        while i < b.len() && b[i].is_ascii_digit() {
            i += 1;
        }
        let touched = b.get(i).is_some_and(|&c| word(c)) || (b.get(i) == Some(&b'.') && b.get(i + 1).is_some_and(u8::is_ascii_digit));
        if !touched {
            found.insert(text[start..i].to_string());
        }
        while i < b.len() && (word(b[i]) || b[i] == b'.') {
            i += 1;
        }
    }
    found
}

/// The prose of a markdown page: fenced code blocks, link targets and web addresses left out.
fn prose(md: &str) -> String {
    let mut out = String::new();
    let mut fenced = false;
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            fenced = !fenced;
            continue;
        }
        if fenced {
            continue;
        }
        let mut rest = line;
        while let Some(i) = rest.find("](") {
            out.push_str(&rest[..i + 1]);
            rest = rest[i + 2..].split_once(')').map_or("", |(_, after)| after);
        }
        out.push_str(&rest.split_whitespace().filter(|w| !w.contains("://")).collect::<Vec<_>>().join(" "));
        out.push('\n');
    }
    out
}

/// The `semlook` commands of a page's fenced `sh` blocks: for each, the words of its command path
/// (`["map", "build"]`: after the program and its leading options, the lowercase words up to the
/// first option or argument) and its line.
fn semlook_commands(md: &str) -> Vec<(Vec<String>, String)> {
    let is_word =
        |w: &str| w.starts_with(|c: char| c.is_ascii_lowercase()) && w.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-');
    let mut commands = vec![];
    let (mut fenced, mut in_sh) = (false, false);
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            in_sh = !fenced && line.trim() == "```sh";
            fenced = !fenced;
            continue;
        }
        if !in_sh {
            continue;
        }
        let code = line.split(" #").next().unwrap();
        let words: Vec<&str> = code.split_whitespace().take_while(|w| !w.starts_with('#')).collect();
        for (i, w) in words.iter().enumerate() {
            // the program (`semlook`, `target/release/semlook`), not an option's value (`--bin .../semlook`)
            let program = *w == "semlook" || w.ends_with("/semlook");
            let an_option_value = i > 0 && words[i - 1].starts_with('-');
            if !program || an_option_value {
                continue;
            }
            let mut j = i + 1;
            while j < words.len() && words[j].starts_with('-') {
                j += if words[j] == "--backend" { 2 } else { 1 };
            }
            let path = words[j.min(words.len())..].iter().take_while(|w| is_word(w)).map(|w| w.to_string()).collect();
            commands.push((path, line.trim().to_string()));
        }
    }
    commands
}

/// Every figure README shows is traced (issue 58 part 5): each number with a decimal point in its
/// prose (fenced code, link targets and web addresses aside) is, word for word, on a measurement
/// page README links to: a linked `.md` page with a fenced `sh` block that runs `semlook`. The
/// `semlook` commands of those pages' `sh` blocks name only commands docs/cli.md lists (the
/// synopsis cli/tests/cli.rs holds to `--help`), so the command beside a figure is one that exists.
/// Every untraced figure and every unknown command is listed at once.
#[test]
fn readme_figures_are_on_measurement_pages() {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let readme = std::fs::read_to_string(root.join("README.md")).unwrap();
    let figures = decimal_figures(&prose(&readme));
    assert!(figures.len() >= 40, "only {} figures read from README: {figures:?}", figures.len());
    // the pages README links to
    let mut linked = BTreeSet::new();
    let mut rest = readme.as_str();
    while let Some(i) = rest.find("](") {
        rest = &rest[i + 2..];
        let Some(end) = rest.find(')') else { break };
        let target = rest[..end].split('#').next().unwrap().trim();
        if target.ends_with(".md") && !target.contains("://") {
            linked.insert(target.to_string());
        }
        rest = &rest[end..];
    }
    // the commands docs/cli.md lists: the `semlook ...` lines of its synopsis (its first fenced block)
    let cli = std::fs::read_to_string(root.join("docs/cli.md")).unwrap();
    let synopsis = cli.split("```").nth(1).expect("docs/cli.md's synopsis block");
    let known: BTreeSet<Vec<String>> = synopsis
        .lines()
        .filter_map(|l| l.strip_prefix("semlook "))
        .map(|l| {
            let is_word = |w: &&str| w.starts_with(|c: char| c.is_ascii_lowercase()) && w.chars().all(|c| c.is_ascii_lowercase() || c == '-');
            l.split_whitespace().take_while(is_word).map(str::to_string).collect()
        })
        .collect();
    assert!(known.len() >= 20, "docs/cli.md's commands not read: {known:?}");
    let mut measurement_pages = vec![];
    let mut traced = BTreeSet::new();
    let mut unknown = vec![];
    for page in &linked {
        let text = std::fs::read_to_string(root.join(page)).unwrap_or_else(|e| panic!("{page}: {e}"));
        let commands = semlook_commands(&text);
        if commands.is_empty() {
            continue;
        }
        for (path, line) in &commands {
            if !known.iter().any(|k| path.starts_with(k)) {
                unknown.push(format!("{page}: `{line}`"));
            }
        }
        traced.extend(decimal_figures(&text));
        measurement_pages.push(page.as_str());
    }
    assert!(measurement_pages.len() >= 3, "README links to {} measurement pages: {measurement_pages:?}", measurement_pages.len());
    let untraced: Vec<&String> = figures.iter().filter(|f| !traced.contains(*f)).collect();
    assert!(
        untraced.is_empty() && unknown.is_empty(),
        "README's figures on no measurement page it links to ({}): {untraced:?}\n`semlook` commands of those pages that docs/cli.md does not list: {unknown:?}",
        measurement_pages.join(", ")
    );
}
