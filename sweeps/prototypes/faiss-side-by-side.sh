#!/usr/bin/env bash
# The exact coarse scan beside faiss-cpu's flat inner product, one run, one machine (issue 29 part 3):
#
#   bash sweeps/prototypes/faiss-side-by-side.sh [--refs 100000] [--queries 1000] [--bin target/release/semlook] [--json FILE]
#
# 1. `semlook dev bench --cpu-only --sizes REFS --batches QUERIES`: the exact SSIM coarse stage, REFS references
#    x QUERIES queries, comparisons/s.
# 2. faiss-cpu `IndexFlatIP` (PyPI, installed into .venv-faiss on first use) on random unit vectors of the same
#    size as a global descriptor (48 x 64 = 3,072 float32), REFS x QUERIES, comparisons/s, the same thread count.
# Both rows go to stdout (and to --json FILE as a list); the two are timed back to back, so a figure of one is
# comparable with the other's only within one run.
set -euo pipefail
cd "$(dirname "$0")/../.."

refs=100000 queries=1000 bin=target/release/semlook json=""
while [ $# -gt 0 ]; do
    case "$1" in
        --refs) refs=$2; shift 2 ;;
        --queries) queries=$2; shift 2 ;;
        --bin) bin=$2; shift 2 ;;
        --json) json=$2; shift 2 ;;
        *) echo "faiss-side-by-side: unknown argument $1" >&2; exit 2 ;;
    esac
done
[ -x "$bin" ] || cargo build --release >&2
if [ ! -x .venv-faiss/bin/python ]; then
    python3 -m venv .venv-faiss
    .venv-faiss/bin/pip install -q "faiss-cpu>=1.8,<2" "numpy>=1.24" >&2
fi
threads=$(nproc)
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT

echo "[side-by-side] semlook exact coarse: $refs references x $queries queries" >&2
"$bin" dev bench --cpu-only --sizes "$refs" --batches "$queries" --json -q > "$work/semlook.jsonl"

echo "[side-by-side] faiss-cpu IndexFlatIP: the same shape, 3,072 float32 per vector, $threads threads" >&2
.venv-faiss/bin/python - "$refs" "$queries" "$threads" "$work/semlook.jsonl" "$json" <<'PY'
import json, sys, time
import numpy as np
import faiss

refs, queries, threads, ours_path, out = int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5]
faiss.omp_set_num_threads(threads)
d = 48 * 64
rng = np.random.default_rng(7)
xb = rng.standard_normal((refs, d), dtype=np.float32)
xb /= np.linalg.norm(xb, axis=1, keepdims=True)
xq = rng.standard_normal((queries, d), dtype=np.float32)
xq /= np.linalg.norm(xq, axis=1, keepdims=True)
index = faiss.IndexFlatIP(d)
index.add(xb)
index.search(xq[: min(10, queries)], 30)  # warm-up
t = time.perf_counter()
index.search(xq, 30)
s = time.perf_counter() - t
rows = []
for line in open(ours_path):
    r = json.loads(line)
    if r.get("backend") == "cpu":
        rows.append({"what": "semlook exact SSIM coarse (dev bench --cpu-only)", "references": r["map_size"], "queries": r["batch"],
                     "seconds": r["seconds"], "comparisons_per_s": r["comparisons_per_s"], "gflops": r.get("gflops")})
rows.append({"what": f"faiss-cpu {faiss.__version__} IndexFlatIP, top-30", "references": refs, "queries": queries, "seconds": s,
             "comparisons_per_s": refs * queries / s, "gflops": 2.0 * d * refs * queries / s / 1e9})
for r in rows:
    print(json.dumps(r))
if out:
    json.dump(rows, open(out, "w"), indent=1)
PY
