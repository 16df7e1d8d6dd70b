#!/usr/bin/env bash
# The Python suite with a poisoned installed segmenter (issue 56): the model folder holds everything
# setup.sh installed, but its espnetv2_cityscapes.onnx labels every pixel "road"
# (scripts/make_poisoned_segmenter.py), and the lookup searches that folder alone. A test that quietly
# reads the installed segmenter sees a world without edges and fails; those that need the real one name
# it from ../shared/models (tests/common, python/tests/conftest.py) and are not fooled. The Rust suite
# needs no poison: the test command runs it through scripts/as-fresh.sh, where no segmenter is
# installed at all, so a quiet read fails there at once.
#   bash scripts/poisoned-tests.sh [PYTEST ARGS...]
set -euo pipefail
cd "$(dirname "$0")/.."
installed=${SEMLOOK_MODELS:-$PWD/.semlook}
models=$(mktemp -d)
trap 'rm -rf "$models"' EXIT
for f in "$installed"/*; do
    case "$(basename "$f")" in
        espnetv2*|*.part*) ;;
        *) ln -s "$(readlink -f "$f")" "$models/$(basename "$f")" ;;
    esac
done
.venv-export/bin/python scripts/make_poisoned_segmenter.py "$models/espnetv2_cityscapes.onnx" >&2
echo "[poisoned] models: $(ls "$models" | tr '\n' ' ')(the segmenter labels everything road)" >&2
SEMLOOK_MODELS="$models" SEMLOOK_MODELS_ONLY=1 .venv/bin/python -m pytest python/tests -q "$@"
