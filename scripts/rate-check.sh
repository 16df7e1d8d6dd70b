#!/usr/bin/env bash
# Issue 48's rate check: a map recorded at one frame rate, a camera at another. Nordland's dev set
# (frames 1 s apart, query k <-> ref k-1..k+1) with every STEP-th query frame as the stream (a
# camera at 1/STEP of the map's frame rate), localized with the single-frame R@1 beside the
# stream's answer R@1, three ways: the velocity range as configured (0 to 4 positions per frame:
# what a stream without timestamps gets), derived from the timestamps of the map
# (`map build --timestamps`) and of the stream (`localize --timestamps`), and set by hand
# (`--velocity-scale STEP`). RATE_ARGS: more localize options (e.g. "--config FILE"). Everything in a
# temporary folder.
#
#   bash scripts/rate-check.sh [STEP] [SETTINGS]     (defaults 4, "verified appearance"; needs a release build)
set -euo pipefail
cd "$(dirname "$0")/.."
step=${1:-4}
settings=${2:-verified appearance}
set_dir=../shared/data/real-vpr/nordland-spring-winter
bin=${SEMLOOK_BIN:-target/release/semlook}
export SEMLOOK_MODELS=${SEMLOOK_MODELS:-$(pwd)/.semlook}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
mkdir "$work/query"
: > "$work/ref-times.txt"
for f in "$set_dir"/ref/*.jpg; do n=$(basename "$f" .jpg); echo "$n.jpg $((10#$n))" >> "$work/ref-times.txt"; done
: > "$work/query-times.txt"
for f in "$set_dir"/query/*.jpg; do
    n=$(basename "$f" .jpg)
    if (( (10#$n - 1) % step == 0 )); then ln -s "$(realpath "$f")" "$work/query/$n.jpg"; echo "$n.jpg $((10#$n))" >> "$work/query-times.txt"; fi
done
"$bin" -q --backend cpu map build --images "$set_dir/ref" --timestamps "$work/ref-times.txt" --no-segmenter --map "$work/map"
echo "queries: $(ls "$work/query" | wc -l) (every ${step}th frame); map: 60 places, 1 s apart"
printf "%-11s %-26s %8s %8s %9s %6s\n" setting velocity "frame R@1" "seq R@1" accepted scale
for s in $settings; do
    for how in configured timestamps hand; do
        case $how in
            configured) extra=() ;;
            timestamps) extra=(--timestamps "$work/query-times.txt") ;;
            hand) extra=(--velocity-scale "$step") ;;
        esac
        "$bin" -q --backend cpu localize --map "$work/map" --images "$work/query" --no-segmenter --setting "$s" --json "${extra[@]}" ${RATE_ARGS:-} > "$work/out.jsonl"
        python3 - "$work/out.jsonl" "$s" "$how" <<'PY'
import json, sys
rows = [json.loads(l) for l in open(sys.argv[1]) if '"frame"' in l]
ok = lambda q, r: abs(int(r) - int(q)) <= 1
frame = sum(ok(r["id"], r["top_k"][0]["id"]) for r in rows) / len(rows)
seq = sum(ok(r["id"], r["answer"]["id"]) for r in rows) / len(rows)
acc = sum(bool(r["sequence"] and r["sequence"]["accepted"]) for r in rows)
scale = max((r["sequence"] or {}).get("velocity_scale", 1.0) for r in rows)
label = {"configured": "as configured", "timestamps": "from timestamps", "hand": "--velocity-scale"}[sys.argv[3]]
print(f"{sys.argv[2]:<11} {label:<26} {frame:>8.3f} {seq:>8.3f} {acc:>5}/{len(rows):<3} {scale:>6.2f}")
PY
    done
done
