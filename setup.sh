#!/usr/bin/env bash
# One-time set-up of what semlook needs beyond a Rust toolchain, on a fresh Debian/Ubuntu machine.
# Safe to run again: every step checks first and does nothing if its result is already there.
#
#   - Mesa's Vulkan driver (lavapipe) and the Vulkan loader, so the GPU path runs on any machine
#     (on a real GPU, the vendor driver is used instead).
set -euo pipefail
cd "$(dirname "$0")"

say() { echo "[setup] $*" >&2; }

as_root() {
    if [ "$(id -u)" = 0 ]; then "$@"
    elif command -v sudo >/dev/null 2>&1; then sudo "$@"
    else return 1; fi
}

# 1. Vulkan loader + lavapipe
if ldconfig -p 2>/dev/null | grep -q 'libvulkan.so.1' && ls /usr/share/vulkan/icd.d/lvp_icd*.json >/dev/null 2>&1; then
    say "Vulkan loader and lavapipe present"
elif command -v apt-get >/dev/null 2>&1; then
    say "installing mesa-vulkan-drivers and libvulkan1"
    if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends mesa-vulkan-drivers libvulkan1 >/dev/null; }; then
        say "could not install the Vulkan driver (no root?); GPU tests will skip with a message"
        [ -z "${CI:-}" ] || { say "CI must exercise the GPU path: failing"; exit 1; }
    fi
else
    say "no apt-get: install a Vulkan driver yourself for the GPU path; GPU tests will skip with a message"
fi
say "done"
