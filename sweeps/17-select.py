#!/usr/bin/env python3
"""Sweep 17's choice (issue 51), from the table `semlook dev tune --table 17.tsv` writes.

Leave-one-set-out (LOSO): for each held-out set, the candidate chosen on the other sets scores the held-out
one. Two questions, in this order:
  1. which form of the inliers' evidence generalises: LOSO restricted to each form's grid;
  2. the weights within the chosen form: the best mean R@1 over the sets among the candidates that meet the
     issue's bars on the sets it is chosen on (each set at least `fused` and `hog` minus one query; the
     real sets' mean at least the default of before, grid row 0; Nordland 64x32 at least `hog`).
Usage: python3 sweeps/17-select.py 17.tsv
"""
import csv
import sys

QUERIES = {"nordland-spring-winter": 60, "gardenspoint-day-night-mini": 10, "landmarks-multiview-dev": 110,
           "ie-tower-dev": 294, "nordland-64x32": 60, "gardenspoint-day-night-mini-64x32": 10}
REAL = ["nordland-spring-winter", "gardenspoint-day-night-mini", "landmarks-multiview-dev", "ie-tower-dev"]

rows = list(csv.reader(open(sys.argv[1]), delimiter="\t"))
head, data = rows[0], rows[1:]
nvals = sum(1 for h in head if not h.count(":"))
SETS = [s for s in QUERIES if f"{s}:verified:R@1" in head]


def r1(i, s, setting="verified"):
    return float(data[i][head.index(f"{s}:{setting}:R@1")])


def auc(i, s):
    return float(data[i][head.index(f"{s}:verified:AUC")])


def meets_bars(i, sets):
    for s in sets:
        for base in ("fused", "hog"):
            if round((r1(i, s) - r1(i, s, base)) * QUERIES[s]) < -1:
                return False
    real = [s for s in sets if s in REAL]
    if sum(r1(i, s) for s in real) < sum(r1(0, s) for s in real) - 1e-9:
        return False
    return "nordland-64x32" not in sets or r1(i, "nordland-64x32") >= r1(i, "nordland-64x32", "hog")


def choose(sets, candidates, bars):
    pool = [i for i in candidates if not bars or meets_bars(i, sets)] or candidates
    return max(pool, key=lambda i: (round(sum(r1(i, s) for s in sets) / len(sets), 9), sum(auc(i, s) for s in sets), -i))


def loso(candidates, bars):
    held = {}
    for s in SETS:
        held[s] = choose([t for t in SETS if t != s], candidates, bars)
    return held


def values(i):
    return " ".join(f"{head[k].split('.')[-1]}={data[i][k]}" for k in range(nvals))


forms = sorted({data[i][head.index("verification.inliers")] for i in range(len(data))})
print("1. the form, LOSO restricted to each form's grid (held-out mean R@1 over the sets; over the real ones)")
for form in forms:
    cand = [i for i in range(len(data)) if data[i][head.index("verification.inliers")] == form]
    for bars in (False, True):
        held = loso(cand, bars)
        m = sum(r1(held[s], s) for s in SETS) / len(SETS)
        real = [s for s in SETS if s in REAL]
        held_real = {s: choose([t for t in real if t != s], cand, bars) for s in real}
        mr = sum(r1(held_real[s], s) for s in real) / len(real)
        print(f"  {form:8s} {'with the bars' if bars else 'best mean   '}: {m:.3f} over {len(SETS)} sets; {mr:.3f} LOSO over the real sets alone")
form = "unusual"
cand = [i for i in range(len(data)) if data[i][head.index("verification.inliers")] == form]
best = choose(SETS, cand, True)
held = loso(cand, True)
print(f"\n2. the default: row {best}: {values(best)}")
print("\n| set (queries) | `verified` in sample | `verified` held out (row chosen without the set) | `fused` | `appearance` | `hog` |")
print("|---|---|---|---|---|---|")
for s in SETS:
    print(f"| {s} ({QUERIES[s]}) | {r1(best, s):.3f} | {r1(held[s], s):.3f} (row {held[s]}) | {r1(0, s, 'fused'):.3f} | {r1(0, s, 'appearance'):.3f} | {r1(0, s, 'hog'):.3f} |")
m_in = sum(r1(best, s) for s in SETS) / len(SETS)
m_ho = sum(r1(held[s], s) for s in SETS) / len(SETS)
print(f"| mean | {m_in:.3f} | {m_ho:.3f} | " + " | ".join(f"{sum(r1(0, s, b) for s in SETS) / len(SETS):.3f}" for b in ("fused", "appearance", "hog")) + " |")
real = [s for s in SETS if s in REAL]
print(f"| mean of the real sets | {sum(r1(best, s) for s in real) / len(real):.3f} | {sum(r1(held[s], s) for s in real) / len(real):.3f} | "
      + " | ".join(f"{sum(r1(0, s, b) for s in real) / len(real):.3f}" for b in ("fused", "appearance", "hog")) + " |")
print(f"\nthe default of before (row 0: {values(0)}):", " ".join(f"{s} {r1(0, s):.3f}" for s in SETS),
      f"real mean {sum(r1(0, s) for s in real) / len(real):.3f}")
for i in sorted(set(held.values())):
    print(f"row {i}: {values(i)}")
