import sys, cv2, torch, numpy as np
from torchtrack.geometry import warp_depth
from torchtrack.image.shape_index import compute_sim
from torchtrack.frontend import smooth_depth_mask
torch.set_num_threads(1)
K=torch.tensor([[525,0,319.5],[0,525,239.5],[0,0,1.]])[None]; Kd=torch.tensor([[600,0,320],[0,600,240],[0,0,1.]])[None]
T=torch.eye(4)[None]; T[0,0,3]=-0.1
def rd(p): return torch.from_numpy(cv2.imread(p,cv2.IMREAD_UNCHANGED).astype('float32')/5000.)[None,None]
s=int(sys.argv[1]) if len(sys.argv)>1 else 0
fill = sys.argv[2] if len(sys.argv)>2 else None
import importlib
tot={}
for f in range(0,60,6):
    ts=f'{f/30:.6f}'
    dt=rd(f'/tmp/cases/boxclean{s}/depth/{ts}.png'); dd=rd(f'/tmp/cases/boxcleanrig{s}/depth/{ts}.png')
    w=warp_depth(dd,Kd,K,T,(480,640))
    if fill:
        mod=importlib.import_module('fillmod'); w=mod.fill(w)
    obj=dt>0
    hole=(w==0)&obj; extra=(w>0)&~obj
    err=(w-dt)[(w>0)&obj]
    far=((w-dt)>0.01)&obj&(w>0); near=((dt-w)>0.01)&obj&(w>0)
    st=compute_sim(dt,K); sw=compute_sim(w,K)
    vm=st.valid&obj
    d=dict(obj=obj.sum().item(), hole=hole.sum().item(), extra=extra.sum().item(), far=far.sum().item(), near=near.sum().item(),
           rmse_mm=(err.pow(2).mean().sqrt()*1000).item(),
           simvalid_true=st.valid.sum().item(), simvalid_warp=sw.valid.sum().item(), simvalid_both=(st.valid&sw.valid).sum().item(),
           si_diff_both=((st.si-sw.si).abs()[st.valid&sw.valid]).mean().item(),
           img_diff=((st.image-sw.image).abs()).mean().item()*255,
           sel_true=smooth_depth_mask(dt,0.03).sum().item(), sel_warp=smooth_depth_mask(w,0.03).sum().item(), sel_both=(smooth_depth_mask(dt,0.03)&smooth_depth_mask(w,0.03)).sum().item())
    for k,v in d.items(): tot[k]=tot.get(k,0)+v/10
print(' '.join(f'{k}={v:.3f}' if isinstance(v,float) and v<100 else f'{k}={v:.0f}' for k,v in tot.items()))
