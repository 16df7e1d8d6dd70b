"""Sweep 14b (issue 32): pair-local rules for where LighterGlue runs beside MNN, offline from run.sh's
output. For each candidate: T = the verified score less its MNN inlier term; the fusion ranks by
T + 2 ln(1 + MNN inliers) + 0.5 ln(1 + LighterGlue inliers) (sweep 14's best), the LighterGlue term only on
the pairs a rule admits. Prints R@1 per set, the mean and the share of pairs LighterGlue runs on.
Usage: OUT=... .venv/bin/python sweeps/prototypes/verification-prototype/gate.py [lg | the suffix of another LighterGlue run]"""
import math, os, sys
sys.path.insert(0, os.path.dirname(__file__))
from common import SETS, candidates, ground_truth

LG = sys.argv[1] if len(sys.argv) > 1 else "lg"
cands = {}
for s in SETS:
    gt, glue = ground_truth(s), dict(candidates(s, LG))
    rows = []
    for q, c in candidates(s, "mnn"):
        g = {r: (t, n) for r, t, n in glue[q]}
        for r, t, _ in c:
            assert abs(g[r][0] - t) < 1e-3, (s, q, r)  # the same score but for its inlier term
        rows.append((gt.get(q, set()), [(r, t, n, g[r][1]) for r, t, n in c]))
    cands[s] = rows


def show(name, gate, a=0.5, b=2.0):
    """R@1 per set of T + b ln(1 + MNN) + a ln(1 + LighterGlue) where gate admits the pair, and the share admitted."""
    r1, admitted, pairs = [], 0, 0
    for rows in cands.values():
        score = lambda x: x[1] + b * math.log1p(x[2]) + (a * math.log1p(x[3]) if gate(x) else 0)
        r1.append(sum(max(c, key=score)[0] in gt for gt, c in rows) / len(rows))
        admitted += sum(gate(x) for _, c in rows for x in c)
        pairs += sum(len(c) for _, c in rows)
    print(f"{name:40s} " + " ".join(f"{x:.3f}" for x in r1) + f"  mean {sum(r1) / len(r1):.3f}  glued {admitted / pairs:.3f}")


show("mnn only (b=1)", lambda x: False, b=1.0)
show("mnn only (b=2)", lambda x: False)
show("all glued", lambda x: True)
for t in [2, 3, 4, 5, 6, 8, 10, 12, 15]:
    show(f"mnn>={t}", lambda x, t=t: x[2] >= t)
for th in [2.5, 3, 3.5, 4, 4.5, 5, 5.5, 6, 6.5, 7]:
    show(f"pre>={th}", lambda x, th=th: x[1] + 2 * math.log1p(x[2]) >= th)
for th in [-1, 0, 0.5, 1, 1.5, 2, 2.5, 3]:
    show(f"T>={th}", lambda x, th=th: x[1] >= th)
