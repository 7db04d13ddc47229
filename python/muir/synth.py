"""Synthetic stereo pairs with exact disparity, for training MUIR without a rendered data set.

A scene is a list of layers. Each layer is a surface with a disparity function d(x, y) of the
*left-view* coordinates (a slanted plane, optionally with a quadratic bump), a coverage function (what
part of that surface exists: full plane, ellipse / ring, star-shaped polygon, noisy blob, thin bar,
fence of parallel bars) and a texture, all defined in left-view coordinates. Both views are rendered
from that description with a z-buffer (larger disparity = closer):

* left view: pixel (x, y) shows the closest layer covering (x, y); GT disparity is exactly its d(x, y);
* right view: pixel (xr, y) shows the closest layer among those whose point x_k with x_k - d_k(x_k, y) = xr
  is covered (x_k solved in closed form for planes, by fixed-point iteration for bumps).

So occlusions are exact, disoccluded right-view pixels show whatever layer is behind (no holes), and
subpixel disparities come out right (the texture is sampled bilinearly at x_k). Both views sample the
texture bilinearly (the left one at a random fractional offset per layer), so neither view is
systematically sharper. A photometric stage then makes the views differ: gain, gamma, colour, blur,
noise, JPEG, and occasionally an "eraser" patch in the right view.

Samples are deterministic: sample(seed, index) always returns the same pair (numpy Generator seeded
with (seed, index); cv2 runs single-threaded). Textures: left views of the real pairs without GT
(../shared/data/nogt/*/left.png, never a right view, never a scene with GT), scikit-image's bundled
photographs when scikit-image is installed, and procedural textures.

CLI (PYTHONPATH=python):
    python -m muir.synth dump --out runs/synth_preview --n 8      # PNGs: left, right, disparity, checks
    python -m muir.synth bench --n 50                             # ms per sample
"""
from __future__ import annotations

import argparse
import glob
import math
import os
import sys
import time

import cv2
import numpy as np

# MUIR_NOGT_DIR points elsewhere where ../shared is not beside the checkout (a leased GPU machine gets
# a copy of the left views: scripts/device-train.sh).
DEFAULT_NOGT_DIR = os.environ.get("MUIR_NOGT_DIR") or os.path.normpath(
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../shared/data/nogt"))
# scikit-image data photographs used as textures (motorcycle_* is a Middlebury stereo pair: not used).
SKIMAGE_IMAGES = (
    "astronaut.png", "brick.png", "camera.png", "cell.png", "chelsea.png", "coffee.png", "coins.png",
    "color.png", "grass.png", "gravel.png", "hubble_deep_field.jpg", "ihc.png", "microaneurysms.png",
    "moon.png", "page.png", "retina.jpg", "rocket.jpg", "text.png", "clock_motion.png",
)


# ------------------------------------------------------------------------------------------------
# Texture sources
# ------------------------------------------------------------------------------------------------
def photo_paths(nogt_dir: str | None = DEFAULT_NOGT_DIR, use_skimage: bool = True) -> list[str]:
    """The texture photographs' files, in the pool's (deterministic) order."""
    paths = []
    if nogt_dir and os.path.isdir(nogt_dir):
        # Left views only: right views and scenes with GT never feed training.
        paths += sorted(glob.glob(os.path.join(nogt_dir, "*", "left.png")))
    if use_skimage:
        try:
            import skimage  # noqa: F401  (only to locate its data dir)

            d = os.path.join(os.path.dirname(skimage.__file__), "data")
            paths += [os.path.join(d, n) for n in SKIMAGE_IMAGES if os.path.exists(os.path.join(d, n))]
        except ImportError:
            pass
    return paths


class PhotoPool:
    """Photographs as float32 RGB in [0, 1], loaded once per process (sorted, so deterministic)."""

    def __init__(self, nogt_dir: str | None = DEFAULT_NOGT_DIR, use_skimage: bool = True, max_side: int = 800):
        self.paths = photo_paths(nogt_dir, use_skimage)
        self.images = []
        for p in self.paths:
            im = cv2.imread(p, cv2.IMREAD_COLOR)  # gray files come back as 3 equal channels
            if im is None:
                continue
            s = max_side / max(im.shape[:2])
            if s < 1:
                im = cv2.resize(im, None, fx=s, fy=s, interpolation=cv2.INTER_AREA)
            self.images.append(np.ascontiguousarray(im[:, :, ::-1], dtype=np.float32) / 255.0)

    def __len__(self):
        return len(self.images)

    def patch(self, rng, h: int, w: int) -> np.ndarray:
        im = self.images[rng.integers(len(self.images))]
        scale = math.exp(rng.uniform(math.log(0.35), math.log(1.6)))  # texture magnification
        ih, iw = im.shape[:2]
        sh = min(ih, max(2, int(math.ceil(h / scale))))
        sw = min(iw, max(2, int(math.ceil(w / scale))))
        y0 = rng.integers(0, ih - sh + 1)
        x0 = rng.integers(0, iw - sw + 1)
        p = im[y0 : y0 + sh, x0 : x0 + sw]
        p = cv2.resize(p, (w, h), interpolation=cv2.INTER_LINEAR if scale > 1 else cv2.INTER_AREA)
        if rng.random() < 0.5:
            p = p[:, ::-1]
        if rng.random() < 0.3:
            p = p[::-1]
        return np.ascontiguousarray(p)


def _smooth_noise(rng, h: int, w: int, cell: float) -> np.ndarray:
    """Value noise in [-1, 1] with features of about `cell` pixels (bicubic upsampling of a grid)."""
    gh = max(2, int(h / cell) + 2)
    gw = max(2, int(w / cell) + 2)
    g = rng.uniform(-1, 1, (gh, gw)).astype(np.float32)
    return cv2.resize(g, (w, h), interpolation=cv2.INTER_CUBIC)


def _rand_colour(rng) -> np.ndarray:
    return rng.uniform(0.0, 1.0, 3).astype(np.float32)


def _two_colour(t: np.ndarray, c1, c2) -> np.ndarray:
    """Blend two colours by t in [0, 1] (h, w) -> (h, w, 3)."""
    return c1[None, None] + t[..., None] * (c2 - c1)[None, None]


def procedural_texture(rng, h: int, w: int, kind: str, photos: PhotoPool | None) -> np.ndarray:
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    if kind == "noise":  # several octaves; colour from independent channel mixes
        t = np.zeros((h, w, 3), np.float32)
        base = math.exp(rng.uniform(math.log(1.0), math.log(40.0)))
        for o in range(int(rng.integers(2, 5))):
            amp = rng.uniform(0.2, 1.0) / (o + 1)
            n = _smooth_noise(rng, h, w, max(1.0, base / 2**o))
            t += amp * n[..., None] * rng.uniform(0.3, 1.0, 3).astype(np.float32)[None, None]
        t = t / (np.abs(t).max() + 1e-6)
        return np.clip(0.5 + rng.uniform(0.2, 0.5) * t + rng.uniform(-0.3, 0.3, 3).astype(np.float32), 0, 1)
    if kind in ("stripes", "checker", "dots"):  # repetitive patterns (ambiguous matching)
        th = rng.uniform(0, math.pi)
        per = math.exp(rng.uniform(math.log(3.0), math.log(32.0)))
        u = (xx * math.cos(th) + yy * math.sin(th)) / per
        v = (-xx * math.sin(th) + yy * math.cos(th)) / per
        if kind == "stripes":
            s = 0.5 + 0.5 * np.sin(2 * math.pi * u + rng.uniform(0, 6.3))
            if rng.random() < 0.5:
                s = (s > 0.5).astype(np.float32)
        elif kind == "checker":
            s = ((np.floor(u) + np.floor(v)) % 2).astype(np.float32)
        else:
            s = (((u % 1) - 0.5) ** 2 + ((v % 1) - 0.5) ** 2 < rng.uniform(0.03, 0.2)).astype(np.float32)
        return _two_colour(s, _rand_colour(rng), _rand_colour(rng))
    if kind == "tiled" and photos is not None and len(photos):  # a small photo patch repeated
        th_, tw_ = int(rng.integers(6, 40)), int(rng.integers(6, 40))
        p = photos.patch(rng, th_, tw_)
        reps = (h // th_ + 1, w // tw_ + 1, 1)
        return np.ascontiguousarray(np.tile(p, reps)[:h, :w])
    if kind == "gradient":
        th = rng.uniform(0, 2 * math.pi)
        u = xx * math.cos(th) + yy * math.sin(th)
        u = (u - u.min()) / (u.max() - u.min() + 1e-6)
        return _two_colour(u, _rand_colour(rng), _rand_colour(rng))
    if kind == "flat":  # textureless
        return np.broadcast_to(_rand_colour(rng)[None, None], (h, w, 3)).copy()
    # photo (default)
    if photos is None or not len(photos):
        return procedural_texture(rng, h, w, "noise", None)
    p = photos.patch(rng, h, w)
    if rng.random() < 0.3:  # recolour: keep the structure, change the palette
        p = np.clip(p * rng.uniform(0.6, 1.4, 3).astype(np.float32)[None, None], 0, 1)
    return p


TEXTURE_KINDS = ("photo", "noise", "stripes", "checker", "dots", "tiled", "gradient", "flat")
TEXTURE_P_OBJECT = (0.42, 0.2, 0.08, 0.05, 0.03, 0.06, 0.06, 0.10)
TEXTURE_P_BAR = (0.25, 0.2, 0.05, 0.0, 0.0, 0.0, 0.1, 0.40)
TEXTURE_P_BACKGROUND = (0.55, 0.2, 0.04, 0.03, 0.0, 0.05, 0.05, 0.08)


# ------------------------------------------------------------------------------------------------
# Layers
# ------------------------------------------------------------------------------------------------
class Layer:
    """One surface. Disparity d(x, y) = a + b (x - cx) + c (y - cy) + q ((x - cx)^2 + (y - cy)^2) / R^2.
    Coverage and texture live in left-view coordinates; bbox (x0, x1, y0, y1) is where coverage may be
    true, clipped to the canvas of left coordinates visible in either view."""

    def __init__(self, kind, cx, cy, a, b, c, q=0.0, R=1.0, **shape):
        self.kind, self.cx, self.cy = kind, float(cx), float(cy)
        self.a, self.b, self.c, self.q, self.R = float(a), float(b), float(c), float(q), float(R)
        self.shape = shape
        self.bbox = None
        self.tex = None
        self.phase = (0.0, 0.0)
        self.shade = (1.0, 0.0, 0.0)

    def disp(self, x, y):
        dx = x - self.cx
        dy = y - self.cy
        d = self.a + self.b * dx + self.c * dy
        if self.q:
            d = d + self.q * (dx * dx + dy * dy) / (self.R * self.R)
        return d

    def solve_left_x(self, xr, y):
        """x with x - d(x, y) = xr (the left-view point seen at right-view column xr). Plane: closed
        form; bump: Newton (|dd/dx| <= 0.5 on the bbox keeps x - d(x) monotonic, one solution)."""
        x = (xr + self.a - self.b * self.cx + self.c * (y - self.cy)) / (1.0 - self.b)
        if self.q:  # Newton on f(x) = x - d(x, y) - xr from the plane's solution
            k = 2.0 * self.q / (self.R * self.R)
            for _ in range(4):
                f = x - self.disp(x, y) - xr
                x = x - f / (1.0 - self.b - k * (x - self.cx))
        return x

    def cover(self, x, y):
        s = self.shape
        if self.kind == "full":
            return np.ones(np.broadcast(x, y).shape, bool)
        dx = x - self.cx
        dy = y - self.cy
        cs, sn = s["cos"], s["sin"]
        u = dx * cs + dy * sn
        v = -dx * sn + dy * cs
        if self.kind == "ellipse":
            r2 = (u / s["rx"]) ** 2 + (v / s["ry"]) ** 2
            m = r2 <= 1.0
            if s.get("hole", 0) > 0:
                m &= r2 >= s["hole"] ** 2
            return m
        if self.kind == "blob":  # ellipse whose radius is modulated by smooth noise
            r2 = (u / s["rx"]) ** 2 + (v / s["ry"]) ** 2
            n = _bilinear1(s["noise"], x - self.bbox[0], y - self.bbox[2])
            return r2 <= 1.0 + s["amp"] * n
        if self.kind == "bar":
            return (np.abs(u) <= s["len"] / 2) & (np.abs(v) <= s["width"] / 2)
        if self.kind == "fence":  # parallel bars: thin repetitive structure
            return (np.abs(u) <= s["len"] / 2) & (np.abs(v) <= s["extent"] / 2) & (
                np.mod(v + s["off"], s["period"]) < s["width"]
            )
        if self.kind == "poly":  # star-shaped polygon around the centre (angles sorted)
            ang = np.arctan2(v, u)
            va = s["ang"]  # (n,) sorted in (-pi, pi]
            k = np.searchsorted(va, ang) % len(va)  # edge from vertex k-1 to k
            p0x, p0y = s["vx"][k - 1], s["vy"][k - 1]
            p1x, p1y = s["vx"][k], s["vy"][k]
            cross = (p1x - p0x) * (v - p0y) - (p1y - p0y) * (u - p0x)
            return cross >= 0  # vertices counter-clockwise: inside is on the left of each edge
        raise ValueError(self.kind)


def _bilinear1(img, x, y):
    """Bilinear sample of a 2D array at float coords (clamped to the border)."""
    h, w = img.shape
    x = np.clip(x, 0, w - 1.001)
    y = np.clip(y, 0, h - 1.001)
    x0 = x.astype(np.int32)
    y0 = y.astype(np.int32)
    fx = x - x0
    fy = y - y0
    i = y0 * w + x0
    f = img.ravel()
    top = f[i] * (1 - fx) + f[i + 1] * fx
    bot = f[i + w] * (1 - fx) + f[i + w + 1] * fx
    return top * (1 - fy) + bot * fy


def _remap(img, x, y):
    """Bilinear sample of img at float maps x, y (same shape); clamped at the border. cv2.remap
    quantises positions to 1/32 px, well below the GT precision of the evaluation sets."""
    return cv2.remap(img, x.astype(np.float32), y.astype(np.float32), cv2.INTER_LINEAR,
                     borderMode=cv2.BORDER_REPLICATE)


# ------------------------------------------------------------------------------------------------
# Scene sampling
# ------------------------------------------------------------------------------------------------
def _disparity_range(rng, w: int):
    """(background disparity, max disparity). Large disparities are favoured: 65 % of the scenes reach
    10-32 % of the crop width (the evaluation scenes go to ~17 % of their width)."""
    if rng.random() < 0.65:
        dmax = rng.uniform(0.10, 0.32) * w
    else:
        dmax = rng.uniform(0.015, 0.10) * w
    u = rng.random()
    dbg = 0.0 if u < 0.1 else rng.uniform(0.0, 0.6) * dmax  # 10 % of scenes have a background at infinity
    return dbg, dmax


def sample_scene(rng, h: int, w: int, photos: PhotoPool | None):
    dbg, dmax = _disparity_range(rng, w)
    layers = []
    # Background: one slanted plane, sometimes with a floor plane in front of its lower part.
    b = rng.uniform(-0.08, 0.08) if rng.random() < 0.6 else 0.0
    c = rng.uniform(-0.1, 0.1) if rng.random() < 0.6 else 0.0
    layers.append(("bg", Layer("full", w / 2, h / 2, dbg, b, c)))
    if rng.random() < 0.25:
        horizon = rng.uniform(-0.2, 0.7) * h
        slope = rng.uniform(0.15, 0.6)  # disparity grows by `slope` per row below the horizon
        layers.append(("bg", Layer("full", w / 2, horizon, dbg, rng.uniform(-0.05, 0.05), slope)))

    # Objects between the background and dmax.
    n_obj = int(rng.integers(3, 15))  # cluttered, like the indoor evaluation scenes
    for _ in range(n_obj):
        d0 = rng.uniform(dbg, dmax) if rng.random() < 0.8 else dmax * rng.uniform(0.85, 1.0)
        cx = rng.uniform(-0.1 * w, 1.05 * w + d0)  # left coords; shifted by d0 in the right view
        cy = rng.uniform(-0.1 * h, 1.1 * h)
        size = math.exp(rng.uniform(math.log(6.0), math.log(0.8 * h)))
        rx = size * rng.uniform(0.5, 1.6)
        ry = size * rng.uniform(0.5, 1.6)
        th = rng.uniform(0, math.pi)
        kind = rng.choice(["ellipse", "poly", "poly", "blob"])
        slant_b = rng.uniform(-0.2, 0.2) if rng.random() < 0.7 else 0.0
        slant_c = rng.uniform(-0.2, 0.2) if rng.random() < 0.7 else 0.0
        q = 0.0
        if kind in ("ellipse", "blob") and rng.random() < 0.4:  # bulging surface (ball, leaf, face)
            q = -rng.uniform(0.0, 0.25) * max(rx, ry)
        shape = dict(cos=math.cos(th), sin=math.sin(th), rx=rx, ry=ry)
        if kind == "ellipse" and rng.random() < 0.15:
            shape["hole"] = rng.uniform(0.3, 0.8)
        if kind == "poly":
            n = int(rng.integers(3, 9))
            ang = np.sort(rng.uniform(-math.pi, math.pi, n))
            rad = rng.uniform(0.4, 1.0, n) if rng.random() < 0.5 else np.ones(n)
            shape.update(ang=ang, vx=rad * rx * np.cos(ang), vy=rad * ry * np.sin(ang))
        if kind == "blob":
            shape.update(amp=rng.uniform(0.3, 0.9))
        layers.append(("obj", Layer(kind, cx, cy, d0, slant_b, slant_c, q, max(rx, ry), **shape)))

    # Thin structures: wires, poles, fences.
    n_bar = int(rng.integers(0, 5)) if rng.random() < 0.7 else 0
    for _ in range(n_bar):
        d0 = rng.uniform(dbg, dmax)
        cx = rng.uniform(0, w + d0)
        cy = rng.uniform(0, h)
        th = rng.uniform(0, math.pi) if rng.random() < 0.5 else rng.choice([0.0, math.pi / 2]) + rng.normal(0, 0.05)
        length = rng.uniform(0.3, 2.0) * h
        if rng.random() < 0.75:
            shape = dict(len=length, width=math.exp(rng.uniform(math.log(1.0), math.log(8.0))))
            kind = "bar"
        else:
            period = rng.uniform(4, 24)
            shape = dict(len=length, width=rng.uniform(1.0, 0.6 * period), period=period,
                         extent=rng.uniform(0.2, 1.0) * w, off=rng.uniform(0, period))
            kind = "fence"
        shape.update(cos=math.cos(th), sin=math.sin(th))
        bslant = rng.uniform(-0.15, 0.15) if rng.random() < 0.5 else 0.0
        cslant = rng.uniform(-0.15, 0.15) if rng.random() < 0.5 else 0.0
        layers.append(("bar", Layer(kind, cx, cy, d0, bslant, cslant, **shape)))
    return layers, dmax


def _layer_extent(layer: Layer, w_canvas: int, h: int):
    """Conservative left-coordinate bbox of the coverage, clipped to the canvas."""
    s = layer.shape
    if layer.kind == "full":
        return 0, w_canvas, 0, h
    if layer.kind in ("bar", "fence"):
        a = s["len"] / 2
        bb = (s.get("extent", s["width"])) / 2
    else:
        a = max(s["rx"], s["ry"]) * (1.0 + s.get("amp", 0.0))
        bb = a
    r = math.hypot(a, bb) + 2
    x0 = max(0, int(math.floor(layer.cx - r)))
    x1 = min(w_canvas, int(math.ceil(layer.cx + r)) + 1)
    y0 = max(0, int(math.floor(layer.cy - r)))
    y1 = min(h, int(math.ceil(layer.cy + r)) + 1)
    return x0, x1, y0, y1


def _finish_layers(rng, layers, h: int, w: int, dmax: float, photos):
    """Fix disparity ranges (>= 0, contraction for bumps), bboxes, textures and shading."""
    dcap = max(dmax * 1.15, 2.0)
    m = int(math.ceil(dcap)) + 4
    w_canvas = w + m
    kept = []
    for role, L in layers:
        x0, x1, y0, y1 = _layer_extent(L, w_canvas, h)
        if x1 - x0 < 1 or y1 - y0 < 1:
            continue
        # Disparity over the bbox (corners + centre; exact for planes, close enough for bumps).
        xs = np.array([x0, x1, x0, x1, np.clip(L.cx, x0, x1)], np.float64)
        ys = np.array([y0, y0, y1, y1, np.clip(L.cy, y0, y1)], np.float64)
        d = L.disp(xs, ys)
        if d.max() - d.min() > dcap:  # too steep for [0, dcap]: flatten the slant
            f = 0.95 * dcap / (d.max() - d.min())
            L.b, L.c, L.q = L.b * f, L.c * f, L.q * f
            d = L.disp(xs, ys)
        if d.min() < 0:  # keep d >= 0 everywhere (shift the plane up)
            L.a -= d.min()
        elif d.max() > dcap:  # and <= dcap, so the canvas margin holds every match
            L.a -= min(d.max() - dcap, d.min())
        if L.q:
            # |dd/dx| <= 0.5 on the bbox: x - d(x, y) stays monotonic, a single right-view match.
            grad = abs(L.b) + 2 * abs(L.q) * max(abs(x0 - L.cx), abs(x1 - L.cx)) / L.R**2
            if grad > 0.5:
                L.q *= 0.5 / grad
        if L.kind == "blob":
            L.shape["noise"] = _smooth_noise(rng, y1 - y0 + 1, x1 - x0 + 1, max(3.0, L.R / 3))
        L.bbox = (x0, x1, y0, y1)
        probs = {"bg": TEXTURE_P_BACKGROUND, "obj": TEXTURE_P_OBJECT, "bar": TEXTURE_P_BAR}[role]
        kind = TEXTURE_KINDS[rng.choice(len(TEXTURE_KINDS), p=probs)]
        L.tex = procedural_texture(rng, y1 - y0 + 2, x1 - x0 + 2, kind, photos)
        L.phase = (rng.random(), rng.random())  # left-view subpixel offset into the texture
        # Smooth shading (same in both views: Lambertian-like), so no layer is perfectly flat-lit.
        L.shade = (rng.uniform(0.6, 1.2), rng.uniform(-0.4, 0.4) / max(w, 1), rng.uniform(-0.4, 0.4) / max(h, 1))
        kept.append(L)
    return kept, w_canvas


def _shade(L: Layer, x, y, col):
    g, gx, gy = L.shade
    s = g + gx * (x - L.cx) + gy * (y - L.cy)
    return col * np.clip(s, 0.2, 1.6)[..., None].astype(np.float32)


def render(layers, h: int, w: int, dy_right: float = 0.0):
    """Render left/right views and left/right disparity from the layer list (z-buffer on disparity)."""
    left = np.zeros((h, w, 3), np.float32)
    right = np.zeros((h, w, 3), np.float32)
    zl = np.full((h, w), -np.inf, np.float32)
    zr = np.full((h, w), -np.inf, np.float32)
    for L in layers:
        x0, x1, y0, y1 = L.bbox
        # ---- left view: the layer's own coordinates
        if x0 < w:
            X, Y = np.meshgrid(np.arange(x0, min(x1, w), dtype=np.float32), np.arange(y0, y1, dtype=np.float32))
            d = L.disp(X, Y)
            sub = zl[y0:y1, x0 : min(x1, w)]
            upd = L.cover(X, Y) & (d > sub)
            if upd.any():
                # Texture shifted by the layer's subpixel phase (bilinear, like the right view gets).
                col = _shade(L, X, Y, _remap(L.tex, X - x0 + L.phase[0], Y - y0 + L.phase[1]))
                np.copyto(left[y0:y1, x0 : min(x1, w)], col, where=upd[..., None])
                np.copyto(sub, d, where=upd)
        # ---- right view: xr = x - d(x, y); solve for x per right pixel
        dlo = float(L.disp(np.array([x0, x1, x0, x1], np.float32), np.array([y0, y0, y1, y1], np.float32)).min())
        dhi = float(L.disp(np.array([x0, x1, x0, x1], np.float32), np.array([y0, y0, y1, y1], np.float32)).max())
        if L.q:  # bumps: the extreme may be inside the bbox
            dlo, dhi = dlo - abs(L.q), dhi + abs(L.q)
        r0 = max(0, int(math.floor(x0 - dhi)) - 1)
        r1 = min(w, int(math.ceil(x1 - dlo)) + 2)
        ry0 = max(0, int(math.floor(y0 - dy_right)) - 1)
        ry1 = min(h, int(math.ceil(y1 - dy_right)) + 1)
        if r1 <= r0 or ry1 <= ry0:
            continue
        XR, YR = np.meshgrid(np.arange(r0, r1, dtype=np.float32), np.arange(ry0, ry1, dtype=np.float32))
        YS = YR + dy_right  # row in the layer (left) coordinates: vertical misalignment of the right camera
        XL = L.solve_left_x(XR, YS)
        d = XL - XR
        sub = zr[ry0:ry1, r0:r1]
        # Up to 1 px outside the bbox is kept (texture clamped), so a vertical shift of the right
        # camera or a disparity of exactly 0 at the border leaves no empty right-view pixel.
        upd = (XL > x0 - 1) & (XL < x1 - 1) & (YS > y0 - 1) & (YS < y1) & (d > sub)
        if not upd.any():
            continue
        upd[upd] = L.cover(XL[upd], YS[upd])
        if not upd.any():
            continue
        col = _remap(L.tex, XL - x0 + L.phase[0], YS - y0 + L.phase[1])  # same texture coords as left
        np.copyto(right[ry0:ry1, r0:r1], _shade(L, XL, YS, col), where=upd[..., None])
        np.copyto(sub, d, where=upd)
    return left, right, zl, zr


# ------------------------------------------------------------------------------------------------
# Photometric stage
# ------------------------------------------------------------------------------------------------
def _jpeg(rng, img_u8):
    q = int(rng.integers(55, 96))
    ok, buf = cv2.imencode(".jpg", img_u8, [cv2.IMWRITE_JPEG_QUALITY, q])
    return cv2.imdecode(buf, cv2.IMREAD_UNCHANGED).reshape(img_u8.shape) if ok else img_u8


def photometric(rng, left, right, gray: bool):
    """Shared colour/contrast jitter, then per-view gain, gamma, colour, blur, noise, JPEG."""
    if gray:
        wts = np.array([0.299, 0.587, 0.114], np.float32)
        left = np.repeat((left @ wts)[..., None], 3, 2)
        right = np.repeat((right @ wts)[..., None], 3, 2)
    else:  # saturation jitter (shared)
        s = rng.uniform(0.6, 1.4)
        for im in (left, right):
            g = im.mean(axis=2, keepdims=True)
            im[:] = g + s * (im - g)
    contrast = rng.uniform(0.6, 1.3)
    bright = rng.uniform(-0.15, 0.15)
    gain0 = rng.uniform(0.8, 1.2)
    gamma0 = math.exp(rng.uniform(math.log(0.75), math.log(1.33)))
    out = []
    for im in (left, right):
        im = np.clip(0.5 + contrast * (im - 0.5) + bright, 0, 1)
        gain = gain0 * rng.uniform(0.92, 1.08)  # asymmetric exposure
        gamma = gamma0 * math.exp(rng.uniform(-0.08, 0.08))
        im = cv2.pow(np.clip(im * gain, 0, 1), gamma)
        if not gray and rng.random() < 0.5:
            im = im * rng.uniform(0.95, 1.05, 3).astype(np.float32)[None, None]
        if rng.random() < 0.5:
            s = rng.uniform(0.2, 1.1)
            im = cv2.GaussianBlur(im, (0, 0), s)
        noise = rng.uniform(0.0, 0.025) if rng.random() < 0.8 else 0.0
        if noise > 0:
            n = rng.standard_normal(im.shape[:2] if gray else im.shape).astype(np.float32) * noise
            im = im + (n[..., None] if gray else n)
        u8 = np.clip(im * 255.0 + 0.5, 0, 255).astype(np.uint8)
        if rng.random() < 0.25:
            u8 = _jpeg(rng, u8)
        out.append(u8)
    return out


def _eraser(rng, right_u8):
    """RAFT-Stereo-style occlusion augmentation: flat patches in the right view (GT unchanged)."""
    h, w = right_u8.shape[:2]
    mean = right_u8.reshape(-1, 3).mean(0)
    for _ in range(int(rng.integers(1, 3))):
        ew, eh = int(rng.integers(20, 80)), int(rng.integers(20, 80))
        x0, y0 = int(rng.integers(0, w)), int(rng.integers(0, h))
        right_u8[y0 : y0 + eh, x0 : x0 + ew] = mean
    return right_u8


# ------------------------------------------------------------------------------------------------
# Public API
# ------------------------------------------------------------------------------------------------
_POOL: PhotoPool | None = None


def photo_pool() -> PhotoPool:
    global _POOL
    if _POOL is None:
        _POOL = PhotoPool()
    return _POOL


def sample(seed: int, index: int, h: int = 160, w: int = 384, photos: PhotoPool | None = None,
           with_right_disp: bool = False, raw: bool = False):
    """Sample `index` of stream `seed`: dict(left (h,w,3) u8 RGB, right (h,w,3) u8, disp (h,w) f32,
    gray bool, dy_right (right row r shows left-coordinate row r + dy_right), [disp_right (h,w) f32: right-view GT, for checks]). raw=True skips the photometric
    stage (identical photometry in both views, for checking the geometry)."""
    cv2.setNumThreads(1)
    photos = photo_pool() if photos is None else photos
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(index)])
    layers, dmax = sample_scene(rng, h, w, photos)
    layers, _ = _finish_layers(rng, layers, h, w, dmax, photos)
    dy = rng.uniform(-0.6, 0.6) if rng.random() < 0.2 else 0.0  # slight rectification error
    left, right, dl, dr = render(layers, h, w, dy)
    gray = bool(rng.random() < 0.3)  # OAK-D style mono pairs
    lu8, ru8 = photometric(rng, left, right, gray)
    if raw:
        lu8, ru8 = (np.clip(v * 255 + 0.5, 0, 255).astype(np.uint8) for v in (left, right))
    elif rng.random() < 0.15:
        ru8 = _eraser(rng, ru8)
    out = dict(left=lu8, right=ru8, disp=np.maximum(dl, 0).astype(np.float32), gray=gray, dy_right=dy)
    if with_right_disp:
        out["disp_right"] = dr.astype(np.float32)
    return out


def colorize(disp, vmax=None, invalid=None):
    """Disparity -> BGR u8 (turbo colormap); invalid pixels black."""
    d = np.nan_to_num(disp.astype(np.float32), nan=0, posinf=0, neginf=0)
    vmax = float(d.max()) if vmax is None else float(vmax)
    im = cv2.applyColorMap(np.clip(d / max(vmax, 1e-6) * 255, 0, 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    if invalid is not None:
        im[invalid] = 0
    return im


def _check_images(s):
    """Warp the right view to the left with GT; mark pixels failing the left-right GT check."""
    h, w = s["disp"].shape
    xs = np.arange(w, dtype=np.float32)[None].repeat(h, 0) - s["disp"]
    ys = np.arange(h, dtype=np.float32)[:, None].repeat(w, 1) - np.float32(s.get("dy_right", 0.0))
    warped = cv2.remap(s["right"], xs, ys, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)
    dr = cv2.remap(s["disp_right"], xs, ys, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=-1)
    occ = (np.abs(dr - s["disp"]) > 1) | (xs < 0)
    err = np.abs(warped.astype(np.float32) - s["left"].astype(np.float32)).mean(2)
    err_vis = np.clip(err * 4, 0, 255).astype(np.uint8)
    err_vis = cv2.cvtColor(err_vis, cv2.COLOR_GRAY2BGR)
    err_vis[occ] = (err_vis[occ] * 0.3 + np.array([0, 0, 180])).astype(np.uint8)  # occluded: red tint
    return warped, err_vis, occ, err


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m muir.synth", description="Synthetic stereo generator")
    sub = p.add_subparsers(dest="cmd", required=True)
    d = sub.add_parser("dump", help="write PNGs of a few samples (left, right, disparity, warp check)")
    d.add_argument("--out", required=True)
    d.add_argument("--n", type=int, default=8)
    d.add_argument("--seed", type=int, default=0)
    d.add_argument("--start", type=int, default=0, help="first sample index")
    d.add_argument("--size", default="160x384", help="HxW")
    d.add_argument("--raw", action="store_true", help="no photometric stage (checks the geometry alone)")
    b = sub.add_parser("bench", help="time sample generation (single thread)")
    b.add_argument("--n", type=int, default=50)
    b.add_argument("--size", default="160x384")
    a = p.parse_args(argv)
    try:
        h, w = (int(v) for v in a.size.lower().split("x"))
    except ValueError:
        p.error(f"--size must be HxW, got {a.size}")
    pool = photo_pool()
    print(f"{len(pool)} texture photographs", file=sys.stderr)
    if a.cmd == "bench":
        sample(0, 0, h, w)
        t = time.perf_counter()
        for i in range(a.n):
            sample(1, i, h, w)
        dt = (time.perf_counter() - t) / a.n
        print(f"{dt * 1e3:.1f} ms per {h}x{w} sample")
        return 0
    os.makedirs(a.out, exist_ok=True)
    for i in range(a.start, a.start + a.n):
        s = sample(a.seed, i, h, w, with_right_disp=True, raw=a.raw)
        warped, err_vis, occ, err = _check_images(s)
        vmax = max(float(s["disp"].max()), 1.0)
        row1 = np.concatenate([s["left"][:, :, ::-1], s["right"][:, :, ::-1]], 1)
        row2 = np.concatenate([colorize(s["disp"], vmax), colorize(s["disp_right"], vmax)], 1)
        row3 = np.concatenate([warped[:, :, ::-1], err_vis], 1)
        cv2.imwrite(os.path.join(a.out, f"sample_{a.seed}_{i:05d}.png"), np.concatenate([row1, row2, row3], 0))
        print(f"sample {i}: d {s['disp'].min():.1f}..{s['disp'].max():.1f}, occluded {occ.mean() * 100:.1f} %, "
              f"warp err (non-occ) {err[~occ].mean():.2f}, gray {s['gray']}", file=sys.stderr)
    print(f"wrote {a.n} samples to {a.out} (rows: left|right, GT left|GT right, right warped by GT|error, "
          "occluded red)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
