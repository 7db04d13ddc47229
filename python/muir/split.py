"""The declared train / held-out split of the ground-truth scenes in ../shared/data (issue #20).

Training may use the GT scenes listed in TRAIN; every headline accuracy figure is measured on HELDOUT,
scenes never trained on. A scene and its copy at another resolution (`*_half`) are the same scene and
sit on the same side. The held-out set has 11 scenes from four sources (Middlebury 2003, Middlebury
2005, ETH3D, KITTI 2015), so it covers a lab set-up the training set also has (Middlebury, other
years, other objects) and two it has not (ETH3D's grey outdoor views, KITTI's road scene).

    PYTHONPATH=python python -m muir.split          # print the split and check it
"""
from __future__ import annotations

import os
import sys

from . import data as D

TRAIN_DATASETS = ("middlebury2001", "middlebury2006", "middlebury2006_half")
HELDOUT_DATASETS = ("middlebury2003", "middlebury2005", "middlebury2005_half", "eth3d_twoview", "kitti2015")

# The held-out headline set: one entry per scene (the *_half copy of Reindeer is the same scene as
# middlebury2005/Reindeer and is left out of the means so no scene counts twice).
HELDOUT_HEADLINE = (
    "middlebury2003/cones", "middlebury2003/teddy",
    "middlebury2005/Art", "middlebury2005/Books", "middlebury2005/Dolls", "middlebury2005/Laundry",
    "middlebury2005/Moebius", "middlebury2005/Reindeer",
    "eth3d_twoview/playground", "eth3d_twoview/terrace",
    "kitti2015/000005_10",
)


def scene_name(key: str) -> str:
    """'middlebury2006_half/Cloth3' -> 'Cloth3' (the identity of a scene across resolutions)."""
    return key.split("/", 1)[1]


def train_scenes(root: str = D.DEFAULT_ROOT):
    """[(dataset, scene)] of the training side, as found under root."""
    return D.list_scenes(root, TRAIN_DATASETS)


def heldout_scenes(root: str = D.DEFAULT_ROOT):
    return D.list_scenes(root, HELDOUT_DATASETS)


def check(root: str = D.DEFAULT_ROOT):
    """Raises ValueError if a scene sits on both sides (by name across resolutions) or a headline
    scene is missing from the held-out side."""
    tr = {f"{d}/{s}" for d, s in train_scenes(root)}
    ho = {f"{d}/{s}" for d, s in heldout_scenes(root)}
    # Middlebury names are unique across years; compare within the Middlebury family only.
    def mb(keys):
        return {scene_name(k).lower() for k in keys if k.startswith("middlebury")}
    both = mb(tr) & mb(ho)
    if both:
        raise ValueError(f"scenes on both sides of the split: {sorted(both)}")
    missing = [k for k in HELDOUT_HEADLINE if k not in ho]
    if missing:
        raise ValueError(f"held-out headline scenes not found under {root}: {missing}")
    return sorted(tr), sorted(ho)


def main():
    tr, ho = check()
    print(f"train ({len(tr)} directories): " + ", ".join(tr))
    print(f"held out ({len(ho)} directories, {len(HELDOUT_HEADLINE)} headline scenes): " + ", ".join(ho))
    return 0


if __name__ == "__main__":
    sys.exit(main())
