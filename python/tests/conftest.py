"""Fixtures: small synthetic places as label-id arrays (no model files needed), label PNGs
written without extra packages, maps in segments small enough to shard."""

import os
import struct
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest

import semlook

REPO = Path(__file__).resolve().parents[2]
CLI = REPO / "target" / "release" / "semlook"
# where setup.sh installs the models (importing semlook sets SEMLOOK_MODELS to .semlook/ for a
# development install)
MODELS = Path(os.environ.get("SEMLOOK_MODELS", REPO / ".semlook"))


def require_models(*names):
    """The one rule for tests that need installed model files `names` (setup.sh's, in MODELS):
    where one is missing the test fails under CI or REQUIRE_MODELS=1, and skips saying which
    elsewhere."""
    missing = ", ".join(str(MODELS / n) for n in names if not (MODELS / n).is_file())
    if missing:
        if os.environ.get("CI") or os.environ.get("REQUIRE_MODELS") == "1":
            pytest.fail(f"required here (CI or REQUIRE_MODELS=1) but missing: {missing} (run setup.sh)")
        pytest.skip(f"missing {missing} (run setup.sh)")

# Cityscapes train ids of the default class table: road, sidewalk, building, wall, vegetation,
# terrain, sky, car, person, pole
CLASSES = [0, 1, 2, 3, 8, 9, 10, 13, 11, 5]


def place(seed, h=72, w=96, shift=0):
    """A street-like label map of place `seed`: sky, buildings, road, then objects; `shift`
    moves the view sideways by that many pixels (a query of the same place)."""
    rng = np.random.default_rng(seed)
    big = np.full((h, w + 16), 10, np.uint8)
    big[h // 2:, :] = 0
    for _ in range(rng.integers(4, 8)):
        c = CLASSES[rng.integers(1, len(CLASSES))]
        y0, x0 = rng.integers(0, h - 8), rng.integers(0, w + 8)
        big[y0:y0 + rng.integers(6, h // 2), x0:x0 + rng.integers(6, w // 3)] = c
    return big[:, 8 + shift:8 + shift + w].copy()


def write_png(path, a):
    """An 8-bit grey PNG of array `a`."""
    h, w = a.shape
    raw = b"".join(b"\x00" + a[y].astype(np.uint8).tobytes() for y in range(h))
    chunk = lambda t, d: struct.pack(">I", len(d)) + t + d + struct.pack(">I", zlib.crc32(t + d) & 0xFFFFFFFF)  # noqa: E731
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0)) + chunk(b"IDAT", zlib.compress(raw)) + chunk(b"IEND", b""))


@pytest.fixture(scope="session")
def cpu():
    """The CPU path, for comparisons that are bit for bit (the default engine may be a GPU)."""
    return semlook.Engine("cpu")


@pytest.fixture(scope="session")
def synth_dataset(tmp_path_factory):
    """`semlook synth`'s benchmark, 8 places at 160x120."""
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    ds = tmp_path_factory.mktemp("synth") / "bench"
    subprocess.run([str(CLI), "synth", "--out", str(ds), "--places", "8", "--size", "160x120"], check=True, capture_output=True)
    return ds


@pytest.fixture(scope="session")
def encoder():
    return semlook.Encoder(semlook.Config.without_appearance())


def encode_places(enc, seeds, prefix, shift=0):
    return semlook.Descriptors.concat([enc.encode(f"{prefix}{s}", labels=place(s, shift=shift)) for s in seeds])


@pytest.fixture
def small_map(tmp_path, encoder):
    """12 places stored twice (ids a*, b*: identical descriptors 12 apart, so ties cross
    segments and shards), 3 images per segment (8 segments), two images removed."""
    refs = semlook.Descriptors.concat([encode_places(encoder, range(12), "a"), encode_places(encoder, range(12), "b")])
    m = semlook.Map.create(str(tmp_path / "map"), refs, encoder, segment_images=3)
    m.remove(["a3", "b10"])
    return m


@pytest.fixture
def queries(encoder):
    return encode_places(encoder, range(1, 11), "q", shift=3)
