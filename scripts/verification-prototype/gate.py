"""Sweep 14b (issue 32): pair-local rules for where LighterGlue runs beside MNN, offline from run.sh's
output. For each candidate: T = the verified score less its MNN inlier term; the fusion ranks by
T + 2 ln(1 + MNN inliers) + 0.5 ln(1 + LighterGlue inliers) (sweep 14's best), the LighterGlue term only on
the pairs a rule admits. Prints R@1 per set, the mean and the share of pairs LighterGlue runs on.
Usage: OUT=... python3 scripts/verification-prototype/gate.py [lg | the suffix of another LighterGlue run]"""
import csv, json, math, os, sys
D=os.environ.get("REAL_VPR","../shared/data/real-vpr"); G=os.environ.get("OUT","/tmp/verification-prototype")+"/localize"
SETS=["gardenspoint-day-night-mini","nordland-spring-winter","landmarks-multiview-dev"]
LG=sys.argv[1] if len(sys.argv)>1 else "lg"
stem=lambda p: os.path.splitext(os.path.basename(p))[0]
def load(f):
    rows={}
    for line in open(f):
        d=json.loads(line)
        if "top_k" in d: rows[d["id"]]={t["id"]:(t["score"],t["inliers"]) for t in d["top_k"]}
    return rows
cands={}
for s in SETS:
    if not os.path.exists(f"{G}/{s}-{LG}.jsonl"): continue
    gt={}
    for row in csv.DictReader(open(f"{D}/{s}/ground_truth.csv")): gt.setdefault(stem(row["query"]),set()).add(stem(row["reference"]))
    m,g=load(f"{G}/{s}-mnn.jsonl"),load(f"{G}/{s}-{LG}.jsonl")
    rows=[]
    for q in m:
        c=[]
        for r,(sc,nm) in m[q].items():
            t=sc-math.log1p(nm); gs,ng=g[q][r]
            assert abs(gs-math.log1p(ng)-t)<1e-3,(s,q,r,gs,ng,t)
            c.append((r,t,nm,ng))
        rows.append((gt.get(q,set()),c))
    cands[s]=rows
def ev(gate,a=0.5,b=2.0):
    res=[];n=0;tot=0
    for s,rows in cands.items():
        ok=0
        for gt,c in rows:
            def sc(x):
                nonlocal n,tot
                return x[1]+b*math.log1p(x[2])+(a*math.log1p(x[3]) if gate(x) else 0)
            best=max(c,key=sc); ok+=best[0] in gt
            n+=sum(gate(x) for x in c); tot+=len(c)
        res.append(ok/len(rows))
    return res,n/tot
def show(name,gate,**k):
    r,f=ev(gate,**k); print(f"{name:40s} "+" ".join(f"{x:.3f}" for x in r)+f"  mean {sum(r)/len(r):.3f}  glued {f:.3f}")
show("mnn only (b=1)",lambda x:False,b=1.0)
show("mnn only (b=2)",lambda x:False)
show("all glued",lambda x:True)
for t in [2,3,4,5,6,8,10,12,15]:
    show(f"mnn>={t}",lambda x,t=t:x[2]>=t)
for th in [2.5,3,3.5,4,4.5,5,5.5,6,6.5,7]:
    show(f"pre>={th}",lambda x,th=th:x[1]+2*math.log1p(x[2])>=th)
for th in [-1,0,0.5,1,1.5,2,2.5,3]:
    show(f"T>={th}",lambda x,th=th:x[1]>=th)
# T distribution
import statistics
for s,rows in cands.items():
    ts=sorted(x[1] for gt,c in rows for x in c); print(s, "T quantiles", [round(ts[int(len(ts)*q)],2) for q in (0.1,0.5,0.9)])
