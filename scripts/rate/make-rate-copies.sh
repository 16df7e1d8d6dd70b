#!/usr/bin/env bash
# The camera-rate regimes of issue 57's rate check: streams played at another rate than their map
# was recorded at, as ref/ + query/ + ground_truth.csv datasets (links to the frames, no copies)
# that `semlook dev tune --sequence` streams in name order:
#   nordland-x1..x4   Nordland dev: the map of ref/, the stream every 1st..4th query/ frame
#   nordland-slow     every query/ frame twice (a camera at twice the map's rate)
#   camvid-x1..x4     CamVid's Seq05VD drive (frames 1 s apart): the map of its even frames, the
#   camvid-slow       stream its odd frames (half a place on), every 1st..4th, or each twice
# Ground truth: Nordland's own (query k <-> ref k-1..k+1); CamVid's odd frame 2i+1 <-> even 2i, 2i+2,
# and where the car stands still (a stop: consecutive frames whose median absolute grey difference,
# at 160x120, is at most 2 of 255; moving frames differ by 3 or more) every frame of the stop is one
# place: Seq05VD waits at a red light from f01920 to f02850, 30 s in which frame numbers move and the
# camera does not. Needs numpy and PIL (.venv-export of setup.sh, or $PYTHON).
# No timestamps: what a stream without them gets. OUT default target/rate-data; a copy that exists
# keeps its links, and gets this version's ground truth where its own differs.   bash scripts/rate/make-rate-copies.sh [OUT]
set -euo pipefail
cd "$(dirname "$0")/../.."
shared=../shared/data
out=${1:-target/rate-data}
[ -d "$shared/real-vpr/nordland-spring-winter" ] || { echo "no $shared (the shared data folder beside the repository)" >&2; exit 1; }
mkdir -p "$out"
py=${PYTHON:-.venv-export/bin/python}
"$py" -c 'import numpy, PIL' 2>/dev/null || { echo "$py lacks numpy or PIL: run setup.sh, or set PYTHON" >&2; exit 1; }
"$py" - "$shared" "$out" <<'PY'
import csv, os, sys
import numpy as np
from PIL import Image
shared, out = sys.argv[1], sys.argv[2]

def write(name, refs, queries, truth):
    """refs: [(name, path)]; queries: [(name, path, source query name)]; truth: source query -> [ref names]."""
    dest = os.path.join(out, name)
    gt = os.path.join(dest, "ground_truth.csv")
    rows = [("query", "reference")] + [(f"query/{n}", f"ref/{r}") for n, _, src in queries for r in truth[src]]
    if os.path.exists(gt):
        # the links are kept; a ground truth of another version of this script is written anew
        if list(csv.reader(open(gt, newline=""))) == [list(r) for r in rows]:
            print(f"{dest} exists", file=sys.stderr)
            return
        print(f"{dest}: ground truth rewritten (another version of this script made it)", file=sys.stderr)
    for sub in ("ref", "query"):
        os.makedirs(os.path.join(dest, sub), exist_ok=True)
    for sub, items in (("ref", refs), ("query", [(n, p) for n, p, _ in queries])):
        for n, p in items:
            link = os.path.join(dest, sub, n)
            if not os.path.lexists(link):
                os.symlink(os.path.realpath(p), link)
    with open(gt, "w", newline="") as f:
        csv.writer(f).writerows(rows)
    print(f"{dest}: {len(refs)} references, {len(queries)} stream frames", file=sys.stderr)

def plays(prefix, refs, qs, truth):
    """qs: [(name, path)] in stream order."""
    for step in (1, 2, 3, 4):
        write(f"{prefix}-x{step}", refs, [(n, p, n) for n, p in qs[::step]], truth)
    ext = lambda n: os.path.splitext(n)
    write(f"{prefix}-slow", refs, [(f"{ext(n)[0]}-{k}{ext(n)[1]}", p, n) for n, p in qs for k in (0, 1)], truth)

nord = os.path.join(shared, "real-vpr", "nordland-spring-winter")
truth = {}
for r in csv.DictReader(open(os.path.join(nord, "ground_truth.csv"))):
    truth.setdefault(os.path.basename(r["query"]), []).append(os.path.basename(r["reference"]))
listing = lambda d: sorted((n, os.path.join(d, n)) for n in os.listdir(d))
plays("nordland", listing(os.path.join(nord, "ref")), listing(os.path.join(nord, "query")), truth)

cam = os.path.join(shared, "camvid-test", "images")
drive = sorted(n for n in os.listdir(cam) if n.startswith("Seq05VD_"))
refs = [(n, os.path.join(cam, n)) for n in drive[0::2]]
qs = [(n, os.path.join(cam, n)) for n in drive[1::2]]
truth = {n: [drive[i - 1]] + ([drive[i + 1]] if i + 1 < len(drive) else []) for i, n in enumerate(drive) if i % 2 == 1}
# stops: a frame that differs from the one before by a median of at most 2 grey levels joins its stop
grey = lambda n: np.asarray(Image.open(os.path.join(cam, n)).convert("L").resize((160, 120)), dtype=np.float32)
stop, prev = {}, None
for i, n in enumerate(drive):
    g = grey(n)
    still = prev is not None and float(np.median(np.abs(g - prev))) <= 2.0
    stop[n] = stop[drive[i - 1]] if still else n
    prev = g
members = {}
for n in drive:
    members.setdefault(stop[n], []).append(n)
for q in truth:
    same = [r for r in members[stop[q]] if r in dict(refs) and r not in truth[q]]
    truth[q] += same
stops = [m for m in members.values() if len(m) > 1]
print("stops: " + ", ".join(f"{m[0]}..{m[-1]} ({len(m)} frames)" for m in stops), file=sys.stderr)
plays("camvid", refs, qs, truth)
PY
