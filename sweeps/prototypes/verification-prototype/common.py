"""Shared loading for the verification prototypes (issue 32): run.sh's localize output, the keypoints
dump.py wrote, ground truth, and mutual nearest neighbours as the product computes them."""
import csv, json, math, os
import numpy as np

REAL_VPR = os.environ.get("REAL_VPR", "../shared/data/real-vpr")
OUT = os.environ.get("OUT", "/tmp/verification-prototype")
SETS = ["gardenspoint-day-night-mini", "nordland-spring-winter", "landmarks-multiview-dev"]
MIN_DOT = math.ceil(0.82 * 200 * 200)  # verification.min_cosine on int8 descriptors (scale 200)
stem = lambda p: os.path.splitext(os.path.basename(p))[0]


def ground_truth(s):
    gt = {}
    for row in csv.DictReader(open(f"{REAL_VPR}/{s}/ground_truth.csv")):
        gt.setdefault(stem(row["query"]), set()).add(stem(row["reference"]))
    return gt


def candidates(s, run="mnn"):
    """(query id, [(reference id, T, MNN inliers)]) per query: T the verified score less ln(1 + inliers)."""
    out = []
    for line in open(f"{OUT}/localize/{s}-{run}.jsonl"):
        d = json.loads(line)
        if "top_k" in d:
            out.append((d["id"], [(t["id"], t["score"] - math.log1p(t["inliers"]), t["inliers"]) for t in d["top_k"]]))
    return out


def keypoints(z, prefix, i):
    """int32 descriptors, positions in pixels at a 640 px long side, classes of image i."""
    o = z[f"{prefix}_keypoint_offsets"]
    a, b = o[i], o[i + 1]
    return (z[f"{prefix}_keypoint_descriptors"][a:b].astype(np.int32), z[f"{prefix}_keypoint_xy"][a:b].astype(np.float64) / 65535 * 640,
            z[f"{prefix}_keypoint_classes"][a:b] if f"{prefix}_keypoint_classes" in z else None)


def mnn(dq, dr):
    """Mutual nearest neighbours above the cosine floor: (query keypoint, reference keypoint) rows."""
    if len(dq) == 0 or len(dr) == 0:
        return np.zeros((0, 2), int)
    s = dq @ dr.T
    bq, br = s.argmax(1), s.argmax(0)
    i = np.arange(len(dq))
    ok = (br[bq] == i) & (s[i, bq] >= MIN_DOT)
    return np.stack([i[ok], bq[ok]], 1)


def r1(data, score):
    """R@1 per set of candidates ranked by score(candidate)."""
    return [sum(max(c, key=score)[0] in g for g, c in data[s]) / len(data[s]) for s in SETS]


def show(name, v):
    print(f"{name:28s} " + " ".join(f"{x:.3f}" for x in v) + f"  mean {sum(v) / len(v):.3f}")
