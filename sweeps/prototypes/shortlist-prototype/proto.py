import os, numpy as np, sys
OUT = os.environ.get("OUT", "shortlist-prototype-out")
W = 0.25
sets = ["gardenspoint-day-night-mini", "nordland-spring-winter", "landmarks-multiview-dev"]
D = {s: np.load(f"{OUT}/{s}.npz") for s in sets}
def nrm(x): return x / np.maximum(np.linalg.norm(x, axis=-1, keepdims=True), 1e-12)
def recall(score, gt, ks=(1, 10, 30, 100)):
    order = np.argsort(-score, axis=1, kind="stable")
    hit = np.take_along_axis(gt, order, axis=1)
    return [hit[:, :k].any(1).mean() for k in ks]
def base(ra, qa, ssim): return qa @ ra.T + W * ssim
def qe(ra, qa, ssim, n=3, alpha=3.0, fused_first=True):
    s = base(ra, qa, ssim) if fused_first else qa @ ra.T
    top = np.argsort(-s, 1)[:, :n]
    c = np.take_along_axis(qa @ ra.T, top, 1)
    w = np.maximum(c, 0) ** alpha
    q2 = nrm(qa + (w[..., None] * ra[top]).sum(1))
    return q2 @ ra.T + W * ssim
def dba(ra, n=2, alpha=3.0):
    c = ra @ ra.T
    top = np.argsort(-c, 1)[:, :n+1]  # self included
    w = np.maximum(np.take_along_axis(c, top, 1), 0) ** alpha
    return nrm((w[..., None] * ra[top]).sum(1))
def whiten(ra, dims=None, shrink=0.0, power=0.5):
    mu = ra.mean(0)
    X = ra - mu
    U, S, Vt = np.linalg.svd(X, full_matrices=False)
    lam = S**2 / len(ra)
    k = dims or len(S) - 1
    P = Vt[:k] / ((lam[:k] + shrink * lam[:k].mean()) ** power)[:, None]
    return lambda x: nrm((x - mu) @ P.T)
variants = {"base": lambda ra, qa, ss: base(ra, qa, ss)}
for n in (1, 2, 3, 5):
    for a in (0, 1, 3):
        variants[f"qe n{n} a{a}"] = (lambda n, a: lambda ra, qa, ss: qe(ra, qa, ss, n, a))(n, a)
for n in (1, 2, 3):
    for a in (0, 3):
        variants[f"dba n{n} a{a}"] = (lambda n, a: lambda ra, qa, ss: base(dba(ra, n, a), qa, ss))(n, a)
        variants[f"dba+qe n{n} a{a}"] = (lambda n, a: lambda ra, qa, ss: qe(dba(ra, n, a), qa, ss, n, a))(n, a)
for sh in (0.1, 1.0, 10.0):
    for pw in (0.25, 0.5):
        def f(ra, qa, ss, sh=sh, pw=pw):
            t = whiten(ra, None, sh, pw)
            return t(qa) @ t(ra).T + W * ss
        variants[f"whiten sh{sh} p{pw}"] = f
print(f"{'variant':22s} " + " ".join(f"{s[:10]:>24s}" for s in sets) + "   mean R@1/R@30")
for name, f in variants.items():
    row = []; m1 = []; m30 = []
    for s in sets:
        d = D[s]
        r = recall(f(d["ra"], d["qa"], d["ssim"]), d["gt"])
        row.append("/".join(f"{x:.3f}" for x in r)); m1.append(r[0]); m30.append(r[2])
    print(f"{name:22s} " + " ".join(f"{x:>24s}" for x in row) + f"   {np.mean(m1):.3f}/{np.mean(m30):.3f}")
