# prototype data: per dev set, reference + query appearance vectors, SSIM (global) matrix, ground truth
import sys, os, csv, numpy as np, semlook
R = os.environ.get("REAL_VPR", "../shared/data/real-vpr")
out = os.environ.get("OUT", "shortlist-prototype-out")
os.makedirs(f"{out}/maps", exist_ok=True)
for name in ["gardenspoint-day-night-mini", "nordland-spring-winter", "landmarks-multiview-dev"]:
    d = f"{R}/{name}"
    mp = f"{out}/maps/{name}"
    if not os.path.exists(mp):
        m = semlook.Map.build(mp, images=f"{d}/ref")
    else:
        m = semlook.Map.open(mp)
    ids = m.ids
    enc = semlook.Encoder.for_map(m)
    qfiles = sorted(os.listdir(f"{d}/query"))
    qd = enc.encode_files([f"query/{f}" for f in qfiles], images=[f"{d}/query/{f}" for f in qfiles])
    ra = []
    for s in range(m.n_segments):
        v = m.segment_view(s, "image_appearance")
        for row in m.live_rows(s):
            ra.append(np.asarray(v[row], np.float32).reshape(-1))
    ra = np.stack(ra); qa = np.asarray(qd.image_appearance, np.float32)
    mt = m.query(qd, "global", k=len(ids))
    refs = np.asarray(mt.references); sc = np.asarray(mt.scores)
    ssim = np.full((len(qfiles), len(ids)), np.nan, np.float32)
    for q in range(len(qfiles)):
        ssim[q, refs[q]] = sc[q]
    gt = np.zeros((len(qfiles), len(ids)), bool)
    idx = {i: j for j, i in enumerate(ids)}
    print(ids[:3])
    qi = {f"query/{f}": j for j, f in enumerate(qfiles)}
    for row in csv.DictReader(open(f"{d}/ground_truth.csv")):
        r = row["reference"]
        key = r if r in idx else os.path.basename(r) if os.path.basename(r) in idx else os.path.splitext(os.path.basename(r))[0]
        gt[qi[row["query"]], idx[key]] = True
    print(name, ra.shape, qa.shape, np.isnan(ssim).sum(), gt.sum(1).min())
    np.savez(f"{out}/{name}.npz", ra=ra, qa=qa, ssim=ssim, gt=gt)
