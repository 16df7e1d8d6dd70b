"""Throughput of matching against a synthetic 100k-reference map, in one process and sharded over
1, 2 and 4 Ray actors on this machine, with a check that every run gives identical top-K lists.

    .venv/bin/python python/benchmarks/shard_throughput.py --refs 100000 --queries 100 --out DIR

The map: a pool of 64 synthetic places (label maps, no appearance), reference i a copy of place
(i * 7919) % 64 with a tiny deterministic offset on its global descriptor (so scores are distinct,
except where --jitter 0 makes every top-K a block of ties), 2048 images per segment.
Prints a Markdown table; the JSON rows go to OUT/shard_throughput.json.
"""

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import semlook  # noqa: E402
from conftest import place  # noqa: E402

POOL = 64


def build_map(path, n, jitter, per_segment=2048):
    enc = semlook.Encoder(semlook.Config.without_appearance())
    pool = semlook.Descriptors.concat([enc.encode(f"p{s}", labels=place(s)) for s in range(POOL)])
    m = None
    for start in range(0, n, per_segment):
        idx = [(i * 7919) % POOL for i in range(start, min(n, start + per_segment))]
        a = {k: (np.array(v) if isinstance(v, np.ndarray) else v) for k, v in pool.take(idx).to_arrays().items()}
        a["ids"] = [f"r{i:07d}" for i in range(start, start + len(idx))]
        if jitter:
            i = np.arange(start, start + len(idx), dtype=np.uint64)[:, None]
            j = np.arange(a["globals"].shape[1], dtype=np.uint64)[None, :]
            h = ((i * np.uint64(2654435761) + j * np.uint64(40503)) % np.uint64(1000)).astype(np.float32) / 1000.0
            a["globals"] = np.clip(a["globals"] + jitter * (h - 0.5), 0.0, 1.0).astype(np.float32)
        d = semlook.Descriptors.from_arrays(a)
        if m is None:
            m = semlook.Map.create(path, d, enc, segment_images=per_segment)
        else:
            m.add(d, segment_images=per_segment)
    return m, enc


def timed(fn, reps):
    fn()  # warm-up: first-use checks of every segment, page cache
    times = []
    for _ in range(reps):
        t = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t)
    return float(np.median(times)), out


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--refs", type=int, default=100_000)
    ap.add_argument("--queries", type=int, default=100)
    ap.add_argument("--setting", default="semlook")
    ap.add_argument("--jitter", type=float, default=1e-3)
    ap.add_argument("--reps", type=int, default=2)
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"map-{a.refs}"
    t = time.perf_counter()
    if path.exists():
        m = semlook.Map.open(str(path))
        enc = semlook.Encoder(semlook.Config.without_appearance())
    else:
        m, enc = build_map(str(path), a.refs, a.jitter)
    build_s = time.perf_counter() - t
    queries = semlook.Descriptors.concat([enc.encode(f"q{i}", labels=place(i % POOL, shift=3)) for i in range(a.queries)])
    qbytes = sum(v.nbytes for v in queries.to_arrays().values() if isinstance(v, np.ndarray))
    comparisons = a.refs * a.queries
    rows = []

    def row(kind, actors, cpus, threads, s, matches, busy=None):
        r = {"run": kind, "actors": actors, "cpus_per_actor": cpus, "threads_per_actor": threads, "queries": a.queries, "refs": a.refs,
             "s_per_batch": round(s, 3), "comparisons_per_s": round(comparisons / s), "identical": matches.equals(reference),
             "query_bytes_per_node": qbytes, "ray_overhead_s": None if busy is None else round(s - max(busy) / (a.reps + 1), 3),
             "loadavg_1m": os.getloadavg()[0]}
        rows.append(r)
        print(json.dumps(r), flush=True)

    s, reference = timed(lambda: m.query(queries, a.setting, threads=2), a.reps)
    row("single process", 1, 2, 2, s, reference)
    import ray

    os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
    ray.init(num_cpus=2, include_dashboard=False, log_to_driver=False, configure_logging=False)
    from semlook.distributed import ShardedMap

    for actors, cpus, threads in [(1, 2, 2), (2, 1, 1), (4, 0.5, 1)]:
        sm = ShardedMap(str(path), actors, config=semlook.Config.for_map(m), cpus_per_shard=cpus, threads_per_shard=threads)
        sm.busy_seconds()
        s, res = timed(lambda: sm.query(queries, a.setting), a.reps)
        row("ray", actors, cpus, threads, s, res, sm.busy_seconds())
        sm.close()
    ray.shutdown()
    (out / "shard_throughput.json").write_text(json.dumps({"build_s": build_s, "segments": m.n_segments, "rows": rows}, indent=1))
    base = rows[0]["s_per_batch"]
    print(f"\n{a.refs} references ({m.n_segments} segments), {a.queries} queries, setting {a.setting}; map built in {build_s:.0f} s\n")
    print("| run | actors | CPUs / threads per actor | s per batch | comparisons/s | vs single process | Ray overhead s | identical top-K |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['run']} | {r['actors']} | {r['cpus_per_actor']} / {r['threads_per_actor']} | {r['s_per_batch']:.2f} | {r['comparisons_per_s']:,} | {base / r['s_per_batch']:.2f}x | {r['ray_overhead_s'] if r['ray_overhead_s'] is not None else '-'} | {r['identical']} |")


if __name__ == "__main__":
    main()
