"""Sweep 22's prototype (issue 60): the compact HOGs' evidence rescored offline from candidate dumps.

`semlook dev tune --candidates DIR --null-evidence ...` on the dev sets and their 160x120 and 64x32 copies
(compact HOGs) writes per set the candidates (`*--row0.tsv`), the map's null pairs (`.null.tsv`), the same
sources' neighbours one position away (`.near.tsv`) and the candidates' evidence from an unrelated image
(`.unrelated.tsv`). The inliers are scored as sweep 21's default (floor 15, alarms 1000, w 4, cap 32); the
compact HOGs either as a significance test against the look-alikes, gated by the map's same-place separation
(`gate`: AUC of near against null at least tau), or as the likelihood ratio the product kept (`lr`:
w x max(0, log10(P(near >= c) / P(null >= c)) - log10(lam)), optionally only where the test against the
look-alikes is significant at `ah` alarms). Printed per set: queries gained against the default and the share
of queries that keep the coarse order on the unrelated image.
Usage: python3 ratio.py DIR [DIR ...]
"""
import sys, itertools, glob, os, math, bisect
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), '..', 'evidence-floor'))
import evidence as E
sets=[]
for d in sys.argv[1:]:
    for pre in sorted(glob.glob(d+'/*--row0.tsv')):
        p=pre[:-4]; sets.append((os.path.basename(p).split('--')[0], E.load(p)))
def nan(x): return x in('NaN','nan')
def score(qs,null,near,ur,P,unrel=False):
    t0=E.Tail([E.l1p(int(r['inliers'])) for r in null])
    h=[float(r['compact_hog']) for r in null if not nan(r['compact_hog'])]
    th=E.Tail(h) if h else None
    nh=sorted(float(r['compact_hog']) for r in near if not nan(r['compact_hog']) and abs(int(r['source'])-int(r['reference']))<=P.get('d',1))
    auc=None
    if nh and h:
        hs=sorted(h); auc=sum(bisect.bisect_left(hs,a)+0.5*(bisect.bisect_right(hs,a)-bisect.bisect_left(hs,a)) for a in nh)/len(nh)/len(hs)
    right=kept=0
    for q,c in qs.items():
        K=len(c); sc=[]
        for r in c:
            rk=int(r['rank'])
            if unrel: u=ur[q][rk]; inl=int(u['inliers']); ch=u['compact_hog']
            else: inl=int(r['inliers']); ch=r['compact_hog']
            ch=None if nan(ch) else float(ch)
            dec=lambda p,a: max(0.0, math.log10(a/(K*max(p,1e-300))))
            b=4*dec(t0.p(E.l1p(inl)),1000) if inl>=15 else 0.0
            if ch is not None and th and len(nh)>=20:
                ph=th.p(ch)
                if P['form']=='gate':
                    if auc>=P['tau']: b+=P['wh']*dec(ph,P['ah'])
                else:
                    # both samples' survival with the same tail model (src/matching/null.rs)
                    lr=math.log10(E.Tail(nh).p(ch)/ph)
                    if dec(ph,P['ah'])>0: b+=P['wh']*max(0,lr-math.log10(P['lam']))
            b=min(b,32)
            sc.append((2*float(r['coarse'])+b,rk,r))
        o=sorted(sc,key=lambda t:(-t[0],t[1]))
        right+=o[0][2]['correct']=='1'
        kept+=[t[1] for t in o]==sorted(t[1] for t in o)
    return right/len(qs), kept/len(qs), len(qs)
names=[n for n,_ in sets]
base=[score(*s,dict(form='gate',tau=2,wh=0,ah=1))[0] for n,s in sets]
print('P\t'+'\t'.join(n.replace('nordland-spring-winter','nord').replace('gardenspoint-day-night-mini','gp').replace('landmarks-multiview-dev','lm').replace('ie-tower-dev','ie') for n in names))
grid=[dict(form='gate',tau=0.75,wh=wh,ah=ah) for wh in [2,4,8] for ah in [0.1,1,3,10]]
grid+=[dict(form='lr',lam=lam,wh=wh,ah=ah) for lam in [1,3,10,30] for wh in [1,2,4,8] for ah in [1,30,1e6]]
for P in grid:
    res=[];worst=1
    for (n,s),b in zip(sets,base):
        r,_,nq=score(*s,P); k=score(*s,P,True)[1] if s[3] else 1
        worst=min(worst,k)
        res.append(f'{round((r-b)*nq):+d}/{k:.2f}')
    print(' '.join(f'{k}={v}' for k,v in P.items())+'\t'+'\t'.join(res))
