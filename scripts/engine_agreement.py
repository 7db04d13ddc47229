#!/usr/bin/env python3
"""Fixed-point vs float engine on whole real pairs: the 11 held-out scenes of python/muir/split.py
at stored resolution (full-resolution refinement on, as `muir run`), per scene and mean over
scenes: mean |d_fixed - d_float| and the share of pixels within 1 px, for the u8-trunk and the
wide-trunk blob. About 4 minutes on 2 cores.

    cargo build --release --bin muir && python3 scripts/engine_agreement.py [--data ../shared/data]
"""
import argparse
import os
import subprocess
import sys
import tempfile

import numpy as np

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "python"))
from muir import split  # noqa: E402
from muir.data import read_pfm  # noqa: E402


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--data", default=os.path.join(ROOT, "..", "shared", "data"))
    p.add_argument("--muir-bin", default=os.path.join(ROOT, "target", "release", "muir"))
    a = p.parse_args()
    if not os.path.exists(a.muir_bin):
        sys.exit(f"error: {a.muir_bin} missing: cargo build --release --bin muir")
    engines = {
        "float": ["--model", os.path.join(ROOT, "models", "muir-slim.safetensors")],
        "fixed u8": ["--model", os.path.join(ROOT, "models", "muir-slim.muirq")],
        "fixed wide": ["--model", os.path.join(ROOT, "models", "muir-slim-wide.muirq")],
    }
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for i, scene in enumerate(split.HELDOUT_HEADLINE):
            d = os.path.join(a.data, scene)
            left, right = os.path.join(d, "left.png"), os.path.join(d, "right.png")
            if not os.path.exists(left):
                sys.exit(f"error: {left} missing")
            out = {}
            for name, args in engines.items():
                path = os.path.join(tmp, name.replace(" ", "_") + ".pfm")
                r = subprocess.run([a.muir_bin, "run", *args, "--left", left, "--right", right, "--disparity", path],
                                   capture_output=True, text=True)
                if r.returncode != 0:
                    sys.exit(f"error: muir run {scene} ({name}): {r.stderr.strip()}")
                out[name] = read_pfm(path)
            row = [scene]
            for name in ("fixed u8", "fixed wide"):
                e = np.abs(out[name] - out["float"])
                row += [float(e.mean()), 100.0 * float((e <= 1).mean())]
            rows.append(row)
            print(f"[{i + 1}/{len(split.HELDOUT_HEADLINE)}] {scene}", file=sys.stderr)
    print("| scene | u8: mean px | u8: within 1 px | wide: mean px | wide: within 1 px |")
    print("|---|---:|---:|---:|---:|")
    for r in rows:
        print(f"| {r[0]} | {r[1]:.3f} | {r[2]:.2f} % | {r[3]:.3f} | {r[4]:.2f} % |")
    m = np.mean([r[1:] for r in rows], axis=0)
    print(f"| **mean over scenes** | {m[0]:.3f} | {m[1]:.2f} % | {m[2]:.3f} | {m[3]:.2f} % |")


if __name__ == "__main__":
    main()
