#!/usr/bin/env bash
# The low-resolution dev check of issue 51: a 64x32 copy of ../shared's nordland-spring-winter
# (every frame resized with an area-like filter, PNG; the ground truth's names follow), what
# SeqSLAM-style pipelines and small robots feed a place recogniser.
#   bash scripts/lowres/make-nordland-64x32.sh [OUT]   (default: target/dev-data/nordland-64x32)
set -euo pipefail
cd "$(dirname "$0")/../.."
src=../shared/data/real-vpr/nordland-spring-winter
out=${1:-target/dev-data/nordland-64x32}
[ -d "$src" ] || { echo "no $src (the shared data folder beside the repository)" >&2; exit 1; }
[ -x target/release/semlook ] || cargo build --release
if [ -f "$out/ground_truth.csv" ]; then echo "$out exists" >&2; exit 0; fi
mkdir -p "$(dirname "$out")"
target/release/semlook dev downscale --dataset "$src" --size 64x32 --out "$out"
