#!/usr/bin/env bash
# Sweep 14 (issue 32): per-candidate scores of `verified` with each matcher on the three real dev sets, at the
# default 384 stored keypoints and at 768, written as `semlook localize --json` lines (score and inliers of
# each of the 30 candidates) for fuse.py. Usage: sweeps/prototypes/lighterglue-fusion/run.sh OUT_DIR [path/to/real-vpr]
# Takes about 25 minutes on the 2-core development machine (LighterGlue at 768 keypoints: 5 min on landmarks).
set -euo pipefail
out=${1:?output folder}; data=${2:-../shared/data/real-vpr}
B=${SEMLOOK:-target/release/semlook}
mkdir -p "$out"
for k in 384 768; do
  for c in mnn lighterglue; do
    printf '[keypoints]\nstored = %s\n[verification]\nmatcher = "%s"\n' "$k" "$c" > "$out/k$k-$c.toml"
  done
  for s in gardenspoint-day-night-mini nordland-spring-winter landmarks-multiview-dev; do
    [ -d "$out/map$k-$s" ] || "$B" -q map build --images "$data/$s/ref" --map "$out/map$k-$s" --config "$out/k$k-mnn.toml"
    for c in mnn lighterglue; do
      "$B" -q localize --map "$out/map$k-$s" --images "$data/$s/query" --setting verified --no-sequence --json \
        --config "$out/k$k-$c.toml" > "$out/k$k-$s-$c.jsonl"
    done
  done
done
