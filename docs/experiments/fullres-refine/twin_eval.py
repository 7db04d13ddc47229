import sys, os, numpy as np, time
sys.path.insert(0, 'python')
from muir import data as D, split, fullres as F
SET = os.environ.get('SET', 'train')
keys = list(split.HELDOUT_HEADLINE) if SET == 'heldout' else [f'{d}/{s}' for d, s in split.train_scenes() if not d.endswith('_half')]
rows = []
for key in keys:
    ds, s = key.split('/')
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    z = np.load(os.path.join(sys.argv[1], key.replace('/', '__') + '.npz'))
    v = np.isfinite(sc.disp)
    t = time.time()
    r, ok = F.refine(sc.left, sc.right, z['disp'], z['u'])
    e = np.abs(r[v] - sc.disp[v]); res = [e.mean(), np.median(e), (e > 2).mean() * 100]
    rows.append(res); print(key, np.round(res, 3), '%.1fs' % (time.time() - t), flush=True)
print('mean', np.round(np.mean(rows, 0), 3))
