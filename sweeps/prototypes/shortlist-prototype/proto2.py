import os, numpy as np
exec(open(os.path.join(os.path.dirname(os.path.abspath(__file__)), "proto.py")).read().split("variants = ")[0])
V = {}
V["base"] = lambda ra, qa, ss: base(ra, qa, ss)
for dims in (32, 64, 128, None):
    for sh in (0.1, 1.0):
        for beta in (0.5, 1.0):
            for wg in (0.25, 0.5):
                def f(ra, qa, ss, dims=dims, sh=sh, beta=beta, wg=wg):
                    t = whiten(ra, dims, sh, 0.5)
                    return beta * (t(qa) @ t(ra).T) + (1 - beta) * (qa @ ra.T) + wg * ss
                V[f"w d{dims} sh{sh} b{beta} wg{wg}"] = f
res = []
for name, f in V.items():
    row = []
    for s in sets:
        d = D[s]
        row.append(recall(f(d["ra"], d["qa"], d["ssim"]), d["gt"]))
    res.append((name, row))
res.sort(key=lambda x: -(x[1][1][2] + x[1][2][2]))
for name, row in res[:25]:
    print(f"{name:28s} " + "  ".join("/".join(f"{x:.3f}" for x in r) for r in row))
