import os, numpy as np
exec(open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "proto.py")).read().split("variants = ")[0])
M = {s: np.load(f"{OUT}/{s}-ms.npz") for s in sets}
def sanity():
    for s in sets:
        print(s, "ref self-consistency (cos r640 vs r800 diag mean)", float(np.mean(np.sum(D[s]["ra"] * M[s]["r800"], 1))))
sanity()
V = {}
combos = {"640": ["640"], "480": ["480"], "800": ["800"], "480+640": ["480", "640"], "640+800": ["640", "800"], "480+640+800": ["480", "640", "800"]}
def vec(s, side, kind):
    return D[s]["qa" if kind == "q" else "ra"] if side == "640" else M[s][f"{kind}{side}"]
for qn, qs in combos.items():
    for rn in ("640", qn):
        for wg in (0.25,):
            name = f"q {qn} r {rn}"
            row = []
            for s in sets:
                q = nrm(sum(vec(s, x, "q") for x in qs)); r = nrm(sum(vec(s, x, "r") for x in combos[rn]))
                row.append(recall(q @ r.T + wg * D[s]["ssim"], D[s]["gt"]))
            V[name] = row
for name, row in V.items():
    print(f"{name:28s} " + "  ".join("/".join(f"{x:.3f}" for x in r) for r in row) + f"   mean@1 {np.mean([r[0] for r in row]):.3f} mean@30 {np.mean([r[2] for r in row]):.3f}")
