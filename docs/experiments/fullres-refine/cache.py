import sys, os, numpy as np, torch
sys.path.insert(0, 'python')
torch.set_num_threads(1)
from muir.checkpoint import load_model
from muir.evaluate import run_model
from muir import data as D, split
model_path, out = sys.argv[1], sys.argv[2]
os.makedirs(out, exist_ok=True)
m = load_model(model_path).eval()
keys = sys.argv[3].split(',') if len(sys.argv) > 3 else list(split.HELDOUT_HEADLINE)
for k in keys:
    ds, s = k.split('/')
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    o = run_model(m, sc.left, sc.right)
    np.savez_compressed(os.path.join(out, k.replace('/', '__') + '.npz'), disp=o['disp'], u=o['u'])
    print(k, flush=True)
