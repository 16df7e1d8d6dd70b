#!/usr/bin/env bash
# Issue 32 prototypes: per-candidate scores of `verified` on the three real dev sets, written as
# `semlook localize --json` lines, for gate.py, geometry.py and aliked_lightglue.py: the default (MNN) and LighterGlue with glue_threshold 0.7 (sweep 14's
# fusion threshold). Maps by the default segmenter. Usage: sweeps/prototypes/verification-prototype/run.sh
# [OUT] [path/to/real-vpr]; about 6 minutes on the 2-core development machine.
set -euo pipefail
out=${1:-/tmp/verification-prototype}; data=${2:-../shared/data/real-vpr}
B=${SEMLOOK:-target/release/semlook}
mkdir -p "$out/localize"
printf '[index]\nsearch = "exact"\n' > "$out/mnn.toml"
printf '[index]\nsearch = "exact"\n[verification]\nmatcher = "lighterglue"\nglue_threshold = 0.7\n' > "$out/lg.toml"
for s in gardenspoint-day-night-mini nordland-spring-winter landmarks-multiview-dev; do
  [ -d "$out/maps/$s" ] || "$B" -q map build --images "$data/$s/ref" --map "$out/maps/$s"
  for c in mnn lg; do
    "$B" -q localize --map "$out/maps/$s" --images "$data/$s/query" --setting verified --no-sequence --json \
      --config "$out/$c.toml" > "$out/localize/$s-$c.jsonl"
  done
done
