"""semlook: SemLook visual place recognition (semantic edge + forest descriptors).

Encode frames to ``Descriptors``, build and grow a ``Map`` (memory-mapped segments), query it,
evaluate datasets; ``semlook.distributed`` matches against a map sharded over Ray actors with
exactly the results of one process.

    import semlook
    enc = semlook.Encoder(semlook.Config.without_appearance())
    refs = enc.encode_files(ids, labels=label_paths)
    m = semlook.Map.create("my-map", refs, enc)
    m.add(more)                                   # add, remove, compact: in place
    matches = m.query(semlook.Encoder.for_map(m).encode_files(qids, labels=qpaths))
    matches = m.query([label_array, ...])         # or arrays, encoded with the map's encoder
    matches.references, matches.scores, matches.ids[0]

``Engine("gpu")`` (or "auto") runs encoding and matching on a GPU through wgpu: pass
``engine=`` to ``Encoder.encode_files``, ``Map.query`` and ``evaluate``; keep one per process
(the map stays resident on the device between calls). Without ``engine=`` they run on
``default_engine()``, an ``Engine(DEFAULT_BACKEND)``: "auto", as on the command line.

Processes: heavy calls release the GIL and run on rayon threads. Do not fork a process that has
used semlook (``multiprocessing``'s default on Linux): use the 'spawn' start method (Ray does).

Model files (XFeat weights, ONNX Runtime, segmenter) are looked up at run time: the
``SEMLOOK_MODELS`` folder, else the repository's ``.semlook`` folder for a development install.
"""

import os as _os
from pathlib import Path as _Path

_repo_models = _Path(__file__).resolve().parents[2] / ".semlook"
if "SEMLOOK_MODELS" not in _os.environ and _repo_models.is_dir():
    _os.environ["SEMLOOK_MODELS"] = str(_repo_models)
# Mesa's Vulkan loader prints "error: XDG_RUNTIME_DIR is invalid or not set" (twice) when the
# engine probes adapters on a headless machine; the folder is not used for compute. As the CLI
# does, point it at the temporary folder when it is unset or not a folder.
if not _os.path.isdir(_os.environ.get("XDG_RUNTIME_DIR", "")):
    import tempfile as _tempfile

    _os.environ["XDG_RUNTIME_DIR"] = _tempfile.gettempdir()

from ._native import (  # noqa: E402
    DEFAULT_BACKEND,
    EVAL_SETTINGS,
    Config,
    CorruptMapError,
    DatasetError,
    Descriptors,
    DuplicateImageIdError,
    Encoder,
    Engine,
    GpuError,
    IncompatibleConfigError,
    InputFileError,
    InvalidConfigError,
    InvalidImageError,
    InvalidInputError,
    Localizer,
    Map,
    MapVersionError,
    Matches,
    MissingFileError,
    ModelError,
    SemlookError,
    Shard,
    __version__,
    default_engine,
    evaluate,
    list_len,
    merge_candidates,
    plan_shards,
    rank,
    reranks,
    settings,
)

SETTINGS = tuple(settings())

__all__ = [
    "Config", "Descriptors", "Encoder", "Engine", "Localizer", "Map", "Matches", "Shard", "evaluate", "list_len",
    "DEFAULT_BACKEND", "EVAL_SETTINGS", "default_engine",
    "merge_candidates", "plan_shards", "rank", "reranks", "settings", "SETTINGS", "__version__",
    "SemlookError", "CorruptMapError", "DatasetError", "DuplicateImageIdError", "GpuError",
    "IncompatibleConfigError", "InputFileError", "InvalidConfigError", "InvalidImageError",
    "InvalidInputError", "MapVersionError", "MissingFileError", "ModelError",
]
