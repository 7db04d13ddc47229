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
        for k, v in times[1].items():
            if k.startswith("full-res"):
                continue  # --no-refine: the network only, as scripts/speed.py
            one, two = statistics.median(v), statistics.median(times[2][k])
            print(f"| {k} | {one:.1f} | {two:.1f} | {one / two:.2f}x |")


if __name__ == "__main__":
    main()
