//! Targets for model files: `.pt` state dicts (a tiny network of XFeat's graph, written here as
//! PyTorch writes them: a zip of a pickle and raw storages), ONNX keypoint and segmenter models
//! with generated outputs (a protobuf writer of the few ONNX messages needed), and keypoint
//! decoding of arbitrary network outputs.

use crate::mutate::{random_seeds, Entropy};
use crate::{Target, Verdict};
use image::{Rgb, RgbImage};
use semlook::appearance::keypoints::{self, KeypointParams};
use semlook::appearance::AppearanceModel;
use semlook::config::{AppearanceConfig, AppearanceModelKind, ModelPaths, Sampling, SegmentationConfig};
use semlook::networks::xfeat::XFeat;
use semlook::networks::NetOutputs;
use semlook::nn::conv::Chw;
use semlook::Error;
use std::io::Write;
use std::path::{Path, PathBuf};

/// One tensor of a state dict: name, shape, stride, offset, storage size and values.
#[derive(Clone)]
pub struct PtTensor {
    pub name: String,
    pub shape: Vec<i64>,
    pub stride: Vec<i64>,
    pub offset: i64,
    pub numel: i64,
    pub data: Vec<f32>,
}

pub struct StateDict(pub Vec<PtTensor>);

fn contiguous(name: String, shape: &[i64], seed: u32) -> PtTensor {
    let n: i64 = shape.iter().product();
    let mut stride = vec![1i64; shape.len()];
    for d in (0..shape.len().saturating_sub(1)).rev() {
        stride[d] = stride[d + 1] * shape[d + 1];
    }
    let data = (0..n).map(|i| (((i as u32).wrapping_mul(2_654_435_761) ^ seed) % 1000) as f32 / 1000.0 + 0.05).collect();
    PtTensor { name, shape: shape.to_vec(), stride, offset: 0, numel: n, data }
}

/// XFeat's graph with few channels (the native loader reads the counts from the weights).
pub fn tiny_xfeat() -> StateDict {
    let mut t = Vec::new();
    let mut basic = |p: &str, cout: i64, cin: i64, k: i64| {
        let s = t.len() as u32;
        t.push(contiguous(format!("{p}.layer.0.weight"), &[cout, cin, k, k], s));
        t.push(contiguous(format!("{p}.layer.1.running_mean"), &[cout], s + 1));
        t.push(contiguous(format!("{p}.layer.1.running_var"), &[cout], s + 2));
    };
    for (i, (cout, cin)) in [(2, 1), (2, 2), (2, 2), (4, 2)].into_iter().enumerate() {
        basic(&format!("block1.{i}"), cout, cin, 3);
    }
    for i in 0..2 {
        basic(&format!("block2.{i}"), 4, 4, 3);
    }
    for (b, ks) in [("block3", &[3, 3, 1][..]), ("block4", &[3, 3, 3]), ("block5", &[3, 3, 3, 1]), ("block_fusion", &[3, 3])] {
        for (i, &k) in ks.iter().enumerate() {
            basic(&format!("{b}.{i}"), 4, 4, k);
        }
    }
    basic("heatmap_head.0", 4, 8, 1);
    basic("heatmap_head.1", 4, 4, 1);
    basic("keypoint_head.0", 4, 64, 1);
    basic("keypoint_head.1", 4, 4, 1);
    basic("keypoint_head.2", 4, 4, 1);
    for (p, cout, cin) in [("skip1.1", 4, 1), ("block_fusion.2", 8, 4), ("heatmap_head.2", 1, 4), ("keypoint_head.3", 65, 4)] {
        let s = t.len() as u32;
        t.push(contiguous(format!("{p}.weight"), &[cout, cin, 1, 1], s));
        t.push(contiguous(format!("{p}.bias"), &[cout], s + 1));
    }
    StateDict(t)
}

/// EfficientNet-Lite's graph with few channels and three blocks (stem 4; a block without
/// expansion, 4 -> 2; a new stage, stride 2, 2 -> 6 -> 3, 3x3; a residual block 3 -> 6 -> 3, 5x5;
/// head 5), with its BatchNorms (variances positive).
pub fn tiny_efficientnet() -> StateDict {
    let mut t = Vec::new();
    let mut conv_bn = |conv: &str, bn: &str, shape: [i64; 4]| {
        let s = t.len() as u32;
        t.push(contiguous(format!("{conv}.weight"), &shape, s));
        for (i, part) in ["weight", "bias", "running_mean", "running_var"].iter().enumerate() {
            t.push(contiguous(format!("{bn}.{part}"), &[shape[0]], s + 1 + i as u32));
        }
    };
    conv_bn("_conv_stem", "_bn0", [4, 3, 3, 3]);
    conv_bn("_blocks.0._depthwise_conv", "_blocks.0._bn1", [4, 1, 3, 3]);
    conv_bn("_blocks.0._project_conv", "_blocks.0._bn2", [2, 4, 1, 1]);
    for (b, cin, k) in [(1, 2, 3), (2, 3, 5)] {
        conv_bn(&format!("_blocks.{b}._expand_conv"), &format!("_blocks.{b}._bn0"), [6, cin, 1, 1]);
        conv_bn(&format!("_blocks.{b}._depthwise_conv"), &format!("_blocks.{b}._bn1"), [6, 1, k, k]);
        conv_bn(&format!("_blocks.{b}._project_conv"), &format!("_blocks.{b}._bn2"), [3, 6, 1, 1]);
    }
    conv_bn("_conv_head", "_bn1", [5, 3, 1, 1]);
    StateDict(t)
}

/// A small EfficientNet-Lite checkpoint in the legacy format loads with its layout read from the
/// weights and runs at odd sizes; one with a tensor missing or of the wrong shape is a typed error
/// naming the file.
#[test]
fn a_tiny_efficientnet_checkpoint_loads_runs_and_is_checked() {
    use semlook::networks::embedding::EfficientNetLite;
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("tiny.pth");
    let sd = tiny_efficientnet();
    std::fs::write(&path, sd.legacy(&sd.pickle())).unwrap();
    let net = EfficientNetLite::load(&path).unwrap();
    assert_eq!(format!("{net:?}"), "EfficientNetLite(3 blocks, 5 values)");
    for (h, w) in [(33, 41), (32, 32), (1, 1)] {
        let rgb = Chw { c: 3, h, w, data: (0..3 * h * w).map(|i| (i * 37 % 256) as f32).collect() };
        let e = net.forward(&rgb).unwrap();
        let norm = e.iter().map(|v| v * v).sum::<f32>().sqrt();
        assert!(e.len() == 5 && (norm - 1.0).abs() < 1e-5, "{h}x{w}: {e:?}");
    }
    let mut broken = tiny_efficientnet();
    broken.0.retain(|t| t.name != "_blocks.1._bn1.running_var");
    let mut wrong = tiny_efficientnet();
    wrong.0.iter_mut().filter(|t| t.name == "_blocks.2._expand_conv.weight").for_each(|t| t.shape = vec![6, 2, 1, 1]);
    for (what, sd) in [("a missing tensor", broken), ("a wrong shape", wrong)] {
        std::fs::write(&path, sd.legacy(&sd.pickle())).unwrap();
        match EfficientNetLite::load(&path) {
            Err(Error::Model { path: p, reason }) => assert!(p == path && !reason.is_empty(), "{what}"),
            other => panic!("{what}: {other:?}"),
        }
    }
}

/// Pickle opcodes (protocol 2) for what `torch.save` writes.
struct Pk(Vec<u8>);

impl Pk {
    fn op(&mut self, b: &[u8]) -> &mut Self {
        self.0.extend_from_slice(b);
        self
    }
    fn global(&mut self, module: &str, name: &str) -> &mut Self {
        self.op(format!("c{module}\n{name}\n").as_bytes())
    }
    fn str(&mut self, s: &str) -> &mut Self {
        self.op(b"X").op(&(s.len() as u32).to_le_bytes()).op(s.as_bytes())
    }
    fn int(&mut self, v: i64) -> &mut Self {
        match i32::try_from(v) {
            Ok(v) => self.op(b"J").op(&v.to_le_bytes()),
            Err(_) => self.op(b"\x8a\x08").op(&v.to_le_bytes()),
        }
    }
    fn ints(&mut self, v: &[i64]) -> &mut Self {
        self.op(b"(");
        for &x in v {
            self.int(x);
        }
        self.op(b"t")
    }
}

impl StateDict {
    /// `data.pkl`: an OrderedDict of `_rebuild_tensor_v2(storage, offset, shape, stride, ...)`.
    pub fn pickle(&self) -> Vec<u8> {
        let mut p = Pk(b"\x80\x02".to_vec());
        p.global("collections", "OrderedDict").op(b")R(");
        for (i, t) in self.0.iter().enumerate() {
            p.str(&t.name).global("torch._utils", "_rebuild_tensor_v2").op(b"(");
            p.op(b"(").str("storage").global("torch", "FloatStorage").str(&i.to_string()).str("cpu").int(t.numel).op(b"tQ");
            p.int(t.offset).ints(&t.shape).ints(&t.stride).op(b"\x89").global("collections", "OrderedDict").op(b")R").op(b"tR");
        }
        p.op(b"u.");
        p.0
    }

    /// The legacy (non-zip) file `torch.save(..., _use_new_zipfile_serialization=False)` writes:
    /// the magic number, the protocol version, the system's description, `pickle` (the object), the
    /// storage keys, then each storage's element count and data.
    pub fn legacy(&self, pickle: &[u8]) -> Vec<u8> {
        let mut f = b"\x80\x02\x8a\x0a\x6c\xfc\x9c\x46\xf9\x20\x6a\xa8\x50\x19.".to_vec();
        f.extend_from_slice(b"\x80\x02M\xe9\x03.");
        let mut sys = Pk(b"\x80\x02}(".to_vec());
        sys.str("protocol_version").int(1001).str("little_endian").op(b"\x88").op(b"u.");
        f.extend_from_slice(&sys.0);
        f.extend_from_slice(pickle);
        let mut keys = Pk(b"\x80\x02(".to_vec());
        for i in 0..self.0.len() {
            keys.str(&i.to_string());
        }
        f.extend_from_slice(&keys.op(b"l.").0);
        for t in &self.0 {
            f.extend_from_slice(&t.numel.to_le_bytes());
            f.extend(t.data.iter().flat_map(|v| v.to_le_bytes()));
        }
        f
    }

    /// The zip PyTorch writes: `archive/data.pkl` (here `pickle`) and `archive/data/<i>`.
    pub fn zip(&self, pickle: &[u8]) -> Vec<u8> {
        let mut z = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
        let opts = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
        let mut file = |name: &str, bytes: &[u8]| {
            z.start_file(name, opts).expect("zip entry");
            z.write_all(bytes).expect("zip write");
        };
        file("archive/data.pkl", pickle);
        for (i, t) in self.0.iter().enumerate() {
            let raw: Vec<u8> = t.data.iter().flat_map(|v| v.to_le_bytes()).collect();
            file(&format!("archive/data/{i}"), &raw);
        }
        z.finish().expect("zip finish").into_inner()
    }
}

/// A grey-ish test frame.
fn frame(w: u32, h: u32) -> RgbImage {
    RgbImage::from_fn(w, h, |x, y| Rgb([((x * 7) ^ (y * 3)) as u8, (x * y) as u8, (x + 2 * y) as u8]))
}

fn model_kind(e: &Error) -> bool {
    matches!(e, Error::Model { .. })
}

/// Loads `path` as the configured keypoint network and runs it on two frames, in both
/// samplings; every failure must be a typed error naming the file.
fn load_and_run(kind: AppearanceModelKind, path: &Path) -> Verdict {
    let name = path.display().to_string();
    let mut verdict = Verdict::Refused;
    for sampling in [Sampling::Keypoints, Sampling::Dense] {
        let cfg = AppearanceConfig { model: kind, sampling, ..Default::default() };
        let paths = match kind {
            AppearanceModelKind::Onnx => ModelPaths { keypoint_onnx: Some(path.into()), ..Default::default() },
            _ => ModelPaths { xfeat_weights: Some(path.into()), ..Default::default() },
        };
        let model = match AppearanceModel::load(&cfg, &paths) {
            Ok(Some(m)) => m,
            Ok(None) => return Verdict::Violation("no model".into()),
            Err(e) => return Verdict::refused(&e, &name, model_kind),
        };
        for (w, h) in [(64, 64), (96, 70)] {
            match model.keypoints(&frame(w, h)) {
                Ok(k) if k.descriptors.len() == k.len() * k.dim && k.scores.len() == k.len() => verdict = Verdict::Accepted,
                Ok(_) => return Verdict::Violation("keypoints and descriptors of different counts".into()),
                Err(e) => {
                    if let v @ Verdict::Violation(_) = Verdict::refused(&e, &name, model_kind) {
                        return v;
                    }
                }
            }
        }
    }
    verdict
}

fn pt_target(name: &'static str, seeds: Vec<Vec<u8>>, quick: usize, build: fn(&[u8]) -> Vec<u8>) -> Option<Target> {
    let dir = tempfile::tempdir().expect("temp dir");
    let path = dir.path().join("xfeat.pt");
    let run = move |b: &[u8]| {
        let _keep = &dir;
        if let Err(e) = std::fs::write(&path, build(b)) {
            return Verdict::Violation(format!("fixture: {e}"));
        }
        load_and_run(AppearanceModelKind::Xfeat, &path)
    };
    Some(Target { name, seeds, fixup: None, quick, run: Box::new(run) })
}

/// Mutations of the archive bytes themselves.
pub fn pt_archive() -> Option<Target> {
    let sd = tiny_xfeat();
    pt_target("pt_archive", vec![sd.zip(&sd.pickle())], 150, |b| b.to_vec())
}

/// Mutations of `data.pkl`, zipped with the storages (so the zip's checksums hold).
pub fn pt_pickle() -> Option<Target> {
    pt_target("pt_pickle", vec![tiny_xfeat().pickle()], 150, |b| tiny_xfeat().zip(b))
}

/// Mutations of the legacy-format file (the five pickles and the storages after them).
pub fn pt_legacy() -> Option<Target> {
    let sd = tiny_xfeat();
    pt_target("pt_legacy", vec![sd.legacy(&sd.pickle())], 150, |b| b.to_vec())
}

/// The same state dict in the zip and the legacy format reads the same: every tensor, and the
/// network's outputs on a frame.
#[test]
fn the_legacy_format_reads_as_the_zip_format() {
    let sd = tiny_xfeat();
    let dir = tempfile::tempdir().unwrap();
    let (zip, legacy) = (dir.path().join("zip.pt"), dir.path().join("legacy.pt"));
    std::fs::write(&zip, sd.zip(&sd.pickle())).unwrap();
    std::fs::write(&legacy, sd.legacy(&sd.pickle())).unwrap();
    let a = semlook::nn::torch_pt::read_state_dict(&zip).unwrap();
    let b = semlook::nn::torch_pt::read_state_dict(&legacy).unwrap();
    assert_eq!(a.len(), sd.0.len());
    assert_eq!(a, b);
    let grey = semlook::nn::conv::Chw { c: 1, h: 64, w: 96, data: (0..64 * 96).map(|i| (i % 17) as f32 / 17.0).collect() };
    let (na, nb) = (XFeat::load(&zip).unwrap(), XFeat::load(&legacy).unwrap());
    let (oa, ob) = (na.forward(&grey).unwrap(), nb.forward(&grey).unwrap());
    assert_eq!((oa.descriptors, oa.logits), (ob.descriptors, ob.logits));
    // a storage cut short, a wrong element count, and a missing key list are typed errors naming the file
    let full = sd.legacy(&sd.pickle());
    for (what, bytes) in [("cut", full[..full.len() - 3].to_vec()), ("header only", full[..40].to_vec())] {
        std::fs::write(&legacy, &bytes).unwrap();
        match semlook::nn::torch_pt::read_state_dict(&legacy) {
            Err(semlook::Error::Model { path, .. }) => assert_eq!(path, legacy, "{what}"),
            other => panic!("{what}: {other:?}"),
        }
    }
}

/// Shapes, strides, offsets and storage sizes chosen by the fuzz bytes: wrong ranks, kernels,
/// channel counts, negative sizes, storages too short or too long, tensors missing.
fn perturbed(b: &[u8]) -> Vec<u8> {
    let mut e = Entropy::new(b);
    let mut sd = tiny_xfeat();
    sd.0.retain(|_| !e.chance(60));
    for t in sd.0.iter_mut() {
        if !e.chance(6) {
            continue;
        }
        match e.below(7) {
            0 => {
                let d = e.below(t.shape.len().max(1));
                if let Some(s) = t.shape.get_mut(d) {
                    *s = *e.pick(&[0, 1, 2, 3, 5, 64, 65, -1, 1 << 20]);
                }
            }
            1 => {
                t.shape.pop();
            }
            2 => t.shape.push(*e.pick(&[1, 2, 0])),
            3 => t.stride = t.stride.iter().map(|&s| s * *e.pick(&[1, 2, -1, 0, 1 << 40])).collect(),
            4 => t.offset = *e.pick(&[1, -1, 7, 1 << 33]),
            5 => t.numel = *e.pick(&[0, -1, t.numel - 1, t.numel + 1, i64::MAX, 1 << 40]),
            _ => {
                let keep = e.below(t.data.len() + 2);
                t.data.resize(keep, 0.5);
            }
        }
        // a storage as long as it claims to be, unless the size was the point
        if e.chance(2) {
            if let Ok(n) = usize::try_from(t.numel) {
                if n <= 1 << 16 {
                    t.data.resize(n, 0.25);
                }
            }
        }
    }
    sd.zip(&sd.pickle())
}

pub fn pt_shapes() -> Option<Target> {
    let mut seeds = vec![vec![0u8; 96]]; // all zero: the valid state dict
    seeds.extend(random_seeds(11, 15, 96));
    pt_target("pt_shapes", seeds, 150, perturbed)
}

/// A CHW tensor with sizes from the fuzz bytes, sometimes inconsistent with its data.
fn chw(e: &mut Entropy, channels: &[usize]) -> Chw {
    let c = *e.pick(channels);
    let (h, w) = (e.below(7), e.below(7));
    let mut n = c * h * w;
    if e.chance(8) {
        n = e.below(n + 3);
    }
    let special = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -0.0, 1e30, -1e30];
    let data = (0..n).map(|_| if e.chance(10) { *e.pick(&special) } else { e.byte() as f32 / 16.0 - 8.0 }).collect();
    Chw { c, h, w, data }
}

pub fn keypoint_decoding() -> Option<Target> {
    let run = |b: &[u8]| {
        let mut e = Entropy::new(b);
        let logits = chw(&mut e, &[65, 65, 65, 64, 66, 0, 1]);
        let descriptors = chw(&mut e, &[8, 3, 1, 0, 64]);
        let reliability = (!e.chance(3)).then(|| chw(&mut e, &[1, 1, 1, 2, 0]));
        let out = NetOutputs { descriptors, logits, reliability };
        let params = KeypointParams { nms_radius: e.below(9), threshold: e.byte() as f32 / 512.0, max_keypoints: e.below(64), border: e.below(40) };
        let dense = keypoints::dense(&out);
        if dense.descriptors.len() != dense.len() * dense.dim {
            return Verdict::Violation("dense: descriptors and positions disagree".into());
        }
        match keypoints::extract(&out, &params) {
            Ok(k) if k.descriptors.len() == k.len() * k.dim && k.len() <= params.max_keypoints => Verdict::Accepted,
            Ok(_) => Verdict::Violation("extract: counts disagree".into()),
            Err(_) => Verdict::Refused,
        }
    };
    Some(Target { name: "keypoint_decoding", seeds: random_seeds(5, 16, 256), fixup: None, quick: 1500, run: Box::new(run) })
}

/// Protocol-buffer writer for the ONNX messages below.
#[derive(Default)]
struct Pb(Vec<u8>);

impl Pb {
    fn varint(&mut self, mut v: u64) {
        while v >= 0x80 {
            self.0.push(v as u8 | 0x80);
            v >>= 7;
        }
        self.0.push(v as u8);
    }
    fn int(mut self, field: u64, v: i64) -> Self {
        self.varint(field << 3);
        self.varint(v as u64);
        self
    }
    fn bytes(mut self, field: u64, b: &[u8]) -> Self {
        self.varint((field << 3) | 2);
        self.varint(b.len() as u64);
        self.0.extend_from_slice(b);
        self
    }
    fn str(self, field: u64, s: &str) -> Self {
        self.bytes(field, s.as_bytes())
    }
    fn msg(self, field: u64, m: Pb) -> Self {
        self.bytes(field, &m.0)
    }
}

const FLOAT: i64 = 1;
const INT64: i64 = 7;

/// A `ValueInfoProto`: name, element type and dims (a number, or a name when negative).
fn value_info(name: &str, elem: i64, dims: Option<&[i64]>) -> Pb {
    let mut tensor = Pb::default().int(1, elem);
    if let Some(dims) = dims {
        let shape = dims.iter().enumerate().fold(Pb::default(), |s, (i, &d)| {
            let dim = if d >= 0 { Pb::default().int(1, d) } else { Pb::default().str(2, &format!("d{i}")) };
            s.msg(1, dim)
        });
        tensor = tensor.msg(2, shape);
    }
    Pb::default().str(1, name).msg(2, Pb::default().msg(1, tensor))
}

fn node(op: &str, inputs: &[&str], output: &str, attrs: Vec<Pb>) -> Pb {
    let n = inputs.iter().fold(Pb::default(), |n, i| n.str(1, i)).str(2, output).str(3, output).str(4, op);
    attrs.into_iter().fold(n, |n, a| n.msg(5, a))
}

fn ints_attr(name: &str, v: &[i64]) -> Pb {
    v.iter().fold(Pb::default().str(1, name), |a, &x| a.int(8, x)).int(20, 7)
}

fn tensor(name: &str, elem: i64, dims: &[i64], e: &mut Entropy) -> Pb {
    let n: i64 = dims.iter().product();
    let t = dims.iter().fold(Pb::default(), |t, &d| t.int(1, d)).int(2, elem).str(8, name);
    let raw: Vec<u8> = (0..n.max(0))
        .flat_map(|_| if elem == FLOAT { (e.byte() as f32 / 32.0 - 4.0).to_le_bytes().to_vec() } else { (e.byte() as i64).to_le_bytes().to_vec() })
        .collect();
    t.bytes(9, &raw)
}

/// An ONNX model of input `input` ([N, C, H, W], symbolic sizes) whose outputs the fuzz bytes
/// choose. Zero bytes give the valid layout `valid`: per output, a 1x1 convolution to its
/// channel count, then average pooling by its factor.
fn onnx_model(e: &mut Entropy, input: &str, in_channels: i64, valid: &[(&str, i64, i64)]) -> Vec<u8> {
    let mut graph = Pb::default().str(2, "fuzz");
    let mut outputs = Vec::new();
    let count = if e.chance(4) { e.below(5) } else { valid.len() };
    for i in 0..count {
        let (vname, vc, vk) = valid.get(i).copied().unwrap_or(("extra", 8, 8));
        let name = if e.chance(3) { format!("{}{i}", e.pick(&["semi", "desc", "heat", "out", "feat", "logits"])) } else { vname.to_string() };
        let declared: Option<Vec<i64>>;
        match e.below(8) {
            0..=4 => {
                let c = if e.chance(2) { *e.pick(&[vc, 65, 64, 1, 2, 3, 20, 130]) } else { vc };
                let k = if e.chance(2) { *e.pick(&[vk, 1, 2, 4, 8, 16]) } else { vk };
                let w = format!("w{i}");
                graph = graph.msg(5, tensor(&w, FLOAT, &[c, in_channels, 1, 1], e));
                graph = graph.msg(1, node("Conv", &[input, &w], &format!("c{i}"), vec![]));
                let pool = vec![ints_attr("kernel_shape", &[k, k]), ints_attr("strides", &[k, k])];
                graph = graph.msg(1, node("AveragePool", &[&format!("c{i}")], &name, pool));
                declared = Some(vec![-1, c, -1, -1]);
            }
            5 | 6 => {
                let dims: Vec<i64> = (0..e.below(6)).map(|_| e.below(10) as i64).collect();
                let elem = if e.chance(3) { INT64 } else { FLOAT };
                let value = Pb::default().str(1, "value").msg(5, tensor("v", elem, &dims, e)).int(20, 4);
                graph = graph.msg(1, node("Constant", &[], &name, vec![value]));
                declared = (!e.chance(2)).then_some(dims);
            }
            _ => {
                graph = graph.msg(1, node("Identity", &[input], &name, vec![]));
                declared = Some(vec![-1, in_channels, -1, -1]);
            }
        }
        let declared = if e.chance(5) { None } else { declared };
        outputs.push(value_info(&name, FLOAT, declared.as_deref()));
    }
    graph = graph.msg(11, value_info(input, FLOAT, Some(&[-1, in_channels, -1, -1])));
    for o in outputs {
        graph = graph.msg(12, o);
    }
    Pb::default().int(1, 8).str(2, "semlook-fuzz").msg(7, graph).msg(8, Pb::default().str(1, "").int(2, 13)).0
}

/// ONNX Runtime, or `None` after saying why it is missing.
fn onnx_runtime() -> Option<()> {
    let tiny = Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/tiny_segmenter.onnx");
    match semlook::nn::onnx::session(&tiny, None) {
        Ok(_) => Some(()),
        Err(e) => {
            crate::common::skip_unless_required("REQUIRE_MODELS", e);
            None
        }
    }
}

fn onnx_target(name: &'static str, run: impl Fn(&[u8], &Path) -> Verdict + 'static) -> Option<Target> {
    onnx_runtime()?;
    let dir = tempfile::tempdir().expect("temp dir");
    let path: PathBuf = dir.path().join(format!("{name}.onnx"));
    let mut seeds = vec![vec![0u8; 64]];
    seeds.extend(random_seeds(name.len() as u64, 15, 512));
    let run = move |b: &[u8]| {
        let _keep = &dir;
        run(b, &path)
    };
    Some(Target { name, seeds, fixup: None, quick: 40, run: Box::new(run) })
}

pub fn onnx_keypoints() -> Option<Target> {
    onnx_target("onnx_keypoints", |b, path| {
        let model = onnx_model(&mut Entropy::new(b), "image", 1, &[("semi", 65, 8), ("desc", 16, 8), ("heatmap", 1, 8)]);
        if let Err(e) = std::fs::write(path, model) {
            return Verdict::Violation(format!("fixture: {e}"));
        }
        load_and_run(AppearanceModelKind::Onnx, path)
    })
}

pub fn onnx_segmenter() -> Option<Target> {
    onnx_target("onnx_segmenter", |b, path| {
        let model = onnx_model(&mut Entropy::new(b), "rgb", 3, &[("logits", 3, 2)]);
        if let Err(e) = std::fs::write(path, model) {
            return Verdict::Violation(format!("fixture: {e}"));
        }
        let cfg = SegmentationConfig {
            input_width: 64,
            input_height: 48,
            class_map: vec!["road".into(), "vegetation".into(), "sky".into()],
            ..Default::default()
        };
        let name = path.display().to_string();
        let seg = match semlook::networks::segmenter::Segmenter::load(path, &cfg, &semlook::classes::ClassTable::cityscapes(), None) {
            Ok(s) => s,
            Err(e) => return Verdict::refused(&e, &name, model_kind),
        };
        let (a, c) = (frame(80, 60), frame(33, 47));
        let results = [seg.segment(&a, Path::new("a.png")).map(|m| vec![m]), seg.segment_batch(&[&a, &c])];
        let mut verdict = Verdict::Refused;
        for r in results {
            match r {
                Ok(maps) if maps.iter().all(|m| m.classes().len() == (m.width() * m.height()) as usize) => verdict = Verdict::Accepted,
                Ok(_) => return Verdict::Violation("a label map of the wrong size".into()),
                Err(e) => {
                    if let v @ Verdict::Violation(_) = Verdict::refused(&e, &name, model_kind) {
                        return v;
                    }
                }
            }
        }
        verdict
    })
}
