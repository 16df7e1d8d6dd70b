#!/usr/bin/env bash
# Python's tests of the newcomer's path as a fresh machine runs them (issue 49): through
# scripts/as-fresh.sh, the model folder holds only what setup.sh installs without the default
# segmenter (which a machine without ../shared cannot make), and the model lookup searches that folder
# alone, so a path that needs the segmenter fails here as it fails on such a machine. The Rust suite
# runs the same way in the test command (README, .ci/run); this adds the Python API and CLI
# equivalence tests of the newcomer's path.
set -euo pipefail
cd "$(dirname "$0")/.."
exec bash scripts/as-fresh.sh .venv/bin/python -m pytest python/tests/test_newcomer.py python/tests/test_api.py python/tests/test_cli_equivalence.py -q
