#!/usr/bin/env bash
# Receive-to-publish latency of semlook_node against a real ROS 2 peer (the README's ROS 2 figure):
# CamVid's 233 frames as the map (built without segmentation and with the real-time profile, a pose per
# place from a generated pose list, so every answer also publishes a PoseStamped), the night copy of `semlook synth
# --from-camvid` (960x720 JPEG) sent by rclpy as CompressedImage, each frame answered before the
# next, with the real-time profile (configs/stream-realtime.toml) on the CPU. Prints the node's
# summary line (receive_to_publish_ms p50/p99) and the peer's counts. Loopback DDS only.
#
#   bash ros2/scripts/latency.sh [FRAMES]      (default 120; needs setup.sh's .venv-ros and a release build)
set -euo pipefail
cd "$(dirname "$0")/../.."
frames=${1:-120}
camvid=../shared/data/camvid-test
venv=.venv-ros
bin=target/release/semlook node=target/release/semlook_node
for f in "$bin" "$node" "$venv/bin/python" "$camvid/images"; do
    [ -e "$f" ] || { echo "latency: $f is missing (cargo build --release --workspace; bash setup.sh)" >&2; exit 2; }
done
work=$(mktemp -d)
trap 'kill "${pid:-}" 2>/dev/null || true; rm -rf "$work"' EXIT
export ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST ROS_DOMAIN_ID=$((150 + $$ % 50)) ROS_DISTRO=kilted
export SEMLOOK_MODELS=${SEMLOOK_MODELS:-$(pwd)/.semlook}
"$bin" -q synth --from-camvid "$camvid" --change night --out "$work/camvid"
ref=$(ls -d "$work"/camvid/*/images | grep -v night | head -1)
night=$(ls -d "$work"/camvid/night*/images | head -1)
# a pose per place: along x, turning slowly about the camera's y axis (world-to-camera quaternion, centre)
ls "$ref" | awk '{ a = 0.01 * NR; printf "%s %.9f 0 %.9f 0 %d -1 0\n", $1, cos(a / 2), sin(a / 2), NR }' > "$work/poses.txt"
"$bin" -q --backend cpu map build --images "$ref" --poses "$work/poses.txt" --no-segmenter --config configs/stream-realtime.toml --map "$work/map"
"$node" --ros-args -p map:="$work/map" -p backend:=cpu -p config:=configs/stream-realtime.toml -p queue_size:=2 \
    > "$work/node.out" 2> "$work/node.err" &
pid=$!
sleep 2
ls "$night" | head -n "$frames" | awk -v d="$night" 'BEGIN { printf "{\"wait\": true, \"timeout\": 600, \"linger\": 2.0, \"expect\": 0, \"frames\": [" }
    { printf "%s{\"kind\": \"jpeg\", \"file\": \"%s/%s\", \"sec\": %d, \"nanosec\": 0}", (NR > 1 ? "," : ""), d, $1, 1000 + NR }
    END { print "]}" }' > "$work/plan.json"
msgs=$venv/semlook_msgs
PYTHONPATH=$msgs/python LD_LIBRARY_PATH=$msgs/lib "$venv/bin/python" ros2/tests/peer.py "$work/plan.json" "$work/peer.json"
kill -TERM "$pid"
wait "$pid" || true
pid=
grep -h "semlook_node\] INFO: map\|100 frames" "$work/node.err" || true
cat "$work/node.out"
"$venv/bin/python" -c "import json, sys; r = json.load(open(sys.argv[1])); print(json.dumps({'sent': r['published'], 'matches': len(r['matches']), 'poses': len(r['poses'])}))" "$work/peer.json"
