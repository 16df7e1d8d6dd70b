#!/usr/bin/env python3
"""A stream's answers against a rate copy's ground truth (scripts/rate/make-rate-copies.sh): the
single frame's R@1, the stream's answer's R@1, and the precision of the accepted answers, each wrong
accepted answer listed. The stream is `semlook localize --json` over the copy's query/ folder:

    semlook map build --images DATASET/ref --map MAP
    semlook localize --map MAP --images DATASET/query --json -q > OUT.jsonl
    python3 scripts/rate/stream-answers.py DATASET OUT.jsonl
"""
import json, csv, sys, collections
d = sys.argv[1]
truth = collections.defaultdict(set)
for r in csv.DictReader(open(f"{d}/ground_truth.csv")):
    truth[r["query"].split("/")[-1].rsplit(".",1)[0]].add(r["reference"].split("/")[-1].rsplit(".",1)[0])
rows = [json.loads(l) for l in open(sys.argv[2]) if l.startswith('{"frame"')]
acc = wrong = single = ans = 0
for r in rows:
    t = truth[r["id"]]
    a = r["answer"]; best = r["top_k"][0]["id"] if r["top_k"] else None
    single += best in t; ans += a["id"] in t
    if a["accepted"]:
        acc += 1
        if a["id"] not in t:
            wrong += 1
            s = r["sequence"]
            print(r["frame"], r["id"], "ans", a["id"], a["source"], "truth", sorted(t), "best", best, "end", s["end"]["position"], "v", s["velocity"], "u", round(s["uniqueness"],2), "n", s["frames"])
print(f"frames {len(rows)} single {single/len(rows):.3f} answer {ans/len(rows):.3f} accepted {acc} wrong {wrong} precision {(acc-wrong)/max(acc,1):.3f}")
