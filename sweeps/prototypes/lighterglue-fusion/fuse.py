"""Sweep 14 (issue 32): how LighterGlue's inliers combine with today's verified score, offline from run.sh's output.
For every query and candidate: T = the verified score less its MNN inlier term (2 coarse + 2 tree similarity, the
same in both runs: checked), n_mnn and n_glue the RANSAC inliers of each matcher. Ranks by
T + a ln(1 + n_glue) + b ln(1 + n_mnn) and prints R@1 per set for a grid of (a, b); (0, 1) is today's default.
Usage: python3 sweeps/prototypes/lighterglue-fusion/fuse.py OUT_DIR KEYPOINTS [path/to/real-vpr]"""
import csv, itertools, json, math, os, sys

out, k = sys.argv[1], sys.argv[2]
data = sys.argv[3] if len(sys.argv) > 3 else "../shared/data/real-vpr"
SETS = [s for s in ["gardenspoint-day-night-mini", "nordland-spring-winter", "landmarks-multiview-dev"] if os.path.exists(f"{out}/k{k}-{s}-mnn.jsonl")]
stem = lambda p: os.path.splitext(os.path.basename(p))[0]


def load(s, c):
    rows = {}
    for line in open(f"{out}/k{k}-{s}-{c}.jsonl"):
        d = json.loads(line)
        if "top_k" in d:  # the last line is the timing summary
            rows[d["id"]] = {t["id"]: (t["score"], t["inliers"]) for t in d["top_k"]}
    return rows


cands = {}
for s in SETS:
    gt = {}
    for row in csv.DictReader(open(f"{data}/{s}/ground_truth.csv")):
        gt.setdefault(stem(row["query"]), set()).add(stem(row["reference"]))
    m, g = load(s, "mnn"), load(s, "lighterglue")
    rows = []
    for q in m:
        c = []
        for r, (score, n_mnn) in m[q].items():
            t = score - math.log1p(n_mnn)
            gs, n_glue = g[q][r]
            assert abs(gs - math.log1p(n_glue) - t) < 1e-4, (s, q, r)
            c.append((r, t, n_mnn, n_glue))
        rows.append((gt.get(q, set()), c))
    cands[s] = rows


def r1(s, a, b):
    return sum(max(c, key=lambda x: x[1] + a * math.log1p(x[3]) + b * math.log1p(x[2]))[0] in gt for gt, c in cands[s]) / len(cands[s])


grid = []
for a, b in itertools.product([0, 0.5, 1, 2, 4], [0, 0.5, 1, 2]):
    v = [r1(s, a, b) for s in SETS]
    grid.append((sum(v) / len(v), a, b, v))
grid.sort(key=lambda x: (-x[0], x[1], x[2]))
print(f"keypoints {k}\ta (glue)\tb (mnn)\tmean R@1\t" + "\t".join(s.split("-")[0] for s in SETS))
for mean, a, b, v in grid:
    print(f"\t{a}\t{b}\t{mean:.3f}\t" + "\t".join(f"{x:.3f}" for x in v))
for s in SETS:
    line = []
    for i, name in [(2, "mnn"), (3, "lighterglue")]:
        ok = sum(max(c, key=lambda x: (x[i], x[1]))[0] in gt for gt, c in cands[s]) / len(cands[s])
        pos = [x[i] for gt, c in cands[s] for x in c if x[0] in gt]
        neg = [x[i] for gt, c in cands[s] for x in c if x[0] not in gt]
        line.append(f"{name}: R@1 by inliers alone {ok:.3f}, mean inliers right {sum(pos)/max(1,len(pos)):.1f} / wrong {sum(neg)/max(1,len(neg)):.1f}")
    print(f"# {s}: " + "; ".join(line))
