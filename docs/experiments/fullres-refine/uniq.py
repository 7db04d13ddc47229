import sys, os, numpy as np
sys.path.insert(0, 'python')
from muir import data as D, split, fullres
fullres.UNIQUENESS = int(sys.argv[2])
keys = [f'{d}/{s}' for d,s in split.train_scenes() if not d.endswith('_half')]
rows=[]
for key in keys:
    ds, s = key.split('/')
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    z = np.load(os.path.join(sys.argv[1], key.replace('/', '__') + '.npz'))
    r, ok = fullres.refine(sc.left, sc.right, z['disp'], z['u'])
    v=np.isfinite(sc.disp); e1=np.abs(r[v]-sc.disp[v])
    rows.append((e1.mean(), np.median(e1), (e1>2).mean()*100, ok.mean()*100))
a=np.array(rows).mean(0); print(sys.argv[2], " ".join(f"{x:.3f}" for x in a), flush=True)
