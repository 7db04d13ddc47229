"""Proxy labels on real pairs without GT: filtered OpenCV StereoSGBM disparities (issue #3).

The synthetic stream teaches the network to match everything (occlusions, textureless and thin
structures) but, with the CPU budget we have, not to match real textures to a fraction of a pixel:
on Middlebury the shipped phase-7 model has a median error of 0.56 px on non-occluded pixels where
SGBM has 0.21 px. Confident SGBM pixels on *other* real pairs carry exactly that sub-pixel signal
(proxy supervision, as in Tonioni et al., "Unsupervised adaptation for deep stereo", ICCV 2017).

Sources: the left/right pairs of `../shared/data/nogt/` (never a scene with GT, never an evaluation
scene), each at a few scales. A pixel keeps its SGBM disparity only if
  * SGBM found one (uniqueness ratio, speckle filter, its own disp12MaxDiff check),
  * a left-right check with SGBM run on the mirrored pair agrees within `LR_TOL` px,
  * it is not at the left border where the match would leave the right image,
  * it is below the top of the search range (128 px), where SGBM saturates.
Everything else is NaN (no loss there). The labels are computed once per (pair, scale) and cached
under `.cache/proxy/` (gitignored).

    PYTHONPATH=python python -m muir.proxy build            # labels + density table
    PYTHONPATH=python python -m muir.proxy check            # the same filter on GT scenes not used
                                                            # for evaluation: how good the labels are
"""
from __future__ import annotations

import argparse
import glob
import os
import sys

import cv2
import numpy as np

from . import data as D

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))
CACHE = os.path.join(REPO, ".cache", "proxy")
NOGT = os.path.join(D.DEFAULT_ROOT, "nogt")
LR_TOL = 1.0
# Scales per source, chosen so that the largest disparities stay within the synthetic range (~100 px
# at a 320-px crop) and every crop of 128x320 fits: KITTI at 1242 px wide reaches ~230 px.
SCALES = {"kitti2015": (0.4, 0.55), "oakd": (0.75, 1.0), "shimizu": (0.5, 0.7)}
PROXY_SGBM = {"blockSize": 5, "P1": 8, "P2": 32, "uniquenessRatio": 15, "speckleWindowSize": 100,
              "speckleRange": 2, "disp12MaxDiff": 1, "preFilterCap": 63, "mode": "HH"}


def _sgbm(left, right, num_disp):
    from .evaluate import run_sgbm

    return run_sgbm(left, right, num_disp, PROXY_SGBM)


def proxy_labels(left: np.ndarray, right: np.ndarray, num_disp: int, lr_tol: float = LR_TOL):
    """(H, W) float32 left-view disparity, NaN where the filters reject the SGBM value."""
    dl = _sgbm(left, right, num_disp)
    # Right-view disparity: SGBM on the mirrored pair (mirrored right is the reference view).
    dr = _sgbm(np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1]), num_disp)[:, ::-1]
    h, w = dl.shape
    xs = np.arange(w)[None].repeat(h, 0)
    xr = np.rint(xs - np.nan_to_num(dl, nan=0)).astype(np.int64)
    inside = np.isfinite(dl) & (xr >= 0) & (xr < w)
    drs = np.full_like(dl, np.nan)
    rows = np.arange(h)[:, None].repeat(w, 1)
    drs[inside] = dr[rows[inside], xr[inside]]
    # A value at the top of the search range may be a match beyond it: drop it.
    ok = inside & np.isfinite(drs) & (np.abs(dl - drs) <= lr_tol) & (dl < num_disp - 2)
    return np.where(ok, dl, np.nan).astype(np.float32)


def sources():
    """[(name, scale)] over the nogt pairs."""
    out = []
    for d in sorted(glob.glob(os.path.join(NOGT, "*", "left.png"))):
        name = os.path.basename(os.path.dirname(d))
        key = next((k for k in SCALES if name.startswith(k)), None)
        for s in SCALES.get(key, (1.0,)):
            out.append((name, s))
    return out


def _load_pair(name, scale):
    left, _ = D.read_image_rgb(os.path.join(NOGT, name, "left.png"))
    right, _ = D.read_image_rgb(os.path.join(NOGT, name, "right.png"))
    if scale != 1.0:
        h, w = left.shape[:2]
        size = (int(round(w * scale)), int(round(h * scale)))
        left = cv2.resize(left, size, interpolation=cv2.INTER_AREA)
        right = cv2.resize(right, size, interpolation=cv2.INTER_AREA)
    return left, right


def cache_path(name, scale):
    return os.path.join(CACHE, f"{name}@{scale:.2f}.npz")


def load(name, scale, build=True):
    """dict(left, right, disp) for one source, from the cache (built on first use)."""
    p = cache_path(name, scale)
    if os.path.exists(p):
        z = np.load(p)
        return {k: z[k] for k in ("left", "right", "disp")}
    if not build:
        raise FileNotFoundError(p)
    left, right = _load_pair(name, scale)
    disp = proxy_labels(left, right, 128)
    os.makedirs(CACHE, exist_ok=True)
    tmp = p + ".tmp.npz"
    np.savez_compressed(tmp, left=left, right=right, disp=disp)
    os.replace(tmp, p)
    return {"left": left, "right": right, "disp": disp}


class ProxyPool:
    """All proxy sources in memory; `sample(rng, h, w)` draws a labelled crop."""

    def __init__(self):
        self.items = [load(n, s) for n, s in sources()]
        if not self.items:
            raise FileNotFoundError(f"no proxy sources under {NOGT}")

    def sample(self, rng: np.random.Generator, h: int, w: int, min_valid: float = 0.25):
        for _ in range(20):
            it = self.items[int(rng.integers(len(self.items)))]
            H, W = it["disp"].shape
            if H < h or W < w:
                continue
            y, x = int(rng.integers(0, H - h + 1)), int(rng.integers(0, W - w + 1))
            d = it["disp"][y : y + h, x : x + w]
            if np.isfinite(d).mean() >= min_valid:
                break
        left = it["left"][y : y + h, x : x + w].astype(np.float32)
        right = it["right"][y : y + h, x : x + w].astype(np.float32)
        # Mild photometric asymmetry (gain, gamma per view), as in the synthetic stream.
        out = []
        for v in (left, right):
            g = rng.uniform(0.92, 1.08)
            gam = rng.uniform(0.92, 1.08)
            out.append(np.clip(255.0 * (np.clip(v * g, 0, 255) / 255.0) ** gam + 0.5, 0, 255).astype(np.uint8))
        return {"left": out[0], "right": out[1], "disp": d.astype(np.float32)}


_POOL = None


def pool() -> ProxyPool:
    global _POOL
    if _POOL is None:
        _POOL = ProxyPool()
    return _POOL


def check(args):
    """The same filter on GT scenes outside the headline evaluation: label precision and density."""
    rows = []
    for ds in ("middlebury2001", "eth3d_twoview"):
        for ds_, s in D.list_scenes(D.DEFAULT_ROOT, [ds]):
            sc = D.load_scene(D.DEFAULT_ROOT, ds_, s)
            d = proxy_labels(sc.left, sc.right, int(16 * np.ceil(1.1 * D.MAX_DISP[ds] / 16)), args.lr_tol)
            v = np.isfinite(sc.disp)
            k = v & np.isfinite(d)
            e = np.abs(d[k] - sc.disp[k])
            rows.append((f"{ds}/{s}", k.sum() / v.sum(), np.median(e), (e > 1).mean(), (e > 2).mean()))
            print(f"{rows[-1][0]:32s} density {100 * rows[-1][1]:5.1f}%  A50 {rows[-1][2]:.3f}  "
                  f"bad1 {100 * rows[-1][3]:5.2f}%  bad2 {100 * rows[-1][4]:5.2f}%", flush=True)
    a = np.array([r[1:] for r in rows])
    print(f"{'mean':32s} density {100 * a[:, 0].mean():5.1f}%  A50 {a[:, 1].mean():.3f}  "
          f"bad1 {100 * a[:, 2].mean():5.2f}%  bad2 {100 * a[:, 3].mean():5.2f}%")


def build(_args):
    for n, s in sources():
        z = load(n, s)
        print(f"{n}@{s:.2f}: {z['disp'].shape[1]}x{z['disp'].shape[0]}, labelled {100 * np.isfinite(z['disp']).mean():.1f}%, "
              f"disparity {np.nanmin(z['disp']):.1f}..{np.nanmax(z['disp']):.1f}", flush=True)


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m muir.proxy", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sub.add_parser("build", help="compute (or read) the cached labels and print their density")
    c = sub.add_parser("check", help="label precision on middlebury2001 and eth3d_twoview (GT)")
    c.add_argument("--lr-tol", type=float, default=LR_TOL)
    a = p.parse_args(argv)
    cv2.setNumThreads(2)
    return {"build": build, "check": check}[a.cmd](a) or 0


if __name__ == "__main__":
    sys.exit(main())
