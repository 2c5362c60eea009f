import torch,cv2,os,time,statistics as st
from torchtrack.frontend import depth_in_colour, fill_cracks, refine_along_rays, sim_in_colour
from torchtrack.geometry import warp_depth
from torchtrack.image.shape_index import compute_sim
from types import SimpleNamespace as NS
torch.set_num_threads(1)
K=torch.tensor([[525,0,319.5],[0,525,239.5],[0,0,1.]])[None]; Kd=torch.tensor([[600,0,320],[0,600,240],[0,0,1.]])[None]
T=torch.eye(4)[None]; T[0,0,3]=-0.1
dd=torch.from_numpy(cv2.imread('/tmp/cases/boxcleanrig0/depth/1.000000.png',-1).astype('float32')/5000)[None,None]
fr=NS(depth=dd,K=K,K_depth=Kd,T_color_depth=T,rgb=torch.zeros(1,3,480,640))
w=warp_depth(dd,Kd,K,T,(480,640)); sd=compute_sim(dd,Kd)
def tm(f,name,n=30):
    f(); ts=[]
    for _ in range(n):
        t=time.perf_counter(); f(); ts.append((time.perf_counter()-t)*1000)
    print(f'{name}: median {st.median(ts):.2f} ms, min {min(ts):.2f} ms')
tm(lambda: warp_depth(dd,Kd,K,T,(480,640)),'warp_depth (existing)')
tm(lambda: compute_sim(w,K),'compute_sim (existing)')
tm(lambda: fill_cracks(w),'(b) fill_cracks')
tm(lambda: refine_along_rays(w,fr),'(c) refine_along_rays')
tm(lambda: sim_in_colour(sd,w,fr),'(a) sim_in_colour lookup')
print('object pixels with depth', (w>0).sum().item())
