import sys, numpy as np, torch
import os
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../python"))
from muir import synth
from muir.evaluate import run_model
from muir.checkpoint import load_model
torch.set_num_threads(1)
model = load_model(sys.argv[1]).eval()
E_=[]
for i in range(40):
    s = synth.sample(999, i, 256, 320, with_right_disp=True, raw=(sys.argv[2]=="raw"))
    d = run_model(model, s["left"], s["right"])["disp"]
    gl, gr = s["disp"], s["disp_right"]
    h, w = gl.shape
    xs = np.arange(w)[None].repeat(h,0); xr = np.rint(xs-gl).astype(int); ok=(xr>=0)
    rows=np.arange(h)[:,None].repeat(w,1)
    noc = ok.copy(); noc[ok] = np.abs(gl[ok]-gr[rows[ok],xr[ok]])<=1
    e = np.abs(d-gl)
    E_.append((np.median(e[noc]), (e[noc]>2).mean()*100, e.mean()))
a=np.array(E_); print(f"synthetic {sys.argv[2]}: noc A50 {a[:,0].mean():.3f} noc Bad2 {a[:,1].mean():.1f} EPE {a[:,2].mean():.2f}")
