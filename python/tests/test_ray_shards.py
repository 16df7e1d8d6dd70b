"""A local Ray cluster (2 CPUs) serving a map split into 4 shards gives exactly the top-K lists
and scores of one process, in every setting and score fusion, with ties across shards."""

import json
import os
import subprocess
import sys

import pytest

import semlook
from conftest import place, write_png

ray = pytest.importorskip("ray")
from semlook.distributed import ShardedMap  # noqa: E402


@pytest.fixture(scope="module")
def cluster():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, object_store_memory=200 * 1024 * 1024, log_to_driver=False, configure_logging=False)
    yield
    ray.shutdown()


def test_four_shards_on_two_workers_equal_one_process(cluster, small_map, queries, cpu):
    path = str(small_map.path)
    assert small_map.n_segments == 8 and len(small_map) == 22
    plan = semlook.plan_shards(path, 4)
    assert sum(p["len"] for p in plan) == 22 and all(p["len"] > 0 for p in plan)
    for fusion_toml in ["", '[matching]\nscore = "fine_times_global"\n']:
        cfg = semlook.Config(fusion_toml + "[appearance]\nmodel = \"none\"\n").with_top_k(6)
        sm = ShardedMap(path, 4, config=cfg, cpus_per_shard=0.5, backend="cpu")
        for setting in ["global", "forest", "global-forest", "semlook"]:
            single = small_map.query(queries, setting, config=cfg, engine=cpu)
            sharded = sm.query(queries, setting)
            assert sharded.equals(single), (setting, fusion_toml)
            # the fixture stores every place twice: the best two of each query are a tie
            if setting == "global":
                ties = sum(single.scores[i, 0] == single.scores[i, 1] for i in range(len(single)))
                assert ties >= 5
        sm.close()


def test_a_changed_map_is_refused_by_its_shards(cluster, small_map):
    plan = semlook.plan_shards(str(small_map.path), 2)
    small_map.remove(["a0"])
    seg = plan[1]["segments"]
    with pytest.raises(semlook.InvalidInputError, match="plan again"):
        semlook.Shard(str(small_map.path), seg["start"], seg["end"], plan[1]["generation"])


def test_the_command_line_driver_joins_a_cluster_and_equals_one_process(cluster, small_map, tmp_path, cpu):
    """`python -m semlook.distributed --address ADDR` joins the running cluster, encodes the
    query files with the map's encoder and prints the single process's results."""
    qs = tmp_path / "q"
    qs.mkdir()
    qids = [f"q{s}" for s in range(3, 9)]
    for s, q in zip(range(3, 9), qids):
        write_png(qs / f"{q}.png", place(s, shift=2))
    out = tmp_path / "out.json"
    address = ray.get_runtime_context().gcs_address
    env = dict(os.environ, RAY_USAGE_STATS_ENABLED="0")
    run = subprocess.run([sys.executable, "-m", "semlook.distributed", "--address", address, "--map", str(small_map.path), "--shards", "3", "--labels", str(qs), "--setting", "semlook", "-k", "5", "--backend", "cpu", "--json", str(out)], capture_output=True, text=True, env=env, timeout=300)
    assert run.returncode == 0, run.stderr[-3000:]
    queries = semlook.Encoder.for_map(small_map).encode_files(qids, labels=[str(qs / f"{q}.png") for q in qids])
    single = small_map.query(queries, "semlook", k=5, engine=cpu)
    assert json.loads(out.read_text()) == single.to_list()
