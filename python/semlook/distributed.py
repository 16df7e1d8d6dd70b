"""Matching against a map sharded over Ray actors, with exactly the results of one process.

A map is cut into contiguous ranges of segments (``plan_shards``); one actor per range opens
only those segment files (memory-mapped) and computes, for a batch of queries, its candidate
lists in the whole map's index space. The driver merges them (``merge_candidates``: the same
top-K fold one process runs, ties to the lower index), asks the owner of each candidate for its
fine score, and ranks (``rank``). Only Rust orders results.

What travels per query batch: the query descriptors once to every node (Ray stores one copy per
node), each actor's candidate lists back (Q x L x 12 bytes), then the candidate pairs to their
owners and their fine scores and ids back (Q x K x ~30 bytes). See docs/library.md, "Python and Ray".

    ray.init()                                  # or ray.init(address="auto") on a cluster
    sm = ShardedMap("/maps/city", shards=4)
    matches = sm.query(queries, setting="semlook")
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time

import numpy as np

import semlook


def _actor_class():
    import ray

    @ray.remote
    class ShardActor:
        """One shard of a map, opened alone; methods run one at a time."""

        def __init__(self, map_dir, seg_start, seg_end, generation, config_toml, k, threads, models, backend):
            if models:
                os.environ.setdefault("SEMLOOK_MODELS", models)
            # the GPU Ray reserved for this actor (its CUDA index, which Vulkan usually lists in
            # the same order on NVIDIA; not guaranteed by either), else the first adapter
            gpus = ray.get_gpu_ids() if backend != "cpu" else []
            adapter = int(gpus[0]) if gpus else None
            self.shard = semlook.Shard(map_dir, seg_start, seg_end, generation, config_toml, k, threads, backend, adapter)
            self.busy = 0.0

        def info(self):
            node = ray.get_runtime_context().get_node_id()
            return dict(self.shard.info(), backend=self.shard.backend, gpu_calls=self.shard.gpu_calls, node_id=node)

        def candidates(self, queries, setting):
            t = time.perf_counter()
            out = self.shard.candidates(queries, setting)
            self.busy += time.perf_counter() - t
            return out

        def fine(self, queries, setting, q, r):
            t = time.perf_counter()
            scores = self.shard.fine(queries, setting, q, r)
            ids = self.shard.reference_ids(r.tolist())
            self.busy += time.perf_counter() - t
            return scores, ids

        def reference_ids(self, r):
            return self.shard.reference_ids(r.tolist())

        def take_busy_seconds(self):
            b, self.busy = self.busy, 0.0
            return b

    return ShardActor


class ShardedMap:
    """A map served by ``shards`` Ray actors (call ``ray.init`` first).

    ``cpus_per_shard`` is what each actor reserves from Ray (fractions allowed; default: the
    cluster's CPUs divided among the shards), ``threads_per_shard`` the rayon threads it runs
    (default: max(1, floor(cpus_per_shard))). ``backend`` is each shard's ``Engine`` backend
    ("cpu", "gpu", "auto"; default ``semlook.DEFAULT_BACKEND``, as on the command line; on a GPU
    the shard's part of the map stays resident on the device),
    ``gpus_per_shard`` what each actor reserves from Ray's GPUs (default: 1 with backend "gpu",
    else 0; with "auto" reserve them yourself where nodes have GPUs, or Ray may place several
    shards on one GPU); a shard opens the GPU Ray gave it (``ray.get_gpu_ids()``). ``node_ids`` pins shard i to node ``node_ids[i]``
    (each node then needs only the manifest, the codebook and its own segment files); without
    it every node must see the whole map directory at the same path (a shared file system).
    """

    def __init__(self, map_dir, shards, *, config=None, k=None, cpus_per_shard=None, threads_per_shard=None, node_ids=None, backend=None, gpus_per_shard=None):
        import ray

        backend = backend or semlook.DEFAULT_BACKEND
        self.map_dir = os.path.abspath(map_dir)
        self.plan = semlook.plan_shards(self.map_dir, shards)
        self.starts = np.array([p["global_start"] for p in self.plan], dtype=np.int64)
        if cpus_per_shard is None:
            cpus_per_shard = max(0.01, ray.cluster_resources().get("CPU", 1) / shards)
        threads = threads_per_shard or max(1, math.floor(cpus_per_shard))
        cfg = config if config is not None else semlook.Config.for_map_dir(self.map_dir)
        self.config = cfg.with_top_k(k) if k is not None else cfg
        toml = self.config.to_toml()
        models = os.environ.get("SEMLOOK_MODELS")
        Actor = _actor_class()
        self.actors = []
        for i, p in enumerate(self.plan):
            opts = {"num_cpus": cpus_per_shard}
            gpus = gpus_per_shard if gpus_per_shard is not None else (1 if backend == "gpu" else 0)
            if gpus:
                opts["num_gpus"] = gpus
            if node_ids is not None:
                from ray.util.scheduling_strategies import NodeAffinitySchedulingStrategy

                opts["scheduling_strategy"] = NodeAffinitySchedulingStrategy(node_ids[i], soft=False)
            seg = p["segments"]
            self.actors.append(Actor.options(**opts).remote(self.map_dir, seg["start"], seg["end"], p["generation"], toml, None, threads, models, backend))
        # wait until every shard is open (and fail here if one cannot open)
        self.shard_info = ray.get([a.info.remote() for a in self.actors])

    def query(self, queries, setting="verified", fusion=None):
        """The ranked references of every query: a ``Matches`` equal to ``Map.query`` on the
        whole map with the same config."""
        import ray

        qref = ray.put(queries)
        parts = ray.get([a.candidates.remote(qref, setting) for a in self.actors])
        length = semlook.list_len(setting, self.config)
        scores, refs, counts = semlook.merge_candidates(parts, length)
        # every candidate, row by row: the order `rank` takes fine scores and ids in
        real = np.arange(refs.shape[1]) < counts[:, None]
        flat_q = np.nonzero(real)[0].astype(np.uint32)
        flat_r = refs[real]
        owner = np.searchsorted(self.starts, flat_r, side="right") - 1
        two_stages = semlook.reranks(setting)
        # per candidate: fine score, inliers (-1: none), compact HOGs' cosine, the inliers' tail
        # probability and the compact HOGs' likelihood ratio against the map's null (NaN: none),
        # the columns of Shard.fine
        fine = np.full((len(flat_r), 5), np.nan, dtype=np.float32)
        ids = [""] * len(flat_r)
        calls = []
        for s, actor in enumerate(self.actors):
            sel = np.nonzero(owner == s)[0]
            if len(sel) == 0:
                continue
            if two_stages:
                calls.append((sel, actor.fine.remote(qref, setting, flat_q[sel], flat_r[sel])))
            else:
                calls.append((sel, actor.reference_ids.remote(flat_r[sel])))
        for sel, ref in calls:
            got = ray.get(ref)
            if two_stages:
                fine[sel] = got[0]
                got = got[1]
            for i, name in zip(sel, got):
                ids[i] = name
        fusion = fusion or self.config.score_fusion
        return semlook.rank(setting, scores, refs, counts, fine if two_stages else None, queries.ids, ids, fusion, self.config)

    def info(self):
        """Per shard: its plan entry, its engine ("backend"), the calls it ran on a GPU and the
        Ray node it runs on ("node_id")."""
        import ray

        return ray.get([a.info.remote() for a in self.actors])

    def busy_seconds(self):
        """Per actor, seconds spent in engine calls since the last call of this method."""
        import ray

        return ray.get([a.take_busy_seconds.remote() for a in self.actors])

    def close(self):
        import ray

        for a in self.actors:
            ray.kill(a)
        self.actors = []

def main(argv=None):
    """``python -m semlook.distributed``: encode query frames in the driver, match them against
    a map sharded over Ray actors, print or write the JSON of ``Matches.to_list()``."""
    ap = argparse.ArgumentParser(prog="semlook-ray", description=main.__doc__)
    ap.add_argument("--address", default=None, help="Ray cluster address ('auto', host:port); default: start a local one")
    ap.add_argument("--map", required=True)
    ap.add_argument("--shards", type=int, required=True)
    ap.add_argument("--images", help="folder of query images")
    ap.add_argument("--labels", help="folder of query label maps (same file stems)")
    ap.add_argument("--setting", default="verified", choices=semlook.SETTINGS)
    ap.add_argument("-k", type=int, default=None)
    ap.add_argument("--cpus-per-shard", type=float, default=None)
    ap.add_argument("--backend", default=semlook.DEFAULT_BACKEND, choices=["cpu", "gpu", "auto"], help=f"each shard's engine (default: {semlook.DEFAULT_BACKEND}, as semlook's)")
    ap.add_argument("--gpus-per-shard", type=float, default=None, help="Ray GPUs per shard (default: 1 with --backend gpu)")
    ap.add_argument("--json", help="write the results here (default: stdout)")
    a = ap.parse_args(argv)
    import ray

    ray.init(address=a.address, include_dashboard=False, log_to_driver=False)
    folder = a.labels or a.images
    if folder is None:
        sys.exit("give --images and/or --labels")
    # each folder listed once: file stem -> path
    index = {d: {os.path.splitext(f)[0]: os.path.join(d, f) for f in os.listdir(d)} for d in (a.images, a.labels) if d}
    stems = sorted(index[folder])
    for d, files in index.items():
        if missing := [s for s in stems if s not in files]:
            sys.exit(f"{d}: no file for {missing[:5]} ({len(missing)} stems of {folder} missing)")
    images = [index[a.images][s] for s in stems] if a.images else None
    labels = [index[a.labels][s] for s in stems] if a.labels else None
    # the manifest and codebook suffice here: the segment files need only be on the shards' nodes
    queries = semlook.Encoder.for_map_dir(a.map).encode_files(stems, images=images, labels=labels)
    sm = ShardedMap(a.map, a.shards, k=a.k, cpus_per_shard=a.cpus_per_shard, backend=a.backend, gpus_per_shard=a.gpus_per_shard)
    text = json.dumps(sm.query(queries, a.setting).to_list(), indent=1)
    if a.json:
        with open(a.json, "w") as f:
            f.write(text)
    else:
        print(text)
    sm.close()


if __name__ == "__main__":
    main()
