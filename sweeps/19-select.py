#!/usr/bin/env python3
"""Sweep 19's choice (issue 60), from the table `semlook dev tune --null-evidence --table 19.tsv` writes.

Sixteen sets: the four real dev sets at full size and their 320x240, 160x120 and 64x32 copies
(scripts/lowres/make-dev-copies.sh). Leave-one-set-out (LOSO): for each held-out set, the row chosen on the
other fifteen scores it. A row is eligible where it is silent on unrelated images: on every set it is chosen
on, at least 99 % of the queries keep `fused`'s order when their candidates are verified against an unrelated
image (column `verified~null`). Among the eligible rows of a grid, the one with the best mean R@1 over the sets
(ties: mean AUC, then the earlier row). Printed: per set, `verified` held out (the row chosen without it), in
sample (the row chosen on all sixteen), `fused`, `appearance`, `hog`, the null-evidence share, and whether the
held-out `verified` is at least `fused` and `hog` minus one query; then the rule of issue 60 part 3.
Sweep 21 adds a second eligibility rule (--never-below-fused): a row is eligible only where it also gives
at least `fused`'s R@1 on every set it is chosen on, so that part 3's rule (never below the coarse stage) is part
of the choice rather than only its check.
Usage: python3 sweeps/19-select.py 19.tsv
       python3 sweeps/19-select.py --never-below-fused 21.tsv
"""
import csv
import sys

SIZE = {"": 0}
QUERIES = {"nordland-spring-winter": 60, "gardenspoint-day-night-mini": 10, "landmarks-multiview-dev": 110, "ie-tower-dev": 294}
REAL = list(QUERIES)

args = sys.argv[1:]
NEVER_BELOW_FUSED = "--never-below-fused" in args
rows = list(csv.reader(open([a for a in args if not a.startswith("--")][0]), delimiter="\t"))
head, data = rows[0], rows[1:]
SETS = sorted({h.split(":")[0] for h in head if h.count(":") == 2 and not h.startswith("mean:")}, key=lambda s: head.index(f"{s}:verified:R@1"))


def queries(s):
    return next(n for base, n in QUERIES.items() if s.startswith(base))


def col(i, s, setting, what="R@1"):
    return float(data[i][head.index(f"{s}:{setting}:{what}")])


def form(i):
    return data[i][head.index("verification.inliers")]


def silent(i, sets):
    quiet = all(col(i, s, "verified~null") >= 0.99 for s in sets)
    return quiet and (not NEVER_BELOW_FUSED or all(round((col(i, s, "verified") - col(i, s, "fused")) * queries(s)) >= 0 for s in sets))


def best(rows_, sets):
    def key(i):
        return (round(sum(col(i, s, "verified") for s in sets) / len(sets), 9), round(sum(col(i, s, "verified", "AUC") for s in sets) / len(sets), 9), -i)
    return max(rows_, key=key) if rows_ else None


def loso(candidates):
    out = {}
    for s in SETS:
        others = [o for o in SETS if o != s]
        out[s] = best([i for i in candidates if silent(i, others)], others)
    return out


def describe(i):
    vals = [f"{h.split('.')[-1]}={data[i][k]}" for k, h in enumerate(head) if ":" not in h]
    return f"row {i} ({', '.join(vals)})"


for name, rows_ in [("significant", [i for i in range(len(data)) if form(i) == "significant"]), ("any form", list(range(len(data))))]:
    picks = loso(rows_)
    whole = best([i for i in rows_ if silent(i, SETS)], SETS)
    rule = " and never below fused" if NEVER_BELOW_FUSED else ""
    print(f"\n== LOSO over the rows of {name} that are silent on unrelated images (>= 99 % on the sets chosen on){rule}")
    print("set\tverified held out\t(row)\tin sample\tfused\tappearance\thog\tnull share (held-out row)\tvs fused (queries)\tvs hog (queries)")
    fails = []
    for s in SETS:
        i = picks[s]
        if i is None:
            print(f"{s}\tno eligible row")
            fails.append(s)
            continue
        n = queries(s)
        held, fused, hog = col(i, s, "verified"), col(i, s, "fused"), col(i, s, "hog")
        dq, dh = round((held - fused) * n), round((held - hog) * n)
        ins = col(whole, s, "verified") if whole is not None else float("nan")
        print(f"{s}\t{held:.3f}\t{i}\t{ins:.3f}\t{fused:.3f}\t{col(i, s, 'appearance'):.3f}\t{hog:.3f}\t{col(i, s, 'verified~null'):.3f}\t{dq:+d}\t{dh:+d}")
        if dq < -1 or dh < -1:
            fails.append(s)
    real = [s for s in SETS if s in REAL]
    if whole is not None:
        print(f"in sample: {describe(whole)}; real sets' mean {sum(col(whole, s, 'verified') for s in real) / len(real):.3f}")
        print(f"row 0 (the default of before): real sets' mean {sum(col(0, s, 'verified') for s in real) / len(real):.3f}; "
              f"null share min {min(col(0, s, 'verified~null') for s in SETS):.3f}")
    print("held-out verified at least fused and hog minus one query on every set:", "yes" if not fails else f"no ({', '.join(fails)})")
