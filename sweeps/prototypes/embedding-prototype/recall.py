# Prototype (sweep 16): coarse R@1/10/30/100 of the fused coarse score (cos(appearance) + 0.25 SSIM, from
# sweeps/prototypes/shortlist-prototype/dump.py's OUT/<set>.npz) plus w x cos(pooled network features of TAG.npz), per dev set.
import os, sys, numpy as np
OUT = os.environ.get('OUT', 'embedding-prototype-out')
tag = sys.argv[1]
C = np.load(f'{OUT}/{tag}.npz')
sets = ['gardenspoint-day-night-mini', 'nordland-spring-winter', 'landmarks-multiview-dev']
def rec(S, gt, ks=(1, 10, 30, 100)):
    order = np.argsort(-S, 1)
    return [np.mean([gt[q, order[q, :k]].any() for q in range(len(S))]) for k in ks]
def l2(x): return x / np.linalg.norm(x, axis=1, keepdims=True)
rows = {}
for s in sets:
    D = np.load(f'{OUT}/{s}.npz')
    ra, qa, ssim, gt = D['ra'], D['qa'], D['ssim'], D['gt']
    base = qa @ ra.T + 0.25 * ssim
    rows.setdefault('base', []).append(rec(base, gt))
    for pool in ["gem", "avg", "max"]:
        r, q = C[f'{s}/ref/{pool}'], C[f'{s}/query/{pool}']
        # centre on the map's mean? plain and centred variants
        for cen in [0, 1]:
            rr, qq = (r - r.mean(0), q - r.mean(0)) if cen else (r, q)
            c = l2(qq) @ l2(rr).T
            rows.setdefault(f'{pool}{"-c" if cen else ""} alone', []).append(rec(c, gt))
            for w in [0.25, 0.5, 1.0, 2.0, 3.0, 4.0]:
                rows.setdefault(f'{pool}{"-c" if cen else ""} +{w}', []).append(rec(base + w * c, gt))
for k, v in rows.items():
    v = np.array(v)
    print(f'{k:14s}', ' | '.join(' '.join(f'{x:.3f}' for x in r) for r in v), '| mean R1 %.3f R30 %.3f' % (v[:, 0].mean(), v[:, 2].mean()))
