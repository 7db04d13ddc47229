import sys, numpy as np, torch, time
import os
sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../python"))
from muir import data as D
from muir.evaluate import run_model
from muir.checkpoint import load_model
import torch.nn.functional as F
torch.set_num_threads(2)
model = load_model(sys.argv[1]).eval()
iters_list = [int(x) for x in sys.argv[2].split(",")]
scale = float(sys.argv[3]) if len(sys.argv) > 3 else 1.0
scenes = D.list_scenes(D.DEFAULT_ROOT, D.HEADLINE)
import cv2
res = {it: [] for it in iters_list}
for ds, s in scenes:
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    L, R = sc.left, sc.right
    if scale != 1.0:
        h, w = L.shape[:2]
        L = cv2.resize(L, (int(round(w*scale)), int(round(h*scale))), interpolation=cv2.INTER_CUBIC)
        R = cv2.resize(R, (int(round(w*scale)), int(round(h*scale))), interpolation=cv2.INTER_CUBIC)
    for it in iters_list:
        o = run_model(model, L, R, it)
        d = o["disp"]
        if scale != 1.0:
            d = cv2.resize(d, (sc.disp.shape[1], sc.disp.shape[0]), interpolation=cv2.INTER_LINEAR) / scale
        v = sc.valid() if callable(getattr(sc, "valid", None)) else np.isfinite(sc.disp)
        noc = v & (sc.nonocc if sc.nonocc is not None else v)
        e = d - sc.disp
        res[it].append((np.abs(e[v]).mean(), (np.abs(e[v]) > 2).mean()*100, np.median(e[noc]), np.median(np.abs(e[noc])), (np.abs(e[noc])>2).mean()*100))
for it in iters_list:
    a = np.array(res[it])
    print(f"iters {it} scale {scale}: EPE {a[:,0].mean():.3f} Bad2 {a[:,1].mean():.2f} noc signed median {a[:,2].mean():+.3f} (per-scene range {a[:,2].min():+.2f}..{a[:,2].max():+.2f}) noc A50 {a[:,3].mean():.3f} noc Bad2 {a[:,4].mean():.2f}")
