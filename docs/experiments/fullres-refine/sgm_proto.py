"""Prototype: semi-global aggregation inside the network's band (float, full volume)."""
import sys, os, json, numpy as np
sys.path.insert(0, 'python')
from muir import data as D, split, fullres as F

INF = np.float32(1e6)

def box(c, r):
    if r == 0: return c
    k = 2*r+1
    p = np.pad(c, ((0,0),(r,r),(r,r)), mode='edge')
    s = np.zeros((p.shape[0], p.shape[1]+1, p.shape[2]+1), np.float32)
    s[:,1:,1:] = p.cumsum(1).cumsum(2)
    h, w = c.shape[1:]
    return s[:,k:k+h,k:k+w]-s[:,:h,k:k+w]-s[:,k:k+h,:w]+s[:,:h,:w]

def path(C, axis, rev, P1, P2, G=None, t=0):
    # C: (D, H, W) float32 with INF outside band
    Cm = np.moveaxis(C, axis, 0)  # (N, D, M)
    if rev: Cm = Cm[::-1]
    L = np.empty_like(Cm)
    L[0] = Cm[0]
    if G is not None:
        Gm = np.moveaxis(G, axis-1, 0)
        if rev: Gm = Gm[::-1]
    for i in range(1, Cm.shape[0]):
        prev = L[i-1]
        p2 = P2 if G is None or not t else np.maximum(P1 + 1, P2 * t / (t + np.abs(Gm[i] - Gm[i-1])))[None]
        m = prev.min(0, keepdims=True)
        up = np.concatenate([prev[1:], np.full_like(prev[:1], INF)], 0)
        dn = np.concatenate([np.full_like(prev[:1], INF), prev[:-1]], 0)
        best = np.minimum(np.minimum(prev, np.minimum(up, dn) + P1), m + p2)
        L[i] = np.minimum(Cm[i] + best - m, INF)
    if rev: L = L[::-1]
    return np.moveaxis(L, 0, axis)

def diag(C, dy, dx, P1, P2, G=None, t=0):
    Dn, H, W = C.shape
    L = np.empty_like(C)
    ys = range(H) if dy > 0 else range(H-1, -1, -1)
    first = True
    for y in ys:
        if first:
            L[:, y] = C[:, y]; first = False; continue
        prev = L[:, y-dy]
        # shift along x: pixel x takes prev at x-dx
        W_ = prev.shape[1]
        idx = np.clip(np.arange(W_) - dx, 0, W_ - 1)
        prev = prev[:, idx]
        m = prev.min(0, keepdims=True)
        up = np.concatenate([prev[1:], np.full_like(prev[:1], INF)], 0)
        dn = np.concatenate([np.full_like(prev[:1], INF), prev[:-1]], 0)
        if G is not None and t:
            gp = G[y-dy][np.clip(np.arange(G.shape[1]) - dx, 0, G.shape[1] - 1)]
            p2 = np.maximum(P1 + 1, P2 * t / (t + np.abs(G[y] - gp)))[None]
        else: p2 = P2
        best = np.minimum(np.minimum(prev, np.minimum(up, dn) + P1), m + p2)
        L[:, y] = np.minimum(C[:, y] + best - m, INF)
    return L

def refine(left, right, disp, u, P):
    gl, gr = F.grey(left), F.grey(right)
    cl, cr = F.census(gl), F.census(gr)
    h, w = disp.shape
    dq = F.quantize_disp(disp); base = dq >> 5
    rad = F.band_radius(F.quantize_u(u)) if P.get('band', 1) else np.full((h,w), 3)
    rad = np.minimum(rad + P.get('extra', 0), P.get('rmax', 99))
    lo = np.maximum(base - rad, 0); hi = base + rad + 1
    d0, d1 = int(lo.min()), int(hi.max())
    Dn = d1 - d0 + 1
    xs = np.arange(w)
    C = np.empty((Dn, h, w), np.float32)
    for k in range(Dn):
        d = d0 + k
        src = np.maximum(xs - d, 0)
        C[k] = F.popcount(cl ^ cr[:, src])
    C0 = C
    C = box(C0, P.get('win', 1))
    Csub = box(C0, P['subwin']) if 'subwin' in P else C
    dd = (np.arange(Dn) + d0)[:, None, None]
    inband = (dd >= lo[None]) & (dd <= hi[None])
    C = np.where(inband, C, INF).astype(np.float32)
    P1, P2 = P['P1'], P['P2']
    S = np.zeros_like(C)
    dirs = P.get('dirs', 4)
    G = gl.astype(np.float32); t = P.get('t', 0)
    S += path(C, 2, False, P1, P2, G, t)
    S += path(C, 2, True, P1, P2, G, t)
    S += path(C, 1, False, P1, P2, G, t)
    if dirs in (4, 8): S += path(C, 1, True, P1, P2, G, t)
    if dirs in (5, 8) and dirs != 7:
        S += diag(C, 1, 1, P1, P2, G, t); S += diag(C, 1, -1, P1, P2, G, t)
    if dirs == 8:
        S += diag(C, -1, 1, P1, P2, G, t); S += diag(C, -1, -1, P1, P2, G, t)
    if dirs == 7:
        S += diag(C, 1, 1, P1, P2, G, t); S += diag(C, 1, -1, P1, P2, G, t)
        S += diag(C, 1, 2, P1, P2, G, t); S += diag(C, 1, -2, P1, P2, G, t)
    S = np.where(inband, S, np.float32(1e9))
    i = S.argmin(0)
    a1 = np.take_along_axis(S, i[None], 0)[0]
    a0 = np.take_along_axis(S, np.clip(i-1, 0, Dn-1)[None], 0)[0]
    a2 = np.take_along_axis(S, np.clip(i+1, 0, Dn-1)[None], 0)[0]
    ok = (i > 0) & (i < Dn-1) & (a0 < 1e8) & (a2 < 1e8)
    curv = a0 + a2 - 2*a1
    ok &= curv > 0
    if P.get('uniq'):
        o = np.arange(Dn)[:, None, None]
        far = np.abs(o - i[None]) > 1
        af = np.where(far, S, 1e9).min(0)
        ok &= (af >= 1e8) | (af * 100 >= a1 * (100 + P['uniq']))
    if P.get('sub') == 'C':
        b0 = np.take_along_axis(Csub, np.clip(i-1, 0, Dn-1)[None], 0)[0]; b1 = np.take_along_axis(Csub, i[None], 0)[0]; b2 = np.take_along_axis(Csub, np.clip(i+1, 0, Dn-1)[None], 0)[0]
        cc = b0 + b2 - 2*b1
        good = ok & (cc > 0) & (b0 < 1e5) & (b2 < 1e5)
        offS = np.where(ok, (a0 - a2) / np.maximum(2*curv, 1e-6), 0)
        offC = np.clip((b0 - b2) / np.maximum(2*cc, 1e-6), -0.5, 0.5)
        if P.get('mix') == 'avg': offC = (offC + offS) / 2
        off = np.where(good, offC, offS)
    else:
        off = np.where(ok, (a0 - a2) / np.maximum(2*curv, 1e-6), 0)
    off = np.clip(off, -P.get('clampoff', 1), P.get('clampoff', 1))
    r = (i + d0 + off).astype(np.float32)
    r = np.where(ok, r, disp).astype(np.float32)
    if P.get('med'):
        from scipy.ndimage import median_filter
        r = median_filter(r, size=3, mode='nearest')
    return r, ok
    return np.where(ok, r, disp).astype(np.float32), ok

def main():
    cache = sys.argv[1]; P = json.loads(sys.argv[2])
    SET = os.environ.get('SET', 'train')
    keys = list(split.HELDOUT_HEADLINE) if SET == 'heldout' else [f'{d}/{s}' for d, s in split.train_scenes() if not d.endswith('_half')]
    if os.environ.get('KEYS'): keys = os.environ['KEYS'].split(',')
    rows = []
    for key in keys:
        ds, s = key.split('/')
        sc = D.load_scene(D.DEFAULT_ROOT, ds, s)
        z = np.load(os.path.join(cache, key.replace('/', '__') + '.npz'))
        v = np.isfinite(sc.disp)
        base, _ = F.refine(sc.left, sc.right, z['disp'], z['u'])
        r, ok = refine(sc.left, sc.right, z['disp'], z['u'], P)
        res = []
        for a in (z['disp'], base, r):
            e = np.abs(a[v] - sc.disp[v]); res += [e.mean(), np.median(e), (e > 2).mean()*100]
        rows.append(res)
        if os.environ.get('V'): print(key, np.round(res, 3), flush=True)
    m = np.mean(rows, 0)
    print(json.dumps(P), 'net %.3f %.3f %.2f | stage %.3f %.3f %.2f | sgm %.3f %.3f %.2f' % tuple(m), flush=True)

if __name__ == '__main__':
    main()
