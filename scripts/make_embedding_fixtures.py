"""Writes tests/data/embedding/<name>.json: reference embeddings of the image-embedding network
(`efficientnet_lite1_gem.onnx`, EfficientNet-Lite1 ImageNet with GeM pooling, made by
python/tools/export_embedding.py; see docs/models.md) on two real images from ../shared and one synthetic
image, which the crate's embedding (src/networks/embedding.rs) can be held to.

The images (paths relative to ../shared):
    street-frame        data/street-frames/<first image file, sorted>   (Cityscapes, 2048x1024)
    landmarks-ref-0000  data/real-vpr/landmarks-multiview-dev/ref/0000.jpg  (640x480)

Each image is converted to RGB and resized with PIL's BICUBIC filter (Image.resize, which antialiases when it
shrinks) to the working size: the long side 448, the short side short * 448 / long in float64 rounded half
away from zero (Rust's f64::round; the same as src/networks/embedding.rs::working_size), at least 32. The pixels
go to the network as float32 RGB 0..255, NCHW [1, 3, h, w]; onnxruntime (CPU, one thread) runs it, and the
output, already L2-normalised by the graph, is stored with every value rounded to 7 significant digits.

Each JSON file holds:
    image           the image's path relative to ../shared
    image_sha256    SHA-256 of that file
    image_size      [width, height] of the file
    size            [width, height] the network saw (the working size)
    resize          "PIL BICUBIC"
    network         the ONNX file's name, network_sha256 its SHA-256
    embedding       the 1280 values

A third file, synthetic-448x336.json, needs no image and no resizing: the pixels are
value(x, y, c) = (7 x + 13 y + 85 c) mod 256 (c = 0, 1, 2 for R, G, B) at 448x336, which is its own working
size, so an implementation that resizes only when the size changes (image's `resize` copies then) feeds the
network exactly these values; its JSON has "image": "synthetic", "pattern", "resize": "none" and no
image_sha256. A test on the two real images that resizes with another filter (image's Catmull-Rom) gets
slightly different pixels, and the network is sensitive to them (adding random -1, 0 or +1 to every pixel value
moves the cosine to about 0.99), so compare those with a tolerance; the synthetic one can be compared within float
rounding.

Run where the exporter's packages are (setup.sh makes the venv and the network):
    .venv-export/bin/python scripts/make_embedding_fixtures.py [--model .semlook/efficientnet_lite1_gem.onnx]
        [--shared ../shared]
Checked with onnxruntime 1.31.1, pillow 13.0.0, numpy 2.4.6.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import sys
from pathlib import Path

import numpy as np
import onnxruntime as ort
from PIL import Image

REPO = Path(__file__).resolve().parent.parent
LONG_SIDE = 448
MIN_SIDE = 32
IMAGE_EXTS = {".png", ".jpg", ".jpeg"}
SYNTHETIC_SIZE = (448, 336)


def synthetic(width: int, height: int) -> np.ndarray:
    """[height, width, 3] uint8: (7 x + 13 y + 85 c) mod 256."""
    y, x, c = np.meshgrid(np.arange(height), np.arange(width), np.arange(3), indexing="ij")
    return ((7 * x + 13 * y + 85 * c) % 256).astype(np.uint8)


def working_size(width: int, height: int, long_side: int = LONG_SIDE) -> tuple[int, int]:
    """(w, h) with the long side `long_side`, the short one in proportion, rounded half away from zero."""
    long = max(width, height, 1)

    def scale(v: int) -> int:
        x = v * long_side / long
        r = math.floor(x)
        return max(MIN_SIDE, r + 1 if x - r >= 0.5 else r)

    return scale(width), scale(height)


def sig7(v: float) -> float:
    return float(f"{v:.7g}")


def images(shared: Path) -> list[tuple[str, Path]]:
    frames = shared / "data" / "street-frames"
    first = sorted(p for p in frames.iterdir() if p.suffix.lower() in IMAGE_EXTS)[0]
    return [
        ("street-frame", first),
        ("landmarks-ref-0000", shared / "data" / "real-vpr" / "landmarks-multiview-dev" / "ref" / "0000.jpg"),
    ]


def main(argv=None) -> int:
    models = Path(os.environ.get("SEMLOOK_MODELS", REPO / ".semlook"))
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--model", type=Path, default=models / "efficientnet_lite1_gem.onnx")
    ap.add_argument("--shared", type=Path, default=REPO.parent / "shared")
    ap.add_argument("--out", type=Path, default=REPO / "tests" / "fixtures" / "embedding")
    args = ap.parse_args(argv)
    shared = args.shared.resolve()

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = 1
    opts.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(args.model), sess_options=opts, providers=["CPUExecutionProvider"])
    model_sha = hashlib.sha256(args.model.read_bytes()).hexdigest()
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = []
    for name, path in images(shared):
        im = Image.open(path).convert("RGB")
        w, h = working_size(*im.size)
        pixels = np.asarray(im.resize((w, h), Image.BICUBIC))
        jobs.append((name, pixels, {
            "image": path.relative_to(shared).as_posix(),
            "image_sha256": hashlib.sha256(path.read_bytes()).hexdigest(),
            "image_size": list(im.size),
            "size": [w, h],
            "resize": "PIL BICUBIC",
        }))
    w, h = SYNTHETIC_SIZE
    assert working_size(w, h) == (w, h)
    jobs.append((f"synthetic-{w}x{h}", synthetic(w, h), {
        "image": "synthetic",
        "pattern": "(7 x + 13 y + 85 c) mod 256, c = 0 R, 1 G, 2 B",
        "image_size": [w, h],
        "size": [w, h],
        "resize": "none",
    }))
    for name, pixels, head in jobs:
        x = pixels.astype(np.float32).transpose(2, 0, 1)[None]
        emb = sess.run(["embedding"], {"rgb": np.ascontiguousarray(x)})[0][0]
        values = [sig7(float(v)) for v in emb]
        err = float(np.abs(np.array(values) - emb.astype(np.float64)).max())
        head.update({"network": args.model.name, "network_sha256": model_sha})
        w, h = head["size"]
        iw, ih = head["image_size"]
        fields = {**head, "embedding": values}
        text = "{\n" + ",\n".join(f" {json.dumps(k)}: {json.dumps(v)}" for k, v in fields.items()) + "\n}\n"
        assert json.loads(text)["embedding"] == values
        out = args.out / f"{name}.json"
        out.write_text(text)
        print(f"{out.relative_to(REPO)}: {head['image']} {iw}x{ih} -> {w}x{h}, "
              f"|e| = {np.linalg.norm(emb):.7f}, rounding error <= {err:.1e}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
