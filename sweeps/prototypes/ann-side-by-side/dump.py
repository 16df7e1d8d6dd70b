import os, pickle, numpy as np, semlook, time
m = semlook.Map.open(os.environ["MAP"])
qd = pickle.load(open(os.path.join(os.environ["OUT"], "q.pkl"), "rb"))
ra = np.empty((len(m), m.manifest()["appearance_dim"]), np.float32)
i = 0
for s in range(m.n_segments):
    v = m.segment_view(s, "image_appearance")
    for row in m.live_rows(s):
        ra[i] = np.asarray(v[row], np.float32).reshape(-1); i += 1
assert i == len(m)
np.save(os.path.join(os.environ["OUT"], "ra.npy"), ra)
np.save(os.path.join(os.environ["OUT"], "qa.npy"), np.asarray(qd.image_appearance, np.float32))
eng = semlook.Engine("cpu")
exact = semlook.Config('[index]\nsearch = "exact"\n')
approx = semlook.Config('[index]\nsearch = "approximate"\nprobe = 96\nshortlist = 1000\n')
t = time.time()
f = m.query(qd, "fused", k=30, config=exact, engine=eng)
np.save(os.path.join(os.environ["OUT"], "fused_exact.npy"), np.asarray(f.references))
np.save(os.path.join(os.environ["OUT"], "fused_exact_scores.npy"), np.asarray(f.scores))
a = m.query(qd, "fused", k=30, config=approx, engine=eng)
np.save(os.path.join(os.environ["OUT"], "fused_ivf.npy"), np.asarray(a.references))
print("done", time.time() - t)
