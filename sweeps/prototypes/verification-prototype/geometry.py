"""Sweep 15 (issue 32): whether the verification's geometry, the query's keypoint scales or class weights
separate right from wrong candidates better than today's LO-RANSAC homography, offline with OpenCV on the
keypoints dump.py wrote and the candidates of run.sh's MNN run. Per candidate, from the MNN matches of the
stored keypoints: inliers of OpenCV homographies (RANSAC 4 px; MAGSAC 4 and 8 px) and fundamental matrices
(RANSAC 2 and 4 px; MAGSAC 2 px), all at a 640 px long side; the homography's inliers with the queries'
keypoints detected at 448, 896 and 1,024 px; the classes at both ends of the 640 px inliers. Ranks by
T + w ln(1 + inliers) (T: the verified score less its inlier term) and prints R@1 per set.
Usage: OUT=... PYTHONPATH=<opencv-python-headless> .venv/bin/python sweeps/prototypes/verification-prototype/geometry.py"""
import itertools, math, os, pickle, sys
import numpy as np, cv2
sys.path.insert(0, os.path.dirname(__file__))
from common import OUT, SETS, candidates, ground_truth, keypoints, mnn, r1, show

MODELS = {
    "homography RANSAC 4 px": lambda p, q: cv2.findHomography(p, q, cv2.RANSAC, 4.0, maxIters=1000, confidence=0.999),
    "homography MAGSAC 4 px": lambda p, q: cv2.findHomography(p, q, cv2.USAC_MAGSAC, 4.0, maxIters=1000, confidence=0.999),
    "homography MAGSAC 8 px": lambda p, q: cv2.findHomography(p, q, cv2.USAC_MAGSAC, 8.0, maxIters=1000, confidence=0.999),
    "fundamental RANSAC 2 px": lambda p, q: cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, 2.0, 0.999, 1000),
    "fundamental RANSAC 4 px": lambda p, q: cv2.findFundamentalMat(p, q, cv2.FM_RANSAC, 4.0, 0.999, 1000),
    "fundamental MAGSAC 2 px": lambda p, q: cv2.findFundamentalMat(p, q, cv2.USAC_MAGSAC, 2.0, 0.999, 1000),
}
H = "homography RANSAC 4 px"


def fit(name, p, q):
    """The inlier mask of `name` on the matched positions (None: no model)."""
    if len(p) < (4 if name.startswith("homography") else 8):
        return None
    cv2.setRNGSeed(1)
    try:
        M, mask = MODELS[name](p, q)
    except cv2.error:
        return None
    return None if M is None or mask is None else mask.ravel().astype(bool)


cache = f"{OUT}/geometry.pkl"
data = pickle.load(open(cache, "rb")) if os.path.exists(cache) else {}
for s in SETS:
    if s in data:
        continue
    z = np.load(f"{OUT}/{s}.npz")
    qi = {k: i for i, k in enumerate(z["query_ids"])}
    ri = {k: i for i, k in enumerate(z["ref_ids"])}
    gt, rows = ground_truth(s), []
    for q, cands in candidates(s):
        dq, pq, cq = keypoints(z, "query", qi[q])
        scaled = {size: keypoints(z, f"q{size}", qi[q]) for size in (448, 896, 1024)}
        c = []
        for r, t, ours in cands:
            dr, pr, cr = keypoints(z, "ref", ri[r])
            m = mnn(dq, dr)
            v = {"ours (LO-RANSAC homography)": ours}
            for name in MODELS:
                k = fit(name, pq[m[:, 0]], pr[m[:, 1]])
                v[name] = 0 if k is None else int(k.sum())
                if name == H:
                    v["classes"] = np.zeros((0, 2), int) if k is None else np.stack([cq[m[k, 0]], cr[m[k, 1]]], 1)
            for size, (dqs, pqs, _) in scaled.items():
                ms = mnn(dqs, dr)
                k = fit(H, pqs[ms[:, 0]], pr[ms[:, 1]])
                v[size] = 0 if k is None else int(k.sum())
            c.append((r, t, v))
        rows.append((gt.get(q, set()), c))
    data[s] = rows
    pickle.dump(data, open(cache, "wb"))
    print(s, "done", flush=True)

print("# the model (R@1 Gardens Point / Nordland / landmarks), best weight w of 0.5 / 1 / 1.5 / 2 by mean")
for name in ["ours (LO-RANSAC homography)"] + list(MODELS):
    best = max(((r1(data, lambda x, w=w: x[1] + w * math.log1p(x[2][name])), w) for w in (0.5, 1, 1.5, 2)), key=lambda b: sum(b[0]))
    show(f"{name}, w {best[1]}", best[0])
print("# the query's keypoints at other sizes (homography RANSAC 4 px, w 1): one size, or the most inliers of several")
for name, f in [("640", lambda v: v[H]), ("448", lambda v: v[448]), ("896", lambda v: v[896]), ("1024", lambda v: v[1024]),
                ("max 640, 448", lambda v: max(v[H], v[448])), ("max 640, 896", lambda v: max(v[H], v[896])),
                ("max of all four", lambda v: max(v[H], v[448], v[896], v[1024]))]:
    show(name, r1(data, lambda x, f=f: x[1] + math.log1p(f(x[2]))))
print("# inliers weighted by class (the lower of both ends; homography RANSAC 4 px, w 1): the best 3 of 48, and all 1")


def weighted(v, w):
    cls = v["classes"]
    return 0.0 if len(cls) == 0 else float(np.minimum(w[cls[:, 0]], w[cls[:, 1]]).sum())


res = []
for dyn, veg, road, sky in itertools.product([0, 0.25, 0.5, 1], [0.5, 1], [0.5, 1], [0, 0.5, 1]):
    w = np.ones(256)
    w[[11, 12, 13, 14, 15, 16, 17, 18]], w[[8, 9]], w[[0, 1]], w[10] = dyn, veg, road, sky
    res.append((r1(data, lambda x, w=w: x[1] + math.log1p(weighted(x[2], w))), (dyn, veg, road, sky)))
res.sort(key=lambda r: -sum(r[0]))
for v, (dyn, veg, road, sky) in res[:3] + [r for r in res if r[1] == (1, 1, 1, 1)]:
    show(f"dynamic {dyn} veg {veg} road {road} sky {sky}", v)
