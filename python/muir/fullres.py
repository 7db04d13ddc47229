"""Full-resolution refinement of the network's disparity, bit for bit the Rust stage
(`src/kernels/fullres.rs`, where the algorithm and its constants are specified).

The network's disparity is quantised to the engine's output format (Q10.5, 1/32 px) and its
uncertainty to Q4.11; every pixel is re-matched in a band around it with a 7x7 census cost summed
over a 9x9 window, and keeps the network's value where the cost cannot decide. Vectorised over
the image (one cost plane per absolute disparity), integer throughout.

    from muir.fullres import refine
    d_ref, refined_mask = refine(left_rgb_uint8, right_rgb_uint8, disp_float_px, u_float_or_None)
"""
from __future__ import annotations

import numpy as np

CENSUS_RADIUS = 3
WINDOW_RADIUS = 4
MIN_BAND = 3
MAX_BAND = 12
MIN_CURVATURE = 2 * (2 * WINDOW_RADIUS + 1) ** 2
BAND_U_THRESHOLDS = np.array([0, 1178, 2092, 2839, 3470, 4017, 4499, 4931, 5321], np.int32)
UNIQUENESS = 10  # percent (UNIQUENESS_PERCENT)
DISP_FRAC = 5
LOG_FRAC = 11
_POP8 = np.array([bin(i).count("1") for i in range(256)], np.int32)


def grey(img: np.ndarray) -> np.ndarray:
    """(H, W, 3) or (H, W) uint8 -> int32 grey, (77 R + 150 G + 29 B) >> 8."""
    if img.ndim == 2:
        return img.astype(np.int32)
    i = img.astype(np.int32)
    return (77 * i[..., 0] + 150 * i[..., 1] + 29 * i[..., 2]) >> 8


def census(g: np.ndarray) -> np.ndarray:
    h, w = g.shape
    r = CENSUS_RADIUS
    p = np.pad(g, r, mode="edge")
    code = np.zeros((h, w), np.uint64)
    bit = 0
    for dy in range(-r, r + 1):
        for dx in range(-r, r + 1):
            if dy == 0 and dx == 0:
                continue
            code |= (p[r + dy : r + dy + h, r + dx : r + dx + w] < g).astype(np.uint64) << np.uint64(bit)
            bit += 1
    return code


def popcount(x: np.ndarray) -> np.ndarray:
    c = np.zeros(x.shape, np.int32)
    for k in range(8):
        c += _POP8[((x >> np.uint64(8 * k)) & np.uint64(255)).astype(np.intp)]
    return c


def box_sum(c: np.ndarray) -> np.ndarray:
    """9x9 sums with replicated borders (exact integers)."""
    r = WINDOW_RADIUS
    p = np.pad(c, r, mode="edge").astype(np.int64)
    s = np.zeros((p.shape[0] + 1, p.shape[1] + 1), np.int64)
    s[1:, 1:] = p.cumsum(0).cumsum(1)
    k = 2 * r + 1
    h, w = c.shape
    return (s[k : k + h, k : k + w] - s[:h, k : k + w] - s[k : k + h, :w] + s[:h, :w]).astype(np.int32)


def band_radius(uq: np.ndarray) -> np.ndarray:
    return MIN_BAND + (uq[..., None] > BAND_U_THRESHOLDS).sum(-1)


def div_round(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Half away from zero, as arith::div_round (d > 0 here)."""
    q = (np.abs(n) + d // 2) // d
    return np.where(n < 0, -q, q)


def refine_q(left: np.ndarray, right: np.ndarray, dq: np.ndarray, uq: np.ndarray | None):
    """Integer core: dq (H, W) int Q10.5, uq int Q4.11 or None -> (refined Q10.5 int32, mask)."""
    h, w = dq.shape
    cl, cr = census(grey(left)), census(grey(right))
    dq = dq.astype(np.int32)
    base = dq >> DISP_FRAC
    rad = band_radius(uq.astype(np.int32)) if uq is not None else np.full((h, w), MIN_BAND, np.int32)
    n_off = 2 * MAX_BAND + 2
    big = np.iinfo(np.int32).max
    A = np.full((n_off, h, w), big, np.int32)  # offset o = d - base + MAX_BAND
    lo = base - rad
    hi = base + rad + 1
    xs = np.arange(w)
    for d in range(max(0, int(lo.min())), int(hi.max()) + 1):
        sel = (lo <= d) & (d <= hi)
        if not sel.any():
            continue
        src = np.maximum(xs - d, 0)
        a = box_sum(popcount(cl ^ cr[:, src]))
        o = d - base + MAX_BAND
        ys, xs_ = np.nonzero(sel)
        A[o[ys, xs_], ys, xs_] = a[ys, xs_]
    i = np.argmin(A, axis=0)  # first minimum: the smallest d on ties
    a1 = np.take_along_axis(A, i[None], 0)[0]
    im, ip = np.clip(i - 1, 0, n_off - 1), np.clip(i + 1, 0, n_off - 1)
    a0 = np.where(i > 0, np.take_along_axis(A, im[None], 0)[0], big)
    a2 = np.where(i < n_off - 1, np.take_along_axis(A, ip[None], 0)[0], big)
    ok = (a1 < big) & (a0 < big) & (a2 < big)
    a0_, a1_, a2_ = a0.astype(np.int64), a1.astype(np.int64), a2.astype(np.int64)
    curv = np.where(ok, a0_ + a2_ - 2 * a1_, 0)
    ok &= curv >= MIN_CURVATURE
    if UNIQUENESS:
        # every candidate outside the winner's +-1 neighbourhood must cost UNIQUENESS % more
        o = np.arange(n_off)[:, None, None]
        far = np.abs(o - i[None]) > 1
        a_far = np.where(far, A, big).min(axis=0).astype(np.int64)
        ok &= (a_far == big) | (a_far * 100 >= a1_ * (100 + UNIQUENESS))
    dstar = base + i - MAX_BAND
    off = div_round(16 * (a0_ - a2_), np.maximum(curv, 1))
    refined = np.clip((dstar.astype(np.int64) << DISP_FRAC) + off, -32768, 32767)
    out = np.where(ok, refined, dq).astype(np.int32)
    return out, ok


def quantize_disp(d: np.ndarray) -> np.ndarray:
    """Float px -> Q10.5 (round half away from zero, saturating), as the float engine does."""
    d = d.astype(np.float64)
    v = np.where(np.isfinite(d), d * (1 << DISP_FRAC), 0.0)  # non-finite -> 0, as the Rust side
    return np.clip(np.sign(v) * np.floor(np.abs(v) + 0.5), -32768, 32767).astype(np.int32)


def quantize_u(u: np.ndarray) -> np.ndarray:
    v = u.astype(np.float64) * (1 << LOG_FRAC)
    return np.clip(np.sign(v) * np.floor(np.abs(v) + 0.5), -32768, 32767).astype(np.int32)


def refine(left: np.ndarray, right: np.ndarray, disp: np.ndarray, u: np.ndarray | None = None):
    """Float disparity (px) -> refined float disparity: refined pixels take the integer result /32,
    the others keep their float value. Returns (disparity, mask of the pixels the stage decided)."""
    dq = quantize_disp(disp)
    uq = quantize_u(u) if u is not None else None
    out, ok = refine_q(left, right, dq, uq)
    # As the Rust float engine (Prediction::refine_full_res): a pixel whose refined value equals
    # its rounded input keeps its float value.
    changed = ok & (out != dq)
    return np.where(changed, out.astype(np.float32) / (1 << DISP_FRAC), disp).astype(np.float32), ok
