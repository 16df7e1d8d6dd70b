#!/usr/bin/env bash
# Runs a command as a fresh machine would (issue 56): the model folder holds what setup.sh installs
# where the default segmenter cannot be made (everything installed but the segmenter and its
# checkpoint), and the model lookup searches that folder alone (SEMLOOK_MODELS_ONLY=1: neither the
# repository's .semlook nor the user's data folders). A test that needs the real segmenter names it
# explicitly (tests/common: with_real_segmenter, from ../shared/models); one that quietly reached the
# installed segmenter fails here, as on such a machine. The test command runs the Rust suite this way.
#   bash scripts/as-fresh.sh COMMAND [ARGS...]
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
# AS_FRESH_SEGMENTER=FILE puts FILE in as the installed segmenter (scripts/poisoned-tests.sh's poison)
if [ -n "${AS_FRESH_SEGMENTER:-}" ]; then
    ln -s "$(readlink -f "$AS_FRESH_SEGMENTER")" "$models/espnetv2_cityscapes.onnx"
    echo "[as-fresh] models: $(ls "$models" | tr '\n' ' ')(the segmenter: $AS_FRESH_SEGMENTER; the lookup searches this folder alone)" >&2
else
    echo "[as-fresh] models: $(ls "$models" | tr '\n' ' ')(no segmenter; the lookup searches this folder alone)" >&2
fi
SEMLOOK_MODELS="$models" SEMLOOK_MODELS_ONLY=1 "$@"
