//! Validates every WGSL shader, in every variant, with naga before the crate compiles (as vello
//! does): a shader error fails the build with the file, line and column. The pipelines are built
//! from the same sources (`src/wgsl.rs`, included here), so what runs is what was checked.

#[path = "src/wgsl.rs"]
#[allow(dead_code)]
mod wgsl;

use naga::valid::{Capabilities, ShaderStages, SubgroupOperationSet, ValidationFlags, Validator};

fn main() {
    println!("cargo:rerun-if-changed=../shaders");
    println!("cargo:rerun-if-changed=src/wgsl.rs");
    let mut failures = Vec::new();
    for (name, src) in wgsl::INCLUDES {
        let path = format!("shaders/{name}");
        let ok = naga::front::wgsl::parse_str(src).map_err(|e| e.emit_to_string_with_path(src, &path)).and_then(|m| {
            Validator::new(ValidationFlags::all(), Capabilities::empty()).validate(&m).map(|_| ()).map_err(|e| e.emit_to_string_with_path(src, &path))
        });
        if let Err(e) = ok {
            failures.push(format!("{path}:\n{e}"));
        }
    }
    for (name, src) in wgsl::SHADERS {
        let path = format!("shaders/{name}");
        for on in wgsl::variants(src) {
            let what = if on.is_empty() { path.clone() } else { format!("{path} (with {})", on.join(", ")) };
            let text = match wgsl::preprocess(src, &on) {
                Ok(t) => t,
                Err(e) => {
                    failures.push(format!("{path}: {e}"));
                    continue;
                }
            };
            let module = match naga::front::wgsl::parse_str(&text) {
                Ok(m) => m,
                Err(e) => {
                    failures.push(format!("{what}:\n{}", e.emit_to_string_with_path(&text, &path)));
                    continue;
                }
            };
            let subgroups = on.contains(&"SUBGROUPS");
            let caps = if subgroups { Capabilities::SUBGROUP } else { Capabilities::empty() };
            let mut v = Validator::new(ValidationFlags::all(), caps);
            if subgroups {
                v.subgroup_stages(ShaderStages::COMPUTE).subgroup_operations(SubgroupOperationSet::all());
            }
            if let Err(e) = v.validate(&module) {
                failures.push(format!("{what}:\n{}", e.emit_to_string_with_path(&text, &path)));
            }
        }
    }
    if !failures.is_empty() {
        for f in &failures {
            // the variant, naga's message and its `┌─ file:line:column`
            let lines: Vec<&str> = f.lines().filter(|l| !l.trim().is_empty() && !l.trim_start().starts_with('│')).take(3).collect();
            println!("cargo:warning={}", lines.join(" ").replace("┌─", "at"));
        }
        panic!("WGSL validation failed:\n{}", failures.join("\n"));
    }
}
