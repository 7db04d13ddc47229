#!/usr/bin/env python3
"""Regenerates the raw 8-bit stereo pairs of this folder from the shared data set (see README.md).

Usage (from the repository root): python3 boards/qemu-mps2/assets/make_assets.py [DATA_DIR]
DATA_DIR defaults to ../shared/data. Needs Pillow only.
"""
import hashlib
import os
import sys

from PIL import Image

SCENE = "nogt/oakd_cycles"
# (width, height) -> integer box-filter factor from the 640x480 original.
SIZES = {(64, 48): 10, (160, 120): 4}

here = os.path.dirname(os.path.abspath(__file__))
data = sys.argv[1] if len(sys.argv) > 1 else os.path.join(here, "..", "..", "..", "..", "shared", "data")
for view in ("left", "right"):
    src = Image.open(os.path.join(data, SCENE, f"{view}.png"))
    assert src.mode == "L" and src.size == (640, 480), (src.mode, src.size)
    for (w, h), f in SIZES.items():
        img = src.reduce(f)  # mean of each f x f block: rows stay rows, so the pair stays rectified
        assert img.size == (w, h)
        raw = img.tobytes()
        name = f"{view}_{w}x{h}.gray"
        with open(os.path.join(here, name), "wb") as out:
            out.write(raw)
        print(name, len(raw), hashlib.sha256(raw).hexdigest()[:16])
