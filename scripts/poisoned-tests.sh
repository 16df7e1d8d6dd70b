#!/usr/bin/env bash
# The Python suite with a poisoned installed segmenter (issue 56): scripts/as-fresh.sh's model folder
# (everything setup.sh installed, the lookup limited to it) with an espnetv2_cityscapes.onnx that
# labels every pixel "road" (scripts/make_poisoned_segmenter.py). A test that quietly reads the
# installed segmenter sees a world without edges and fails; those that need the real one name it from
# ../shared/models (tests/common, python/tests) and are not fooled. The Rust suite needs no poison:
# the test command runs it through scripts/as-fresh.sh, where no segmenter is installed at all, so a
# quiet read fails there at once.
#   bash scripts/poisoned-tests.sh [PYTEST ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
poison=$(mktemp -d)
trap 'rm -rf "$poison"' EXIT
.venv-export/bin/python scripts/make_poisoned_segmenter.py "$poison/poisoned.onnx" >&2
AS_FRESH_SEGMENTER="$poison/poisoned.onnx" bash scripts/as-fresh.sh .venv/bin/python -m pytest python/tests -q "$@"
