"""Python results equal `semlook query` on the same map and frames (ids and f32 scores), and
Python's defaults are the command line's (backend, evaluated settings)."""

import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

import semlook
from conftest import CLI, place, require_models, write_png


def test_map_query_equals_the_cli(tmp_path, encoder, cpu):
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
        py = m.query(queries, setting, engine=cpu)
        for i, q in enumerate(py.queries):
            assert [t["reference"] for t in cli[q]] == py.ids[i], (setting, q)
            n = py.counts[i]
            assert np.array_equal(np.array([t["score"] for t in cli[q]], np.float32), py.scores[i, :n]), (setting, q)


@pytest.fixture(scope="module")
def cli_eval(synth_dataset):
    """`semlook eval --json` on the synthetic benchmark with no --backend and no --setting."""
    out = subprocess.run([str(CLI), "eval", "--dataset", str(synth_dataset), "--no-appearance", "--json"], check=True, capture_output=True, text=True)
    return json.loads(out.stdout), out.stderr


def test_the_default_backend_is_the_command_lines(cli_eval, small_map):
    """Without `engine=` (and `Engine()`, `Shard(...)`) Python runs on the backend the command line
    runs on without --backend: the CLI's "backend" lines are the default engine's (before, Python
    ran on the CPU, so its engine said nothing where the CLI said "backend auto: no hardware GPU")."""
    lines = [line for line in cli_eval[1].splitlines() if line.startswith("backend")]
    default = semlook.default_engine()
    want = ([f"backend auto: {default.fallback_reason}"] if default.fallback_reason else []) + [f"backend: {default.describe}"]
    assert lines == want
    assert semlook.DEFAULT_BACKEND == "auto" and semlook.Engine().describe == default.describe
    assert semlook.Shard(str(small_map.path), 0, 1).backend == default.describe


def test_evaluate_runs_the_settings_the_command_line_runs(cli_eval, synth_dataset):
    """`evaluate` without `settings` runs what `semlook eval` runs without --setting: all nine
    (`EVAL_SETTINGS`, from the engine), in the same order, skipping the same ones."""
    assert semlook.EVAL_SETTINGS == tuple(semlook.settings()) and len(semlook.EVAL_SETTINGS) == 9
    cli, _ = cli_eval
    py = semlook.evaluate(dataset=str(synth_dataset), config=semlook.Config.without_appearance(), engine=semlook.Engine("cpu"))
    ran = lambda r: [(x["query_set"], x["setting"]) for x in r["results"]]  # noqa: E731
    assert ran(py) == ran(cli) and py["skipped"] == cli["skipped"]
    asked = [s for s in dict.fromkeys(x["setting"] for x in cli["results"])] + [s for s, _ in cli["skipped"]]
    assert sorted(asked, key=semlook.EVAL_SETTINGS.index) == list(semlook.EVAL_SETTINGS)


TINY = Path(__file__).resolve().parents[2] / "tests" / "data" / "tiny_segmenter.onnx"
TINY_CONFIG = '[appearance]\nmodel = "none"\n[segmentation]\ninput_width = 64\ninput_height = 48\nclass_map = ["road", "vegetation", "sky"]\n'


def test_a_labelled_map_never_scores_photos_without_labels(tmp_path, synth_dataset, cpu):
    """Issue 49: `Map.query` on a map built with a segmenter. Before, photo queries with no
    segmenter to label them were encoded without labels, without a word, and scored against the
    map's labelled references (`semlook` scored every query 0.0). Now they are refused before any
    encoding, naming the fix; with the map's segmenter given as `segmenter=` they are segmented
    and score as the command line's `query --segmenter` does."""
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    photos = synth_dataset / "day" / "RGB" / "Stereo_Left" / "Omni_F"
    night = synth_dataset / "night" / "RGB" / "Stereo_Left" / "Omni_F"
    cfg = semlook.Config(TINY_CONFIG)
    try:
        m = semlook.Map.build(tmp_path / "m", images=photos, segmenter=str(TINY), config=cfg, engine=cpu)
    except semlook.SemlookError as e:
        if "ONNX Runtime" in str(e) and not os.environ.get("CI"):
            pytest.skip(f"no ONNX Runtime ({e})")
        raise
    assert m.manifest().get("without_labels") in (None, False), "the map holds the segmenter's labels"
    with pytest.raises(semlook.SemlookError, match="holds semantic labels") as e:
        m.query(night, "semlook", segmenter=False, engine=cpu)
    assert "segmenter" in str(e.value)
    # arrays too: RGB frames alone
    rgb = [np.zeros((72, 96, 3), np.uint8) + 40]
    with pytest.raises(semlook.SemlookError, match="holds semantic labels"):
        m.query(rgb, "semlook", segmenter=False, engine=cpu)
    # the encoder for the map refuses them as well
    enc = semlook.Encoder.for_map(m, semlook.Config(TINY_CONFIG + "[models]\ndefault_segmenter = false\n"))
    with pytest.raises(semlook.SemlookError, match="holds semantic labels"):
        enc.encode("q", image=rgb[0])
    got = m.query(night, "semlook", segmenter=str(TINY), engine=cpu)
    out = subprocess.run([str(CLI), "query", "--map", str(tmp_path / "m"), "--images", str(night), "--segmenter", str(TINY), "--setting", "semlook", "--json", "--backend", "cpu"],
                         check=True, capture_output=True, text=True)
    cli = {row["query"]: row["top_k"] for row in json.loads(out.stdout)["queries"]}
    assert sorted(cli) == sorted(got.queries)
    for i, q in enumerate(got.queries):
        assert [t["reference"] for t in cli[q]] == got.ids[i], q
        assert np.array_equal(np.array([t["score"] for t in cli[q]], np.float32), got.scores[i, :got.counts[i]]), q
    assert float(np.max(got.scores)) > 0.0, "segmented queries score above zero"


def safetensors_content(path):
    """A safetensors file's header as a dict and its data bytes (its header's key order is not
    fixed: the writer's metadata is a hash map)."""
    raw = Path(path).read_bytes()
    n = int.from_bytes(raw[:8], "little")
    return json.loads(raw[8:8 + n]), raw[8 + n:]


def test_map_build_gives_the_command_lines_map(tmp_path, synth_dataset):
    """Issue 58 part 3: Python's `Map.build` built no index at any size while `semlook map build`
    builds one from `index.min_places` images (`--index auto`): one folder and one config gave two
    maps. Both now run the library's job (`semlook::batch::build_map`): the same manifest, index
    included (min_places 4, so the 8 places get one), and the same files, but for the map's uid,
    the index files' header order and the time the index took."""
    if not CLI.exists():
        pytest.skip(f"{CLI} not built (cargo build --release)")
    require_models("xfeat.pt", "efficientnet_lite1_gem.onnx")
    photos = synth_dataset / "day" / "RGB" / "Stereo_Left" / "Omni_F"
    labels = synth_dataset / "day" / "GT" / "LABELS" / "Stereo_Left" / "Omni_F"
    toml = tmp_path / "index.toml"
    toml.write_text("[index]\nmin_places = 4\n")
    semlook.Map.build(tmp_path / "py", images=photos, labels=labels, config=semlook.Config(toml.read_text()), engine=semlook.Engine("cpu"))
    subprocess.run([str(CLI), "--backend", "cpu", "map", "build", "--images", str(photos), "--labels", str(labels), "--config", str(toml), "--map", str(tmp_path / "cli"), "-q"],
                   check=True, capture_output=True)
    py, cli = (json.loads((tmp_path / d / "manifest.json").read_text()) for d in ("py", "cli"))
    assert "index" in py and "index" in cli, "min_places 4: both maps have their index"
    files = sorted(f.name for f in (tmp_path / "py").iterdir())
    assert files == sorted(f.name for f in (tmp_path / "cli").iterdir())
    for f in files:
        a, b = tmp_path / "py" / f, tmp_path / "cli" / f
        if f.startswith("index-"):
            assert safetensors_content(a) == safetensors_content(b), f
        elif f != "manifest.json":
            assert a.read_bytes() == b.read_bytes(), f
    # what differs: the uid, the checksum over it, the index files' sha256 (their header order),
    # the time the index took
    for m in (py, cli):
        del m["uid"], m["checksum"], m["index"]["build_ms"]
        for seg in m["segments"]:
            seg.get("index", {}).pop("sha256", None)
    assert py == cli
