import sys, os, numpy as np, cv2
sys.path.insert(0, 'python')
from muir import data as D, split

def gray(img):
    return ((img[..., 0].astype(np.int32) * 77 + img[..., 1].astype(np.int32) * 150 + img[..., 2].astype(np.int32) * 29) >> 8).astype(np.int32)

def census(g, r):
    h, w = g.shape
    p = np.pad(g, r, mode='edge')
    code = np.zeros((h, w), np.uint64)
    bit = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0: continue
            nb = p[r + dy:r + dy + h, r + dx:r + dx + w]
            code |= (nb < g).astype(np.uint64) << np.uint64(bit)
            bit += 1
    return code

def popcount64(x):
    x = x.copy()
    c = np.zeros(x.shape, np.int32)
    # byte LUT
    lut = np.array([bin(i).count('1') for i in range(256)], np.int32)
    for k in range(8):
        c += lut[((x >> np.uint64(8 * k)) & np.uint64(255)).astype(np.int64)]
    return c

def refine(L, R, d0, sigma, P):
    gl, gr = gray(L), gray(R)
    h, w = gl.shape
    cl, cr = census(gl, P['cr']), census(gr, P['cr'])
    dmax = int(np.ceil(np.nanmax(d0))) + P['rmax'] + 2
    base = np.floor(d0).astype(np.int32)
    rad = np.clip(np.ceil(P['k'] * sigma), P['rmin'], P['rmax']).astype(np.int32)
    offs = np.arange(-P['rmax'], P['rmax'] + 2)
    A = np.full((len(offs), h, w), 1e9, np.float32)
    # cost volume over absolute d needed: compute per absolute d plane, aggregate, scatter into band
    dlo = max(0, int(base.min()) - P['rmax']); dhi = int(base.max()) + P['rmax'] + 1
    win = P['win']
    for d in range(dlo, dhi + 1):
        crs = np.empty_like(cr); 
        if d > 0:
            crs[:, d:] = cr[:, :-d]; crs[:, :d] = cr[:, :1]
            grs = np.empty_like(gr); grs[:, d:] = gr[:, :-d]; grs[:, :d] = gr[:, :1]
        else:
            crs = cr; grs = gr
        c = popcount64(cl ^ crs).astype(np.float32) + P['lam'] * np.minimum(np.abs(gl - grs), P['tad']).astype(np.float32)
        if P.get('bilat'):
            agg = cv2.ximgproc.jointBilateralFilter(gl.astype(np.float32), c, win, P['bilat'], win) if False else None
        if P.get('bil'):
            r = win // 2
            cp = np.pad(c, r, mode='edge'); gp = np.pad(gl, r, mode='edge')
            num = np.zeros_like(c); den = np.zeros_like(c)
            for dy in range(-r, r + 1):
                for dx in range(-r, r + 1):
                    wt = (np.abs(gp[r+dy:r+dy+h, r+dx:r+dx+w] - gl) <= P['bil']).astype(np.float32) * (1 - P.get('bilmin', 0)) + P.get('bilmin', 0)
                    num += wt * cp[r+dy:r+dy+h, r+dx:r+dx+w]; den += wt
            agg = num / den
        else:
            agg = cv2.boxFilter(c, -1, (win, win), normalize=True, borderType=cv2.BORDER_REPLICATE)
        o = d - base  # offset of this d relative to each pixel's base
        for i, oo in enumerate(offs):
            sel = (o == oo)
            A[i][sel] = agg[sel]
    # restrict to band
    oi = offs[:, None, None]
    A = np.where((oi >= -rad[None]) & (oi <= rad[None] + 1), A, 1e9)
    i = np.argmin(A, axis=0)
    best = np.take_along_axis(A, i[None], 0)[0]
    ok = (i > 0) & (i < len(offs) - 1)
    im = np.clip(i - 1, 0, len(offs) - 1); ip = np.clip(i + 1, 0, len(offs) - 1)
    a0 = np.take_along_axis(A, im[None], 0)[0]; a2 = np.take_along_axis(A, ip[None], 0)[0]
    ok &= (a0 < 1e8) & (a2 < 1e8)
    curv = a0 + a2 - 2 * best
    sub = np.where(curv > 0, (a0 - a2) / (2 * np.maximum(curv, 1e-6)), 0)
    dref = base + offs[i] + sub
    ok &= curv >= P['curv']
    if P.get('occ'):
        # occluded by the network's own disparity: some pixel to the right lands at or left of x - d
        xs = np.arange(w)[None, :] - d0
        mn = np.minimum.accumulate(xs[:, ::-1], axis=1)[:, ::-1]
        nxt = np.concatenate([mn[:, 1:], np.full((h, 1), 1e9)], axis=1)
        occ = xs >= nxt - P['occ']
        ok &= ~occ
    out = np.where(ok, dref, d0)
    return out, ok

def metrics(pred, gt):
    v = np.isfinite(gt)
    e = np.abs(pred[v] - gt[v])
    return e.mean(), np.median(e), (e > 2).mean() * 100

P = dict(cr=3, win=9, lam=0.0, tad=20, k=2.0, rmin=2, rmax=8, curv=2.0)
for kv in sys.argv[2:]:
    k, v = kv.split('='); P[k] = type(P.get(k, 1.0))(float(v)) if k in P else float(v)
cache = sys.argv[1]
rows = []
keys = list(split.HELDOUT_HEADLINE) if os.environ.get('SET','heldout')=='heldout' else [f'{d}/{s}' for d,s in split.train_scenes() if not d.endswith('_half')]
for key in keys:
    ds, s = key.split('/')
    if ds == 'kitti2015' and 'nokitti' in P: continue
    sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
    z = np.load(os.path.join(cache, key.replace('/', '__') + '.npz'))
    d0, sigma = z['disp'], np.exp(z['u'] / 2)
    r, ok = refine(sc.left, sc.right, d0, sigma, P)
    m0, m1 = metrics(d0, sc.disp), metrics(r, sc.disp)
    rows.append((m0, m1))
    if os.environ.get('QUIET'): continue
    print(f"{key:28s} net EPE {m0[0]:.2f} A50 {m0[1]:.2f} bad2 {m0[2]:5.1f} | ref EPE {m1[0]:.2f} A50 {m1[1]:.2f} bad2 {m1[2]:5.1f} | refined {ok.mean()*100:.0f}%", flush=True)
a = np.array([[x for x in r0 + r1] for r0, r1 in rows])
print(f"{'mean':28s} net EPE {a[:,0].mean():.2f} A50 {a[:,1].mean():.2f} bad2 {a[:,2].mean():5.1f} | ref EPE {a[:,3].mean():.2f} A50 {a[:,4].mean():.2f} bad2 {a[:,5].mean():5.1f}  {P}")
