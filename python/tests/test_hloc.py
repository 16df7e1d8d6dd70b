"""hloc interop: `semlook query --pairs` read as hloc's `parse_retrieval` reads it, and the
global-feats `.h5` of `semlook.hloc` read back with h5py as hloc's `pairs_from_retrieval` does
(names, shapes, values)."""

import os
import sys
import subprocess
from collections import defaultdict

import h5py
import numpy as np
import pytest

import semlook
import semlook.hloc
from conftest import CLI, require_models

OMNI = "RGB/Stereo_Left/Omni_F"


def parse_retrieval(path):
    """hloc.utils.parsers.parse_retrieval, as hloc 1.5 has it."""
    retrieval = defaultdict(list)
    with open(path, "r") as f:
        for p in f.read().rstrip("\n").split("\n"):
            if len(p) == 0:
                continue
            q, r = p.split()
            retrieval[q].append(r)
    return dict(retrieval)


def list_h5_names(path):
    """hloc.utils.io.list_h5_names: the groups holding a dataset, by their path."""
    names = []
    with h5py.File(str(path), "r", libver="latest") as fd:
        def visit_fn(_, obj):
            if isinstance(obj, h5py.Dataset):
                names.append(obj.parent.name.strip("/"))
        fd.visititems(visit_fn)
    return list(set(names))


def get_descriptors(names, path, key="global_descriptor"):
    """hloc.pairs_from_retrieval.get_descriptors."""
    with h5py.File(str(path), "r", libver="latest") as fd:
        return np.stack([fd[n][key].__array__() for n in names], 0)


def cli(*args):
    return subprocess.run([str(CLI), *map(str, args)], check=True, capture_output=True, text=True).stdout


@pytest.fixture
def built(tmp_path):
    """A synthetic day/night set and a map of the day frames (no appearance)."""
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    data = tmp_path / "data"
    cli("synth", "--out", data, "--places", "6", "--size", "160x120", "--query-condition", "night", "-q")
    day, labels = data / "day" / OMNI, data / "day/GT/LABELS/Stereo_Left/Omni_F"
    cli("map", "build", "--images", day, "--labels", labels, "--map", tmp_path / "map", "--no-appearance", "-q")
    return data, tmp_path / "map"


def test_pairs_parse_as_hloc_reads_them_and_name_files_under_the_root(tmp_path, built):
    data, m = built
    pairs = tmp_path / "pairs-semlook.txt"
    night = data / "night" / OMNI
    cli("query", "--map", m, "--images", night, "--labels", data / "night/GT/LABELS/Stereo_Left/Omni_F", "--no-appearance", "-q",
        "--pairs", pairs, "--references", data / "day" / OMNI, "--pairs-k", 4)
    retrieval = parse_retrieval(pairs)
    assert sorted(retrieval) == [f"night/{OMNI}/{f}" for f in sorted(os.listdir(night))]
    assert all(len(refs) == 4 and len(set(refs)) == 4 for refs in retrieval.values()), retrieval
    for q, refs in retrieval.items():
        assert (data / q).is_file() and all((data / n).is_file() and n.startswith(f"day/{OMNI}/") for n in refs), (q, refs)
    # the map's own h5 holds every reference the pairs name, under the same names
    semlook.hloc.export_global_features(semlook.Map.open(str(m)), tmp_path / "global-feats-semlook.h5", images=[data / "day" / OMNI], root=data)
    stored = set(list_h5_names(tmp_path / "global-feats-semlook.h5"))
    assert {r for refs in retrieval.values() for r in refs} <= stored


def test_global_features_read_back_with_h5py(tmp_path, built):
    data, m = built
    # a removed image is left out (the map serves its live images only)
    m = semlook.Map.open(str(m))
    m.remove(["000001"])
    h5 = tmp_path / "global-feats-semlook.h5"
    n = semlook.hloc.export_global_features(m, h5, images=[data / "day" / OMNI], root=data)
    names = [f"day/{OMNI}/{i}.png" for i in m.ids]
    assert n == 5 and sorted(list_h5_names(h5)) == sorted(names) and f"day/{OMNI}/000001.png" not in names
    want = np.concatenate([m.segment_view(s, "globals")[m.live_rows(s)] for s in range(m.n_segments)]).reshape(5, -1)
    got = get_descriptors(names, h5)
    assert got.dtype == np.float32 and got.shape == (5, 64 * 48)
    assert np.array_equal(got, want)
    # from Descriptors, with names given: groups of the same name are replaced, others kept
    d = semlook.Encoder.for_map(m).encode_files(["x"], labels=[str(data / "night/GT/LABELS/Stereo_Left/Omni_F/000002.png")])
    semlook.hloc.export_global_features(d, h5, names=[names[0]])
    assert len(list_h5_names(h5)) == 5
    assert np.array_equal(get_descriptors(names[:1], h5)[0], d.globals[0])
    with pytest.raises(semlook.InvalidInputError, match="no appearance"):
        semlook.hloc.export_global_features(m, h5, kind="appearance")
    with pytest.raises(semlook.InvalidInputError, match="000000"):
        semlook.hloc.export_global_features(m, h5, images=[data / "night/GT/LABELS"])


def test_appearance_vectors_and_the_command_line(tmp_path):
    """With XFeat (setup.sh): the whole-image appearance vectors, unit length, as the map holds them."""
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    require_models("xfeat.pt")
    data = tmp_path / "data"
    cli("synth", "--out", data, "--places", "4", "--size", "160x128", "--query-condition", "night", "-q")
    day = data / "day" / OMNI
    cli("map", "build", "--images", day, "--labels", data / "day/GT/LABELS/Stereo_Left/Omni_F", "--map", tmp_path / "map", "-q")
    h5 = tmp_path / "global-feats-appearance.h5"
    out = subprocess.run([sys.executable, "-m", "semlook.hloc", "--map", tmp_path / "map", "--images", day, "--kind", "appearance", "--out", h5],
                         check=True, capture_output=True, text=True).stdout
    assert "wrote 4 appearance descriptors" in out
    m = semlook.Map.open(str(tmp_path / "map"))
    # no --root: names keep their folder (`Omni_F/000000.png`), as `semlook query --pairs` names them
    got = get_descriptors([f"Omni_F/{i}.png" for i in m.ids], h5)
    assert got.shape == (4, m.manifest()["appearance_dim"])
    assert np.allclose(np.linalg.norm(got, axis=1), 1.0, atol=1e-3)
    assert np.array_equal(got, m.segment_view(0, "image_appearance")[m.live_rows(0)])
