//! The host side of the shaders' structs and limits (`#[repr(C)]`, bytemuck), checked field by
//! field against naga's reflection of the WGSL (`layout_tests`): the CPU twins (this crate) and
//! the GPU executors (`semlook::gpu`) both import them from here. They hold numbers only: the
//! library makes them from its configuration (`semlook::config`).

/// Score of an empty top-K slot (below any SSIM, which lies in [-1, 1]).
pub const EMPTY_SCORE: f32 = -3.0e38;
/// Index of an empty top-K slot.
pub const EMPTY_INDEX: u32 = u32::MAX;
/// Most neighbour slots the shader's tree record holds: its `MAX_SLOTS`.
pub const MAX_SLOTS: usize = 8;
/// Most trees per forest the shader's per-workgroup flags hold: its `MAX_TREES`.
pub const MAX_TREES: usize = 256;

/// The shader's `Tree`.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct GpuTree {
    /// The tree's class (trees pair by its key, `TreeSimParams::key`).
    pub class_id: u32,
    /// 1 where the tree has an appearance vector.
    pub has_app: u32,
    /// Area of its object, as a fraction of the image.
    pub area: f32,
    /// Centroid x, in image diagonals.
    pub cx: f32,
    /// Centroid y, in image diagonals.
    pub cy: f32,
    /// The tree's weight (`TreeSimParams::tree_weight`).
    pub weight: f32,
    /// Neighbour indices into the forest, -1 for an empty slot.
    pub nb: [i32; MAX_SLOTS],
}

/// The shader's `FinePass`: one pass at a dynamic offset of the batch's parameter buffer.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct FinePass {
    /// Length of an appearance vector.
    pub dim: u32,
    /// Pairs this pass scores.
    pub pairs: u32,
    /// Stride of one pair's matrices in the scratch buffer (most trees per forest).
    pub max_trees: u32,
    /// 1: every query against a run of references (grid pair g = `pair_first` + j); 0: pairs
    /// listed in the lookup; 2: listed, each scored where its grid pair's score goes.
    pub grid: u32,
    /// Queries of the batch: their spans head the lookup.
    pub queries: u32,
    /// Grid passes: references per query (the row length of the output).
    pub refs: u32,
    /// Grid passes: the first reference of the chunk.
    pub ref_first: u32,
    /// Listed passes: where this pass's pairs start after the query spans.
    pub list_first: u32,
    /// Workgroups per row of the dispatch grid (workgroup = x + y * row).
    pub row: u32,
    /// Where this pass's scores start in `out`.
    pub out_first: u32,
    /// Grid passes: the grid pair of the dispatch's first pair.
    pub pair_first: u32,
    /// 1: `tree_similarity` skips the pairs `tree_similarity_small` scores.
    pub skip_small: u32,
}

/// Uniform parameters of the kernel, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct PoolParams {
    /// Width of the distance transform in pixels.
    pub src_width: u32,
    /// Height of the distance transform in pixels.
    pub src_height: u32,
    /// Width of the pooled output in cells.
    pub dst_width: u32,
    /// Height of the pooled output in cells.
    pub dst_height: u32,
    /// Truncation distance τ in pixels.
    pub tau: f32,
    /// Frames in a GPU batch (the twin handles one frame).
    pub frames: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 2],
}

/// Uniform parameters of `mnn_match`, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct MnnParams {
    /// Pairs in the batch.
    pub pairs: u32,
    /// u32 words per descriptor (dimension / 4).
    pub words: u32,
    /// Most keypoints of any image (rows of the per-pair output).
    pub max_keypoints: u32,
    /// Padding to the shader's layout.
    pub _pad: u32,
}

/// One (query, reference) pair: the ranges of their keypoints in the packed descriptor arrays
/// (in keypoints), in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct MnnPair {
    /// First keypoint of the query in the packed query descriptors.
    pub query_start: u32,
    /// Keypoints of the query.
    pub query_len: u32,
    /// First keypoint of the reference in the packed reference descriptors.
    pub ref_start: u32,
    /// Keypoints of the reference.
    pub ref_len: u32,
}

/// Sizes and constants shared by the SSIM kernel and its twin, in the shader's uniform order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct SsimParams {
    /// Descriptor width and height.
    pub gw: u32,
    /// Descriptor height.
    pub gh: u32,
    /// Window side.
    pub win: u32,
    /// Valid window positions per row and per column.
    pub nw: u32,
    /// Valid window positions per column.
    pub nh: u32,
    /// SSIM's first stabilising constant, K1^2 (descriptor values range over 1).
    pub c1: f32,
    /// SSIM's second stabilising constant, K2^2.
    pub c2: f32,
    /// N / (N - 1) for sample statistics, else 1.
    pub cov_norm: f32,
}

impl SsimParams {
    /// The sizes and constants of a `width` x `height` descriptor compared in `window` x `window`
    /// windows: SSIM's constants `k` = (K1, K2) (descriptor values range over 1), and sample
    /// (N - 1) or population covariance.
    pub fn new(width: usize, height: usize, window: usize, k: (f64, f64), sample_covariance: bool) -> Self {
        let win = window as u32;
        let n = (win * win) as f32;
        SsimParams {
            gw: width as u32,
            gh: height as u32,
            win,
            nw: (width - window + 1) as u32,
            nh: (height - window + 1) as u32,
            c1: (k.0 * k.0) as f32,
            c2: (k.1 * k.1) as f32,
            cov_norm: if sample_covariance { n / (n - 1.0) } else { 1.0 },
        }
    }
    /// Values of one descriptor (gw x gh).
    pub fn len(&self) -> usize {
        (self.gw * self.gh) as usize
    }
    /// Whether a descriptor has no values.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// Valid window positions of one descriptor (nw x nh).
    pub fn windows(&self) -> usize {
        (self.nw * self.nh) as usize
    }
    /// Length of a stats record: window means then window variances.
    pub fn stats_len(&self) -> usize {
        2 * self.windows()
    }
}

/// One pass of the coarse stage on the device, in the field order of the shaders' `PassParams`
/// (`ssim_block.wgsl`, `topk_select.wgsl`): some queries against a run of references of one map
/// chunk, then the top-K of that run merged into the running lists.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct PassParams {
    /// Queries in this pass (the bound query buffer's first `queries`).
    pub queries: u32,
    /// References in this pass: the row length of the scores.
    pub refs: u32,
    /// First reference of the pass in the bound map chunk.
    pub ref_first: u32,
    /// Map index of that reference (what the top-K lists report).
    pub ref_index: u32,
    /// Block shape: references and queries per workgroup.
    pub rb: u32,
    /// Queries per workgroup.
    pub qb: u32,
    /// Top-K list length.
    pub k: u32,
    /// Segments of `topk_select::SEG` references in this pass.
    pub segs: u32,
    /// Which running-list buffer holds the merge's input (0: the first).
    pub parity: u32,
    /// 1 on a query chunk's first pass: the running lists hold nothing yet and are not read (so
    /// no empty lists are written to the device first).
    pub fresh: u32,
    /// Padding to the shader's layout.
    pub _pad1: u32,
    /// Padding to the shader's layout.
    pub _pad2: u32,
}

/// Uniform parameters of a tile, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct TileParams {
    /// Queries in the batch.
    pub queries: u32,
    /// References in the tile.
    pub tile_len: u32,
    /// Map index of the tile's first reference.
    pub tile_start: u32,
    /// Top-K list length.
    pub k: u32,
}

/// One list entry, in the shader's layout: a score and the map index of its reference.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Entry {
    /// SSIM score, or [`EMPTY_SCORE`] for an empty slot.
    pub score: f32,
    /// Map index of the reference, or [`EMPTY_INDEX`] for an empty slot.
    pub index: u32,
}

impl Entry {
    /// An empty slot.
    pub const EMPTY: Entry = Entry { score: EMPTY_SCORE, index: EMPTY_INDEX };
}

/// Uniform parameters of the kernel, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct TreeSimParams {
    /// Weight of the area similarity S_A in S_in.
    pub w_area: f32,
    /// Weight of the position similarity S_P in S_in.
    pub w_position: f32,
    /// Weight of the appearance similarity S_V in S_in.
    pub w_appearance: f32,
    /// Weight of S_in in the tree similarity (w_intrinsic + w_neighbours = 1).
    pub w_intrinsic: f32,
    /// Weight of the neighbour similarity S_N in the tree similarity.
    pub w_neighbours: f32,
    /// Sigma of the Gaussian position similarity, in image diagonals.
    pub position_sigma: f32,
    /// Appearance similarity scored where appearance is missing on either side.
    pub neutral: f32,
    /// 1: Gaussian position similarity, 0: linear.
    pub gaussian_position: u32,
    /// 1: drop a missing appearance term and renormalise, 0: score it `neutral`.
    pub drop_missing: u32,
    /// 1: appearance takes part (SemLook local), 0: Forest only.
    pub use_appearance: u32,
    /// 1: greedy one-to-one, 0: best match per query tree.
    pub greedy: u32,
    /// Neighbour slots per tree (the S_N denominator).
    pub neighbour_slots: u32,
    /// Tree weight: 0 uniform, 1 area, 2 sqrt(area), 3 descriptor count + 1.
    pub tree_weight: u32,
    /// 1: divide by the geometric mean of the forests' total weights, 0: by the larger total.
    pub geometric_norm: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 2],
    /// Per class, the key trees pair by (the class itself, or its category), four u8 to a word:
    /// two trees may pair when their classes' keys are equal.
    pub class_key: [u32; 64],
}

impl TreeSimParams {
    /// The pairing key of class `c`.
    #[inline]
    pub fn key(&self, c: u8) -> u32 {
        (self.class_key[c as usize / 4] >> (8 * (c as u32 % 4))) & 0xff
    }

    /// The weight of a tree of relative area `area` aggregated from `descriptors` descriptors.
    #[inline]
    pub fn tree_weight(&self, area: f32, descriptors: u32) -> f32 {
        match self.tree_weight {
            1 => area,
            2 => area.max(0.0).sqrt(),
            3 => descriptors as f32 + 1.0,
            _ => 1.0,
        }
    }
}

/// Uniform parameters, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct VladParams {
    /// Codebook centres.
    pub centres: u32,
    /// Descriptor dimension.
    pub dim: u32,
    /// Descriptors to assign, over all objects.
    pub keypoints: u32,
    /// Objects, one VLAD vector each.
    pub objects: u32,
    /// 1: signed square root of the VLAD vector, 0: none.
    pub power_norm: u32,
    /// 1: L2-normalise each centre's residual sum, 0: none.
    pub intra_norm: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 2],
}

impl VladParams {
    /// `centres` x `dim` codebook, `keypoints` descriptors over `objects` objects; signed square
    /// root (`power`) and per-centre normalisation (`intra`) of the VLAD vectors.
    pub fn new(centres: usize, dim: usize, keypoints: usize, objects: usize, power: bool, intra: bool) -> Self {
        VladParams {
            centres: centres as u32,
            dim: dim as u32,
            keypoints: keypoints as u32,
            objects: objects as u32,
            power_norm: power as u32,
            intra_norm: intra as u32,
            _pad: [0; 2],
        }
    }
}

/// The `Dims` uniform of `semantic_edges.wgsl`, `edt.wgsl` and `ssim_stats.wgsl`: frames of
/// `width` x `height` pixels, `frames` of them from frame `first` of the bound buffers (the
/// statistics of a stored map's chunk are computed a run of frames at a time).
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct Dims {
    /// Frame width in pixels.
    pub width: u32,
    /// Frame height in pixels.
    pub height: u32,
    /// Frames to process.
    pub frames: u32,
    /// First frame to process in the bound buffers.
    pub first: u32,
}

/// 256 u8 keys, four to a little-endian word (as the kernel reads them).
pub fn pack_key(key: &[u8; 256]) -> [u32; 64] {
    std::array::from_fn(|w| (0..4).fold(0u32, |acc, l| acc | (key[4 * w + l] as u32) << (8 * l)))
}

/// `conv2d`'s uniform, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct ConvParams {
    /// Input channels.
    pub cin: u32,
    /// Output channels.
    pub cout: u32,
    /// Input height.
    pub h: u32,
    /// Input width.
    pub w: u32,
    /// Output height.
    pub ho: u32,
    /// Output width.
    pub wo: u32,
    /// Kernel side.
    pub k: u32,
    /// Stride.
    pub stride: u32,
    /// Zero padding on each side of the input, in pixels.
    pub pad: u32,
    /// Input channels per pass through workgroup memory.
    pub chunk: u32,
    /// Input tile rows ((TILE_H - 1) x stride + k), columns ((TILE_W - 1) x stride + k) and row
    /// pitch (columns rounded up to 8 mod 32).
    pub rows: u32,
    /// Input tile columns.
    pub cols: u32,
    /// Input tile row pitch.
    pub pitch: u32,
    /// Where the layer's packed weights, epilogue subtrahends and factors start in `weights`.
    pub weight_at: u32,
    /// Where the layer's epilogue subtrahends start in `weights`.
    pub sub_at: u32,
    /// Where the layer's epilogue factors start in `weights`.
    pub mul_at: u32,
    /// Activation after the epilogue: 0 none, 1 ReLU, 2 sigmoid.
    pub act: u32,
    /// 1: a tensor (`conv_add`) is added to the output after the activation, 0: none.
    pub has_add: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 2],
}

/// The uniform of the element-wise kernels (`avg_pool`, `space_to_depth8`, `bilinear_add`), in
/// the shader's field order. Invocation i = (x + y * row) * LANES + lane handles output value i
/// (of n).
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct MapParams {
    /// Channels (planes) of the output.
    pub c: u32,
    /// Input plane height.
    pub h: u32,
    /// Input plane width.
    pub w: u32,
    /// Output plane height.
    pub ho: u32,
    /// Output plane width.
    pub wo: u32,
    /// Window side and stride: the pooling window of `avg_pool`, 8 for `space_to_depth8`.
    pub k: u32,
    /// Workgroups per row of the dispatch grid.
    pub row: u32,
    /// Output values (c x ho x wo).
    pub n: u32,
    /// `bilinear_add`: the sizes of its second and third input, and the scales (source length /
    /// output length, as PyTorch computes them in f32) of their axes.
    pub h1: u32,
    /// `bilinear_add`: width of the second input.
    pub w1: u32,
    /// `bilinear_add`: height of the third input.
    pub h2: u32,
    /// `bilinear_add`: width of the third input.
    pub w2: u32,
    /// `bilinear_add`: vertical scale of the second input.
    pub sy1: f32,
    /// `bilinear_add`: horizontal scale of the second input.
    pub sx1: f32,
    /// `bilinear_add`: vertical scale of the third input.
    pub sy2: f32,
    /// `bilinear_add`: horizontal scale of the third input.
    pub sx2: f32,
    /// `avg_pool`: 1 / (k * k).
    pub inv: f32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 3],
}

/// The uniform of the instance-norm kernels, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct NormParams {
    /// Values of the grey input.
    pub n: u32,
    /// Chunks of CHUNK values (`instance_norm_partials`' workgroups).
    pub chunks: u32,
    /// Workgroups per grid row of `instance_norm_apply` and of `instance_norm_partials`.
    pub row: u32,
    /// Workgroups per grid row of `instance_norm_partials`.
    pub chunk_row: u32,
}

/// The uniform of `lighterglue.wgsl`'s kernels, in the shader's field order; which fields a
/// kernel reads is documented at each twin (`lighterglue`).
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct LgParams {
    /// Rows (points of the batch) the pass covers.
    pub rows: u32,
    /// Input width (`lg_linear`), row width (`lg_layer_norm`, `lg_gather`) or the descriptor
    /// dimension (`lg_rotary`, `lg_attention`, `lg_row_lse`, `lg_assignment_best`).
    pub n_in: u32,
    /// Output width (`lg_linear`).
    pub n_out: u32,
    /// `lg_linear`: input columns read from `a`; the rest from `b`.
    pub split: u32,
    /// Offset of the weight matrix in the weights buffer.
    pub w_off: u32,
    /// Offset of the bias (or the layer norm's shift).
    pub b_off: u32,
    /// Offset of the layer norm's gain.
    pub g_off: u32,
    /// `lg_linear`: FLAG_ACCUMULATE; `lg_layer_norm`: FLAG_GELU.
    pub flags: u32,
    /// Output scale (`lg_linear`) or score scale (the partner kernels).
    pub scale: f32,
    /// Offset of the output in its buffer.
    pub o_off: u32,
    /// Offsets of the queries, keys and values in `a` (the partner kernels, `lg_rotary`'s output).
    pub q_off: u32,
    /// Offset of the keys.
    pub k_off: u32,
    /// Offset of the values.
    pub v_off: u32,
    /// Padding to the shader's layout.
    pub _pad0: u32,
    /// Padding.
    pub _pad1: u32,
    /// Padding.
    pub _pad2: u32,
}

/// Workgroup memory the hungriest kernel uses (`mnn_match`'s tile: WebGPU's guaranteed 16 KiB;
/// `tree_similarity_small` takes 16,272 bytes), each variable rounded up to 16 bytes as WebGPU
/// counts it (`layout_tests` holds it to naga's reflection): an adapter with less cannot run
/// the kernels.
pub const WORKGROUP_STORAGE: u64 = 16_384;

/// Largest global height x valid windows per row that `ssim_tile`'s workgroup array holds: the
/// shader's `MAX_ROW_SUMS` (15 KiB of the 16 KiB every adapter has).
pub const MAX_ROW_SUMS: usize = 3840;

/// The uniform of `efficientnet.wgsl`'s `conv_direct` (a full or depthwise convolution, one
/// invocation per output value), in the shader's field order. Invocation i = (x + y * row) x
/// LANES + lane computes output value i (of n).
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct EffConvParams {
    /// Input channels.
    pub cin: u32,
    /// Output channels (= cin when depthwise).
    pub cout: u32,
    /// Input height.
    pub h: u32,
    /// Input width.
    pub w: u32,
    /// Output height.
    pub ho: u32,
    /// Output width.
    pub wo: u32,
    /// Kernel side.
    pub k: u32,
    /// Stride.
    pub stride: u32,
    /// Zero rows above the input (TensorFlow's SAME: the odd row falls below, outside the output).
    pub pad_top: u32,
    /// Zero columns left of the input.
    pub pad_left: u32,
    /// 1: each output channel reads its own input channel (weights [c, 1, k, k]); 0: every input
    /// channel (weights [cout, cin, k, k]).
    pub depthwise: u32,
    /// 1: ReLU6 after the bias.
    pub relu6: u32,
    /// In-bounds input values are read as x * scale + shift (padding stays 0).
    pub scale: f32,
    /// See `scale`.
    pub shift: f32,
    /// Workgroups per row of the dispatch grid.
    pub row: u32,
    /// Output values (cout x ho x wo).
    pub n: u32,
}

/// The uniform of `efficientnet.wgsl`'s `pointwise` (a 1x1 convolution as a matrix product), in
/// the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct EffPointParams {
    /// Input channels.
    pub cin: u32,
    /// Output channels.
    pub cout: u32,
    /// Pixels (h x w).
    pub hw: u32,
    /// 1: ReLU6 after the bias.
    pub relu6: u32,
    /// 1: the residual tensor is added last.
    pub residual: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 3],
}

/// The uniform of `efficientnet.wgsl`'s `gem_pool`, in the shader's field order.
#[derive(Debug, Clone, Copy, PartialEq, Default, bytemuck::Pod, bytemuck::Zeroable)]
#[repr(C)]
pub struct GemParams {
    /// Channels.
    pub c: u32,
    /// Pixels per channel.
    pub hw: u32,
    /// Padding to the shader's layout.
    pub _pad: [u32; 2],
}
