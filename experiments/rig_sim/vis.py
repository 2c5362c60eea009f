import sys, cv2, torch
from torchtrack.geometry import warp_depth, backproject_depth, project
torch.set_num_threads(1)
K=torch.tensor([[525,0,319.5],[0,525,239.5],[0,0,1.]])[None]; Kd=torch.tensor([[600,0,320],[0,600,240],[0,0,1.]])[None]
T=torch.eye(4)[None]; T[0,0,3]=-0.1
def rd(p): return torch.from_numpy(cv2.imread(p,cv2.IMREAD_UNCHANGED).astype('float32')/5000.)[None,None]
s=int(sys.argv[1]); tot=[0,0,0,0]
for f in range(0,60,6):
    ts=f'{f/30:.6f}'
    dt=rd(f'/tmp/cases/boxclean{s}/depth/{ts}.png'); dd=rd(f'/tmp/cases/boxcleanrig{s}/depth/{ts}.png')
    w=warp_depth(dd,Kd,K,T,(480,640))
    P=backproject_depth(K,dt).reshape(1,-1,3); P=P - T[:,None,:3,3]  # colour->depth: x + 0.1
    uv=project(Kd,P).round().long()
    u=uv[...,0].clamp(0,639); v=uv[...,1].clamp(0,479)
    zd=dd.reshape(-1)[(v*640+u)[0]]
    vis=((zd-P[0,:,2]).abs()<0.01*P[0,:,2]).reshape(1,1,480,640)&(dt>0)
    hole=(w==0)&(dt>0)
    tot[0]+=hole.sum().item(); tot[1]+=(hole&vis).sum().item(); tot[2]+=((dt>0)&~vis).sum().item()
    # isolated cracks: holes with >=5 valid 8-neighbours
    nb=torch.nn.functional.conv2d((w>0).float(),torch.ones(1,1,3,3),padding=1)
    tot[3]+=(hole&(nb>=5)).sum().item()
print(f'seed{s}: holes {tot[0]/10:.0f}/frame, of which visible from depth cam {tot[1]/10:.0f}; invisible obj px {tot[2]/10:.0f}; holes with >=5 valid nbrs {tot[3]/10:.0f}')
