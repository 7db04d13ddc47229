"""Full-resolution refinement of the network's disparity, bit for bit the Rust stage
(`crates/muir/src/kernels/fullres.rs`, where the algorithm and its constants are specified).

The network's disparity is quantised to the engine's output format (Q10.5, 1/32 px) and its
uncertainty to Q4.11; every pixel is re-matched in a band around it: 7x7 census costs summed over
a 3x3 window, aggregated along five semi-global paths (left, right, top, top-left, top-right) with
penalties that shrink across image edges, winner by least summed cost with an equiangular (V) sub-pixel fit, then a
3x3 median. Vectorised over the image (one cost plane per absolute disparity), integer throughout.

    from muir.fullres import refine
    d_ref, refined_mask = refine(left_rgb_uint8, right_rgb_uint8, disp_float_px, u_float_or_None)
"""
from __future__ import annotations

import numpy as np

CENSUS_RADIUS = 3
WINDOW_RADIUS = 1
BAND_MARGIN = 2  # px added to every band radius (kernels::fullres::BAND_MARGIN)
MIN_BAND = 3 + BAND_MARGIN
MAX_BAND = 12 + BAND_MARGIN
BAND_U_THRESHOLDS = np.array([0, 1178, 2092, 2839, 3470, 4017, 4499, 4931, 5321], np.int32)
P1 = 256  # penalty of a 1 px step along a path
P2 = 2048  # penalty of a larger jump, on a flat image
EDGE_SCALE = 8  # P2 is divided by 1 + |grey step| / EDGE_SCALE (jumps are cheaper across edges)
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
    """(2 WINDOW_RADIUS + 1)^2 sums over the last two axes, replicated borders (exact integers)."""
    r = WINDOW_RADIUS
    pad = [(0, 0)] * (c.ndim - 2) + [(r, r), (r, r)]
    p = np.pad(c, pad, mode="edge").astype(np.int64)
    s = np.zeros(p.shape[:-2] + (p.shape[-2] + 1, p.shape[-1] + 1), np.int64)
    s[..., 1:, 1:] = p.cumsum(-2).cumsum(-1)
    k = 2 * r + 1
    h, w = c.shape[-2:]
    return (s[..., k : k + h, k : k + w] - s[..., :h, k : k + w] - s[..., k : k + h, :w] + s[..., :h, :w]).astype(np.int32)


def band_radius(uq: np.ndarray) -> np.ndarray:
    return MIN_BAND + (uq[..., None] > BAND_U_THRESHOLDS).sum(-1)


def div_round(n: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Half away from zero, as arith::div_round (d > 0 here)."""
    q = (np.abs(n) + d // 2) // d
    return np.where(n < 0, -q, q)


_INF = np.int32(1 << 24)  # outside a pixel's band; far above any path cost (< 2^12)


def penalty2(ga: np.ndarray, gb: np.ndarray) -> np.ndarray:
    """The large-jump penalty between neighbours of grey levels ga, gb (int32 arrays)."""
    return np.maximum(P1 + 1, (P2 * EDGE_SCALE) // (EDGE_SCALE + np.abs(ga - gb)))


def _step(prev: np.ndarray, c: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """One path step: prev, c (D, ...) int32 with _INF outside the band; p2 broadcast (...)."""
    m = prev.min(0)
    inf = np.full_like(prev[:1], _INF)
    nb = np.minimum(np.concatenate([prev[1:], inf], 0), np.concatenate([inf, prev[:-1]], 0)) + P1
    best = np.minimum(np.minimum(prev, nb), (m + p2)[None])
    return np.minimum(c + best - m[None], _INF)


def aggregate(C: np.ndarray, g: np.ndarray) -> np.ndarray:
    """Sum of the five path costs of C (D, H, W) int32, grey g (H, W) int32."""
    D, h, w = C.shape
    S = np.zeros_like(C)
    # left to right, right to left
    for xs in (range(w), range(w - 1, -1, -1)):
        xs = list(xs)
        L = C[:, :, xs[0]].copy()
        S[:, :, xs[0]] += L
        for a, b in zip(xs, xs[1:]):
            L = _step(L, C[:, :, b], penalty2(g[:, b], g[:, a]))
            S[:, :, b] += L
    # top, top-left (predecessor x - 1, clamped), top-right (x + 1, clamped)
    cols = np.arange(w)
    for px in (cols, np.maximum(cols - 1, 0), np.minimum(cols + 1, w - 1)):
        L = C[:, 0].copy()
        S[:, 0] += L
        for y in range(1, h):
            L = _step(L[:, px], C[:, y], penalty2(g[y], g[y - 1, px]))
            S[:, y] += L
    return S


def median3(d: np.ndarray) -> np.ndarray:
    """3x3 median, replicated borders (exact on integers)."""
    h, w = d.shape
    p = np.pad(d, 1, mode="edge")
    stack = np.stack([p[dy : dy + h, dx : dx + w] for dy in range(3) for dx in range(3)])
    return np.sort(stack, axis=0)[4]


def refine_q(left: np.ndarray, right: np.ndarray, dq: np.ndarray, uq: np.ndarray | None):
    """Integer core: dq (H, W) int Q10.5, uq int Q4.11 or None -> (refined Q10.5 int32, mask of
    the pixels the matching decided, before the median)."""
    h, w = dq.shape
    g = grey(left)
    cl, cr = census(g), census(grey(right))
    dq = dq.astype(np.int32)
    base = dq >> DISP_FRAC
    rad = band_radius(uq.astype(np.int32)) if uq is not None else np.full((h, w), MIN_BAND, np.int32)
    lo = np.maximum(base - rad, 0)
    hi = base + rad + 1
    d0 = int(lo.min())
    d1 = max(int(hi.max()), d0)
    D = d1 - d0 + 1
    xs = np.arange(w)
    C = np.empty((D, h, w), np.int32)
    for k in range(D):
        src = np.maximum(xs - (d0 + k), 0)
        C[k] = popcount(cl ^ cr[:, src])
    C = box_sum(C)
    dd = (np.arange(D, dtype=np.int32) + d0)[:, None, None]
    C = np.where((dd >= lo[None]) & (dd <= hi[None]), C, _INF).astype(np.int32)
    S = aggregate(C, g)
    del C
    i = np.argmin(S, axis=0)  # first minimum: the smallest d on ties
    take = lambda j: np.take_along_axis(S, np.clip(j, 0, D - 1)[None], 0)[0].astype(np.int64)
    a0, a1, a2 = take(i - 1), take(i), take(i + 1)
    # S sums five paths of costs < _INF / 8: a value >= _INF means outside the band
    ok = (i > 0) & (i < D - 1) & (a0 < _INF) & (a1 < _INF) & (a2 < _INF)
    curv = a0 + a2 - 2 * a1
    ok &= curv > 0
    # Equiangular (V) fit, as kernels::fullres::decide: divisor max(a0, a2) - a1 >= 1 where ok.
    off = div_round(16 * (a0 - a2), np.maximum(np.maximum(a0 - a1, a2 - a1), 1))
    refined = np.clip(((i + d0).astype(np.int64) << DISP_FRAC) + off, -32768, 32767)
    out = np.where(ok, refined, dq).astype(np.int32)
    return median3(out), ok


def quantize_disp(d: np.ndarray) -> np.ndarray:
    """Float px -> Q10.5 (round half away from zero, saturating), as the float engine does."""
    d = d.astype(np.float64)
    v = np.where(np.isfinite(d), d * (1 << DISP_FRAC), 0.0)  # non-finite -> 0, as the Rust side
    return np.clip(np.sign(v) * np.floor(np.abs(v) + 0.5), -32768, 32767).astype(np.int32)


def quantize_u(u: np.ndarray) -> np.ndarray:
    v = u.astype(np.float64) * (1 << LOG_FRAC)
    return np.clip(np.sign(v) * np.floor(np.abs(v) + 0.5), -32768, 32767).astype(np.int32)


def refine(left: np.ndarray, right: np.ndarray, disp: np.ndarray, u: np.ndarray | None = None):
    """Float disparity (px) -> refined float disparity: pixels the stage changed take the integer
    result / 32, the others keep their float value. Returns (disparity, mask of the pixels the
    matching decided)."""
    dq = quantize_disp(disp)
    uq = quantize_u(u) if u is not None else None
    out, ok = refine_q(left, right, dq, uq)
    # As the Rust float engine (Prediction::refine_full_res): a pixel whose result equals its
    # rounded input keeps its float value.
    changed = out != dq
    return np.where(changed, out.astype(np.float32) / (1 << DISP_FRAC), disp).astype(np.float32), ok
