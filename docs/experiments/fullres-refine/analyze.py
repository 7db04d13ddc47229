import sys, os, numpy as np
sys.path.insert(0, 'python')
from muir import data as D, split, fullres
tot = np.zeros(6); n=0
for key in split.HELDOUT_HEADLINE:
    ds, s = key.split('/')
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    z = np.load(os.path.join(sys.argv[1], key.replace('/', '__') + '.npz'))
    r, ok = fullres.refine(sc.left, sc.right, z['disp'], z['u'])
    v = np.isfinite(sc.disp); gt = sc.disp
    rad = fullres.band_radius(fullres.quantize_u(z['u']))
    e0 = np.abs(z['disp'] - gt); e1 = np.abs(r - gt)
    bad = v & (e1 > 2)
    occ = (~sc.nonocc) if sc.nonocc is not None else np.zeros_like(v)
    outside = bad & (e0 > rad)           # network off by more than the band
    declined = bad & ~ok & ~outside      # inside the band, stage declined
    wrong = bad & ok & ~outside          # inside the band, stage chose wrong
    row = np.array([bad.sum(), (bad & occ).sum(), outside.sum(), declined.sum(), wrong.sum(), v.sum()])
    tot += row / v.sum()
    n += 1
    print(f"{key:28s} bad2 {100*bad.sum()/v.sum():5.1f}%  occluded {100*(bad&occ).sum()/v.sum():4.1f}  outside band {100*outside.sum()/v.sum():4.1f}  declined {100*declined.sum()/v.sum():4.1f}  wrong {100*wrong.sum()/v.sum():4.1f}")
t = 100*tot/n
print(f"mean bad2 {t[0]:.1f} occluded {t[1]:.1f} outside {t[2]:.1f} declined {t[3]:.1f} wrong {t[4]:.1f}")
