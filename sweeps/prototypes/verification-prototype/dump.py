"""The verification keypoints of every query and reference image of the three dev sets, through the Python
API (`Encoder.for_map` on run.sh's maps), and the queries' keypoints at other working sizes (448, 896 and
1,024 px long side) for geometry.py. The other sizes come from copies of the map whose manifest's working
size is rewritten (checksum recomputed, index dropped): a measurement hack, not a supported edit.
Usage: OUT=... .venv/bin/python sweeps/prototypes/verification-prototype/dump.py (about 5 minutes)."""
import hashlib, json, os, shutil, sys
import numpy as np, semlook
sys.path.insert(0, os.path.dirname(__file__))
from common import OUT, REAL_VPR, SETS

COLS = ("keypoint_offsets", "keypoint_descriptors", "keypoint_xy", "keypoint_classes")
for name in SETS:
    d, out = f"{REAL_VPR}/{name}", {}
    enc = semlook.Encoder.for_map(semlook.Map.open(f"{OUT}/maps/{name}"))
    for side in ("query", "ref"):
        files = sorted(os.listdir(f"{d}/{side}"))
        ds = enc.encode_files([os.path.splitext(f)[0] for f in files], images=[f"{d}/{side}/{f}" for f in files])
        out[f"{side}_ids"] = np.array([os.path.splitext(f)[0] for f in files])
        for c in COLS:
            out[f"{side}_{c}"] = np.asarray(ds.column(c)).copy()
    files = sorted(os.listdir(f"{d}/query"))
    for size in (448, 896, 1024):
        mp = f"{OUT}/maps/{name}-{size}"
        shutil.rmtree(mp, ignore_errors=True)
        shutil.copytree(f"{OUT}/maps/{name}", mp)
        mf = json.load(open(f"{mp}/manifest.json"))
        mf["config"]["input"]["working_long_side"] = size
        mf.pop("index", None)
        for seg in mf["segments"]:
            seg.pop("index", None)
        mf["checksum"] = ""
        mf["checksum"] = hashlib.sha256(json.dumps(mf, separators=(",", ":"), ensure_ascii=False).encode()).hexdigest()
        open(f"{mp}/manifest.json", "w").write(json.dumps(mf, indent=2))
        ds = semlook.Encoder.for_map(semlook.Map.open(mp)).encode_files([os.path.splitext(f)[0] for f in files], images=[f"{d}/query/{f}" for f in files])
        for c in COLS[:3]:
            out[f"q{size}_{c}"] = np.asarray(ds.column(c)).copy()
    np.savez(f"{OUT}/{name}.npz", **out)
    print(name, flush=True)
