#!/usr/bin/env bash
# One device check, ready for the day a GPU is lent (issue 19 part 4): builds, runs the GPU equivalence
# suite with REQUIRE_GPU=1, then the benchmark rows, and writes one JSON with the adapter and every row's
# figures (throughput, fraction of the device's peak where the built-in table knows it).
#
#   bash scripts/device-check.sh [--budget SECONDS] [--out FILE] [--bin PATH] [--smoke] [--segmenter FILE]
#
# --budget (default 480): the rows are planned against it; the largest coarse rows are dropped first
#   when the time left (measured as the script goes) cannot hold them.
# --out (default target/device-check.json). --bin: an already-built semlook (skips the build).
# --segmenter: the segmenter the encoding row labels its photos with (default: the installed one; the
#   smoke test names the real one of ../shared/models: tests never read what a machine installed).
# --smoke: the reduced form CI runs on lavapipe so the script cannot rot: no build or test suite (the
#   caller is the test suite), a 1,000-reference coarse row and a 4-frame encoding row at 320x240.
# Rows: coarse top-K (`semlook dev bench`, 100k and 1M references x 1,000 queries, CPU and GPU), encoding
# (`semlook dev bench-encode` on 1920x1080 synthetic frames, GPU backend, the installed segmenter on ONNX
# Runtime's CPU provider), the stream (`semlook dev bench-stream`: the night traversal of synthetic
# 1920x1080 frames replayed against maps of 1k and 10k places through the streaming localizer on the
# GPU backend, the real-time profile configs/stream-realtime.toml; target >= 100 frames/s), and the fine
# stage (criterion `benches/matching.rs`, group `fine`, K = 20), verification with LighterGlue on the
# device (criterion `benches/verify.rs`, its GPU row, K = 30, target <= 5 ms a query), and the index (`semlook dev index-bench`:
# 1M references, the approximate index on the CPU beside the exact scan on the device).
# Carry the model folder to the device (`.semlook`, about 40 MB) for the encoding row.
set -euo pipefail
cd "$(dirname "$0")/.."

budget=480 out=target/device-check.json bin="" smoke=0 segmenter=()
while [ $# -gt 0 ]; do
    case "$1" in
        --budget) budget=$2; shift 2 ;;
        --out) out=$2; shift 2 ;;
        --bin) bin=$2; shift 2 ;;
        --smoke) smoke=1; shift ;;
        --segmenter) segmenter=(--segmenter "$2"); shift 2 ;;
        *) echo "device-check: unknown argument $1" >&2; exit 2 ;;
    esac
done
start=$(date +%s)
left() { echo $(( budget - ($(date +%s) - start) )); }
say() { echo "[device-check] $*" >&2; }
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
rows="$work/rows.jsonl"
: > "$rows"
# the index row's queries are photos of a labelled map: dev index-bench takes the segmenter in a config
segmenter_config=()
if [ ${#segmenter[@]} -gt 0 ]; then
    printf '[models]\nsegmenter_onnx = "%s"\n' "${segmenter[1]}" > "$work/segmenter.toml"
    segmenter_config=(--config "$work/segmenter.toml")
fi
note() { # kind, name, reason: a row that did not run, with why
    python3 -c 'import json,sys; print(json.dumps({"row": sys.argv[1], "name": sys.argv[2], "status": "not run", "reason": sys.argv[3]}))' "$1" "$2" "$3" >> "$rows"
}

if [ -z "$bin" ]; then
    say "building (cargo build --release)"
    cargo build --release >&2
    bin=target/release/semlook
fi
if [ $smoke = 0 ]; then
    say "GPU equivalence suite (REQUIRE_GPU=1: no adapter is a failure)"
    REQUIRE_GPU=1 cargo test --release --test gpu >&2
fi

# coarse rows, smallest first; a row runs only if the time left holds its predicted time
if [ $smoke = 1 ]; then sizes="1000"; batch=10; else sizes="100000 1000000"; batch=1000; fi
for n in $sizes; do
    t=$(left)
    if [ "$t" -lt 30 ]; then note coarse "coarse $n x $batch" "budget: ${t} s left"; continue; fi
    say "coarse $n references x $batch queries (at most $(( t / 3 )) s per row)"
    "$bin" dev bench --sizes "$n" --batches "$batch" --max-row-seconds $(( t / 3 )) --json -q \
        | python3 -c 'import json,sys
for line in sys.stdin:
    r = json.loads(line); r["row"] = "coarse"; print(json.dumps(r))' >> "$rows"
done

# encoding rows: synthetic frames with label maps at the benchmark size
if [ $smoke = 1 ]; then size=320x240 frames=4; else size=1920x1080 frames=60; fi
if [ "$(left)" -gt 20 ]; then
    say "encoding $frames frames at $size on the GPU backend"
    "$bin" synth --out "$work/frames" --places "$frames" --size "$size" --query-condition night -q
    "$bin" dev bench-encode --images "$work/frames/day/RGB/Stereo_Left/Omni_F" --frames "$frames" --backend gpu ${segmenter[@]+"${segmenter[@]}"} --json -q \
        | python3 -c 'import json,sys; r = json.load(sys.stdin); print(json.dumps({"row": "encode", "size": sys.argv[1], "result": r}))' "$size" >> "$rows" \
        || note encode "encode $size" "dev bench-encode failed (see the log above)"
else
    note encode "encode $size" "budget"
fi

# the stream row: a night traversal replayed against maps of its day traversal plus distractors
if [ $smoke = 1 ]; then ssize=320x240 sframes=8 ssizes=100; else ssize=1920x1080 sframes=200 ssizes=1000,10000; fi
if [ "$(left)" -gt 60 ]; then
    say "stream: $sframes frames at $ssize against maps of $ssizes places on the GPU backend"
    "$bin" synth --out "$work/stream" --places "$sframes" --size "$ssize" --query-condition night --query-condition fog -q
    cam=Stereo_Left/Omni_F
    "$bin" --backend gpu dev bench-stream --references "$work/stream/day/RGB/$cam" --stream "$work/stream/night/RGB/$cam" \
        --distractors "$work/stream/fog/RGB/$cam" --sizes "$ssizes" --frames "$sframes" --config configs/stream-realtime.toml --json -q \
        | python3 -c 'import json,sys
for line in sys.stdin:
    r = json.loads(line); print(json.dumps({"row": "stream", "size": sys.argv[1], "result": r}))' "$ssize" >> "$rows" \
        || note stream "stream $ssize" "dev bench-stream failed (see the log above)"
else
    note stream "stream $ssize" "budget"
fi

# the index row (issue 29): the approximate index on the CPU against the exact fused coarse scan on the
# device, on maps of the synthetic day traversal's real descriptors replicated (`semlook dev index-bench`)
if [ $smoke = 1 ]; then isizes=2000 iq=10 itimed=1 ibatch=10 isearch=4:100; else isizes=1000000 iq=200 itimed=5 ibatch=1000 isearch=48:500:0,96:1000:0,112:150:6000; fi
if [ "$(left)" -gt 120 ] || [ $smoke = 1 ]; then
    say "index: $isizes references, exact on the device, the index on the CPU"
    [ -d "$work/stream" ] || "$bin" synth --out "$work/stream" --places "$sframes" --size "$ssize" --query-condition night -q
    "$bin" map build --images "$work/stream/day/RGB/$cam" --labels "$work/stream/day/GT/LABELS/$cam" --map "$work/index-base" --index none -q \
        && "$bin" --backend gpu dev index-bench --from "$work/index-base" --queries "$work/stream/night/RGB/$cam" --sizes "$isizes" ${segmenter_config[@]+"${segmenter_config[@]}"} \
            --exact-queries "$iq" --exact-timed "$itimed" --batch "$ibatch" --search "$isearch" --dir "$work" --json -q \
        | python3 -c 'import json,sys
for line in sys.stdin:
    r = json.loads(line); print(json.dumps({"row": "index", "result": r}))' >> "$rows" \
        || note index "index $isizes" "dev index-bench failed (see the log above)"
else
    note index "index $isizes" "budget"
fi

# criterion rows (full run only: their build is minutes): the fine stage (group fine, K = 20) and
# verification with LighterGlue on the device (group verify, K = 30; target <= 5 ms a query), the
# embedding network on the device and natively on the CPU (group embedding_forward, 448x336 and 448x252)
criterion_rows() { # row kind, criterion group
    python3 - "$rows" "$1" "$2" <<'PY'
import glob, json, os, sys
rows, kind, group = sys.argv[1:]
for est in glob.glob(f"target/criterion/{group}/*/*/new/estimates.json") + glob.glob(f"target/criterion/{group}/*/new/estimates.json"):
    name = os.path.relpath(os.path.dirname(os.path.dirname(est)), f"target/criterion/{group}")
    with open(est) as f:
        e = json.load(f)
    with open(rows, "a") as out:
        out.write(json.dumps({"row": kind, "name": name, "median_s": e["median"]["point_estimate"] * 1e-9}) + "\n")
PY
}
if [ $smoke = 1 ]; then
    note fine "fine K=20" "smoke: criterion rows run in the full check only"
    note verify "verify K=30 (GPU: LighterGlue)" "smoke: criterion rows run in the full check only"
    note embedding "embedding 448x336 (GPU: EfficientNet-Lite1)" "smoke: criterion rows run in the full check only"
else
    if [ "$(left)" -gt 90 ]; then
        say "fine stage (criterion, group fine)"
        cargo bench --bench matching -- fine --warm-up-time 1 --measurement-time 3 >&2
        criterion_rows fine fine
    else
        note fine "fine K=20" "budget"
    fi
    if [ "$(left)" -gt 90 ]; then
        say "verification with LighterGlue on the device (criterion, group verify, GPU rows)"
        rm -rf target/criterion/verify
        cargo bench --bench verify -- "GPU" --warm-up-time 1 --measurement-time 3 >&2
        criterion_rows verify verify
    else
        note verify "verify K=30 (GPU: LighterGlue)" "budget"
    fi
    if [ "$(left)" -gt 90 ]; then
        say "the embedding network on the device (criterion, group embedding_forward)"
        rm -rf target/criterion/embedding_forward
        cargo bench --bench embedding_gpu -- --warm-up-time 1 --measurement-time 3 >&2
        criterion_rows embedding embedding_forward
        # the bench skips (exit 0) without the checkpoint or a hardware adapter: say so in the report
        [ -d target/criterion/embedding_forward ] || note embedding "embedding 448x336 (GPU: EfficientNet-Lite1)" "the bench ran no row (no checkpoint or no hardware adapter: see the log above)"
    else
        note embedding "embedding 448x336 (GPU: EfficientNet-Lite1)" "budget"
    fi
fi

python3 - "$rows" "$out" "$smoke" "$budget" "$(( $(date +%s) - start ))" <<'PY'
import json, sys
rows_path, out, smoke, budget, took = sys.argv[1:]
rows = [json.loads(l) for l in open(rows_path) if l.strip()]
adapters = sorted({r["adapter"] for r in rows if r.get("row") == "coarse" and r.get("backend") == "gpu"})
report = {"smoke": smoke == "1", "budget_s": int(budget), "took_s": int(took), "gpu_adapters": adapters, "rows": rows}
with open(out, "w") as f:
    json.dump(report, f, indent=1)
print(f"[device-check] {len(rows)} rows, GPU adapters {adapters or 'none'}, {took} s -> {out}", file=sys.stderr)
PY
