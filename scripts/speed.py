#!/usr/bin/env python3
"""Side by side, one stereo pair, the same thread count for each (issue #24 item 4): the Rust fixed-point engine,
the Rust float engine and the PyTorch twin, run interleaved (round k runs all three before round
k+1 starts, so a machine that gets busier slows all of them alike), network only (no full-resolution
refinement: the twin has it in numpy, outside the network). Prints a Markdown table of min and
median seconds and the ratios of the medians; the Rust times are the CLI's own `engine:` figure
(the frame, not the process start or the PNG writing), the twin's the forward pass after one warm-up.

    python3 scripts/speed.py [--pair assets/teddy] [--rounds 5] [--model models/muir-slim.safetensors]
                             [--blob models/muir-slim.muirq] [--threads N]

`--threads N` (default 1): PyTorch's intra-op threads and `muir run --threads N` (the float
engine's matrix products; the fixed-point engine's kernel pool: convolution rows, attention,
correlation lookup).

Needs a release build (`cargo build --release --bin muir`) and the twin (python/README.md).
"""
from __future__ import annotations

import argparse
import os
import re
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def rust_seconds(muir: str, model: str, pair: str, threads: int) -> float:
    cmd = [muir, "run", "--model", model, "--left", os.path.join(pair, "left.png"),
           "--right", os.path.join(pair, "right.png"), "--no-refine", "--threads", str(threads),
           "--out-dir", os.path.join(ROOT, "target", "speed-out")]
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)}: {r.stderr.strip()}")
    m = re.search(r"engine: ([0-9.]+) s", r.stderr)
    if not m:
        sys.exit(f"error: no 'engine: N s' in the output of {' '.join(cmd)}:\n{r.stderr}")
    return float(m.group(1))


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pair", default=os.path.join(ROOT, "assets", "teddy"), help="folder with left.png, right.png")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--model", default=os.path.join(ROOT, "models", "muir-slim.safetensors"))
    p.add_argument("--blob", default=os.path.join(ROOT, "models", "muir-slim.muirq"))
    p.add_argument("--threads", type=int, default=1, help="1 to 4 (muir run --threads; torch.set_num_threads)")
    a = p.parse_args(argv)
    if not 1 <= a.threads <= 4:
        sys.exit("error: --threads must be 1 to 4")
    muir = os.path.join(ROOT, "target", "release", "muir")
    if not os.path.exists(muir):
        sys.exit("error: target/release/muir missing: cargo build --release --bin muir")
    if a.rounds < 1:
        sys.exit("error: --rounds must be at least 1")

    sys.path.insert(0, os.path.join(ROOT, "python"))
    import numpy as np
    import torch
    from PIL import Image

    from muir.checkpoint import load_model
    from muir.evaluate import run_model

    torch.set_num_threads(a.threads)
    model = load_model(a.model).eval()
    left = np.asarray(Image.open(os.path.join(a.pair, "left.png")).convert("RGB"))
    right = np.asarray(Image.open(os.path.join(a.pair, "right.png")).convert("RGB"))
    run_model(model, left, right)  # warm-up

    times = {"muir fixed-point engine": [], "muir float engine": [], "PyTorch twin": []}
    for k in range(a.rounds):
        times["muir fixed-point engine"].append(rust_seconds(muir, a.blob, a.pair, a.threads))
        times["muir float engine"].append(rust_seconds(muir, a.model, a.pair, a.threads))
        t0 = time.perf_counter()
        run_model(model, left, right)
        times["PyTorch twin"].append(time.perf_counter() - t0)
        print(f"round {k + 1}/{a.rounds}: " + ", ".join(f"{n} {v[-1]:.2f} s" for n, v in times.items()), file=sys.stderr)

    h, w = left.shape[:2]
    med = {n: statistics.median(v) for n, v in times.items()}
    print(f"{os.path.basename(os.path.normpath(a.pair))} {w}x{h}, {os.path.basename(a.model)}, {a.threads} thread(s), "
          f"{a.rounds} interleaved rounds, network only\n")
    print("| engine | min s | median s | median / float engine | median / PyTorch |")
    print("|---|---:|---:|---:|---:|")
    for n, v in times.items():
        print(f"| {n} | {min(v):.2f} | {med[n]:.2f} | {med[n] / med['muir float engine']:.2f} | {med[n] / med['PyTorch twin']:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
