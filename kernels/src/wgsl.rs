//! The shader sources and their one preprocessor directive, shared by the pipelines
//! (`semlook::gpu`) and the build script (`build.rs` includes this file), which validates every
//! variant of every shader with naga before the crate compiles.
//!
//! A shader may hold lines that only one variant compiles, between `//#if NAME`, an optional
//! `//#else` and `//#endif` (no nesting). Lines a variant leaves out become empty lines, so naga's
//! line numbers are the file's. The only name in use is `SUBGROUPS`: reductions through subgroup
//! operations where the adapter has them, through workgroup memory where it does not.
//!
//! `//#include FILE` appends one of [`INCLUDES`] (structs and constants several shaders share,
//! the WGSL side of `abi`) after the shader's last line: WGSL declarations may come in
//! any order, and the shader's own lines keep their numbers. Includes hold no directives.

/// The names a shader's variants are chosen by.
pub const DEFINES: [&str; 1] = ["SUBGROUPS"];

/// WGSL sources, by file name.
pub const SHADERS: [(&str, &str); 13] = [
    ("semantic_edges.wgsl", include_str!("../../shaders/semantic_edges.wgsl")),
    ("edt.wgsl", include_str!("../../shaders/edt.wgsl")),
    ("global_pool.wgsl", include_str!("../../shaders/global_pool.wgsl")),
    ("ssim_topk.wgsl", include_str!("../../shaders/ssim_topk.wgsl")),
    ("ssim_block.wgsl", include_str!("../../shaders/ssim_block.wgsl")),
    ("ssim_stats.wgsl", include_str!("../../shaders/ssim_stats.wgsl")),
    ("topk_select.wgsl", include_str!("../../shaders/topk_select.wgsl")),
    ("tree_similarity.wgsl", include_str!("../../shaders/tree_similarity.wgsl")),
    ("vlad_accumulate.wgsl", include_str!("../../shaders/vlad_accumulate.wgsl")),
    ("mnn_match.wgsl", include_str!("../../shaders/mnn_match.wgsl")),
    ("xfeat.wgsl", include_str!("../../shaders/xfeat.wgsl")),
    ("lighterglue.wgsl", include_str!("../../shaders/lighterglue.wgsl")),
    ("efficientnet.wgsl", include_str!("../../shaders/efficientnet.wgsl")),
];

/// Files shaders include, by file name; validated on their own by the build script too.
pub const INCLUDES: [(&str, &str); 1] = [("abi.wgsl", include_str!("../../shaders/abi.wgsl"))];

/// The names `src` branches on (in `DEFINES` order).
pub fn defines_used(src: &str) -> Vec<&'static str> {
    DEFINES.iter().copied().filter(|d| src.lines().any(|l| l.trim() == format!("//#if {d}"))).collect()
}

/// A preprocessor directive out of place (the build script includes this file, so the type stands
/// alone; `semlook::gpu` wraps it into `GpuError::Shader`).
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct DirectiveError {
    /// The directive's line (1-based); `None`: the end of the file.
    pub line: Option<usize>,
    /// What is wrong with the directive.
    pub reason: String,
}

impl std::fmt::Display for DirectiveError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self.line {
            Some(n) => write!(f, "line {n}: {}", self.reason),
            None => f.write_str(&self.reason),
        }
    }
}

impl std::error::Error for DirectiveError {}

/// `src` with the lines of the variant where the names in `on` are set; an error names the line
/// of a directive out of place.
pub fn preprocess(src: &str, on: &[&str]) -> Result<String, DirectiveError> {
    let at = |n: usize, reason: String| DirectiveError { line: Some(n + 1), reason };
    let mut out = String::with_capacity(src.len());
    // None: outside a block; Some(keep): inside one, keeping its lines or not
    let mut state: Option<bool> = None;
    let mut seen_else = false;
    let mut included: Vec<&str> = Vec::new();
    for (n, line) in src.lines().enumerate() {
        let t = line.trim();
        if let Some(name) = t.strip_prefix("//#include ") {
            let name = name.trim();
            if state.is_some() || included.contains(&name) || !INCLUDES.iter().any(|i| i.0 == name) {
                return Err(at(n, format!("cannot include {name:?} here (known: {:?}, once each, outside //#if)", INCLUDES.map(|i| i.0))));
            }
            included.push(name);
            out.push('\n');
            continue;
        }
        let keep = match (t.strip_prefix("//#if "), t, state) {
            (Some(name), _, None) => {
                if !DEFINES.contains(&name.trim()) {
                    return Err(at(n, format!("unknown name {name:?} (known: {DEFINES:?})")));
                }
                state = Some(on.contains(&name.trim()));
                seen_else = false;
                false
            }
            (None, "//#else", Some(k)) if !seen_else => {
                state = Some(!k);
                seen_else = true;
                false
            }
            (None, "//#endif", Some(_)) => {
                state = None;
                false
            }
            (Some(_), _, Some(_)) => return Err(at(n, "nested //#if".into())),
            (None, "//#else" | "//#endif", _) => return Err(at(n, format!("{t} without //#if"))),
            (None, _, s) => s.unwrap_or(true),
        };
        if keep {
            out.push_str(line);
        }
        out.push('\n');
    }
    if state.is_some() {
        return Err(DirectiveError { line: None, reason: "//#if without //#endif".into() });
    }
    for name in included {
        let text = INCLUDES.iter().find(|i| i.0 == name).map_or("", |i| i.1);
        out.push_str(&format!("// ---- shaders/{name} ----\n{text}"));
    }
    Ok(out)
}

/// Every variant of `src`: one per subset of the names it uses, with those names set.
pub fn variants(src: &str) -> Vec<Vec<&'static str>> {
    let used = defines_used(src);
    (0..1usize << used.len()).map(|mask| used.iter().enumerate().filter(|(i, _)| mask >> i & 1 == 1).map(|(_, d)| *d).collect()).collect()
}
