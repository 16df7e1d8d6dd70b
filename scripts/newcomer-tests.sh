#!/usr/bin/env bash
# The command line's and Python's tests as a fresh machine runs them (issue 49): the model folder
# holds only what setup.sh installs without the default segmenter (which a machine without
# ../shared cannot make), and the model lookup searches that folder alone (SEMLOOK_MODELS_ONLY=1:
# neither the repository's .semlook nor the user's data folders), so a path that needs the
# segmenter fails here as it fails on such a machine. Part of the test command (README, .ci/run).
set -euo pipefail
cd "$(dirname "$0")/.."
installed=${SEMLOOK_MODELS:-$PWD/.semlook}
models=$(mktemp -d)
trap 'rm -rf "$models"' EXIT
# every installed model file but the segmenter and its checkpoint
for f in $(SEMLOOK_MODELS="$installed" SEMLOOK_MODELS_ONLY=1 target/release/semlook models --json \
        | .venv/bin/python -c 'import json, sys; print(" ".join(m["path"] for m in json.load(sys.stdin) if m.get("path") and not m["name"].startswith("espnetv2")))'); do
    ln -s "$f" "$models/$(basename "$f")"
done
echo "[newcomer] models: $(ls "$models" | tr '\n' ' ')(no segmenter; the lookup searches this folder alone)"
export SEMLOOK_MODELS="$models" SEMLOOK_MODELS_ONLY=1
cargo test --release --test cli
.venv/bin/python -m pytest python/tests/test_newcomer.py python/tests/test_api.py python/tests/test_cli_equivalence.py -q
