import os, json, hashlib, shutil, numpy as np, semlook
OUT = os.environ.get("OUT", "shortlist-prototype-out")
R = os.environ.get("REAL_VPR", "../shared/data/real-vpr")
for name in ["gardenspoint-day-night-mini", "nordland-spring-winter", "landmarks-multiview-dev"]:
    d = f"{R}/{name}"
    qfiles = sorted(os.listdir(f"{d}/query")); rfiles = sorted(os.listdir(f"{d}/ref"))
    out = {}
    for side in (480, 800):
        mp = f"{OUT}/maps/{name}-{side}"
        shutil.rmtree(mp, ignore_errors=True)
        shutil.copytree(f"{OUT}/maps/{name}", mp)
        mf = json.load(open(f"{mp}/manifest.json"))
        mf["config"]["input"]["working_long_side"] = side
        mf["checksum"] = ""
        mf["checksum"] = hashlib.sha256(json.dumps(mf, separators=(',', ':'), ensure_ascii=False).encode()).hexdigest()
        open(f"{mp}/manifest.json", "w").write(json.dumps(mf, indent=2))
        m = semlook.Map.open(mp)
        enc = semlook.Encoder.for_map(m)
        qd = enc.encode_files([f"q{f}" for f in qfiles], images=[f"{d}/query/{f}" for f in qfiles])
        rd = enc.encode_files([f"r{f}" for f in rfiles], images=[f"{d}/ref/{f}" for f in rfiles])
        out[f"q{side}"] = np.asarray(qd.image_appearance, np.float32)
        out[f"r{side}"] = np.asarray(rd.image_appearance, np.float32)
        print(name, side, flush=True)
    np.savez(f"{OUT}/{name}-ms.npz", **out)
