"""Writes the VPR-Bench ground-truth fixtures of tests/datasets.rs (tests/data/vprbench_*.npy):
object arrays of [query_index, valid_reference_indices] rows as VPR-Bench's scripts save them, in
the variants NumPy produces (Python ints and lists; NumPy int64 scalars and np.where arrays; a
1-D array of row lists; pickle protocols 2 and 4). Run with NumPy >= 1.20:
    python3 scripts/make_vprbench_fixtures.py
All fixtures encode the same ground truth: query 0 -> refs {0, 1}, query 1 -> {1, 2}, query 2 -> {3}."""
import io, pathlib, pickle
import numpy as np

out = pathlib.Path(__file__).resolve().parent.parent / "tests" / "data"
gt = {0: [0, 1], 1: [1, 2], 2: [3]}

def save(name, arr, protocol):
    """np.save's layout (a version 1.0 header, then the pickled array) with a chosen protocol."""
    buf = io.BytesIO()
    np.lib.format.write_array_header_1_0(buf, np.lib.format.header_data_from_array_1_0(arr))
    pickle.dump(arr, buf, protocol=protocol)
    (out / name).write_bytes(buf.getvalue())

lists = np.array([[q, refs] for q, refs in gt.items()], dtype=object)
save("vprbench_lists.npy", lists, 4)
mask = np.zeros((3, 4), dtype=bool)
for q, refs in gt.items():
    mask[q, refs] = True
arrays = np.array([[np.int64(q), np.where(mask[q])[0]] for q in gt], dtype=object)
save("vprbench_arrays_p2.npy", arrays, 2)
rows = np.empty(3, dtype=object)
for q, refs in gt.items():
    rows[q] = [q, refs]
save("vprbench_rows.npy", rows, 4)
