#!/usr/bin/env python3
"""A stream's answers against a rate copy's ground truth (scripts/rate/make-rate-copies.sh): the
single frame's R@1, the stream's answer's R@1, and the precision of the accepted answers, each wrong
accepted answer listed. The stream is `semlook localize --json` over the copy's query/ folder:

    semlook map build --images DATASET/ref --map MAP
    semlook localize --map MAP --images DATASET/query --json -q > OUT.jsonl
    python3 scripts/rate/stream-answers.py DATASET OUT.jsonl
"""
import collections
import csv
import json
import sys

if len(sys.argv) != 3:
    sys.exit(__doc__)
d = sys.argv[1]
truth = collections.defaultdict(set)
for r in csv.DictReader(open(f"{d}/ground_truth.csv")):
    truth[r["query"].split("/")[-1].rsplit(".", 1)[0]].add(r["reference"].split("/")[-1].rsplit(".", 1)[0])
rows = []
for line in open(sys.argv[2]):
    if line.startswith("{"):
        r = json.loads(line)
        # answered frames only: the summary and refused frames (`refused`, `kind`) are left out
        if "frame" in r and "refused" not in r:
            rows.append(r)
if not rows:
    sys.exit(f"no answered frames in {sys.argv[2]}")
acc = wrong = single = ans = 0
for r in rows:
    t = truth[r["id"]]
    a = r["answer"]  # None: no match (counted wrong, not accepted)
    best = r["top_k"][0]["id"] if r["top_k"] else None
    single += best in t
    ans += a is not None and a["id"] in t
    if a is not None and a["accepted"]:
        acc += 1
        if a["id"] not in t:
            wrong += 1
            s = r["sequence"] or {}
            print(r["frame"], r["id"], "answer", a["id"], a["source"], "truth", sorted(t), "best", best,
                  "end", (s.get("end") or {}).get("position"), "velocity", s.get("velocity"), "frames", s.get("frames"))
print(f"frames {len(rows)} single {single / len(rows):.3f} answer {ans / len(rows):.3f} accepted {acc} wrong {wrong} "
      f"precision {(acc - wrong) / max(acc, 1):.3f}")
