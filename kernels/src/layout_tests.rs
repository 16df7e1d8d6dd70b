//! The Rust side of every shader interface, held to naga's reflection of the WGSL: each struct the
//! host writes (sizes and member offsets), each constant both sides must agree on, and each
//! entry point's same-name CPU twin. Nothing here is hand-mirrored: a field added, moved or
//! retyped on one side only fails these tests.

use super::wgsl::{preprocess, INCLUDES, SHADERS};
use naga::{Expression, Literal, TypeInner};
use std::mem::{offset_of, size_of};

fn module(file: &str) -> naga::Module {
    let src = SHADERS.iter().chain(&INCLUDES).find(|s| s.0 == file).unwrap_or_else(|| panic!("no shader {file}")).1;
    naga::front::wgsl::parse_str(&preprocess(src, &[]).unwrap()).unwrap_or_else(|e| panic!("{file}: {e}"))
}

/// (size, [(member, offset)]) of the WGSL struct `name`.
fn wgsl_struct(m: &naga::Module, file: &str, name: &str) -> (usize, Vec<(String, usize)>) {
    let ty = m.types.iter().find(|(_, t)| t.name.as_deref() == Some(name)).unwrap_or_else(|| panic!("{file}: no struct {name}")).1;
    match &ty.inner {
        TypeInner::Struct { members, span } => {
            (*span as usize, members.iter().map(|mb| (mb.name.clone().unwrap_or_default(), mb.offset as usize)).collect())
        }
        other => panic!("{file}: {name} is {other:?}"),
    }
}

/// The size and the named members' offsets of a Rust struct.
macro_rules! rust {
    ($t:ty { $($f:ident),* $(,)? }) => {
        (size_of::<$t>(), vec![$((stringify!($f), offset_of!($t, $f))),*])
    };
}

/// The struct `name` of `file` has the Rust struct's size, and every member the same offset on
/// both sides (WGSL padding members, named `_...`, are covered by the size).
fn same_layout(file: &str, name: &str, rust: (usize, Vec<(&str, usize)>)) {
    let (size, members) = wgsl_struct(&module(file), file, name);
    assert_eq!(size, rust.0, "{file}: {name} is {size} bytes in WGSL, {} in Rust", rust.0);
    for (m, off) in members.iter().filter(|(m, _)| !m.starts_with('_')) {
        let r = rust.1.iter().find(|(f, _)| f == m).unwrap_or_else(|| panic!("{file}: {name}.{m} has no Rust field"));
        assert_eq!(*off, r.1, "{file}: {name}.{m} at {off} in WGSL, {} in Rust", r.1);
    }
    for (f, _) in &rust.1 {
        assert!(members.iter().any(|(m, _)| m == f), "{file}: Rust field {name}.{f} is not in the WGSL struct");
    }
}

#[test]
fn shared_structs_have_the_shaders_layouts() {
    use crate::abi::*;
    same_layout("abi.wgsl", "SsimParams", rust!(SsimParams { gw, gh, win, nw, nh, c1, c2, cov_norm }));
    same_layout("ssim_topk.wgsl", "TileParams", rust!(TileParams { queries, tile_len, tile_start, k }));
    same_layout("abi.wgsl", "PassParams", rust!(PassParams { queries, refs, ref_first, ref_index, rb, qb, k, segs, parity, fresh }));
    same_layout("topk_select.wgsl", "Entry", rust!(Entry { score, index }));
    same_layout(
        "tree_similarity.wgsl",
        "TreeSimParams",
        rust!(TreeSimParams {
            w_area,
            w_position,
            w_appearance,
            w_intrinsic,
            w_neighbours,
            position_sigma,
            neutral,
            gaussian_position,
            drop_missing,
            use_appearance,
            greedy,
            neighbour_slots,
            tree_weight,
            geometric_norm,
            class_key
        }),
    );
    same_layout(
        "tree_similarity.wgsl",
        "FinePass",
        rust!(FinePass { dim, pairs, max_trees, grid, queries, refs, ref_first, list_first, row, out_first, pair_first, skip_small }),
    );
    same_layout("tree_similarity.wgsl", "Tree", rust!(GpuTree { class_id, has_app, area, cx, cy, weight, nb }));
    same_layout("vlad_accumulate.wgsl", "VladParams", rust!(VladParams { centres, dim, keypoints, objects, power_norm, intra_norm }));
    same_layout("global_pool.wgsl", "PoolParams", rust!(PoolParams { src_width, src_height, dst_width, dst_height, tau, frames }));
    same_layout("abi.wgsl", "Dims", rust!(Dims { width, height, frames, first }));
    use crate::abi::{ConvParams, MapParams, NormParams};
    same_layout(
        "xfeat.wgsl",
        "ConvParams",
        rust!(ConvParams { cin, cout, h, w, ho, wo, k, stride, pad, chunk, rows, cols, pitch, weight_at, sub_at, mul_at, act, has_add }),
    );
    same_layout("xfeat.wgsl", "MapParams", rust!(MapParams { c, h, w, ho, wo, k, row, n, h1, w1, h2, w2, sy1, sx1, sy2, sx2, inv }));
    same_layout("xfeat.wgsl", "NormParams", rust!(NormParams { n, chunks, row, chunk_row }));
    use crate::abi::{EffConvParams, EffPointParams, GemParams};
    same_layout(
        "efficientnet.wgsl",
        "EffConvParams",
        rust!(EffConvParams { cin, cout, h, w, ho, wo, k, stride, pad_top, pad_left, depthwise, relu6, scale, shift, row, n }),
    );
    same_layout("efficientnet.wgsl", "EffPointParams", rust!(EffPointParams { cin, cout, hw, relu6, residual }));
    same_layout("efficientnet.wgsl", "GemParams", rust!(GemParams { c, hw }));
    same_layout(
        "lighterglue.wgsl",
        "LgParams",
        rust!(crate::abi::LgParams { rows, n_in, n_out, split, w_off, b_off, g_off, flags, scale, o_off, q_off, k_off, v_off }),
    );
}

/// The value of the WGSL constant `name` of `file`, as f64.
fn wgsl_const(file: &str, name: &str) -> f64 {
    let m = module(file);
    let c = m.constants.iter().find(|(_, c)| c.name.as_deref() == Some(name)).unwrap_or_else(|| panic!("{file}: no const {name}")).1;
    match m.global_expressions[c.init] {
        Expression::Literal(Literal::U32(v)) => v as f64,
        Expression::Literal(Literal::I32(v)) => v as f64,
        Expression::Literal(Literal::F32(v)) => v as f64,
        ref e => panic!("{file}: {name} = {e:?}"),
    }
}

#[test]
fn shared_constants_agree() {
    use crate::lighterglue as lg;
    use crate::xfeat as xf;
    use crate::{abi, ssim_block as b, topk_select as t};
    let checks: [(&str, &str, f64); 39] = [
        ("ssim_topk.wgsl", "LANES", crate::ssim::LANES as f64),
        ("ssim_topk.wgsl", "MAX_ROW_SUMS", crate::abi::MAX_ROW_SUMS as f64),
        ("ssim_block.wgsl", "LANES", crate::ssim::LANES as f64),
        ("ssim_block.wgsl", "PAIR_CAP", b::PAIR_CAP as f64),
        ("ssim_block.wgsl", "PROD_CAP", b::PROD_CAP as f64),
        ("ssim_block.wgsl", "RING_CAP", b::RING_CAP as f64),
        ("topk_select.wgsl", "LANES", t::LANES as f64),
        ("topk_select.wgsl", "SEG", t::SEG as f64),
        ("topk_select.wgsl", "MAX_LISTS", t::MAX_LISTS as f64),
        ("abi.wgsl", "EMPTY_SCORE", abi::EMPTY_SCORE as f64),
        ("abi.wgsl", "EMPTY_INDEX", abi::EMPTY_INDEX as f64),
        ("topk_select.wgsl", "NONE", abi::EMPTY_INDEX as f64),
        ("tree_similarity.wgsl", "LANES", crate::tree_similarity::LANES as f64),
        ("tree_similarity.wgsl", "PAIRS_PER_GROUP", crate::tree_similarity::PAIRS_PER_GROUP as f64),
        ("tree_similarity.wgsl", "SMALL_CELLS", crate::tree_similarity::SMALL_CELLS as f64),
        ("tree_similarity.wgsl", "SMALL_TREES", crate::tree_similarity::SMALL_TREES as f64),
        ("tree_similarity.wgsl", "MAX_TREES", crate::abi::MAX_TREES as f64),
        ("tree_similarity.wgsl", "MAX_SLOTS", crate::abi::MAX_SLOTS as f64),
        ("tree_similarity.wgsl", "MISSING", crate::tree_similarity::MISSING as f64),
        ("tree_similarity.wgsl", "NOT_A_PAIR", crate::tree_similarity::NOT_A_PAIR as f64),
        ("vlad_accumulate.wgsl", "LANES", crate::vlad_accumulate::LANES as f64),
        ("xfeat.wgsl", "LANES", xf::LANES as f64),
        ("xfeat.wgsl", "CHUNK", xf::CHUNK as f64),
        ("xfeat.wgsl", "TILE_W", xf::TILE_W as f64),
        ("xfeat.wgsl", "TILE_H", xf::TILE_H as f64),
        ("xfeat.wgsl", "CO_GROUP", xf::CO_GROUP as f64),
        ("xfeat.wgsl", "IN_CAP", xf::IN_CAP as f64),
        ("xfeat.wgsl", "W_CAP", xf::W_CAP as f64),
        ("xfeat.wgsl", "THREADS", xf::THREADS as f64),
        ("xfeat.wgsl", "ACT_RELU", xf::ACT_RELU as f64),
        ("xfeat.wgsl", "ACT_SIGMOID", xf::ACT_SIGMOID as f64),
        ("lighterglue.wgsl", "LANES", lg::LANES as f64),
        ("lighterglue.wgsl", "TILE", lg::TILE as f64),
        ("lighterglue.wgsl", "LN_ROWS", lg::LN_ROWS as f64),
        ("lighterglue.wgsl", "FLAG_ACCUMULATE", lg::FLAG_ACCUMULATE as f64),
        ("lighterglue.wgsl", "FLAG_GELU", lg::FLAG_GELU as f64),
        ("lighterglue.wgsl", "NO_PARTNER", lg::NO_PARTNER as f64),
        ("lighterglue.wgsl", "LN_EPS", lg::LN_EPS as f64),
        ("lighterglue.wgsl", "LOWEST", lg::LOWEST as f64),
    ];
    for (file, name, rust) in checks {
        assert_eq!(wgsl_const(file, name), rust, "{file}: {name}");
    }
}

/// Every entry point of every shader has a CPU twin of the same name in the file of the same name
/// in this crate (`shaders/x.wgsl` -> `kernels/src/x.rs`, `pub fn entry(`), and every file here
/// but the crate's root, the interface (ABI, bindings, sources), the value views, the generator,
/// the shared SSIM window and the tests is a shader's twin.
#[test]
fn every_kernel_has_a_same_name_twin() {
    let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("src");
    for (file, _) in SHADERS {
        let twin = dir.join(file.replace(".wgsl", ".rs"));
        let text = std::fs::read_to_string(&twin).unwrap_or_else(|e| panic!("{file}: no twin {}: {e}", twin.display()));
        for ep in &module(file).entry_points {
            assert!(
                text.contains(&format!("pub fn {}(", ep.name)),
                "{file}: entry point {} has no `pub fn {}(` in {}",
                ep.name,
                ep.name,
                twin.display()
            );
        }
    }
    for e in std::fs::read_dir(&dir).unwrap().flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(stem) = name.strip_suffix(".rs") else { continue };
        let shader = format!("{}.wgsl", stem.trim_end_matches("_tests"));
        let known = SHADERS.iter().chain(&INCLUDES).any(|s| s.0 == shader)
            || ["lib", "bindings", "wgsl", "values", "rng", "layout_tests", "test_data", "ssim"].contains(&stem);
        assert!(known, "kernels/src/{name} mirrors no shader");
    }
}

/// The workgroup memory the context requires of an adapter (`abi::WORKGROUP_STORAGE`) is
/// what the hungriest entry point uses, in every preprocessing variant: the workgroup variables
/// it reaches, each rounded up to 16 bytes as WebGPU counts them.
#[test]
fn the_context_requires_the_workgroup_memory_the_kernels_use() {
    let mut most = (0u64, String::new());
    for (file, src) in SHADERS {
        for defs in [&[][..], &["SUBGROUPS"][..]] {
            let m = naga::front::wgsl::parse_str(&preprocess(src, defs).unwrap()).unwrap_or_else(|e| panic!("{file}: {e}"));
            let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
                .validate(&m)
                .unwrap_or_else(|e| panic!("{file}: {e:?}"));
            for (i, ep) in m.entry_points.iter().enumerate() {
                let uses = info.get_entry_point(i);
                let bytes: u64 = m
                    .global_variables
                    .iter()
                    .filter(|(h, g)| g.space == naga::AddressSpace::WorkGroup && !uses[*h].is_empty())
                    .map(|(_, g)| (m.types[g.ty].inner.size(m.to_ctx()) as u64).next_multiple_of(16))
                    .sum();
                if bytes > most.0 {
                    most = (bytes, format!("{file}: {}", ep.name));
                }
            }
        }
    }
    assert_eq!(most.0, crate::abi::WORKGROUP_STORAGE, "the most workgroup memory is {} bytes, in {}", most.0, most.1);
    assert!(most.0 <= 16_384, "{}: beyond WebGPU's guaranteed 16 KiB", most.1);
}

/// Every entry point's bind groups as the host lists them (`bindings::BINDINGS`, what the
/// pipelines are built from) are the shader's, checked from naga's reflection with no adapter:
/// each binding the entry point uses (in every preprocessing variant) is listed in its group with
/// its address space and access (uniform; storage read-only; storage read-write), each listed
/// slot is a binding of the shader of that kind, and every entry point of every shader is listed.
#[test]
fn every_kernels_bind_groups_are_its_shaders() {
    use crate::bindings::{Slot, BINDINGS};
    for (file, _) in SHADERS {
        for ep in &module(file).entry_points {
            assert!(BINDINGS.iter().any(|b| b.0 == file && b.1 == ep.name), "{file}: entry point {} has no bind groups listed", ep.name);
        }
    }
    let kind = |g: &naga::GlobalVariable| match g.space {
        naga::AddressSpace::Uniform => "uniform",
        naga::AddressSpace::Storage { access } if access.contains(naga::StorageAccess::STORE) => "storage read-write",
        naga::AddressSpace::Storage { .. } => "storage read-only",
        _ => "other",
    };
    let slot_kind = |s: &Slot| match s {
        Slot::Uniform | Slot::UniformAt(_) => "uniform",
        Slot::Read => "storage read-only",
        Slot::ReadWrite => "storage read-write",
    };
    let mut problems = vec![];
    for (file, entry, groups) in BINDINGS {
        let src = SHADERS.iter().find(|s| s.0 == *file).unwrap_or_else(|| panic!("BINDINGS names {file}, not a shader")).1;
        for defs in [&[][..], &["SUBGROUPS"][..]] {
            let m = naga::front::wgsl::parse_str(&preprocess(src, defs).unwrap()).unwrap_or_else(|e| panic!("{file}: {e}"));
            let info = naga::valid::Validator::new(naga::valid::ValidationFlags::all(), naga::valid::Capabilities::all())
                .validate(&m)
                .unwrap_or_else(|e| panic!("{file}: {e:?}"));
            let Some(i) = m.entry_points.iter().position(|ep| ep.name == *entry) else {
                problems.push(format!("{file}: no entry point {entry}"));
                continue;
            };
            let uses = info.get_entry_point(i);
            for (h, g) in m.global_variables.iter() {
                let Some(rb) = &g.binding else { continue };
                let listed = groups.get(rb.group as usize).and_then(|s| s.iter().find(|(b, _)| *b == rb.binding));
                match listed {
                    None if !uses[h].is_empty() => {
                        problems.push(format!("{file}:{entry} uses @group({}) @binding({}), which is not listed", rb.group, rb.binding))
                    }
                    Some((_, s)) if slot_kind(s) != kind(g) => problems.push(format!(
                        "{file}:{entry} @group({}) @binding({}) is {} in the shader, listed as {}",
                        rb.group,
                        rb.binding,
                        kind(g),
                        slot_kind(s)
                    )),
                    _ => {}
                }
            }
            for (group, slots) in groups.iter().enumerate() {
                for (b, _) in slots.iter() {
                    let declared =
                        m.global_variables.iter().any(|(_, g)| g.binding.as_ref().is_some_and(|rb| rb.group as usize == group && rb.binding == *b));
                    if !declared {
                        problems.push(format!("{file}:{entry}: listed @group({group}) @binding({b}) is not in the shader"));
                    }
                }
            }
        }
    }
    problems.dedup();
    assert!(problems.is_empty(), "bind groups that are not the shaders':\n{}", problems.join("\n"));
}
