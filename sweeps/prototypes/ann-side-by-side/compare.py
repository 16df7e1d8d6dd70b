import os, numpy as np, faiss, time, json, sys
faiss.omp_set_num_threads(2)
ra = np.load(os.path.join(os.environ["OUT"], "ra.npy"), mmap_mode="r"); qa = np.load(os.path.join(os.environ["OUT"], "qa.npy"))
T = np.load(os.path.join(os.environ["OUT"], "fused_exact.npy")); ours = np.load(os.path.join(os.environ["OUT"], "fused_ivf.npy"))
def rec(S): return float(np.mean([len(set(S[q]) & set(T[q])) / 30 for q in range(len(T))]))
print("ours (IVF 1024 lists over PCA-256, int8, probe 96, shortlist 1000, exact rescoring): recall@30", rec(ours))
t = time.time(); pca = faiss.PCAMatrix(4096, 256); sample = np.ascontiguousarray(ra[::4]); pca.train(sample); print("pca train", time.time() - t)
X = np.empty((len(ra), 256), np.float32)
for i in range(0, len(ra), 10000): X[i:i+10000] = pca.apply(np.ascontiguousarray(ra[i:i+10000]))
Q = pca.apply(qa)
faiss.normalize_L2(X); faiss.normalize_L2(Q)
rows = []
def bench(name, index, build_s, bytes_per_ref, params):
    for pname, setp, M in params:
        setp()
        ts = []
        S = np.zeros((len(Q), M), np.int64)
        for q in range(len(Q)):
            t = time.perf_counter(); _, I = index.search(Q[q:q+1], M); ts.append(time.perf_counter() - t); S[q] = I[0]
        r = dict(index=name, params=pname, shortlist=M, recall_at_30=round(rec(S), 4), p50_ms=round(1000 * float(np.median(ts)), 2), build_s=round(build_s, 1), bytes_per_ref=round(bytes_per_ref, 1))
        print(json.dumps(r), flush=True); rows.append(r)
# exact shortlist of the PCA-256 vectors (what any ANN over them can at best reach)
flat = faiss.IndexFlatIP(256); flat.add(X)
bench("flat-pca256", flat, 0, 1024, [("exact", lambda: None, M) for M in (300, 500, 1000)])
# IVF like ours (flat lists, f32) and with 8-bit scalar quantisation
for qtype in ("flat", "sq8"):
    quant = faiss.IndexFlatIP(256)
    ivf = faiss.IndexIVFFlat(quant, 256, 1024, faiss.METRIC_INNER_PRODUCT) if qtype == "flat" else faiss.IndexIVFScalarQuantizer(quant, 256, 1024, faiss.ScalarQuantizer.QT_8bit, faiss.METRIC_INNER_PRODUCT)
    t = time.time(); ivf.train(X); ivf.add(X); b = time.time() - t
    bpr = (256 * (4 if qtype == "flat" else 1) + 8)
    def setter(p): 
        def f(): ivf.nprobe = p
        return f
    bench(f"ivf1024-{qtype}", ivf, b, bpr, [(f"nprobe {p}", setter(p), M) for p, M in ((32, 300), (48, 500), (96, 1000))])
for m in (16, 32):
    h = faiss.IndexHNSWFlat(256, m, faiss.METRIC_INNER_PRODUCT); h.hnsw.efConstruction = 200
    t = time.time(); h.add(X); b = time.time() - t
    bpr = 256 * 4 + 2 * m * 4 * 1.05
    def setter(e):
        def f(): h.hnsw.efSearch = e
        return f
    bench(f"hnsw{m}-flat", h, b, bpr, [(f"efSearch {max(M, 64)}", setter(max(M, 64)), M) for M in (300, 500, 1000)])
json.dump(rows, open(os.path.join(os.environ["OUT"], "hnsw.json"), "w"), indent=1)
