//! The XFeat network on the device (`shaders/xfeat.wgsl`, executor `networks::xfeat` (its device executor)) held to its CPU
//! twins (`semlook_kernels::xfeat`), and the CPU path's fast ops (`nn::conv`) held to the same
//! twins. Tolerances, and the largest differences seen on lavapipe (2-core development machine):
//!
//! - kernel vs twin, random inputs of awkward sizes: `conv2d` within 1e-5 relative to
//!   max(1, |twin|) (seen: 0, and 1.2e-7 with the sigmoid; the twin sums in the shader's order,
//!   a GPU may fuse a multiply and an add), instance-norm statistics within 1e-6 relative (seen:
//!   0), the element-wise kernels within 1e-6 (seen: 0; `bilinear_add` 4.8e-7), space-to-depth
//!   exactly;
//! - fast path (`nn::conv`) vs twin: convolutions (im2col + sgemm, another summation order)
//!   within 1e-4 relative to max(1, |twin|) (seen: 8.7e-6), instance norm (f64 on the fast path)
//!   within 1e-5 (seen: 2.4e-7); pooling, space-to-depth and resize + add exactly;
//! - the whole network on the device vs the native forward pass on real frames at the encoder's
//!   working size: per-cell descriptor cosine 1 - cos under 1e-7 on average and 1e-6 at worst
//!   (seen: 4.3e-13, 8.9e-12), descriptors within 2e-4 (seen: 2.1e-5), reliability within 1e-4
//!   (seen: 1.2e-6), logits within 1e-3 relative to max(1, |logit|) (seen: 2.7e-5), and >= 99 %
//!   of the detector's keypoints at identical positions (seen: 384 of 384 on every frame).

use super::{common, gpu, gpu_with};
use semlook::gpu::{GpuError, GpuOptions};
use semlook::networks::xfeat::XFeat;
use semlook::networks::xfeat::{forward_on_twins, run_kernel, XFeatGpu};
use semlook::networks::NetOutputs;
use semlook::nn::conv::{self as nn, Chw};
use semlook::util::SplitMix64;
use semlook_kernels::abi::{ConvParams, MapParams, NormParams};
use semlook_kernels::xfeat::{self as twin, pack_conv, Epilogue};

fn randn(rng: &mut SplitMix64, n: usize) -> Vec<f32> {
    (0..n).map(|_| rng.normal() as f32).collect()
}

/// Largest |a - b| / max(1, |b|).
fn max_rel(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths");
    a.iter().zip(b).map(|(x, y)| (x - y).abs() / y.abs().max(1.0)).fold(0.0, f32::max)
}

fn max_abs(a: &[f32], b: &[f32]) -> f32 {
    assert_eq!(a.len(), b.len(), "lengths");
    a.iter().zip(b).map(|(x, y)| (x - y).abs()).fold(0.0, f32::max)
}

/// A convolution case: (cin, cout, h, w, k, stride, epilogue 0 batch norm + ReLU / 1 bias /
/// 2 bias + sigmoid, adds a tensor). Odd channel counts, strides 1 and 2, sizes that are not
/// multiples of the 32 x 8 tile, input channels in several chunks with a partial last one, 65
/// output channels (nine groups of 8, the last partial).
const CONV_CASES: [(usize, usize, usize, usize, usize, usize, u8, bool); 7] = [
    (1, 4, 37, 45, 3, 1, 0, false),
    (5, 7, 33, 40, 3, 2, 1, true),
    (6, 3, 50, 47, 1, 1, 2, false),
    (24, 13, 19, 70, 3, 1, 0, true),
    (13, 65, 9, 11, 1, 1, 1, false),
    (9, 17, 41, 9, 3, 2, 0, false),
    (64, 24, 12, 20, 3, 1, 0, false),
];

/// A random layer of `case` packed: (params, packed weights, input, added tensor, the layer's
/// raw weights, means, variances, biases).
struct ConvCase {
    p: ConvParams,
    packed: Vec<f32>,
    input: Vec<f32>,
    add: Vec<f32>,
    weight: Vec<f32>,
    mean: Vec<f32>,
    var: Vec<f32>,
    bias: Vec<f32>,
    epi: u8,
}

fn conv_case(case: (usize, usize, usize, usize, usize, usize, u8, bool), rng: &mut SplitMix64) -> ConvCase {
    let (cin, cout, h, w, k, s, epi, add) = case;
    let weight: Vec<f32> = randn(rng, cout * cin * k * k).iter().map(|v| v * 0.3).collect();
    let mean = randn(rng, cout);
    let var: Vec<f32> = (0..cout).map(|_| rng.range(0.05, 2.0) as f32).collect();
    let bias = randn(rng, cout);
    let e = match epi {
        0 => Epilogue::BatchNormRelu { mean: &mean, var: &var },
        1 => Epilogue::Bias(&bias),
        _ => Epilogue::BiasSigmoid(&bias),
    };
    let mut p = ConvParams::new(cin, cout, h, w, k, s, k / 2, e.act(), add).expect("a case that fits");
    // an offset into a larger weights buffer, as in the executor
    let (vals, sub, mul) = pack_conv(&weight, cin, cout, k, e).unwrap();
    let mut packed = vec![0.5f32; 16];
    packed.extend(vals);
    (p.weight_at, p.sub_at, p.mul_at) = (16, 16 + sub as u32, 16 + mul as u32);
    let input = randn(rng, cin * h * w);
    let add = if add { randn(rng, p.output_len()) } else { vec![0.0; 4] };
    ConvCase { p, packed, input, add, weight, mean, var, bias, epi }
}

fn twin_conv(c: &ConvCase) -> Vec<f32> {
    let mut out = vec![0.0; c.p.output_len()];
    twin::conv2d(&c.p, &c.input, &c.packed, &c.add, &mut out);
    out
}

/// Each `xfeat.wgsl` kernel alone on the device equals its twin on random inputs of awkward sizes.
#[test]
fn xfeat_kernels_match_their_twins_on_random_inputs() {
    let Some(ctx) = gpu() else { return };
    let mut rng = SplitMix64::new(19);
    for (i, &case) in CONV_CASES.iter().enumerate() {
        let c = conv_case(case, &mut rng);
        let dev = run_kernel(&ctx, "conv2d", bytemuck::bytes_of(&c.p), c.p.grid(), &[&c.input, &c.packed, &c.add], c.p.output_len()).unwrap();
        let t = twin_conv(&c);
        let d = max_rel(&dev, &t);
        eprintln!("conv2d case {i} {case:?}: device vs twin {d:.2e} (relative to max(1, |twin|))");
        assert!(d <= 1e-5, "conv2d case {i} {case:?}: device and twin differ by {d}");
    }
    // instance norm over several chunks, the last partial; grids two workgroups wide
    for &(h, w, row) in &[(97usize, 131usize, 2usize), (32, 32, 65_535), (64, 200, 3)] {
        let n = h * w;
        let grey: Vec<f32> = (0..n).map(|_| rng.next_f64() as f32).collect();
        let np = NormParams::new(n, row);
        let chunks = np.chunks as usize;
        let mut partials = vec![0.0; chunks * 3];
        twin::instance_norm_partials(&np, &grey, &mut partials);
        let dev = run_kernel(&ctx, "instance_norm_partials", bytemuck::bytes_of(&np), np.partials_grid(), &[&grey], chunks * 3).unwrap();
        assert!(max_rel(&dev, &partials) <= 1e-6, "instance_norm_partials {h}x{w}: {}", max_rel(&dev, &partials));
        let mut stats = vec![0.0; 4];
        twin::instance_norm_stats(&np, &partials, &mut stats);
        let dev_stats = run_kernel(&ctx, "instance_norm_stats", bytemuck::bytes_of(&np), [1, 1, 1], &[&partials], 4).unwrap();
        assert!(max_rel(&dev_stats[..2], &stats[..2]) <= 1e-6, "instance_norm_stats {h}x{w}: {dev_stats:?} vs {stats:?}");
        let mut normed = vec![0.0; n];
        twin::instance_norm_apply(&np, &grey, &stats, &mut normed);
        let dev = run_kernel(&ctx, "instance_norm_apply", bytemuck::bytes_of(&np), np.apply_grid(), &[&grey, &stats], n).unwrap();
        eprintln!(
            "instance norm {h}x{w}: device vs twin: mean {:.1e}, 1/std {:.1e} (relative), normalised values {:.1e}",
            (dev_stats[0] - stats[0]).abs() / stats[0].abs(),
            (dev_stats[1] - stats[1]).abs() / stats[1],
            max_abs(&dev, &normed)
        );
        assert!(max_abs(&dev, &normed) <= 1e-6, "instance_norm_apply {h}x{w}: {}", max_abs(&dev, &normed));
    }
    // the element-wise kernels, in grids 3 workgroups wide (several rows)
    let x = randn(&mut rng, 3 * 37 * 41);
    let mp = MapParams::avg_pool(3, 37, 41, 4, 3);
    let mut t = vec![0.0; mp.n as usize];
    twin::avg_pool(&mp, &x, &mut t);
    let dev = run_kernel(&ctx, "avg_pool", bytemuck::bytes_of(&mp), mp.grid(), &[&x], mp.n as usize).unwrap();
    eprintln!("avg_pool: device vs twin {:.1e}", max_abs(&dev, &t));
    assert!(max_abs(&dev, &t) <= 1e-6, "avg_pool: {}", max_abs(&dev, &t));
    let x = randn(&mut rng, 40 * 72);
    let mp = MapParams::space_to_depth8(40, 72, 3);
    let mut t = vec![0.0; mp.n as usize];
    twin::space_to_depth8(&mp, &x, &mut t);
    let dev = run_kernel(&ctx, "space_to_depth8", bytemuck::bytes_of(&mp), mp.grid(), &[&x], mp.n as usize).unwrap();
    assert_eq!(dev, t, "space_to_depth8");
    let (a, b, c) = (randn(&mut rng, 5 * 23 * 37), randn(&mut rng, 5 * 12 * 19), randn(&mut rng, 5 * 6 * 10));
    let mp = MapParams::bilinear_add(5, 23, 37, (12, 19), (6, 10), 3);
    let mut t = vec![0.0; mp.n as usize];
    twin::bilinear_add(&mp, &a, &b, &c, &mut t);
    let dev = run_kernel(&ctx, "bilinear_add", bytemuck::bytes_of(&mp), mp.grid(), &[&a, &b, &c], mp.n as usize).unwrap();
    eprintln!("bilinear_add: device vs twin {:.1e}", max_abs(&dev, &t));
    assert!(max_abs(&dev, &t) <= 1e-6, "bilinear_add: {}", max_abs(&dev, &t));
}

/// The CPU path's fast ops (`nn::conv`: im2col + sgemm convolution, batch norm + ReLU,
/// f64 instance norm, pooling, space-to-depth, resize) equal the twins.
#[test]
fn nn_fast_path_matches_the_twins() {
    let mut rng = SplitMix64::new(7);
    for (i, &case) in CONV_CASES.iter().enumerate() {
        let c = conv_case(case, &mut rng);
        let (cin, cout, h, w, k, s, _, _) = case;
        let x = Chw { c: cin, h, w, data: c.input.clone() };
        let bias = (c.epi != 0).then_some(c.bias.as_slice());
        let mut y = nn::conv2d(&x, &c.weight, bias, cout, k, s, k / 2).unwrap();
        match c.epi {
            0 => nn::batchnorm_relu(&mut y, &c.mean, &c.var).unwrap(),
            1 => {}
            _ => y.data.iter_mut().for_each(|v| *v = 1.0 / (1.0 + (-*v).exp())),
        }
        if c.p.has_add != 0 {
            let add = Chw { c: cout, h: y.h, w: y.w, data: c.add.clone() };
            y = y.plus(&add).unwrap();
        }
        let t = twin_conv(&c);
        let d = max_rel(&y.data, &t);
        eprintln!("conv2d case {i} {case:?}: fast path vs twin {d:.2e}");
        assert!(d <= 1e-4, "case {i} {case:?}: the fast path and the twin differ by {d}");
    }
    let (h, w) = (97, 131);
    let grey: Vec<f32> = (0..h * w).map(|_| rng.next_f64() as f32).collect();
    let mut fast = Chw { c: 1, h, w, data: grey.clone() };
    nn::instance_norm(&mut fast);
    let np = NormParams::new(h * w, 65_535);
    let (mut partials, mut stats, mut normed) = (vec![0.0; np.chunks as usize * 3], vec![0.0; 4], vec![0.0; h * w]);
    twin::instance_norm_partials(&np, &grey, &mut partials);
    twin::instance_norm_stats(&np, &partials, &mut stats);
    twin::instance_norm_apply(&np, &grey, &stats, &mut normed);
    let d = max_abs(&fast.data, &normed);
    eprintln!("instance norm: fast path (f64) vs twin {d:.2e}");
    assert!(d <= 1e-5, "instance norm: {d}");
    let x = Chw { c: 3, h: 37, w: 41, data: randn(&mut rng, 3 * 37 * 41) };
    let mp = MapParams::avg_pool(3, 37, 41, 4, 65_535);
    let mut t = vec![0.0; mp.n as usize];
    twin::avg_pool(&mp, &x.data, &mut t);
    assert_eq!(nn::avg_pool(&x, 4).unwrap().data, t, "avg_pool");
    let x = Chw { c: 1, h: 40, w: 72, data: randn(&mut rng, 40 * 72) };
    let mp = MapParams::space_to_depth8(40, 72, 65_535);
    let mut t = vec![0.0; mp.n as usize];
    twin::space_to_depth8(&mp, &x.data, &mut t);
    assert_eq!(nn::space_to_depth8(&x).unwrap().data, t, "space_to_depth8");
    let a = Chw { c: 5, h: 23, w: 37, data: randn(&mut rng, 5 * 23 * 37) };
    let b = Chw { c: 5, h: 12, w: 19, data: randn(&mut rng, 5 * 12 * 19) };
    let c = Chw { c: 5, h: 6, w: 10, data: randn(&mut rng, 5 * 6 * 10) };
    let fast = a.clone().plus(&nn::resize_bilinear(&b, 23, 37).unwrap()).unwrap().plus(&nn::resize_bilinear(&c, 23, 37).unwrap()).unwrap();
    let mp = MapParams::bilinear_add(5, 23, 37, (12, 19), (6, 10), 65_535);
    let mut t = vec![0.0; mp.n as usize];
    twin::bilinear_add(&mp, &a.data, &b.data, &c.data, &mut t);
    assert_eq!(fast.data, t, "bilinear_add");
}

/// The native XFeat weights from the setup folder (required under CI or REQUIRE_MODELS=1).
fn native() -> Option<semlook::appearance::AppearanceModel> {
    let cfg = semlook::config::Config::default();
    match semlook::appearance::AppearanceModel::load(&cfg.appearance, &cfg.models) {
        Ok(Some(m)) if m.xfeat().is_some() => Some(m),
        other => {
            common::skip_unless_required("REQUIRE_MODELS", format!("XFeat weights (setup.sh): {:?}", other.err()));
            None
        }
    }
}

/// The grey network input of a real frame at the encoder's working size (640 long side).
fn working_grey(path: &std::path::Path) -> Chw {
    let rgb = image::open(path).unwrap().to_rgb8();
    let (w, h) = semlook::input::working_size(rgb.width(), rgb.height(), semlook::config::Config::default().input.working_long_side);
    semlook::networks::network_input(&semlook::input::resize_rgb(&rgb, w, h)).unwrap().0
}

/// Per cell, the cosine of two descriptor maps: (mean, min).
fn cosines(a: &Chw, b: &Chw) -> (f64, f64) {
    assert_eq!((a.c, a.h, a.w), (b.c, b.h, b.w));
    let n = a.h * a.w;
    let (mut sum, mut min) = (0.0f64, 1.0f64);
    for i in 0..n {
        let (mut ab, mut aa, mut bb) = (0.0f64, 0.0f64, 0.0f64);
        for c in 0..a.c {
            let (x, y) = (a.data[c * n + i] as f64, b.data[c * n + i] as f64);
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
        let cos = if aa == 0.0 && bb == 0.0 { 1.0 } else { ab / (aa.sqrt() * bb.sqrt()).max(1e-30) };
        sum += cos;
        min = min.min(cos);
    }
    (sum / n as f64, min)
}

/// Share of `a`'s keypoints at a position `b` has too.
fn same_positions(a: &semlook::appearance::keypoints::Keypoints, b: &semlook::appearance::keypoints::Keypoints) -> f64 {
    let set: std::collections::HashSet<(u32, u32)> = b.xy.iter().map(|p| (p[0].to_bits(), p[1].to_bits())).collect();
    a.xy.iter().filter(|p| set.contains(&(p[0].to_bits(), p[1].to_bits()))).count() as f64 / a.len().max(1) as f64
}

fn detector() -> semlook::appearance::keypoints::KeypointParams {
    let k = semlook::config::KeypointsConfig::default();
    semlook::appearance::keypoints::KeypointParams {
        nms_radius: k.nms_radius,
        threshold: k.score_threshold as f32,
        max_keypoints: k.stored,
        border: k.border,
    }
}

/// Device vs reference (native pass, or the twins' plan): descriptor cosines, reliability and
/// logit differences, keypoint positions; panics naming `what` beyond the tolerances.
fn compare(what: &str, dev: &NetOutputs, reference: &NetOutputs) {
    let (mean, min) = cosines(&dev.descriptors, &reference.descriptors);
    let desc = max_abs(&dev.descriptors.data, &reference.descriptors.data);
    let rel = max_abs(&dev.reliability.as_ref().unwrap().data, &reference.reliability.as_ref().unwrap().data);
    let logits = max_rel(&dev.logits.data, &reference.logits.data);
    let (kd, kr) =
        (semlook::appearance::keypoints::detect(dev, &detector()).unwrap(), semlook::appearance::keypoints::detect(reference, &detector()).unwrap());
    let same = same_positions(&kd, &kr);
    eprintln!(
        "{what}: 1 - cosine: mean {:.1e}, worst {:.1e}; descriptors max |diff| {desc:.2e}, reliability {rel:.2e}, logits {logits:.2e} (relative), keypoints {} / {} at identical positions ({:.2} %)",
        1.0 - mean,
        1.0 - min,
        (same * kd.len() as f64).round(),
        kd.len(),
        100.0 * same
    );
    assert!(1.0 - mean <= 1e-7 && 1.0 - min <= 1e-6, "{what}: descriptor cosines mean {mean}, min {min}");
    assert!(desc <= 2e-4, "{what}: descriptors differ by {desc}");
    assert!(rel <= 1e-4, "{what}: reliability differs by {rel}");
    assert!(logits <= 1e-3, "{what}: logits differ by {logits} (relative)");
    assert!(kd.len() == kr.len() && same >= 0.99, "{what}: {} and {} keypoints, {:.2} % at identical positions", kd.len(), kr.len(), 100.0 * same);
}

/// The whole network on the device equals the native forward pass on real frames (two Nordland
/// queries, 1920x1080, and a Cityscapes street frame, 2048x1024) at the encoder's working size
/// (640x352 and 640x320 network inputs); without the heads it gives the same descriptors bit for
/// bit.
#[test]
fn xfeat_on_the_device_matches_the_native_pass_on_real_frames() {
    let (Some(nordland), Some(street)) =
        (common::shared_or_required("data/real-vpr/nordland-spring-winter/query"), common::shared_or_required("data/street-frames"))
    else {
        return;
    };
    let Some(model) = native() else { return };
    let Some(ctx) = gpu() else { return };
    let net: &XFeat = model.xfeat().unwrap();
    let x = XFeatGpu::new(ctx, net).unwrap();
    for path in [nordland.join("001.jpg"), nordland.join("031.jpg"), street.join("frankfurt_000000_000576_leftImg8bit.png")] {
        let grey = working_grey(&path);
        let t = std::time::Instant::now();
        let dev = x.forward_with(&grey, true).unwrap();
        let dev_s = t.elapsed().as_secs_f64();
        let t = std::time::Instant::now();
        let cpu = net.forward_with(&grey, true).unwrap();
        eprintln!("{}: {}x{} network input, device {dev_s:.2} s, CPU fast path {:.2} s", path.display(), grey.w, grey.h, t.elapsed().as_secs_f64());
        compare(&path.display().to_string(), &dev, &cpu);
        let dense = x.forward_with(&grey, false).unwrap();
        assert_eq!(dense.descriptors, dev.descriptors, "descriptors without the heads");
        assert!(dense.reliability.is_none() && dense.logits.c == 0);
    }
}

/// The plan the executor runs, on the twins (CPU), equals the native forward pass, and the
/// device equals it within the kernels' tolerances: on a real frame's 96x128 crop.
#[test]
fn the_plan_on_the_twins_matches_the_native_pass_and_the_device() {
    let Some(street) = common::shared_or_required("data/street-frames/frankfurt_000000_000294_leftImg8bit.png") else { return };
    let Some(model) = native() else { return };
    let net = model.xfeat().unwrap();
    let full = working_grey(&street);
    let (h, w) = (96, 128);
    let data = (0..h).flat_map(|y| full.data[(100 + y) * full.w + 200..(100 + y) * full.w + 200 + w].to_vec()).collect();
    let grey = Chw { c: 1, h, w, data };
    let twins = forward_on_twins(net, &grey, true).unwrap();
    compare("the plan on the twins vs the native pass (96x128)", &twins, &net.forward_with(&grey, true).unwrap());
    let Some(ctx) = gpu() else { return };
    let dev = XFeatGpu::new(ctx, net).unwrap().forward_with(&grey, true).unwrap();
    let d = max_rel(&dev.descriptors.data, &twins.descriptors.data);
    let l = max_rel(&dev.logits.data, &twins.logits.data);
    eprintln!("device vs the plan on the twins (96x128): descriptors {d:.2e}, logits {l:.2e} (relative)");
    assert!(d <= 1e-4 && l <= 1e-4, "device vs twins: descriptors {d}, logits {l}");
}

/// Residency: a second frame of the same size creates no buffer, writes only the frame and
/// reads back only the outputs; another size makes its buffers once.
#[test]
fn a_second_frame_of_the_same_size_creates_no_buffer_and_uploads_only_the_frame() {
    let Some(model) = native() else { return };
    let Some(ctx) = gpu() else { return };
    let x = XFeatGpu::new(ctx.clone(), model.xfeat().unwrap()).unwrap();
    let mut rng = SplitMix64::new(3);
    let frame = |rng: &mut SplitMix64, h: usize, w: usize| Chw { c: 1, h, w, data: (0..h * w).map(|_| rng.next_f64() as f32).collect() };
    let made = x.counters();
    assert!(made.bytes_uploaded > 1_000_000 && made.buffers_created == 2, "weights uploaded once at creation: {made:?}");
    x.forward_with(&frame(&mut rng, 64, 96), true).unwrap();
    let first = x.counters();
    assert!(first.buffers_created > made.buffers_created);
    let ctx_before = ctx.bytes_uploaded();
    x.forward_with(&frame(&mut rng, 64, 96), true).unwrap();
    let second = x.counters();
    assert_eq!(second.buffers_created, first.buffers_created, "a repeated size creates no buffer");
    assert_eq!(second.bytes_uploaded - first.bytes_uploaded, 64 * 96 * 4, "only the frame is uploaded");
    assert_eq!(ctx.bytes_uploaded() - ctx_before, 64 * 96 * 4, "the context counted the same bytes");
    assert_eq!(second.bytes_read_back - first.bytes_read_back, ((64 + 1 + 65) * 8 * 12 * 4) as u64, "descriptors, reliability and logits come back");
    x.forward_with(&frame(&mut rng, 64, 96), false).unwrap();
    let dense = x.counters();
    assert_eq!(dense.buffers_created, second.buffers_created);
    assert_eq!(dense.bytes_read_back - second.bytes_read_back, (64 * 8 * 12 * 4) as u64, "without the heads only the descriptors come back");
    x.forward_with(&frame(&mut rng, 32, 64), true).unwrap();
    assert!(x.counters().buffers_created > dense.buffers_created, "another size makes its buffers");
}

/// A frame whose activations exceed the storage binding, or whose grid exceeds the workgroups
/// per dimension, is a typed error (never a CPU run); so is an input of the wrong shape.
#[test]
fn frames_beyond_the_device_limits_are_typed_errors() {
    let Some(model) = native() else { return };
    let net = model.xfeat().unwrap();
    let frame = Chw::zeros(1, 256, 320);
    let Some(small) = gpu_with(&GpuOptions { max_binding_size: Some(8 << 20), ..Default::default() }) else { return };
    let x = XFeatGpu::new(small, net).unwrap();
    // block1's first layer: 4 x 256 x 320 values = 1.3 MB fits; at 1024 x 1024, 16.8 MB does not
    x.forward_with(&frame, false).unwrap();
    let big = Chw::zeros(1, 1024, 1024);
    assert!(matches!(x.forward_with(&big, false), Err(GpuError::LimitsTooSmall { .. })), "binding limit");
    let Some(few) = gpu_with(&GpuOptions { max_workgroups: Some(8), ..Default::default() }) else { return };
    let r = XFeatGpu::new(few, net).unwrap().forward_with(&frame, false);
    assert!(matches!(r, Err(GpuError::LimitsTooSmall { .. })), "workgroups: {r:?}");
    assert!(matches!(x.forward_with(&Chw::zeros(1, 100, 64), false), Err(GpuError::Failed { .. })), "not a multiple of 32");
}

/// The hook: a GPU engine encodes real frames with the network on the device and gives what the
/// CPU engine gives: the same verification keypoints, and appearance vectors (stored rounded to
/// int8 blocks) equal but for at most 0.1 % of values one rounding step apart.
#[test]
fn the_gpu_engine_runs_xfeat_on_the_device_when_encoding() {
    let Some(dir) = common::shared_or_required("data/real-vpr/nordland-spring-winter") else { return };
    if native().is_none() {
        return;
    }
    let Some(ctx) = gpu() else { return };
    use semlook::input::{FrameSource, LabelFormat};
    let Some(cfg) = common::with_real_segmenter(semlook::config::Config::default()) else { return };
    let frame = |id: &str| FrameSource { id: id.into(), image: Some(dir.join(format!("query/{id}.jpg"))), labels: None };
    let frames = [frame("001"), frame("002")];
    let mut enc = match semlook::encode::Encoder::new(&cfg) {
        Ok(e) => e,
        Err(e) => return common::skip_unless_required("REQUIRE_MODELS", format!("an encoder with appearance: {e}")),
    };
    if enc.train_codebook(&frames, &|| {}).is_err() {
        return common::skip_unless_required("REQUIRE_MODELS", "labels for the Nordland frames (the segmenter)");
    }
    let mut gpu_engine = semlook::engine::Engine::with_context(ctx);
    let g = gpu_engine.encode_all(&enc, &frames, LabelFormat::Auto, &|| {}).unwrap();
    let c = semlook::engine::Engine::cpu().encode_all(&enc, &frames, LabelFormat::Auto, &|| {}).unwrap();
    assert_eq!(gpu_engine.gpu_stages().unwrap().network_frames(), 2, "the network ran on the device");
    for (a, b) in g.iter().zip(&c) {
        let (a, b) = (&a.as_ref().unwrap().0, &b.as_ref().unwrap().0);
        assert_eq!(a.keypoints.xy, b.keypoints.xy, "{}: verification keypoints", a.id);
        assert!(!a.appearance.is_empty() && !a.forest.appearance.is_empty());
        // stored vectors are rounded to int8 blocks (values::round_to_blocks): a 1e-5 difference
        // may move a value by one step of its block (under max |block| / 63.5)
        let (mut steps, mut values) = (0, 0);
        for (x, y) in a.appearance.chunks(64).chain(a.forest.appearance.chunks(64)).zip(b.appearance.chunks(64).chain(b.forest.appearance.chunks(64)))
        {
            let step = y.iter().fold(0.0f32, |m, v| m.max(v.abs())) / 63.5;
            for (p, q) in x.iter().zip(y) {
                assert!((p - q).abs() <= step * 1.001, "{}: {p} and {q} are more than one block step ({step}) apart", a.id);
                steps += (p != q) as usize;
                values += 1;
            }
        }
        eprintln!(
            "{}: {steps} of {values} appearance values one block step apart, the rest equal; {} verification keypoints at the same positions",
            a.id,
            a.keypoints.xy.len() / 2
        );
        assert!(steps * 1000 <= values, "{}: {steps} of {values} values differ", a.id);
    }
}
