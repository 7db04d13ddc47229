import sys, numpy as np, torch
import os
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../python"))
from muir import data as D
from muir.evaluate import run_model
from muir.checkpoint import load_model
torch.set_num_threads(2)
model = load_model(sys.argv[1]).eval()
E_all=[];G=[];GX=[]
for ds, s in D.list_scenes(D.DEFAULT_ROOT, D.HEADLINE):
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    d = run_model(model, sc.left, sc.right)["disp"]
    v = np.isfinite(sc.disp) & (sc.nonocc if sc.nonocc is not None else True)
    E_all.append((d-sc.disp)[v]); G.append(sc.disp[v])
    gx = np.abs(np.gradient(np.nan_to_num(sc.left.mean(2)), axis=1)); GX.append(gx[v])
e=np.concatenate(E_all); g=np.concatenate(G); gx=np.concatenate(GX)
for lo,hi in [(0,10),(10,20),(20,30),(30,40),(40,50),(50,60),(60,70),(70,90)]:
    m=(g>=lo)&(g<hi)
    if m.sum()==0: continue
    print(f"gt {lo:3d}-{hi:3d}: n {m.mean()*100:5.1f}%  signed med {np.median(e[m]):+.3f}  A50 {np.median(np.abs(e[m])):.3f}  bad2 {(np.abs(e[m])>2).mean()*100:5.1f}  bad1 {(np.abs(e[m])>1).mean()*100:5.1f}")
q=np.quantile(gx,[0.25,0.5,0.75])
for lo,hi in [(0,q[0]),(q[0],q[1]),(q[1],q[2]),(q[2],1e9)]:
    m=(gx>=lo)&(gx<hi)
    print(f"grad {lo:6.2f}-{hi:6.2f}: signed med {np.median(e[m]):+.3f} A50 {np.median(np.abs(e[m])):.3f} bad2 {(np.abs(e[m])>2).mean()*100:5.1f}")
