"""hloc interop: semlook's descriptors in hloc's ``global-feats-*.h5`` layout.

hloc (github.com/cvg/Hierarchical-Localization) names an image by its path relative to the image
root (``db/001.jpg``) and reads global descriptors from an HDF5 file holding, per image name, a
group with a ``global_descriptor`` dataset; ``pairs_from_retrieval`` ranks references by the dot
product of these. A map stores ids (file stems), so the names are found in the folders the map
was built from, as ``semlook query --pairs`` finds them::

    import semlook, semlook.hloc
    m = semlook.Map.open("map")
    semlook.hloc.export_global_features(m, "global-feats-semlook.h5", kind="appearance", images=["data/ref"], root="data")

``kind``: by default ``"global"`` for a map with semantic labels and ``"appearance"`` for one
built without them (photos with no segmenter: its global descriptors are all the same, so
``"global"`` is refused there, naming why); ``"global"``, the SemLook global descriptor (the edge distance map, flattened; semlook
compares it by SSIM, so hloc's dot product ranks differently from semlook) or ``"appearance"``,
the whole-image VLAD vector (unit length: hloc's dot product is semlook's cosine). Needs h5py.
From a shell: ``python -m semlook.hloc --map MAP --images DIR [--root DIR] [--kind K] --out FILE``.
"""

from __future__ import annotations

import argparse
import os
from typing import Iterator, Optional, Sequence, Union

import numpy as np

from ._native import Descriptors, InvalidInputError, Map, SemlookError, hloc_names

KINDS = ("global", "appearance")


def _without_labels(source: Union[Map, Descriptors]) -> bool:
    """Whether `source` was encoded without semantic labels: a map marked so, or descriptors
    with no object trees whose global descriptors are all one (nothing to rank them by)."""
    if isinstance(source, Map):
        return bool(source.manifest().get("without_labels", False))
    if len(source) == 0 or source.n_trees > 0:
        return False
    g = np.asarray(source.globals, np.float32).reshape(len(source), -1)
    return bool(np.all(g == g[:1]))
_Path = Union[str, "os.PathLike[str]"]


def _vectors(source: Union[Map, Descriptors], kind: str) -> Iterator[np.ndarray]:
    """Each image's descriptor of `kind`, float32, in the order of the source's ids."""
    if isinstance(source, Descriptors):
        block = source.globals if kind == "global" else source.image_appearance
        yield from np.asarray(block, np.float32)
        return
    for s in range(source.n_segments):
        view = source.segment_view(s, "globals" if kind == "global" else "image_appearance")
        for row in source.live_rows(s):
            yield np.asarray(view[row], np.float32).reshape(-1)


def export_global_features(
    source: Union[Map, Descriptors],
    path: _Path,
    *,
    kind: Optional[str] = None,
    names: Optional[Sequence[str]] = None,
    images: Optional[Sequence[_Path]] = None,
    root: Optional[_Path] = None,
) -> int:
    """Writes (or replaces) one group per image in the HDF5 file `path`, named as hloc names
    images, with a float32 `global_descriptor` of `kind`; returns the number written. Names:
    `names` (one per image, in the source's order), else found in the folders `images` (under
    `root`, default the deepest folder holding their parents, as `semlook query --pairs`
    names them: `ref/00.jpg`), else the ids themselves."""
    import h5py  # type: ignore[import-untyped]

    dim = source.appearance_dim if isinstance(source, Descriptors) else source.manifest()["appearance_dim"]
    label_free = _without_labels(source)
    if kind is None:
        kind = "appearance" if label_free and dim > 0 else "global"
    if kind not in KINDS:
        raise InvalidInputError(f"kind: {kind!r} is not one of {', '.join(KINDS)}")
    if kind == "global" and label_free:
        raise InvalidInputError(
            "kind: 'global', but these images were encoded without semantic labels, so every global descriptor is the same"
            + (" (export kind='appearance')" if dim > 0 else " and they have no appearance vectors either: nothing here ranks images")
        )
    ids = source.ids
    if kind == "appearance" and dim == 0:
        raise InvalidInputError("kind: 'appearance', but these descriptors have no appearance vectors (encoded without a keypoint network)")
    if names is None:
        names = hloc_names(ids, list(images), root) if images else list(ids)
    if len(names) != len(ids):
        raise InvalidInputError(f"names: {len(names)} names for {len(ids)} images")
    written = 0
    with h5py.File(path, "a") as fd:
        for name, vector in zip(names, _vectors(source, kind)):
            if name in fd:
                del fd[name]
            fd.create_group(name).create_dataset("global_descriptor", data=vector)
            written += 1
    return written


def main(argv: Optional[Sequence[str]] = None) -> None:
    p = argparse.ArgumentParser(prog="python -m semlook.hloc", description="Write a map's descriptors as hloc's global-feats HDF5 file.")
    p.add_argument("--map", required=True, help="the map directory")
    p.add_argument("--images", action="append", required=True, help="a folder the map was built from (repeat for several)")
    p.add_argument("--root", help="hloc's image root the names are relative to (default: the deepest folder holding the folders' parents, as semlook query --pairs names images)")
    p.add_argument("--kind", choices=KINDS, help="global: SemLook's global descriptor; appearance: the whole-image VLAD vector (default: global, or appearance for a map built without labels)")
    p.add_argument("--out", required=True, help="the .h5 file (groups of the same names are replaced)")
    a = p.parse_args(argv)
    try:
        m = Map.open(a.map)
        kind = a.kind or ("appearance" if _without_labels(m) and m.manifest()["appearance_dim"] > 0 else "global")
        n = export_global_features(m, a.out, kind=kind, images=a.images, root=a.root)
    except InvalidInputError as e:
        p.exit(1, f"error: {a.map}: {e}\n")
    except SemlookError as e:
        p.exit(1, f"error: {e}\n")
    print(f"wrote {n} {kind} descriptors to {a.out}")


if __name__ == "__main__":
    main()
