#!/usr/bin/env bash
# The regimes of issue 60's development protocol: copies of the four real dev sets of ../shared at
# 320x240, 160x120 and 64x32 (every frame resized, PNG; the ground truth's names follow), what
# phones, robots and SeqSLAM-style pipelines feed a place recogniser. Twelve folders
# OUT/<set>-<W>x<H> (default OUT: target/dev-data); a copy that exists is kept.
#   bash scripts/lowres/make-dev-copies.sh [OUT]
set -euo pipefail
cd "$(dirname "$0")/../.."
src=../shared/data/real-vpr
out=${1:-target/dev-data}
[ -d "$src" ] || { echo "no $src (the shared data folder beside the repository)" >&2; exit 1; }
[ -x target/release/semlook ] || cargo build --release
mkdir -p "$out"
for set in nordland-spring-winter gardenspoint-day-night-mini landmarks-multiview-dev ie-tower-dev; do
    for size in 320x240 160x120 64x32; do
        dest="$out/$set-$size"
        if [ -f "$dest/ground_truth.csv" ]; then echo "$dest exists" >&2; continue; fi
        rm -rf "$dest"
        target/release/semlook dev downscale --dataset "$src/$set" --size "$size" --out "$dest" >&2
    done
done
