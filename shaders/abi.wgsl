// Structs and constants several shaders share: the WGSL side of `kernels/src/abi.rs` (the Rust
// structs are checked against these by the kernels crate's `layout_tests`). A shader takes them with
// `//#include abi.wgsl`; they are appended after its last line.

// Sizes of the SSIM kernels' descriptors and their constants (`ssim_block`, `ssim_topk`).
struct SsimParams {
    gw: u32,
    gh: u32,
    win: u32,
    nw: u32,
    nh: u32,
    c1: f32,
    c2: f32,
    cov_norm: f32,
}

// One pass of the device's coarse stage (`ssim_block`, `topk_select`).
struct PassParams {
    // queries in this pass (the bound query buffer's first `queries` entries)
    queries: u32,
    // references in this pass: the row length of `scores`
    refs: u32,
    // first reference of the pass in the bound map chunk
    ref_first: u32,
    // map index of that reference
    ref_index: u32,
    // block shape: references and queries per workgroup
    rb: u32,
    qb: u32,
    // top-K list length, segments of this pass, which running-list buffer holds the input
    k: u32,
    segs: u32,
    parity: u32,
    // 1 on a query chunk's first pass: the running lists are not read (they hold nothing yet)
    fresh: u32,
    _pad1: u32,
    _pad2: u32,
}

// Frame sizes of the encoding kernels (`semantic_edges`, `edt`, `ssim_stats`): `frames` frames from
// frame `first` of the bound buffers (only `ssim_stats` runs from a `first` other than 0).
struct Dims {
    width: u32,
    height: u32,
    frames: u32,
    first: u32,
}

// An empty top-K slot: a score below any SSIM and an index no reference has.
const EMPTY_SCORE: f32 = -3.0e38;
const EMPTY_INDEX: u32 = 0xffffffffu;

// The cross term's window sums in the twins' pair order (`kernels::ssim::pair_order_sum`): the
// window starting at j sums its values from pair_lo(j) on, `win - 1` of them in index order, then
// adds the one at pair_own(j, win) (windows j and j + 1, j even, share the first `win - 1`).
fn pair_lo(j: u32) -> u32 {
    return select(j, j + 1u, j % 2u == 0u);
}

fn pair_own(j: u32, win: u32) -> u32 {
    return select(j + win - 1u, j, j % 2u == 0u);
}
