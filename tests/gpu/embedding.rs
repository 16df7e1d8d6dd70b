//! The embedding network on the device (`shaders/efficientnet.wgsl`, executor
//! `networks::embedding::EmbedderGpu`) held to its CPU twins (`semlook_kernels::efficientnet`,
//! which the plan runs in `networks::embedding::forward_on_twins`) and to the native pass
//! (`EfficientNetLite::forward`, itself held to the ONNX graph by tests/embedding_native.rs).
//! Tolerances, and the largest differences seen on lavapipe (2-core development machine):
//!
//! - kernel vs twin, random inputs of awkward sizes (odd sides, stride 2 on even and odd sides,
//!   channel counts that fill no tile, empty outputs): `conv_direct` and `pointwise` within 1e-5
//!   relative to max(1, |twin|) (the twin sums in the shader's order; a GPU may fuse a multiply
//!   and an add), `gem_pool` within 1e-5 relative (pow's ulps);
//! - the whole network, a small random one (hermetic) and the real checkpoint where installed:
//!   device vs twins and device vs the native pass within 1 - cosine 1e-6 (the bound for
//!   the embedding is 1e-5).

use super::{common, gpu};
use semlook::gpu::GpuError;
use semlook::networks::embedding::{forward_on_twins, network_input, run_kernel, EfficientNetLite, EmbedderGpu, EMBEDDING_CHECKPOINT};
use semlook::nn::conv::Chw;
use semlook::nn::torch_pt::Tensor;
use semlook::util::SplitMix64;
use semlook_kernels::abi::{EffConvParams, EffPointParams, GemParams};
use semlook_kernels::efficientnet::{self as twin, LANES, TILE};
use std::collections::HashMap;

fn randn(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.normal() as f32).collect()
}

/// Largest |a - b| / max(1, |b|); infinite where either is not finite (a NaN is never lost).
fn max_rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths");
    a.iter().zip(b).map(|(x, y)| if x.is_finite() && y.is_finite() { (x - y).abs() / y.abs().max(1.0) } else { f32::INFINITY }).fold(0.0, f32::max)
}

/// Values read back for an output of `n` values: at least 4, so that an empty output is checked
/// too (the kernel must write nothing: the rest stays zero, as the twin leaves it).
fn read_len(n: usize) -> usize {
    n.max(4)
}

/// 1 - the cosine of two vectors (in f64; f16-rounded ones are not quite of length 1).
fn one_minus_cos(a: &[f32], b: &[f32]) -> f64 {
    assert_eq!(a.len(), b.len(), "lengths");
    let dot = |u: &[f32], v: &[f32]| u.iter().zip(v).map(|(x, y)| *x as f64 * *y as f64).sum::<f64>();
    1.0 - dot(a, b) / (dot(a, a) * dot(b, b)).sqrt()
}

/// A `conv_direct` case: (cin, cout, h, w, k, stride, depthwise, input affine).
type DirectCase = (usize, usize, usize, usize, usize, usize, bool, bool);

/// A convolution's parameters and grid.
fn conv_params((cin, cout, h, w, k, stride, depthwise, affine): DirectCase) -> (EffConvParams, [u32; 3]) {
    let (ho, wo) = (h.div_ceil(stride), w.div_ceil(stride));
    let n = cout * ho * wo;
    // TensorFlow SAME: the network's own rule
    let pad = |n: usize| semlook::nn::conv::same_padding(n, k, stride).0;
    let groups = n.div_ceil(LANES);
    let row = groups.clamp(1, 7);
    let p = EffConvParams {
        cin: cin as u32,
        cout: cout as u32,
        h: h as u32,
        w: w as u32,
        ho: ho as u32,
        wo: wo as u32,
        k: k as u32,
        stride: stride as u32,
        pad_top: if h == 0 { 0 } else { pad(h) as u32 },
        pad_left: if w == 0 { 0 } else { pad(w) as u32 },
        depthwise: depthwise as u32,
        relu6: (cout % 2) as u32,
        scale: if affine { 1.0 / 128.0 } else { 1.0 },
        shift: if affine { -127.0 / 128.0 } else { 0.0 },
        row: row as u32,
        n: n as u32,
    };
    (p, [row as u32, groups.div_ceil(row) as u32, 1])
}

/// Each kernel on the device equals its twin on random inputs: the stem's full convolution with
/// the input affine (stride 2, even and odd sides), depthwise 3x3 and 5x5 at strides 1 and 2,
/// a grid of several rows; 1x1 convolutions with channel counts that fill no tile, with and
/// without ReLU6 and the residual; GeM over channels that fill no workgroup; and the empty
/// cases (no output values, no input channels, no pixels, no channels), which write nothing.
#[test]
fn embedding_kernels_match_their_twins_on_random_inputs() {
    let Some(ctx) = gpu() else { return };
    let mut rng = SplitMix64::new(61);
    // conv_direct: (cin, cout, h, w, k, stride, depthwise, affine)
    let direct: [DirectCase; 8] = [
        (3, 5, 9, 7, 3, 2, false, true),
        (3, 4, 10, 12, 3, 2, false, true),
        (7, 7, 13, 11, 3, 1, true, false),
        (6, 6, 11, 6, 5, 2, true, false),
        (9, 9, 8, 9, 5, 1, true, false),
        (16, 16, 40, 33, 3, 1, true, false),
        (0, 0, 5, 5, 3, 1, true, false),
        (3, 2, 0, 4, 3, 2, false, false),
    ];
    for case in direct {
        let (cin, cout, h, w, k, stride, dw, affine) = case;
        let (p, grid) = conv_params(case);
        let input: Vec<f32> = if affine { (0..cin * h * w).map(|_| (rng.next_u64() % 256) as f32).collect() } else { randn(&mut rng, cin * h * w) };
        let weight = randn(&mut rng, cout * if dw { 1 } else { cin } * k * k);
        let bias = randn(&mut rng, cout);
        let n = read_len(p.n as usize);
        let mut want = vec![0.0; n];
        twin::conv_direct(&p, &input, &weight, &bias, &mut want);
        let got = run_kernel(&ctx, "conv_direct", bytemuck::bytes_of(&p), grid, &[&input, &weight, &bias], n).unwrap();
        let d = max_rel(&got, &want);
        assert!(d <= 1e-5, "conv_direct {cin}->{cout} {w}x{h} k{k} s{stride}: {d}");
    }
    // pointwise: (cin, cout, hw, relu6, residual)
    let point = [
        (37, 19, 45, true, false),
        (16, 16, 256, false, true),
        (5, 33, 17, true, true),
        (40, 3, 1, false, false),
        (0, 7, 9, true, false),
        (8, 4, 0, false, true),
    ];
    for (cin, cout, hw, relu6, residual) in point {
        let p = EffPointParams { cin: cin as u32, cout: cout as u32, hw: hw as u32, relu6: relu6 as u32, residual: residual as u32, _pad: [0; 3] };
        let (input, weight, bias, res) = (randn(&mut rng, cin * hw), randn(&mut rng, cout * cin), randn(&mut rng, cout), randn(&mut rng, cout * hw));
        let res: &[f32] = if residual { &res } else { &[0.0] };
        let mut want = vec![0.0; read_len(cout * hw)];
        twin::pointwise(&p, &input, &weight, &bias, res, &mut want);
        let grid = [hw.div_ceil(TILE) as u32, cout.div_ceil(TILE) as u32, 1];
        let got = run_kernel(&ctx, "pointwise", bytemuck::bytes_of(&p), grid, &[&input, &weight, &bias, res], want.len()).unwrap();
        let d = max_rel(&got, &want);
        assert!(d <= 1e-5, "pointwise {cin}->{cout} x {hw}: {d}");
    }
    for (c, hw) in [(300, 13), (5, 1), (0, 4)] {
        let p = GemParams { c: c as u32, hw: hw as u32, _pad: [0; 2] };
        let input: Vec<f32> = randn(&mut rng, c * hw).iter().map(|v| v.abs() * 3.0).collect();
        let mut want = vec![0.0; read_len(c)];
        twin::gem_pool(&p, &input, &mut want);
        let got = run_kernel(&ctx, "gem_pool", bytemuck::bytes_of(&p), [c.div_ceil(LANES).max(1) as u32, 1, 1], &[&input], want.len()).unwrap();
        let d = got
            .iter()
            .zip(&want)
            .map(|(a, b)| if a.is_finite() && b.is_finite() { (a - b).abs() / b.abs().max(1e-6) } else { f32::INFINITY })
            .fold(0.0, f32::max);
        assert!(d <= 1e-5, "gem_pool {c} x {hw}: {d}");
    }
    match run_kernel(&ctx, "conv3d", &[], [1, 1, 1], &[], 1) {
        Err(GpuError::Failed { reason, .. }) => assert!(reason.contains("conv3d"), "{reason}"),
        other => panic!("an unknown kernel ran: {other:?}"),
    }
}

/// A random EfficientNet-Lite with few channels: stem 3 -> 8, a block without expansion (8 ->
/// 4, 3x3), a stage of stride 2 (4 -> 12 -> 6, 5x5), a residual block (6 -> 12 -> 6, 3x3),
/// another stride-2 stage (6 -> 24 -> 20, 3x3: channels that fill one tile and part of a
/// second), head 20 -> 37. Its BatchNorms have positive variances.
pub fn tiny_network(seed: u64) -> EfficientNetLite {
    let mut rng = SplitMix64::new(seed);
    let mut t: HashMap<String, Tensor> = HashMap::new();
    let mut conv_bn = |conv: &str, bn: &str, shape: [usize; 4]| {
        let n = shape.iter().product();
        let scale = 1.0 / ((shape[1] * shape[2] * shape[3]) as f32).sqrt();
        t.insert(format!("{conv}.weight"), Tensor { shape: shape.to_vec(), data: randn(&mut rng, n).iter().map(|v| v * scale).collect() });
        let c = shape[0];
        let mut part = |name: &str, f: &dyn Fn(f32) -> f32| {
            let data = randn(&mut rng, c).into_iter().map(f).collect();
            t.insert(format!("{bn}.{name}"), Tensor { shape: vec![c], data });
        };
        part("weight", &|v| 4.0 + v);
        part("bias", &|v| 0.5 + 0.3 * v);
        part("running_mean", &|v| 0.1 * v);
        part("running_var", &|v| 0.5 + v.abs());
    };
    conv_bn("_conv_stem", "_bn0", [8, 3, 3, 3]);
    conv_bn("_blocks.0._depthwise_conv", "_blocks.0._bn1", [8, 1, 3, 3]);
    conv_bn("_blocks.0._project_conv", "_blocks.0._bn2", [4, 8, 1, 1]);
    for (b, cin, mid, cout, k) in [(1, 4, 12, 6, 5), (2, 6, 12, 6, 3), (3, 6, 24, 20, 3)] {
        conv_bn(&format!("_blocks.{b}._expand_conv"), &format!("_blocks.{b}._bn0"), [mid, cin, 1, 1]);
        conv_bn(&format!("_blocks.{b}._depthwise_conv"), &format!("_blocks.{b}._bn1"), [mid, 1, k, k]);
        conv_bn(&format!("_blocks.{b}._project_conv"), &format!("_blocks.{b}._bn2"), [cout, mid, 1, 1]);
    }
    conv_bn("_conv_head", "_bn1", [37, 20, 1, 1]);
    EfficientNetLite::from_state_dict(t).unwrap()
}

fn frame(h: usize, w: usize, seed: usize) -> Chw {
    Chw { c: 3, h, w, data: (0..3 * h * w).map(|i| ((i * 7 + i / w.max(1) * 13 + seed * 31) % 256) as f32).collect() }
}

/// The whole network on the device gives the plan on the twins' embedding and the native pass's,
/// for a small random network (always: no file needed) at odd and tiny sizes, the 1x1 frame
/// included.
#[test]
fn a_small_network_on_the_device_gives_the_twins_and_the_native_embedding() {
    let Some(ctx) = gpu() else { return };
    let net = tiny_network(5);
    let gpu = EmbedderGpu::new(ctx, &net).unwrap();
    assert_eq!(gpu.dim(), 37);
    for (h, w) in [(33, 41), (64, 48), (7, 5), (1, 1)] {
        let rgb = frame(h, w, h);
        let (native, twins, device) = (net.forward(&rgb).unwrap(), forward_on_twins(&net, &rgb).unwrap(), gpu.forward(&rgb).unwrap());
        let (dt, dn) = (one_minus_cos(&device, &twins), one_minus_cos(&device, &native));
        eprintln!("small network at {w}x{h}: device vs twins 1 - cos {dt:.2e}, vs native {dn:.2e}");
        assert!(dt.abs() <= 1e-6 && dn.abs() <= 1e-6, "{w}x{h}: device vs twins {dt}, vs native {dn}");
    }
    for bad in [Chw { c: 3, h: 0, w: 4, data: vec![] }, Chw { c: 1, h: 4, w: 4, data: vec![0.0; 16] }] {
        assert!(gpu.forward(&bad).is_err(), "{}x{}x{} was embedded", bad.c, bad.h, bad.w);
        assert!(forward_on_twins(&net, &bad).is_err(), "{}x{}x{} ran on the twins", bad.c, bad.h, bad.w);
    }
}

/// Frames of one size reuse every buffer: the second creates none and uploads only its pixels; a
/// new size makes the frame's buffers again (the weights stay).
#[test]
fn a_second_frame_of_the_same_size_creates_no_embedding_buffer() {
    let Some(ctx) = gpu() else { return };
    let net = tiny_network(6);
    let gpu = EmbedderGpu::new(ctx, &net).unwrap();
    let loaded = gpu.counters();
    gpu.forward(&frame(30, 40, 1)).unwrap();
    let first = gpu.counters();
    gpu.forward(&frame(30, 40, 2)).unwrap();
    let second = gpu.counters();
    assert_eq!(second.buffers_created, first.buffers_created, "a repeated size created buffers");
    assert_eq!(second.bytes_uploaded - first.bytes_uploaded, (3 * 30 * 40 * 4) as u64, "a repeated size uploaded more than its frame");
    assert_eq!(second.bytes_read_back - first.bytes_read_back, 37 * 4);
    assert_eq!(second.frames, 2);
    assert!(first.buffers_created > loaded.buffers_created);
    gpu.forward(&frame(31, 40, 3)).unwrap();
    assert!(gpu.counters().buffers_created > second.buffers_created, "a new size made no buffers");
}

/// The real network (the installed checkpoint) on the device gives the native pass's and the
/// twins' embedding at the working size of a 640x480 frame, at odd sizes and on real frames.
#[test]
fn the_device_pass_gives_the_native_embedding() {
    let Some(ctx) = gpu() else { return };
    let ckpt = match semlook::nn::onnx::find_model(EMBEDDING_CHECKPOINT, None, "embedding checkpoint") {
        Ok(p) => p,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("{EMBEDDING_CHECKPOINT} (run setup.sh): {e}")),
    };
    let net = EfficientNetLite::load(&ckpt).unwrap();
    let gpu = EmbedderGpu::new(ctx, &net).unwrap();
    let mut frames: Vec<(String, Chw)> =
        [(336, 448), (335, 447), (64, 96)].iter().map(|&(h, w)| (format!("synthetic {w}x{h}"), frame(h, w, 0))).collect();
    if let Some(dir) = common::shared_or_required("data") {
        for rel in
            ["camvid-test/images/0001TP_008550.png", "real-vpr/nordland-spring-winter/query/001.jpg", "real-vpr/nordland-spring-winter/ref/001.jpg"]
        {
            let img = image::open(dir.join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}")).to_rgb8();
            frames.push((rel.to_string(), network_input(&img, 448).unwrap()));
        }
    }
    for (i, (name, rgb)) in frames.iter().enumerate() {
        let (native, device) = (net.forward(rgb).unwrap(), gpu.forward(rgb).unwrap());
        let dn = one_minus_cos(&device, &native);
        // the twins are slow (written for equivalence): the first frame only
        let dt = (i == 0).then(|| one_minus_cos(&device, &forward_on_twins(&net, rgb).unwrap()));
        eprintln!("{name}: device vs native 1 - cos {dn:.2e}{}", dt.map_or(String::new(), |d| format!(", vs twins {d:.2e}")));
        assert!(dn.abs() <= 1e-6 && dt.unwrap_or(0.0).abs() <= 1e-6, "{name}: device vs native {dn}, vs twins {dt:?}");
    }
}

/// The hook: a GPU engine whose embedding network runs natively (`embedding.network` names the
/// checkpoint) makes every frame's embedding (and keypoints) on the device, says so in its stage
/// times, and gives
/// the CPU engine's embeddings (the same network on the host) within 1 - cosine 1e-6.
#[test]
fn the_gpu_engine_makes_the_embedding_on_the_device_when_encoding() {
    use semlook::input::{FrameSource, LabelFormat};
    let Some(dir) = common::shared_or_required("data/real-vpr/nordland-spring-winter") else { return };
    let Some(ctx) = gpu() else { return };
    if let Err(e) = semlook::nn::onnx::find_model(EMBEDDING_CHECKPOINT, None, "embedding checkpoint") {
        return common::skip_unless_required("REQUIRE_MODELS", format!("{EMBEDDING_CHECKPOINT} (run setup.sh): {e}"));
    }
    let Some(mut cfg) = common::with_real_segmenter(semlook::config::Config::default()) else { return };
    cfg.embedding.network = EMBEDDING_CHECKPOINT.into();
    let frame = |id: &str| FrameSource { id: id.into(), image: Some(dir.join(format!("query/{id}.jpg"))), labels: None };
    let frames = [frame("001"), frame("002"), frame("003")];
    let mut enc = match semlook::encode::Encoder::new(&cfg) {
        Ok(e) => e,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("an encoder with appearance: {e}")),
    };
    assert!(enc.embedder().and_then(|e| e.native()).is_some(), "the checkpoint runs natively");
    if enc.train_codebook(&frames, &|| {}).is_err() {
        return common::skip_unless_required("REQUIRE_MODELS", "labels for the Nordland frames (the segmenter)");
    }
    let mut gpu_engine = semlook::engine::Engine::with_context(ctx);
    let g = gpu_engine.encode_all(&enc, &frames, LabelFormat::Auto, &|| {}).unwrap();
    let c = semlook::engine::Engine::cpu().encode_all(&enc, &frames, LabelFormat::Auto, &|| {}).unwrap();
    assert_eq!(gpu_engine.gpu_stages().unwrap().embedding_frames(), frames.len() as u64, "the embedding ran on the device");
    for (a, b) in g.iter().zip(&c) {
        let ((a, ta), (b, tb)) = (a.as_ref().unwrap(), b.as_ref().unwrap());
        assert!(ta.embedding_device_ms > 0.0 && ta.embedding_device_ms == ta.embedding_ms, "{}: {ta:?}", a.id);
        // the keypoint network too: of the frame's networks only the segmenter ran on the host
        // (it is not on the device yet, issue 61 part 2)
        assert!(ta.network_ms > 0.0 && ta.network_device_ms == ta.network_ms, "{}: {ta:?}", a.id);
        assert_eq!(tb.network_device_ms, 0.0, "{}: the CPU engine ran XFeat on the host", b.id);
        assert_eq!(tb.embedding_device_ms, 0.0, "{}: the CPU engine ran it on the host", b.id);
        assert_eq!(a.embedding.len(), 1280);
        // both rounded to f16 (a map's values): 1 - cosine within the device pass's bound
        let d = one_minus_cos(&a.embedding, &b.embedding);
        let apart = a.embedding.iter().zip(&b.embedding).filter(|(p, q)| p != q).count();
        assert!(d.abs() <= 1e-6, "{}: 1 - cosine {d}", a.id);
        eprintln!(
            "{}: 1 - cosine {d:.2e}, {apart} of 1280 values not equal after f16 rounding; {:.1} ms on the device",
            a.id, ta.embedding_device_ms
        );
    }
}
