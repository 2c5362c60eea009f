import sys, statistics as st
def load(label):
    d={}
    for ln in open(f'/tmp/rigbench/{label}/summary.txt'):
        p=ln.split()
        if len(p)==2: d[p[0]]=float(p[1])
    return d
base=load('base')
for label in sys.argv[1:]:
    d={**base, **{k:v for k,v in load(label).items()}} if label!='base' else base
    # rig from label, registered from base (registered path unchanged) unless label has it
    print(f'== {label}')
    ratios=[]
    for j in ['', '_j1','_j2','_j3']:
        reg=[d.get(f'boxclean{s}{j}') for s in range(3)]; rig=[d.get(f'boxcleanrig{s}{j}') for s in range(3)]
        if None in reg or None in rig: print(j,'missing'); continue
        r=sum(rig)/sum(reg); ratios.append(r)
        print(f"{j or 'plain':6s} reg {' '.join(f'{x:.3f}' for x in reg)} sum {sum(reg):.3f} | rig {' '.join(f'{x:.3f}' for x in rig)} sum {sum(rig):.3f} | ratio {r:.3f}")
    if ratios:
        REG=sum(d[f'boxclean{s}{j}'] for s in range(3) for j in ['','_j1','_j2','_j3']); RIG=sum(d[f'boxcleanrig{s}{j}'] for s in range(3) for j in ['','_j1','_j2','_j3'])
        print(f'ratios {[round(r,3) for r in ratios]} median {st.median(ratios):.3f}  pooled 12-run ratio {RIG/REG:.3f} (rig sum {RIG:.3f}, reg sum {REG:.3f})')
        for s in range(3):
            rr=[d[f'boxcleanrig{s}{j}'] for j in ['','_j1','_j2','_j3']]; rg=[d[f'boxclean{s}{j}'] for j in ['','_j1','_j2','_j3']]
            print(f'  seed{s}: rig median {st.median(rr):.3f} [{min(rr):.3f}-{max(rr):.3f}]  reg median {st.median(rg):.3f} [{min(rg):.3f}-{max(rg):.3f}]')
    k=[d.get(f'boxkinectrig{s}') for s in range(3)]
    if None not in k:
        kr=[d[f'boxkinect{s}'] for s in range(3)]
        print(f"kinect rig {' '.join(f'{x:.3f}' for x in k)} sum {sum(k):.3f} vs reg {sum(kr):.3f}: {sum(k)/sum(kr):.3f}x")
