"""How well cheap summaries of two global descriptors stand in for their SSIM (issue 29: the index's
thumbnails). Run with the repository's .venv (the semlook package and numpy):

    MAP=BASE QUERIES=QUERY_PHOTOS .venv/bin/python sweeps/prototypes/thumbnail-proxy/proxy.py

MAP: a labelled map with appearance (`semlook map build --images ... --index none`); QUERIES: a folder of
photos, encoded for it. Prints, per proxy, the correlation of proxy and exact SSIM over every (query,
reference) pair (r) and the mean within-query rank correlation. The exact SSIM is the product's `global`
setting (checked against this script's own SSIM, which the thumbnail variants reuse).
"""
import os
import numpy as np
import semlook
from numpy.lib.stride_tricks import sliding_window_view as sw

m = semlook.Map.open(os.environ["MAP"])
enc = semlook.Encoder.for_map(m)
files = sorted(os.listdir(os.environ["QUERIES"]))
qd = enc.encode_files(files, images=[os.path.join(os.environ["QUERIES"], f) for f in files])
cfg = semlook.Config.for_map(m)
h, w = 48, 64
rg = []
for s in range(m.n_segments):
    v = m.segment_view(s, "globals")
    rg += [np.asarray(v[r], np.float64).reshape(h, w) for r in m.live_rows(s)]
rg, qg = np.array(rg), np.asarray(qd.globals, np.float64).reshape(-1, h, w)
f = m.query(qd, "global", k=len(m), config=semlook.Config('[index]\nsearch = "exact"\n'))
G = np.zeros((len(qg), len(rg)))
for q in range(len(qg)):
    G[q, np.asarray(f.references)[q]] = np.asarray(f.scores)[q]


def ssim(X, Y, win, k1=0.01, k2=0.03):
    """Mean SSIM of every X against every Y: uniform window, sample covariance (the product's defaults)."""
    c1, c2, n = k1 * k1, k2 * k2, win * win
    norm = n / (n - 1)

    def stats(Z):
        z = sw(Z, (win, win), axis=(1, 2))
        mu = z.mean((-1, -2))
        return z, mu, ((z * z).mean((-1, -2)) - mu * mu) * norm

    wx, mx, vx = stats(X)
    wy, my, vy = stats(Y)
    out = np.zeros((len(X), len(Y)))
    for i in range(len(X)):
        cxy = (np.einsum("abij,nabij->nab", wx[i], wy) / n - mx[i][None] * my) * norm
        t = ((2 * mx[i][None] * my + c1) * (2 * cxy + c2)) / ((mx[i][None] ** 2 + my**2 + c1) * (vx[i][None] + vy + c2))
        out[i] = t.mean((1, 2))
    return out


def pool(Z, p):
    n, hh, ww = Z.shape
    return Z.reshape(n, hh // p, p, ww // p, p).mean((2, 4))


def quant(Z):
    return np.round(np.clip(Z, 0, 1) * 255) / 255


def blockz(Z, b, eps=1e-2):
    n, hh, ww = Z.shape
    B = Z.reshape(n, hh // b, b, ww // b, b).transpose(0, 1, 3, 2, 4).reshape(n, -1, b * b)
    B = B - B.mean(2, keepdims=True)
    B = B / np.sqrt((B * B).sum(2, keepdims=True) + eps * b * b)
    return B.reshape(n, -1) / np.sqrt((hh // b) * (ww // b))


def unit(Z, centre):
    Z = Z.reshape(len(Z), -1)
    Z = Z - Z.mean(1, keepdims=True) if centre else Z
    return Z / np.maximum(np.linalg.norm(Z, axis=1, keepdims=True), 1e-9)


print("own SSIM against the product's: max difference %.1e" % np.abs(ssim(qg, rg, 7) - G).max())
proxies = {
    "SSIM of 8-bit thumbnails pooled by 2, 3x3": ssim(quant(pool(qg, 2)), quant(pool(rg, 2)), 3),
    "SSIM of thumbnails pooled by 2, 5x5": ssim(pool(qg, 2), pool(rg, 2), 5),
    "SSIM of thumbnails pooled by 4, 3x3": ssim(pool(qg, 4), pool(rg, 4), 3),
    "inner product, z-scored 4x4 blocks": blockz(qg, 4) @ blockz(rg, 4).T,
    "Pearson correlation": unit(qg, True) @ unit(rg, True).T,
    "cosine": unit(qg, False) @ unit(rg, False).T,
}
rank = lambda v: np.argsort(np.argsort(v))
for name, P in proxies.items():
    r = np.corrcoef(P.ravel(), G.ravel())[0, 1]
    within = np.mean([np.corrcoef(rank(P[q]), rank(G[q]))[0, 1] for q in range(len(G))])
    print(f"{name:45s} r = {r:.3f}   rank correlation within a query = {within:.3f}")
