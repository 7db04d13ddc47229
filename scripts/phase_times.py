#!/usr/bin/env python3
"""The fixed engine's time per phase on 1 and 2 threads (issue #24): `muir run --timings`, rounds
alternating the thread counts, medians; prints one Markdown table per pair (docs/performance.md,
"time by phase and thread count").

    python3 scripts/phase_times.py [--rounds 3] [--pair assets/teddy --pair ../shared/data/nogt/oakd_corridor ...]

Needs a release build (`cargo build --release --bin muir`); time only on an otherwise idle machine.
"""
from __future__ import annotations

import argparse
import collections
import os
import re
import statistics
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# With two threads the refinement runs in two streams (`engine::side`): UFI beside the MGA setup,
# and per iteration MUD, the MGA values and the aggregation beside the 1/16 and 1/8 ConvGRUs; the
# timer then books those under the first phase of each group, so the table compares the groups.
GROUPS = [
    ("encoders", ["encoders"]),
    ("ufi + mga setup", ["ufi", "mga setup"]),
    ("mud + mga values + gru16 + motion + mga + gru08", ["mud", "mga values", "gru16", "motion + mga + gru08"]),
    ("flow head", ["flow head"]),
    ("final mud + upsample", ["final mud + upsample"]),
    ("frame", ["frame"]),
]
PAIRS = ["assets/teddy", "../shared/data/nogt/oakd_corridor", "../shared/data/kitti2015/000005_10"]


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--pair", action="append", default=None, help="folder with left.png and right.png (repeatable)")
    p.add_argument("--rounds", type=int, default=3)
    p.add_argument("--blob", default="models/muir-slim.muirq")
    p.add_argument("--muir", default="target/release/muir")
    a = p.parse_args()
    out = os.path.join(ROOT, "target", "phase-times")
    for pair in a.pair or PAIRS:
        times = {1: collections.defaultdict(list), 2: collections.defaultdict(list)}
        for r in range(a.rounds):
            for t in (1, 2):
                cmd = [a.muir, "run", "--model", a.blob, "--left", os.path.join(pair, "left.png"),
                       "--right", os.path.join(pair, "right.png"), "--no-refine", "--timings", "--threads", str(t),
                       "--out-dir", out]
                r = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
                if r.returncode != 0:
                    raise SystemExit(f"{' '.join(cmd)}: {r.stderr.strip()}")
                for line in r.stderr.splitlines():
                    m = re.match(r"muir:\s+(.+?)\s+([\d.]+) ms", line)
                    if m:
                        times[t][m.group(1)].append(float(m.group(2)))
        print(f"\n{pair} ({a.rounds} rounds, medians)\n\n| phase | 1 thread ms | 2 threads ms | speed-up |\n|---|---:|---:|---:|")
        for label, names in GROUPS:
            one = sum(statistics.median(times[1][k]) for k in names if k in times[1])
            two = sum(statistics.median(times[2][k]) for k in names if k in times[2])
            print(f"| {label} | {one:.1f} | {two:.1f} | {one / two:.2f}x |" if two > 0 else f"| {label} | {one:.1f} | {two:.1f} | – |")

if __name__ == "__main__":
    main()
