#!/usr/bin/env python3
"""Adaptive iterations (issue #21 item 3) on real pairs: the fixed-point engine (`muir run --engine
fixed`, full-resolution refinement on, the shipped blob) with every criterion of a grid and with all
7 iterations, through `python -m muir.evaluate --blob ... [--early-stop P --settled PX]`; prints a
Markdown table of mean iterations used, EPE and Bad2.0 per criterion.

    python3 docs/experiments/adaptive-iterations/sweep.py --set train  --out target/es-train
    python3 docs/experiments/adaptive-iterations/sweep.py --set heldout --out target/es-heldout \
        --grid 300:0.25,500:0.5

`--set train` is the training side's small scenes (Middlebury 2001 and the 2006 half-size copies,
9 scenes) on which a criterion is chosen; `--set heldout` the 11 held-out headline scenes of
`python/muir/split.py`, on which the chosen one is reported. Needs `cargo build --release --bin muir`.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
GRID = "100:0.25,300:0.25,500:0.25,100:0.5,300:0.5,500:0.5,100:1,300:1,500:1"


def run(args, name, extra):
    out = os.path.join(args.out, name)
    res = os.path.join(out, f"{name}.json")
    if not os.path.exists(res):
        sel = ["--datasets", "middlebury2001,middlebury2006_half"] if args.set == "train" else ["--set", "heldout"]
        cmd = [sys.executable, "-m", "muir.evaluate", "--blob", args.blob, "--blob-name", name, "--vis", "0",
               "--out", out, *sel, *extra]
        print("+", " ".join(cmd), file=sys.stderr, flush=True)
        subprocess.run(cmd, check=True, cwd=ROOT, env=dict(os.environ, PYTHONPATH=os.path.join(ROOT, "python")),
                       stdout=subprocess.DEVNULL)
    with open(res) as f:
        r = json.load(f)
    m = r["mean"]["all"]
    m["per_scene"] = r["scenes"]
    return m


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--set", choices=("train", "heldout"), default="train")
    p.add_argument("--blob", default=os.path.join(ROOT, "models", "muir-slim.muirq"))
    p.add_argument("--grid", default=GRID, help="comma list of PER_MILLE:PX criteria")
    p.add_argument("--out", required=True)
    a = p.parse_args()
    a.out = os.path.abspath(a.out)
    rows = [("all 7 iterations", run(a, "full", []))]
    for c in a.grid.split(","):
        pm, px = c.split(":")
        rows.append((f"{pm} per mille at {px} px", run(a, f"es-{pm}-{px}", ["--early-stop", pm, "--settled", px])))
    base = rows[0][1]
    print(f"| criterion ({a.set}, {base['scenes']} scenes) | mean iterations | EPE px | Bad2.0 % | D1 % |")
    print("|---|---:|---:|---:|---:|")
    for name, m in rows:
        print(f"| {name} | {m.get('iters_used', 7):.2f} | {m['all.epe']:.3f} ({m['all.epe'] - base['all.epe']:+.3f}) "
              f"| {m['all.bad2']:.2f} ({m['all.bad2'] - base['all.bad2']:+.2f}) | {m['all.d1']:.2f} |")
    # Per scene, the first criterion of the grid against all 7 iterations.
    name, first = rows[1]
    print(f"\n| scene (size) | iterations, {name} | EPE px, 7 -> adaptive | Bad2.0 %, 7 -> adaptive |")
    print("|---|---:|---:|---:|")
    for key, full in base["per_scene"].items():
        e = first["per_scene"][key]
        print(f"| {key} ({full['size']}) | {e['iters_used']} | {full['all']['epe']:.3f} -> {e['all']['epe']:.3f} "
              f"| {full['all']['bad2']:.2f} -> {e['all']['bad2']:.2f} |")


if __name__ == "__main__":
    main()
