#!/usr/bin/env python3
"""Side by side, one stereo pair, the same thread count for each (issue #24 items 3 and 4): the Rust fixed-point
engine, the Rust float engine and the PyTorch twin, run interleaved (round k runs all of them before round
k+1 starts, so a machine that gets busier slows all of them alike), network only (no full-resolution
refinement: the twin has it in numpy, outside the network). Prints a Markdown table of min and
median seconds, the median CPU seconds, the ratios of the medians, and the median (range) of each
round's own ratio to the float engine's run (seconds apart, so less exposed to a machine that
gets busier or quieter over minutes); the Rust times are the CLI's own
`engine:` figure (the frame, not the process start or the PNG writing) and its process's CPU time
(`getrusage` of the child, so it includes loading the model and the PNGs), the twin's the forward pass
(no trace) after one warm-up and its process CPU time over that pass.

    python3 scripts/speed.py [--pair assets/teddy] [--rounds 5] [--model models/muir-slim.safetensors]
                             [--blob models/muir-slim.muirq] [--threads N]
                             [--config NAME [--seed S]] [--size WxH] [--no-fixed] [--baseline OLD_MUIR]

`--threads N` (default 1): PyTorch's intra-op threads and `muir run --threads N` (the float
engine's matrix products; the fixed-point engine's kernel pool: convolution rows, attention,
correlation lookup). A list (`--threads 1,2`) runs every engine at each count in every round and
adds a table of each engine's speed-up over the first count: the median over the rounds of the
ratio within a round (runs a few seconds apart), and the ratio of the medians. On a shared
machine this is the figure to quote: separate invocations for 1 and 2 threads run minutes apart,
and the two-thread runs are the ones a busy neighbour slows most.

`--config NAME` (e.g. `raft-stereo-realtime`): instead of `--model`, seeded weights for that config
(`python/muir/seeded.py`, the same values `src/float/seeded.rs` makes; seed `--seed`, default 11),
written to `target/speed-out/NAME-seedS.safetensors` and run by both the float engine and the twin. There
is no fixed-point model for such weights, so the fixed engine is left out unless `--blob` is named.
`--size WxH`: the pair's top-left WxH crop (written to `target/speed-out/`), e.g. `--size 384x288`
for the issue's `raft-stereo-realtime` case. `--no-fixed` leaves the fixed engine out.
`--baseline OLD_MUIR`: another `muir` binary whose float engine runs in every round too (an
interleaved A/B of two builds; copy the old `target/release/muir` aside before rebuilding).
`--repeat R`: the steady state, as a camera pipeline or the twin in this process sees it. Each
`muir run` gets `--repeat R` (R more frames on the same engine and buffers after the first, the
same bits checked) and its figure is the median of those R frames; the twin's is the median of R
passes in the round. The first frames (a fresh process each: memory the OS maps and zeroes on
first touch, the host kernels' weights re-laid) get a table of their own, and the CPU column is
then the process's CPU time over its R + 1 frames. Without it (the default) each Rust figure is
a fresh process's first frame while the twin's passes follow a warm-up: the Rust engines pay
one-time costs the twin does not.

Examples (issue #24 item 3's figure):

    OMP_NUM_THREADS=1 python3 scripts/speed.py --rounds 7
    python3 scripts/speed.py --config raft-stereo-realtime --size 384x288 --rounds 7 --threads 2
    python3 scripts/speed.py --threads 1,2 --rounds 7   # issue #24's two-thread figure
    python3 scripts/speed.py --threads 1,2 --rounds 7 --repeat 3   # the same in the steady state

Needs a release build (`cargo build --release --bin muir`) and the twin (python/README.md).
"""
from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import time

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
# Seconds to wait after each PyTorch pass before the next run (see `settle`).
PAUSE_S = 1.0
OUT = os.path.join(ROOT, "target", "speed-out")


def child_cpu() -> float:
    r = resource.getrusage(resource.RUSAGE_CHILDREN)
    return r.ru_utime + r.ru_stime


def rust_seconds(muir: str, model: str, pair: str, threads: int, repeat: int = 0) -> tuple[float, float, float | None]:
    """(the first frame's wall seconds as the CLI prints them, the process's CPU seconds, and
    with `repeat` the median of the repeated frames' seconds)."""
    cmd = [muir, "run", "--model", model, "--left", os.path.join(pair, "left.png"),
           "--right", os.path.join(pair, "right.png"), "--no-refine", "--threads", str(threads),
           "--out-dir", OUT] + (["--repeat", str(repeat)] if repeat else [])
    c0 = child_cpu()
    r = subprocess.run(cmd, capture_output=True, text=True)
    cpu = child_cpu() - c0
    if r.returncode != 0:
        sys.exit(f"error: {' '.join(cmd)}: {r.stderr.strip()}")
    m = re.search(r"engine: ([0-9.]+) s", r.stderr)
    if not m:
        sys.exit(f"error: no 'engine: N s' in the output of {' '.join(cmd)}:\n{r.stderr}")
    warm = None
    if repeat:
        w = re.search(r"repeated frame\(s\), the same bits as the first: min [0-9.]+ s, median ([0-9.]+) s", r.stderr)
        if not w:
            sys.exit(f"error: no repeated frames' times in the output of {' '.join(cmd)}:\n{r.stderr}")
        warm = float(w.group(1))
    return float(m.group(1)), cpu, warm


def spread(num: list[float], den: list[float], unit: str = "") -> str:
    """The median (range) of the rounds' own ratios `num[k] / den[k]`."""
    r = [x / y for x, y in zip(num, den)]
    return f"{statistics.median(r):.2f}{unit} ({min(r):.2f}-{max(r):.2f})"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--pair", default=os.path.join(ROOT, "assets", "teddy"), help="folder with left.png, right.png")
    p.add_argument("--rounds", type=int, default=5)
    p.add_argument("--model", default=os.path.join(ROOT, "models", "muir-slim.safetensors"))
    p.add_argument("--blob", default=None, help="fixed-point model (default models/muir-slim.muirq without --config)")
    p.add_argument("--threads", default="1", help="1 to 4, or a list such as 1,2 (muir run --threads; torch.set_num_threads)")
    p.add_argument("--config", default=None, help="seeded weights of this config preset instead of --model")
    p.add_argument("--seed", type=int, default=11, help="seed of the --config weights")
    p.add_argument("--size", default=None, help="WxH: the top-left crop of the pair")
    p.add_argument("--no-fixed", action="store_true", help="leave the fixed-point engine out")
    p.add_argument("--baseline", default=None, help="another muir binary, its float engine run in every round too")
    p.add_argument("--repeat", type=int, default=0, help="steady state: R more frames per muir run (muir run --repeat R), R twin passes per round")
    a = p.parse_args(argv)
    try:
        counts = [int(t) for t in a.threads.split(",")]
    except ValueError:
        sys.exit(f"error: --threads {a.threads}: expected a count or a list such as 1,2")
    if not counts or not all(1 <= t <= 4 for t in counts) or len(set(counts)) != len(counts):
        sys.exit("error: --threads must be distinct counts of 1 to 4")
    muir = os.path.join(ROOT, "target", "release", "muir")
    if not os.path.exists(muir):
        sys.exit("error: target/release/muir missing: cargo build --release --bin muir")
    if a.baseline and not os.path.exists(a.baseline):
        sys.exit(f"error: {a.baseline}: no such file")
    if a.rounds < 1:
        sys.exit("error: --rounds must be at least 1")
    if not 0 <= a.repeat <= 100:
        sys.exit("error: --repeat must be 0 to 100")
    blob = a.blob if a.blob else (None if a.config else os.path.join(ROOT, "models", "muir-slim.muirq"))
    if a.no_fixed:
        blob = None

    sys.path.insert(0, os.path.join(ROOT, "python"))
    import numpy as np
    import torch
    from PIL import Image

    from muir.checkpoint import load_model, save_model
    from muir.config import preset
    from muir.model import MUIR
    from muir import seeded

    torch.set_num_threads(counts[0])
    os.makedirs(OUT, exist_ok=True)
    model_path = a.model
    if a.config:
        model = MUIR(preset(a.config)).eval()
        model.load_state_dict(seeded.state_dict(model, a.seed), strict=True)
        model_path = os.path.join(OUT, f"{a.config}-seed{a.seed}.safetensors")
        save_model(model, model_path)
    else:
        model = load_model(a.model).eval()
    left_im = Image.open(os.path.join(a.pair, "left.png")).convert("RGB")
    right_im = Image.open(os.path.join(a.pair, "right.png")).convert("RGB")
    pair = a.pair
    if a.size:
        w, h = (int(v) for v in a.size.lower().split("x"))
        if w > left_im.width or h > left_im.height:
            sys.exit(f"error: --size {a.size} is larger than the pair ({left_im.width}x{left_im.height})")
        left_im, right_im = left_im.crop((0, 0, w, h)), right_im.crop((0, 0, w, h))
        pair = os.path.join(OUT, f"{os.path.basename(os.path.normpath(a.pair))}-{w}x{h}")
        os.makedirs(pair, exist_ok=True)
        left_im.save(os.path.join(pair, "left.png"))
        right_im.save(os.path.join(pair, "right.png"))
    left, right = np.asarray(left_im), np.asarray(right_im)

    pad = model.cfg.pad_multiple
    ph, pw = (-left.shape[0]) % pad, (-left.shape[1]) % pad

    def prep(img):
        t = torch.from_numpy(img.copy()).permute(2, 0, 1)[None].float()
        return torch.nn.functional.pad(t, (0, pw, 0, ph), mode="replicate") if (ph or pw) else t

    lt, rt = prep(left), prep(right)

    def twin():
        with torch.inference_mode():
            model(lt, rt)

    def settle():
        # PyTorch's OpenMP workers spin for a while after a parallel region before they sleep:
        # a `muir` run started at once shares the cores with them (with 2 threads, 640x480: 0.44
        # s instead of 0.39 s). Each Rust run starts on a quiet machine instead.
        time.sleep(PAUSE_S)

    engines = (["muir fixed-point engine"] if blob else []) + ["muir float engine"]
    engines += ["muir float engine (baseline)"] if a.baseline else []
    engines += ["PyTorch twin"]
    # times[(engine, threads)]: one entry a round.
    times = {(n, t): [] for t in counts for n in engines}
    cpus = {(n, t): [] for t in counts for n in engines}
    # With --repeat: the Rust engines' first frames (fresh processes).
    first = {(n, t): [] for t in counts for n in engines if n != "PyTorch twin"}
    for t in counts:  # warm-up at each count
        torch.set_num_threads(t)
        twin()
        settle()
    runs = []
    if blob:
        runs.append(("muir fixed-point engine", muir, blob))
    runs.append(("muir float engine", muir, model_path))
    if a.baseline:
        runs.append(("muir float engine (baseline)", a.baseline, model_path))
    for k in range(a.rounds):
        # Alternate the order of the thread counts and of the Rust runs from round to round.
        for t in (counts if k % 2 == 0 else counts[::-1]):
            for n, binary, m in (runs if k % 2 == 0 else runs[::-1]):
                s, c, warm = rust_seconds(binary, m, pair, t, a.repeat)
                first[(n, t)].append(s)
                times[(n, t)].append(warm if a.repeat else s)
                cpus[(n, t)].append(c / (a.repeat + 1))
            torch.set_num_threads(t)
            passes = []
            for _ in range(max(a.repeat, 1)):
                c0, t0 = time.process_time(), time.perf_counter()
                twin()
                passes.append((time.perf_counter() - t0, time.process_time() - c0))
            passes.sort()
            times[("PyTorch twin", t)].append(passes[len(passes) // 2][0])
            cpus[("PyTorch twin", t)].append(passes[len(passes) // 2][1])
            settle()
            print(f"round {k + 1}/{a.rounds}, {t} thread(s): " + ", ".join(f"{n} {times[(n, t)][-1]:.3f} s" for n in engines), file=sys.stderr)

    h, w = left.shape[:2]
    med = {key: statistics.median(v) for key, v in times.items()}
    what = f"{a.config} seeded weights (seed {a.seed})" if a.config else os.path.basename(model_path)
    state = (f", steady state (median of {a.repeat} frames after the first in each muir process, "
             f"of {a.repeat} twin passes in each round)") if a.repeat else ""
    for t in counts:
        print(f"{os.path.basename(os.path.normpath(a.pair))} {w}x{h}, {what}, {t} thread(s), "
              f"{a.rounds} interleaved rounds, network only{state}\n")
        print("| engine | min s | median s | median CPU s | median / float engine | median / PyTorch | / float engine, rounds' ratios |")
        print("|---|---:|---:|---:|---:|---:|---:|")
        for n in engines:
            v = times[(n, t)]
            print(f"| {n} | {min(v):.3f} | {med[(n, t)]:.3f} | {statistics.median(cpus[(n, t)]):.3f} | "
                  f"{med[(n, t)] / med[('muir float engine', t)]:.2f} | {med[(n, t)] / med[('PyTorch twin', t)]:.2f} | "
                  f"{spread(v, times[('muir float engine', t)])} |")
        print()
    if a.repeat:
        print("The Rust engines' first frames (a fresh process each), s\n")
        print("| engine | threads | min s | median s | median / float engine's |")
        print("|---|---:|---:|---:|---:|")
        for (n, t), v in first.items():
            print(f"| {n} | {t} | {min(v):.3f} | {statistics.median(v):.3f} | "
                  f"{statistics.median(v) / statistics.median(first[('muir float engine', t)]):.2f} |")
        print()
    if len(counts) > 1:
        t1 = counts[0]
        print(f"Speed-up over {t1} thread(s): the median (range) of the rounds' own ratios, and the ratio of the medians\n")
        print("| engine | " + " | ".join(f"{t} threads: rounds' ratios | {t} threads: medians' ratio" for t in counts[1:]) + " |")
        print("|---|" + "---:|---:|" * (len(counts) - 1))
        for n in engines:
            cells = [f"{spread(times[(n, t1)], times[(n, t)], 'x')} | {med[(n, t1)] / med[(n, t)]:.2f}x" for t in counts[1:]]
            print(f"| {n} | " + " | ".join(cells) + " |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
