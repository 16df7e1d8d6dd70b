"""Python results equal `semlook query` on the same map and frames (ids and f32 scores)."""

import json
import subprocess

import numpy as np
import pytest

import semlook
from conftest import CLI, place, write_png


def test_map_query_equals_the_cli(tmp_path, encoder):
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    refs, qs = tmp_path / "refs", tmp_path / "queries"
    refs.mkdir()
    qs.mkdir()
    for s in range(10):
        write_png(refs / f"r{s}.png", place(s))
    for s in range(2, 8):
        write_png(qs / f"q{s}.png", place(s, shift=2))
    ids = [f"r{s}" for s in range(10)]
    d = encoder.encode_files(ids, labels=[str(refs / f"{i}.png") for i in ids])
    m = semlook.Map.create(str(tmp_path / "m"), d, encoder, segment_images=4)
    qids = [f"q{s}" for s in range(2, 8)]
    queries = semlook.Encoder.for_map(m).encode_files(qids, labels=[str(qs / f"{i}.png") for i in qids])
    for setting in ["semlook", "global", "forest"]:
        out = subprocess.run([str(CLI), "query", "--map", str(tmp_path / "m"), "--labels", str(qs), "--setting", setting, "--json", "--backend", "cpu"], check=True, capture_output=True, text=True)
        cli = {row["query"]: row["top_k"] for row in json.loads(out.stdout)["queries"]}
        py = m.query(queries, setting)
        for i, q in enumerate(py.queries):
            assert [t["reference"] for t in cli[q]] == py.ids(i), (setting, q)
            n = py.counts[i]
            assert np.array_equal(np.array([t["score"] for t in cli[q]], np.float32), py.scores[i, :n]), (setting, q)
