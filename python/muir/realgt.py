"""Real training crops with ground truth: the TRAIN side of muir.split (issue #20, lever 2).

The synthetic stream teaches matching in general; these crops teach what real cameras and real
surfaces look like, with exact (structured-light) labels. Each draw picks a training scene uniformly,
then augments it so that 27 scene directories give many distinct crops:

  * scale: uniform in log space over [max(0.55, what the crop needs), 1.15], images by area (down) or
    bilinear (up) interpolation, GT by nearest neighbour times the scale (so no disparity is invented
    across an edge and unknown pixels stay unknown);
  * mirror: with probability 1/2 (where the right-view GT exists) the pair is mirrored and its views
    swapped, so the right view's GT becomes the left view's: left' = flip(right), right' = flip(left),
    gt' = flip(gt_right);
  * photometric: shared brightness/contrast/saturation jitter, 15 % grey (ETH3D-like sensors), then per
    view gain and gamma (+-10 %), colour balance (+-4 %) and mild sensor noise, as in the synthetic stream;
  * crop: a random window with at least 50 % known GT (KITTI-style sparse GT is not in the training set).

`sample(rng, h, w)` is a pure function of the generator's state, so a resumed run sees the same crops.
"""
from __future__ import annotations

import math

import cv2
import numpy as np

from . import data as D
from . import split


class RealGTPool:
    """The training scenes in memory: [(key, left, right, disp, disp_right or None)]."""

    def __init__(self, root: str = D.DEFAULT_ROOT):
        split.check(root)
        self.items = []
        for ds, name in split.train_scenes(root):
            sc = D.load_scene(root, ds, name)
            self.items.append((sc.key, sc.left, sc.right, sc.disp, sc.disp_right))
        if not self.items:
            raise FileNotFoundError(f"no training scenes with GT under {root}")

    def sample(self, rng: np.random.Generator, h: int, w: int, min_valid: float = 0.5):
        key, left, right, disp, disp_r = self.items[int(rng.integers(len(self.items)))]
        H, W = disp.shape
        s_lo = max(0.55, (h + 1) / H, (w + 1) / W)
        s_hi = max(1.15, s_lo)
        s = math.exp(rng.uniform(math.log(s_lo), math.log(s_hi)))
        if disp_r is not None and rng.random() < 0.5:
            left, right = np.ascontiguousarray(right[:, ::-1]), np.ascontiguousarray(left[:, ::-1])
            disp = np.ascontiguousarray(disp_r[:, ::-1])
        size = (max(w, int(round(W * s))), max(h, int(round(H * s))))
        sx = size[0] / W  # the horizontal scale is the one disparities follow
        interp = cv2.INTER_AREA if s < 1 else cv2.INTER_LINEAR
        left = cv2.resize(left, size, interpolation=interp)
        right = cv2.resize(right, size, interpolation=interp)
        d = cv2.resize(disp, size, interpolation=cv2.INTER_NEAREST) * np.float32(sx)
        Hs, Ws = d.shape
        for _ in range(20):
            y, x = int(rng.integers(0, Hs - h + 1)), int(rng.integers(0, Ws - w + 1))
            dc = d[y : y + h, x : x + w]
            if np.isfinite(dc).mean() >= min_valid:
                break
        lc = left[y : y + h, x : x + w].astype(np.float32)
        rc = right[y : y + h, x : x + w].astype(np.float32)
        lc, rc = photometric(rng, lc, rc)
        return {"left": lc, "right": rc, "disp": np.ascontiguousarray(dc, dtype=np.float32), "key": key}


def photometric(rng: np.random.Generator, left: np.ndarray, right: np.ndarray):
    """float32 RGB 0..255 pair -> uint8 pair with shared and per-view jitter."""
    contrast = rng.uniform(0.8, 1.2)
    bright = rng.uniform(-20, 20)
    sat = rng.uniform(0.7, 1.3)
    grey = rng.random() < 0.15
    out = []
    for v in (left, right):
        m = v.mean()
        v = (v - m) * contrast + m + bright
        g = v.mean(axis=2, keepdims=True)
        v = g + (v - g) * sat
        if grey:
            v = np.repeat(v.mean(axis=2, keepdims=True), 3, axis=2)
        else:
            v = v * rng.uniform(0.96, 1.04, size=(1, 1, 3))
        v = np.clip(v * rng.uniform(0.9, 1.1), 0, 255)
        v = 255.0 * (v / 255.0) ** rng.uniform(0.9, 1.1)
        if rng.random() < 0.5:
            v = v + rng.normal(0, rng.uniform(0.5, 3.0), size=v.shape)
        out.append(np.clip(v + 0.5, 0, 255).astype(np.uint8))
    return out[0], out[1]


_POOL = None


def pool() -> RealGTPool:
    global _POOL
    if _POOL is None:
        _POOL = RealGTPool()
    return _POOL
