import os, pickle, semlook
m = semlook.Map.open(os.environ["MAP"])
enc = semlook.Encoder.for_map(m)
fs = sorted(os.listdir(os.environ["QUERIES"]))
qd = enc.encode_files(fs, images=[os.path.join(os.environ["QUERIES"], f) for f in fs])
pickle.dump(qd, open(os.path.join(os.environ["OUT"], "q.pkl"), "wb"))
