"""The declared split, and the full-resolution refinement's integer helpers."""
from __future__ import annotations

import math
import os

import numpy as np
import pytest

from muir import data as D
from muir import fullres, split


@pytest.mark.skipif(not os.path.isdir(D.DEFAULT_ROOT), reason="../shared/data absent")
def test_split_is_disjoint_and_holds_out_enough():
    tr, ho = split.check()
    assert len(split.HELDOUT_HEADLINE) >= 10
    assert len({k.split("/")[0].split("_")[0] for k in split.HELDOUT_HEADLINE}) >= 2
    names = lambda keys: {split.scene_name(k).lower() for k in keys if k.startswith("middlebury")}
    assert not names(tr) & names(ho)


def test_band_thresholds_match_their_formula():
    for i, t in enumerate(fullres.BAND_U_THRESHOLDS):
        r = fullres.MIN_BAND - fullres.BAND_MARGIN + 1 + i
        assert t == math.floor(2 * math.log((r - 1) / 3) * 2048)
    m = fullres.BAND_MARGIN
    assert fullres.band_radius(np.array([-100, 0, 1, 32767])).tolist() == [3 + m, 3 + m, 4 + m, 12 + m]


def test_div_round_is_half_away_from_zero():
    n = np.array([5, -5, 7, -7, 6, -6])
    d = np.array([2, 2, 2, 2, 4, 4])
    assert fullres.div_round(n, d).tolist() == [3, -3, 4, -4, 2, -2]


def test_quantisation_rounds_and_saturates():
    d = np.array([0.015625, -0.015625, 2000.0, np.nan, np.inf], np.float32)  # 1/64 px
    assert fullres.quantize_disp(d).tolist() == [1, -1, 32767, 0, 0]


def test_recovers_a_known_shift():
    h, w, d_true = 40, 96, 10.25
    y, x = np.mgrid[0:h, 0:w].astype(np.float64)
    tex = lambda xx: 128 + 60 * np.sin(xx * 0.7) * np.cos(y * 0.45 + 1) + 40 * np.sin(xx * 0.23 + y * 0.31)
    left = tex(x).astype(np.uint8)
    right = tex(x + d_true).astype(np.uint8)
    d0 = np.full((h, w), d_true + 2.4, np.float32)
    u = np.full((h, w), 2 * math.log(1.2), np.float32)
    out, ok = fullres.refine(left, right, d0, u)
    # (the parabola through aggregated path costs pulls towards whole pixels)
    assert ok[20, 40] and abs(out[20, 40] - d_true) < 0.25
    # a textureless pair: nothing decided, the network's values stay
    flat = np.full((h, w), 128, np.uint8)
    out, ok = fullres.refine(flat, flat, d0, u)
    assert not ok.any() and (out == d0).all()
