import os, sys, json, numpy as np
sys.path.insert(0, '/work/main/python')
from PIL import Image
from muir import fullres as F
keys = ["middlebury2001__tsukuba", "middlebury2003__teddy", "middlebury2005__Art", "middlebury2006__Aloe", "eth3d_twoview__playground"]
def pfm(p):
    with open(p, 'rb') as f:
        assert f.readline().strip() == b'Pf'
        w, h = map(int, f.readline().split()); s = float(f.readline())
        a = np.frombuffer(f.read(), dtype='<f4' if s < 0 else '>f4').reshape(h, w)
    return np.flipud(a).astype(np.float32)
def run(variant):
    for k, v in variant.items(): setattr(F, k, v)
    res = {}
    for eng in ('fixed', 'wide'):
        sd = sw = n = 0; nd = nw = 0
        for key in keys:
            l = np.asarray(Image.open(f'{key}/left.png')); r = np.asarray(Image.open(f'{key}/right.png'))
            df, ef = pfm(f'{key}/float_d.pfm'), pfm(f'{key}/float_u.pfm')
            dq, eq = pfm(f'{key}/{eng}_d.pfm'), pfm(f'{key}/{eng}_u.pfm')
            uf = 2 * np.log(ef); uq = 2 * np.log(eq)
            rf, _ = F.refine(l, r, df, uf)
            oq, _ = F.refine_q(l, r, F.quantize_disp(dq), F.quantize_u(uq))
            rq = oq / 32.0
            e = np.abs(rf - rq); sd += e.sum(); sw += (e <= 1).sum(); n += e.size
            e0 = np.abs(df - dq); nd += e0.sum(); nw += (e0 <= 1).sum()
        res[eng] = (round(sd / n, 4), round(100 * sw / n, 2), round(nd / n, 4), round(100 * nw / n, 2))
    return res
if __name__ == '__main__':
    print(run(json.loads(sys.argv[1]) if len(sys.argv) > 1 else {}))
