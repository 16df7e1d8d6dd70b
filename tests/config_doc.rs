//! docs/config.md is held to the code: its table names every key of every section of
//! `Config::default()` and no other, and where a row's default is a plain value (a number, a
//! boolean, a quoted string, a list of numbers) it is the code's default, key by key.

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

/// Every `section.key` of the defaults, with its value.
fn code_keys() -> BTreeMap<String, Value> {
    let v = serde_json::to_value(semlook::config::Config::default()).unwrap();
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
