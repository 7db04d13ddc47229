"""Reading the real stereo scenes of ../shared/data (see its MANIFEST.md for the encodings).

Every scene directory holds left.png, right.png and GT files; disparities are left-view, in pixels, at
the stored resolution. `load_scene` returns float32 GT with NaN where invalid and, where possible, a
non-occlusion mask: tsukuba's official nonocc.png, elsewhere the left-right check of the MANIFEST,
|d_L(x) - d_R(x - d_L(x))| <= 1 with the right-view GT sampled at the nearest pixel; a pixel whose match
falls outside the right image or on unknown right-view GT counts as occluded (it cannot be verified).
"""
from __future__ import annotations

import os
from dataclasses import dataclass, field

import numpy as np
from PIL import Image

# ../shared/data beside the repository (python/muir/ -> repo -> its parent).
DEFAULT_ROOT = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../shared/data"))
HEADLINE = ("middlebury2003", "middlebury2005", "middlebury2006")
ALL_GT_DATASETS = ("middlebury2001", "middlebury2003", "middlebury2005", "middlebury2006",
                   "middlebury2005_half", "middlebury2006_half", "eth3d_twoview", "kitti2015")
# Disparity budget per data set (MANIFEST "Max disparities to budget for"); used only to size the
# search range of classical matchers such as SGBM, never by the network.
MAX_DISP = {"middlebury2001": 20, "middlebury2003": 55, "middlebury2005": 78, "middlebury2006": 78,
            "middlebury2005_half": 109, "middlebury2006_half": 109, "eth3d_twoview": 20, "kitti2015": 230}


@dataclass
class Scene:
    dataset: str
    name: str
    left: np.ndarray  # (H, W, 3) uint8 RGB (gray views replicated)
    right: np.ndarray
    disp: np.ndarray  # (H, W) float32 left-view GT, NaN = invalid
    nonocc: np.ndarray | None = None  # (H, W) bool, meaningful on valid pixels
    mask_source: str = "none"  # "official", "lr-check" or "none"
    disp_right: np.ndarray | None = None
    gray: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def key(self) -> str:
        return f"{self.dataset}/{self.name}"

    @property
    def valid(self) -> np.ndarray:
        return np.isfinite(self.disp)


def read_pfm(path: str) -> np.ndarray:
    """PFM ('Pf' gray or 'PF' colour); negative scale = little-endian; rows stored bottom-to-top."""
    with open(path, "rb") as f:
        kind = f.readline().strip()
        if kind not in (b"Pf", b"PF"):
            raise ValueError(f"{path}: not a PFM file")
        w, h = (int(v) for v in f.readline().split())
        scale = float(f.readline().strip())
        data = np.frombuffer(f.read(), dtype="<f4" if scale < 0 else ">f4")
    ch = 3 if kind == b"PF" else 1
    img = data[: w * h * ch].reshape(h, w, ch) if ch == 3 else data[: w * h].reshape(h, w)
    return np.ascontiguousarray(img[::-1]).astype(np.float32)


def read_image_rgb(path: str):
    im = Image.open(path)
    a = np.asarray(im.convert("RGB"), dtype=np.uint8)
    gray = im.mode in ("L", "I;16", "I") or bool((a[..., 0] == a[..., 1]).all() and (a[..., 1] == a[..., 2]).all())
    return a, gray


def decode_gt(path: str, dataset: str) -> np.ndarray:
    """GT file -> float32 disparity with NaN where invalid (per MANIFEST.md)."""
    name = os.path.basename(path)
    if name.endswith(".pfm"):
        d = read_pfm(path)
        d[~np.isfinite(d)] = np.nan
        return d
    raw = np.asarray(Image.open(path))
    if raw.ndim == 3:  # never expected; GT files are single-channel
        raw = raw[..., 0]
    if name == "gt_disparity.png":
        scale = 256.0
    elif name == "truedisp.pgm":
        scale = 16.0
    elif name in ("disp2.pgm", "disp6.pgm"):
        scale = 8.0
    elif name in ("disp2.png", "disp6.png"):
        scale = 4.0
    elif name in ("disp1.png", "disp5.png"):
        scale = 2.0 if dataset.endswith("_half") else 3.0
    else:
        raise ValueError(f"{path}: unknown GT file")
    d = raw.astype(np.float32) / scale
    d[raw == 0] = np.nan
    return d


LEFT_GT = ("truedisp.pgm", "disp2.pgm", "disp2.png", "disp1.png", "disp0.pfm", "gt_disparity.png")
RIGHT_GT = {"disp2.pgm": "disp6.pgm", "disp2.png": "disp6.png", "disp1.png": "disp5.png"}


def lr_check_nonocc(dl: np.ndarray, dr: np.ndarray, thresh: float = 1.0) -> np.ndarray:
    """|d_L(x) - d_R(round(x - d_L(x)))| <= thresh; out-of-image or unknown d_R counts as occluded."""
    h, w = dl.shape
    x = np.arange(w, dtype=np.float32)[None].repeat(h, 0)
    xr = np.rint(x - np.nan_to_num(dl, nan=0.0)).astype(np.int64)
    inside = (xr >= 0) & (xr < w) & np.isfinite(dl)
    rows = np.arange(h)[:, None].repeat(w, 1)
    drx = dr[rows, np.clip(xr, 0, w - 1)]
    ok = inside & np.isfinite(drx) & (np.abs(np.nan_to_num(dl) - np.nan_to_num(drx, nan=1e9)) <= thresh)
    return ok


def load_scene(root: str, dataset: str, name: str) -> Scene:
    """The scene's views and GT; OSError / ValueError with a one-line message naming the file for a
    missing or unreadable file, or GT / views of different sizes."""
    d = os.path.join(root, dataset, name)
    views = []
    for v in ("left.png", "right.png"):
        path = os.path.join(d, v)
        if not os.path.isfile(path):
            raise FileNotFoundError(f"{path}: missing")
        try:
            views.append(read_image_rgb(path))
        except Exception as e:  # PIL's decoder errors
            raise ValueError(f"{path}: not a readable image ({type(e).__name__}: {e})") from None
    (left, gray_l), (right, gray_r) = views
    if left.shape != right.shape:
        raise ValueError(f"{d}: left view is {left.shape[1]}x{left.shape[0]}, right view {right.shape[1]}x{right.shape[0]}")
    gt_name = next((g for g in LEFT_GT if os.path.exists(os.path.join(d, g))), None)
    if gt_name is None:
        raise FileNotFoundError(f"{d}: no GT file (one of {', '.join(LEFT_GT)})")
    try:
        disp = decode_gt(os.path.join(d, gt_name), dataset)
    except (OSError, ValueError) as e:
        raise ValueError(f"{os.path.join(d, gt_name)}: unreadable GT ({e})") from None
    if disp.shape != left.shape[:2]:
        raise ValueError(f"{os.path.join(d, gt_name)}: GT is {disp.shape[1]}x{disp.shape[0]}, the views "
                         f"{left.shape[1]}x{left.shape[0]}")
    # Only plausible disparities count as known (a -1e30 or 1e30 sentinel is not a measurement).
    disp[(disp < 0) | (disp > 10000)] = np.nan
    sc = Scene(dataset, name, left, right, disp, gray=gray_l and gray_r)
    if os.path.exists(os.path.join(d, "nonocc.png")):  # tsukuba: official masks (palette index != 0)
        idx = np.asarray(Image.open(os.path.join(d, "nonocc.png")))
        sc.nonocc = idx != 0
        sc.mask_source = "official"
    elif gt_name in RIGHT_GT and os.path.exists(os.path.join(d, RIGHT_GT[gt_name])):
        sc.disp_right = decode_gt(os.path.join(d, RIGHT_GT[gt_name]), dataset)
        sc.nonocc = lr_check_nonocc(disp, sc.disp_right)
        sc.mask_source = "lr-check"
    return sc


def list_scenes(root: str = DEFAULT_ROOT, datasets=HEADLINE):
    """[(dataset, scene)] with GT, sorted, for the given data sets (directories under root)."""
    out = []
    for ds in datasets:
        p = os.path.join(root, ds)
        if not os.path.isdir(p):
            raise FileNotFoundError(f"no data set directory {p}")
        for s in sorted(os.listdir(p)):
            if os.path.isdir(os.path.join(p, s)) and any(os.path.exists(os.path.join(p, s, g)) for g in LEFT_GT):
                out.append((ds, s))
    return out
