"""Sweep 21's prototype (issue 60): the verified score's evidence rescored offline from candidate dumps.

`semlook dev tune --candidates DIR --null-evidence ...` writes, per dataset, the candidates' features (`*--row0.tsv`),
the map's null pairs (`.null.tsv`), its same-place pairs 1-2 positions apart (`.near.tsv`) and each candidate's
evidence from an unrelated image (`.unrelated.tsv`). This scores them as `src/matching/evidence.rs` does
(`sig`: w x decades of significance beyond `alarms`, NFA = K x p under the null's tail as `src/matching/null.rs`
fits it, at most `cap`, nothing below `min` inliers) and with a likelihood ratio against the same-place pairs
(`lr`, `both`; not kept), and prints per set R@1 / the share of queries whose order stays the coarse one when the
evidence comes from the unrelated image. With the sweep's default row it reproduces the tool's R@1.
Usage: python3 evidence.py DIR [DIR ...]
"""
import csv, math, sys, glob, os, bisect
from collections import defaultdict

def read(path):
    with open(path) as f:
        return list(csv.DictReader(f, delimiter='\t'))

class Tail:
    """src/matching/null.rs Tail: empirical survival, exponential above the top tenth."""
    def __init__(self, xs):
        self.s = sorted(xs); n = len(self.s)
        self.ok = n >= 20  # MIN_NULL_PAIRS? checked below
        if n == 0: self.ok = False; return
        m = min(max(math.ceil(n * 0.1), 10), n)
        self.t = self.s[n - m]
        self.scale = max(sum(x - self.t for x in self.s[n - m:]) / m, 0.05)
        self.at = self.emp(self.t)
    def emp(self, v):
        at_least = len(self.s) - bisect.bisect_left(self.s, v)
        return (1 + at_least) / (len(self.s) + 1)
    def p(self, v):
        if not self.ok: return 1.0
        return self.emp(v) if v <= self.t else self.at * math.exp(-(v - self.t) / self.scale)

def emp_surv(sorted_xs, v):
    at_least = len(sorted_xs) - bisect.bisect_left(sorted_xs, v)
    return (1 + at_least) / (len(sorted_xs) + 1)

def load(prefix):
    c = read(prefix + '.tsv')
    null = read(prefix + '.null.tsv')
    near = read(prefix + '.near.tsv')
    unrel = read(prefix + '.unrelated.tsv') if os.path.exists(prefix + '.unrelated.tsv') else None
    qs = defaultdict(list)
    for r in c:
        qs[int(r['query'])].append(r)
    for q in qs: qs[q].sort(key=lambda r: int(r['rank']))
    ur = None
    if unrel:
        ur = defaultdict(dict)
        for r in unrel: ur[int(r['query'])][int(r['rank'])] = r
    return qs, null, near, ur

def l1p(x): return math.log1p(x)

def score_set(qs, null, near, ur, form, P, use_unrelated=False):
    t0 = Tail([l1p(int(r['inliers'])) for r in null])
    hog0 = [float(r['compact_hog']) for r in null if r['compact_hog'] not in ('NaN', 'nan')]
    th = Tail(hog0) if hog0 else None
    nd = P.get('near', 2)
    near = [r for r in near if abs(int(r['source']) - int(r['reference'])) <= nd]
    s1 = sorted(l1p(int(r['inliers'])) for r in near)
    hog1 = sorted(float(r['compact_hog']) for r in near if r['compact_hog'] not in ('NaN', 'nan'))
    right = kept = 0
    for q, cands in qs.items():
        K = len(cands)
        scored = []
        for r in cands:
            rank = int(r['rank'])
            if use_unrelated:
                u = ur[q][rank]; inl = int(u['inliers']); ch = u['compact_hog']
            else:
                inl = int(r['inliers']); ch = r['compact_hog']
            ch = None if ch in ('NaN', 'nan') else float(ch)
            x = l1p(inl)
            p_i = t0.p(x)
            p_h = th.p(ch) if (th and ch is not None) else None
            bonus = 0.0
            dec = lambda p: max(0.0, math.log10(P['alarms'] / (K * max(p, 1e-300))))
            if form in ('sig', 'both'):
                # the floor gates the inliers' term alone, as src/matching/evidence.rs does
                b = P['w'] * dec(p_i) if inl >= P.get('min', 0) else 0.0
                if p_h is not None and P.get('w_hog', 2.0) > 0: b += P.get('w_hog', 2.0) * dec(p_h)
                bonus += b
            if form in ('lr', 'both') and len(s1) >= 20 and inl >= P.get('min', 0):
                lr = math.log10(emp_surv(s1, x) / max(p_i, 1e-300))
                bonus += P['w_lr'] * max(0.0, lr - math.log10(P['lam']))
                if P.get('lr_hog') and p_h is not None and len(hog1) >= 20:
                    lrh = math.log10(emp_surv(hog1, ch) / max(p_h, 1e-300))
                    bonus += P['w_lr'] * max(0.0, lrh - math.log10(P['lam']))
            bonus = min(bonus, P['cap'])
            s = 2.0 * float(r['coarse']) + bonus
            scored.append((s, rank, r))
        order = sorted(scored, key=lambda t: (-t[0], t[1]))
        if order[0][2]['correct'] == '1': right += 1
        if [t[1] for t in order] == sorted(t[1] for t in order): kept += 1
    n = len(qs)
    return right / n, kept / n, n


def main():
    import itertools
    sets = []
    for d in sys.argv[1:]:
        for pre in sorted(glob.glob(d + '/*--row0.tsv')):
            prefix = pre[:-4]
            sets.append((os.path.basename(prefix).split('--')[0], load(prefix)))
    print('form\tmin,alarms,w,cap,w_lr\t' + '\t'.join(n for n, _ in sets) + '\tmean\tleast kept')
    grid = itertools.product(['sig', 'both'], [0, 6, 8, 10, 12], [0.01, 1, 3, 10, 30], [1, 2, 4], [2, 4, 8], [0.5, 1, 2])
    for form, mn, alarms, w, cap, w_lr in grid:
        if form == 'sig' and w_lr != 0.5:
            continue
        P = dict(alarms=alarms, w=w, cap=cap, w_hog=2, min=mn, w_lr=w_lr, lam=3, near=1)
        r1 = [score_set(*s, form, P)[0] for _, s in sets]
        kept = [score_set(*s, form, P, True)[1] if s[3] else 1.0 for _, s in sets]
        lr = w_lr if form == 'both' else '-'
        print(f"{form}\t{mn},{alarms},{w},{cap},{lr}\t" + '\t'.join(f"{a:.3f}/{k:.2f}" for a, k in zip(r1, kept))
              + f"\t{sum(r1) / len(r1):.3f}\t{min(kept):.3f}")


if __name__ == '__main__':
    main()
