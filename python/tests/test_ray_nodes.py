"""Shards pinned to nodes (`ShardedMap(node_ids=...)`) on a Ray cluster of two nodes (two raylets
on this machine, ray.cluster_utils): each shard runs on the node it was pinned to, and the
results are exactly the single process's."""

import os

import pytest

import semlook

ray = pytest.importorskip("ray")
from ray.cluster_utils import Cluster  # noqa: E402

from semlook.distributed import ShardedMap  # noqa: E402


@pytest.fixture(scope="module")
def two_nodes():
    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    cluster = Cluster(initialize_head=True, head_node_args={"num_cpus": 1, "object_store_memory": 100 * 1024 * 1024})
    cluster.add_node(num_cpus=1, object_store_memory=100 * 1024 * 1024)
    cluster.wait_for_nodes()
    ray.init(address=cluster.address, log_to_driver=False, configure_logging=False)
    yield [n["NodeID"] for n in ray.nodes() if n["Alive"]]
    ray.shutdown()
    cluster.shutdown()


def test_shards_pinned_to_nodes_run_there_and_equal_one_process(two_nodes, small_map, queries, cpu):
    assert len(two_nodes) == 2
    cfg = semlook.Config("[appearance]\nmodel = \"none\"\n").with_top_k(6)
    for order in [two_nodes, two_nodes[::-1]]:
        pins = [order[0], order[1], order[0], order[1]]
        sm = ShardedMap(str(small_map.path), 4, config=cfg, cpus_per_shard=0.5, node_ids=pins, backend="cpu")
        assert [i["node_id"] for i in sm.info()] == pins
        for setting in ["global", "semlook"]:
            assert sm.query(queries, setting).equals(small_map.query(queries, setting, config=cfg, engine=cpu)), setting
        sm.close()
