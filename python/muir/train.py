"""Train the MUIR twin on synthetic stereo (muir.synth), on CPU or CUDA.

    PYTHONPATH=python python -m muir.train --config muir-slim --out runs/slim --steps 10000 \\
        --batch 4 --crop 160x384 --lr 2e-4
    PYTHONPATH=python python -m muir.train --out runs/slim --resume      # continue after a stop

Loss (paper Eq. 7, gamma = 0.9) over the N full-resolution predictions of forward(train_out=True)
(index 0 = UFI initial disparity), prediction i weighted gamma^(N-1-i):
    |d - gt| + u/2 + exp(-u/2) * clamp(|d.detach() - gt|, eps_min, eps_max)
plus the mean of the same per-pixel loss over the 3 UFI candidates, weighted like prediction 0.
Everything is averaged over valid GT pixels (finite, 0 <= gt < 512). The mask is binarised at random
(Eq. 3, binarize_p = 0.5). AdamW + one-cycle (linear anneal), grad-norm clip 1.0.

Run dir: ckpt_last.pt (model + optimizer + scheduler + step + RNG, for --resume), snapshot_XXXXXX.safetensors
every --ckpt-every steps, log.csv, loss.png and, at the end, model.safetensors (with training info in the
metadata). Progress goes to stderr. SIGINT/SIGTERM save a checkpoint before exiting.
"""
from __future__ import annotations

import argparse
import csv
import datetime
import json
import math
import os
import random
import signal
import subprocess
import sys
import time
import warnings

import numpy as np
import torch
import torch.nn as nn

from .checkpoint import save_model
from .config import PRESETS, Config, preset
from .model import MUIR, MultiBasicEncoder
from . import synth

MAX_GT = 512.0


# ------------------------------------------------------------------------------------------------
# Data
# ------------------------------------------------------------------------------------------------
class SynthDataset(torch.utils.data.Dataset):
    """Item i is synthetic sample i of stream `seed` (deterministic), as float tensors; with
    proxy_frac > 0 a seeded share of the items are real crops with proxy labels instead."""

    def __init__(self, seed: int, h: int, w: int, length: int, proxy_frac: float = 0.0, real_frac: float = 0.0):
        self.seed, self.h, self.w, self.length = seed, h, w, length
        self.proxy_frac = proxy_frac
        self.real_frac = real_frac

    def __len__(self):
        return self.length

    def __getitem__(self, i):
        # With --proxy-frac, item i is a real crop with SGBM proxy labels (muir.proxy) when its own coin
        # says so; the coin and the crop are functions of (seed, i), so a resume sees the same data.
        rng = np.random.default_rng([int(self.seed) & 0xFFFFFFFF, int(i), 0x9E37])
        coin = rng.random()
        if self.real_frac > 0 and coin < self.real_frac:
            # --real-frac: a crop of a training-side GT scene (muir.split, muir.realgt).
            from . import realgt

            s = realgt.pool().sample(rng, self.h, self.w)
        elif self.proxy_frac > 0 and coin - self.real_frac < self.proxy_frac:
            from . import proxy

            s = proxy.pool().sample(rng, self.h, self.w)
        else:
            s = synth.sample(self.seed, int(i), self.h, self.w)
        left = torch.from_numpy(s["left"]).permute(2, 0, 1).float()
        right = torch.from_numpy(s["right"]).permute(2, 0, 1).float()
        disp = torch.from_numpy(s["disp"])[None]
        return left, right, disp


class RangeSampler(torch.utils.data.Sampler):
    """Indices start, start+1, ..., end-1: step k always sees samples k*B .. k*B+B-1, so a resumed run
    sees the same data as an uninterrupted one."""

    def __init__(self, start: int, end: int):
        self.start, self.end = start, end

    def __iter__(self):
        return iter(range(self.start, self.end))

    def __len__(self):
        return self.end - self.start


class StepSampler(torch.utils.data.Sampler):
    """This process's share of the global batches of steps start .. end-1: step k uses samples
    k*B .. k*B+B-1 whatever the number of processes, rank r of W taking the r-th slice of B/W. With
    W = 1 it is [`RangeSampler`]'s order; a data-parallel run sees the same samples per step as a
    single process."""

    def __init__(self, start_step: int, end_step: int, batch: int, world: int = 1, rank: int = 0):
        self.start, self.end, self.batch, self.world, self.rank = start_step, end_step, batch, world, rank
        self.per = batch // world

    def __iter__(self):
        for k in range(self.start, self.end):
            base = k * self.batch + self.rank * self.per
            yield from range(base, base + self.per)

    def __len__(self):
        return (self.end - self.start) * self.per


def binarize_coins(seed: int, step: int, batch: int, iters: int, p: float) -> torch.Tensor:
    """Mask-binarisation coins (Eq. 3) of one step's global batch, (batch, iters) in {0, 1}: a
    function of (seed, step), so every process of a data-parallel run draws the same coins."""
    rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, int(step), 0xB1A5])
    return torch.from_numpy((rng.random((batch, iters)) < p).astype(np.float32))


def _worker_init(_):
    torch.set_num_threads(1)
    import cv2

    cv2.setNumThreads(1)
    synth.photo_pool()  # load the texture photographs once per worker


# ------------------------------------------------------------------------------------------------
# Loss
# ------------------------------------------------------------------------------------------------
def pixel_loss(d, u, gt, cfg: Config):
    """Per-pixel Eq. 7 term: L1 + constrained Laplacian NLL (d detached inside L^u)."""
    err = (d - gt).abs()
    if u is None:
        return err
    e = (d.detach() - gt).abs().clamp(cfg.eps_min, cfg.eps_max)
    return err + u / 2 + torch.exp(-u / 2) * e


def sequence_loss(out, gt, valid, cfg: Config, gamma: float = 0.9, denom=None):
    """Returns (loss, metrics dict). out: forward(train_out=True); gt, valid: (B,1,H,W).

    denom: the number of valid pixels to average over (default: those of this batch). A
    data-parallel process passes the count over the whole global batch, so that its loss and
    metrics are its share of the single-process figures and their sum over processes is them."""
    preds, us = out["disp"], out["u"]
    n = len(preds)
    vf = valid.float()
    denom = vf.sum().clamp(min=1.0) if denom is None else denom
    gt0 = torch.where(valid, gt, torch.zeros_like(gt))  # keep inf/nan out of the graph

    def masked_mean(x):
        return (x * vf).sum() / denom

    total = 0.0
    for i, d in enumerate(preds):
        u = us[i] if us is not None else None
        total = total + gamma ** (n - 1 - i) * masked_mean(pixel_loss(d, u, gt0, cfg))
    cand = 0.0
    if out.get("cand_disp") is not None:
        cd, cu = out["cand_disp"], out["cand_u"]
        k = cd.shape[1]
        cand = sum(masked_mean(pixel_loss(cd[:, j : j + 1], cu[:, j : j + 1], gt0, cfg)) for j in range(k)) / k
        total = total + gamma ** (n - 1) * cand
    with torch.no_grad():
        err = (preds[-1] - gt0).abs()
        m = {
            "epe": masked_mean(err).item(),
            "epe0": masked_mean((preds[0] - gt0).abs()).item(),
            "bad1": masked_mean((err > 1).float()).item(),
            "bad3": masked_mean((err > 3).float()).item(),
        }
        if us is not None:
            m["pred_err"] = masked_mean(torch.exp(us[-1] / 2)).item()  # mean predicted error (px)
        if out.get("cand_disp") is not None:
            m["cand"] = float(cand)
    return total, m


def consistency_loss(out_q, out_f, gamma: float = 0.9):
    """Quantisation-aware term: mean |d_rounded - d_float| over all pixels (float detached), for every
    prediction with the sequence loss's weights. It asks for agreement where the answer is wrong too,
    which the ground-truth loss alone does not."""
    dq, df = out_q["disp"], out_f["disp"]
    n = len(dq)
    return sum(gamma ** (n - 1 - i) * (a - b.detach()).abs().mean() for i, (a, b) in enumerate(zip(dq, df)))


# ------------------------------------------------------------------------------------------------
# Model set-up
# ------------------------------------------------------------------------------------------------
def init_weights(model: MUIR):
    """RAFT-Stereo's initialisation of the context/feature encoder (MultiBasicEncoder): Kaiming-normal
    (fan_out, relu) convolutions, unit/zero norm affine. Other modules keep PyTorch defaults (as in
    RAFT-Stereo). BatchNorm stays frozen at its initial statistics (the twin's train() freezes it)."""
    for mod in model.modules():
        if isinstance(mod, MultiBasicEncoder):
            for m in mod.modules():
                if isinstance(m, nn.Conv2d):
                    nn.init.kaiming_normal_(m.weight, mode="fan_out", nonlinearity="relu")
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)
                elif isinstance(m, (nn.BatchNorm2d, nn.InstanceNorm2d)):
                    if m.weight is not None:
                        nn.init.ones_(m.weight)
                    if m.bias is not None:
                        nn.init.zeros_(m.bias)


class ThreadTuner:
    """Picks the torch thread count at run time (--threads auto). On a shared machine a nice'd run with
    2 OpenMP threads stalls when one core is taken by another job: the team waits at every barrier for
    the starved thread (measured 10.7 s/step vs 1.8 s idle). Now and then it runs `probe` steps with the
    other candidate count and keeps whichever had the lower median step time; the interval between
    probes starts at `period` steps and doubles (up to 8x) while probes lose."""

    def __init__(self, max_threads: int, period: int = 60, probe: int = 6):
        self.cands = sorted({1, max(1, max_threads)}, reverse=True)
        self.main = self.cands[0]
        self.period, self.probe = period, probe
        self.times = {c: [] for c in self.cands}
        self.probe_times = []
        self.n = 0
        self.probing = None
        self.interval = period
        self.next_probe = period
        torch.set_num_threads(self.main)

    @property
    def current(self) -> int:
        return self.probing if self.probing is not None else self.main

    def record(self, dt: float):
        if len(self.cands) < 2:
            return
        self.n += 1
        if self.probing is not None:
            self.probe_times.append(dt)
            if len(self.probe_times) >= self.probe:
                alt = float(np.median(self.probe_times[1:]))  # first probe step: warm-up
                cur = float(np.median(self.times[self.main][-20:])) if self.times[self.main] else float("inf")
                if alt < cur:
                    self.times[self.probing] = list(self.probe_times[1:])
                    self.main = self.probing
                    self.interval = self.period
                else:  # a losing probe costs time: probe less often while the choice holds
                    self.interval = min(8 * self.period, 2 * self.interval)
                self.next_probe = self.n + self.interval
                self.probing = None
                self.probe_times = []
                torch.set_num_threads(self.main)
            return
        self.times[self.main].append(dt)
        if self.n >= self.next_probe:
            self.probing = next(c for c in self.cands if c != self.main)
            torch.set_num_threads(self.probing)


def git_commit() -> str:
    try:
        here = os.path.dirname(os.path.abspath(__file__))
        r = subprocess.run(["git", "rev-parse", "HEAD"], cwd=here, capture_output=True, text=True, timeout=10)
        c = r.stdout.strip()
        d = subprocess.run(["git", "status", "--porcelain"], cwd=here, capture_output=True, text=True, timeout=10)
        return c + ("-dirty" if d.stdout.strip() else "") if c else "unknown"
    except Exception:
        return "unknown"


def parse_hw(s: str):
    try:
        h, w = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW, got {s!r}")
    if h % 16 or w % 16 or h <= 0 or w <= 0:
        raise argparse.ArgumentTypeError(f"crop sides must be positive multiples of 16, got {s}")
    return h, w


# ------------------------------------------------------------------------------------------------
# Logging helpers
# ------------------------------------------------------------------------------------------------
CSV_FIELDS = ["step", "lr", "loss", "epe", "epe0", "bad1", "bad3", "pred_err", "cand", "qat_diff", "step_s", "data_s", "time"]


def plot_curves(csv_path: str, png_path: str):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = list(csv.DictReader(open(csv_path)))
    if not rows:
        return
    step = np.array([float(r["step"]) for r in rows])

    def col(k):
        return np.array([float(r[k]) if r.get(k) not in (None, "") else np.nan for r in rows])

    fig, ax = plt.subplots(1, 3, figsize=(15, 4))
    for k in ("loss",):
        ax[0].plot(step, col(k), label=k)
    ax[0].set_yscale("log")
    ax[0].set_title("training loss (Eq. 7 + candidates)")
    for k in ("epe", "epe0", "pred_err", "qat_diff"):
        if np.isfinite(col(k)).any():
            ax[1].plot(step, col(k), label=k)
    ax[1].set_yscale("log")
    ax[1].set_title("EPE (final, initial) and mean predicted error exp(u/2), px")
    ax[1].legend()
    for k in ("bad1", "bad3"):
        ax[2].plot(step, 100 * col(k), label=k)
    ax[2].set_title("bad pixels, % (final prediction)")
    ax[2].legend()
    for a in ax:
        a.set_xlabel("step")
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(png_path, dpi=90)
    plt.close(fig)


def fmt_time(s: float) -> str:
    s = int(max(s, 0))
    return f"{s // 3600}h{(s % 3600) // 60:02d}m" if s >= 3600 else f"{s // 60}m{s % 60:02d}s"


# ------------------------------------------------------------------------------------------------
# Main
# ------------------------------------------------------------------------------------------------
# What defines a run: a resume keeps these from the checkpoint (a quantisation-aware run stays one).
SCHEDULE_KEYS = ("config", "steps", "batch", "crop", "lr", "wd", "pct_start", "seed", "gamma", "binarize_p", "iters",
                 "proxy_frac", "real_frac", "qat", "qat_p", "qat_activations_only", "qat_consistency")


def build_parser():
    p = argparse.ArgumentParser(prog="python -m muir.train", description="Train the MUIR twin on synthetic stereo.")
    p.add_argument("--config", default="muir-slim", choices=sorted(PRESETS))
    p.add_argument("--out", required=True, help="run directory (checkpoints, logs, final model)")
    p.add_argument("--steps", type=int, default=10000)
    p.add_argument("--batch", type=int, default=4)
    p.add_argument("--crop", type=parse_hw, default=(160, 384), help="HxW, multiples of 16")
    p.add_argument("--lr", type=float, default=2e-4, help="one-cycle maximum")
    p.add_argument("--wd", type=float, default=1e-5)
    p.add_argument("--pct-start", type=float, default=0.03, help="warm-up fraction of the one-cycle schedule")
    p.add_argument("--gamma", type=float, default=0.9, help="sequence loss decay")
    p.add_argument("--binarize-p", type=float, default=0.5, help="mask binarisation probability (Eq. 3)")
    p.add_argument("--iters", type=int, default=None, help="refinement iterations (default: the config's)")
    p.add_argument("--clip", type=float, default=1.0, help="gradient-norm clip")
    p.add_argument("--seed", type=int, default=1234, help="seed of the synthetic stream and of torch")
    p.add_argument("--proxy-frac", type=float, default=0.0,
                   help="fraction of samples that are real nogt crops with filtered SGBM labels (muir.proxy)")
    p.add_argument("--real-frac", type=float, default=0.0,
                   help="fraction of samples that are crops of the training-side GT scenes (muir.split, muir.realgt)")
    p.add_argument("--device", default="auto", help="cpu, cuda, cuda:N or auto")
    p.add_argument("--workers", type=int, default=1, help="data-loader processes (0: in the main process)")
    p.add_argument("--threads", default="0",
                   help="torch intra-op threads: N, 0 (torch default) or auto (switch between the default "
                        "and 1 by measured step time; for machines shared with other jobs)")
    p.add_argument("--time-budget", type=float, default=None, metavar="SECONDS",
                   help="fit the run into this much wall-clock time (a leased GPU, a session): after "
                        "--budget-probe steps the step count is cut to what the measured rate fits (--steps "
                        "is the upper bound) and the one-cycle schedule is rebuilt for it")
    p.add_argument("--budget-probe", type=int, default=30,
                   help="with --time-budget: steps timed before the step count is fitted (the first 5 are "
                        "not counted: allocator and cuDNN warm-up)")
    p.add_argument("--ckpt-every", type=int, default=None,
                   help="steps between checkpoints/snapshots (default 500; --resume keeps the run's)")
    p.add_argument("--log-every", type=int, default=None,
                   help="steps between progress lines / CSV rows (default 10; --resume keeps the run's)")
    p.add_argument("--resume", nargs="?", const="auto", default=None,
                   help="continue from OUT/ckpt_last.pt (or the given checkpoint)")
    p.add_argument("--init", default=None, help="start from these weights (.safetensors or ckpt .pt)")
    p.add_argument("--qat", default=None, metavar="FORMATS.json|dynamic",
                   help="quantisation-aware: simulate the integer engine's encoder activation rounding, with the "
                        "slot formats of a blob (`muir info --model BLOB.muirq --json`, e.g. "
                        "models/muir-slim.formats.json) or, with 'dynamic', "
                        "formats re-derived from each batch by the calibration's percentile rule")
    p.add_argument("--qat-p", type=float, default=0.5,
                   help="with --qat: fraction of steps run with the rounding (the rest run the float network)")
    p.add_argument("--qat-activations-only", action="store_true",
                   help="with --qat: leave the encoder's weights unrounded (default: int8 per output channel)")
    p.add_argument("--qat-consistency", type=float, default=3.0,
                   help="with --qat: weight of |d_rounded - d_float| on rounded steps (costs one more forward pass)")
    return p


def ddp_env():
    """(world size, rank, local rank) from torchrun's environment; (1, 0, 0) without it."""
    return int(os.environ.get("WORLD_SIZE", "1")), int(os.environ.get("RANK", "0")), int(os.environ.get("LOCAL_RANK", "0"))


def main(argv=None):
    args = build_parser().parse_args(argv)
    cmdline = "python -m muir.train " + " ".join(sys.argv[1:] if argv is None else argv)
    world, rank, local_rank = ddp_env()
    is_main = rank == 0
    if world > 1:
        # Data-parallel (torchrun): every process runs the same command on its slice of each global
        # batch; gradients are averaged by DistributedDataParallel, the loss is normalised by the
        # global batch's valid pixels, so a step equals the single-process step on the same batch.
        import torch.distributed as dist

        if args.batch % world:
            print(f"error: --batch {args.batch} must be a multiple of the {world} processes", file=sys.stderr)
            return 2
        if args.qat or args.time_budget is not None or args.threads == "auto":
            print("error: --qat, --time-budget and --threads auto are single-process options", file=sys.stderr)
            return 2
        use_cuda = args.device.startswith("cuda") or (args.device == "auto" and torch.cuda.is_available())
        if use_cuda:
            torch.cuda.set_device(local_rank)
            args.device = f"cuda:{local_rank}"
        dist.init_process_group("nccl" if use_cuda else "gloo")
    if not is_main:
        sys.stderr = open(os.devnull, "w")  # one progress stream: rank 0's
    os.makedirs(args.out, exist_ok=True)
    ckpt_path = os.path.join(args.out, "ckpt_last.pt")

    state = None
    if args.resume:
        path = ckpt_path if args.resume == "auto" else args.resume
        if not os.path.exists(path):
            print(f"error: --resume: no checkpoint at {path}", file=sys.stderr)
            return 2
        try:
            state = torch.load(path, map_location="cpu", weights_only=False)
            if not isinstance(state, dict) or "model" not in state or "step" not in state:
                raise ValueError("not a muir.train checkpoint")
        except Exception as e:  # pickle/zip errors of a truncated or foreign file
            print(f"error: --resume: {path}: unreadable checkpoint ({type(e).__name__}: {str(e)[:200]})", file=sys.stderr)
            return 2
        # The schedule is part of the run: keep the stored values, say so if the command differs.
        stored = state["args"]
        for k in SCHEDULE_KEYS:
            if k not in stored:
                continue
            if k.startswith("qat") and stored[k] is None and getattr(args, k) is not None:
                # Checkpoints before the quantisation-aware keys were recorded hold None: the
                # command says whether the run is quantisation-aware.
                print(f"note: --resume: the checkpoint does not record {k}; the command's {getattr(args, k)} is used", file=sys.stderr)
                continue
            v = tuple(stored[k]) if k == "crop" else stored[k]
            if getattr(args, k) != v:
                print(f"note: --resume keeps {k}={v} (command said {getattr(args, k)})", file=sys.stderr)
            setattr(args, k, v)

    # Cadences: given on the command line, else the run's (a resume keeps its snapshot grid), else defaults.
    stored_cadence = state.get("cadence", {}) if state is not None else {}
    for k, default in (("ckpt_every", 500), ("log_every", 10)):
        if getattr(args, k) is None:
            setattr(args, k, int(stored_cadence.get(k, default)))
        if getattr(args, k) < 1:
            print(f"error: --{k.replace('_', '-')} must be at least 1", file=sys.stderr)
            return 2

    tuner = None
    if args.threads == "auto":
        tuner = ThreadTuner(torch.get_num_threads())
    elif args.threads.isdigit():
        if int(args.threads) > 0:
            torch.set_num_threads(int(args.threads))
    else:
        print(f"error: --threads must be a number or auto, got {args.threads}", file=sys.stderr)
        return 2
    if args.time_budget is not None and (args.time_budget <= 0 or args.budget_probe < 10 or state is not None):
        print("error: --time-budget needs a positive budget, --budget-probe >= 10 and a fresh run (not --resume)",
              file=sys.stderr)
        return 2
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    dev = torch.device(args.device)

    cfg = preset(args.config)
    if state is not None and state.get("config_json"):
        cfg = Config.from_json(state["config_json"])
    iters = args.iters or cfg.iters
    torch.manual_seed(args.seed)
    model = MUIR(cfg)
    init_weights(model)
    if args.init and state is None:
        try:
            if args.init.endswith(".safetensors"):
                from .checkpoint import load_model

                model.load_state_dict(load_model(args.init, args.config).state_dict(), strict=True)
            else:
                model.load_state_dict(torch.load(args.init, map_location="cpu", weights_only=False)["model"], strict=True)
        except Exception as e:  # ModelFileError names the file; a .pt gets the same one line
            msg = str(e) if args.init in str(e) else f"{args.init}: {type(e).__name__}: {str(e)[:200]}"
            print(f"error: --init: {msg}", file=sys.stderr)
            return 2
        bad = [k for k, v in model.state_dict().items() if v.is_floating_point() and not torch.isfinite(v).all()]
        if bad:
            print(f"error: --init: {args.init}: NaN or infinite weights in {bad[0]}", file=sys.stderr)
            return 2
    aq = None
    if args.qat:
        from . import qat

        try:
            aq = qat.ActQuant(None if args.qat == "dynamic" else qat.read_report(args.qat), weights=not args.qat_activations_only)
        except (OSError, ValueError) as e:
            print(f"error: --qat: {e}", file=sys.stderr)
            return 2
        qat.attach(model, aq)
        print(f"quantisation-aware: {len(aq.grid)} encoder slots, formats {args.qat}, on {100 * args.qat_p:.0f}% of steps",
              file=sys.stderr)
    model.to(dev).train()
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model, device_ids=[dev.index] if dev.type == "cuda" else None)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=args.wd, betas=(0.9, 0.999), eps=1e-8)

    def one_cycle():  # the schedule over args.steps (rebuilt when --time-budget fits the step count)
        return torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=args.lr, total_steps=args.steps, pct_start=args.pct_start,
            cycle_momentum=False, anneal_strategy="linear",
        )

    sched = one_cycle()
    step = 0
    if state is not None:
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        step = int(state["step"])
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
        random.setstate(state["rng"]["python"])
        if dev.type == "cuda" and state["rng"].get("cuda") is not None:
            torch.cuda.set_rng_state(state["rng"]["cuda"])
        print(f"resumed from step {step}", file=sys.stderr)
    if step >= args.steps:
        print(f"nothing to do: step {step} >= --steps {args.steps}", file=sys.stderr)

    h, w = args.crop
    n_params = sum(p.numel() for p in model.parameters())
    print(f"{cfg.name}: {n_params / 1e6:.2f} M parameters, {iters} iterations, device {dev}, "
          f"{torch.get_num_threads()} threads{f' x {world} processes' if world > 1 else ''}; "
          f"{args.steps} steps of {args.batch}x{h}x{w}, lr {args.lr}", file=sys.stderr)
    # args.json records the command that started the run; a resume appends its own command (with the
    # step it resumed from) instead of replacing the record of how the run was set up.
    args_path = os.path.join(args.out, "args.json")
    record = {**vars(args), "command": cmdline, "config_json": cfg.to_json()}
    if state is not None and os.path.exists(args_path):
        with open(args_path) as f:
            record = json.load(f)
        record.setdefault("resumed", []).append({"step": step, "command": cmdline})
    if is_main:
        with open(args_path, "w") as f:
            json.dump(record, f, indent=1)

    def save_ckpt(step_now):
        if not is_main:
            return
        st = {
            "model": model.state_dict(),
            "optimizer": opt.state_dict(),
            "scheduler": sched.state_dict(),
            "step": step_now,
            "args": {k: getattr(args, k) for k in SCHEDULE_KEYS},
            "cadence": {"ckpt_every": args.ckpt_every, "log_every": args.log_every},
            "config_json": cfg.to_json(),
            "rng": {
                "torch": torch.get_rng_state(),
                "numpy": np.random.get_state(),
                "python": random.getstate(),
                "cuda": torch.cuda.get_rng_state() if dev.type == "cuda" else None,
            },
        }
        tmp = ckpt_path + ".tmp"
        torch.save(st, tmp)
        os.replace(tmp, ckpt_path)  # atomic: a kill during the save leaves the previous checkpoint

    meta_base = {
        "command": cmdline,
        "git_commit": git_commit(),
        "train_data": ("muir.synth (synthetic layered scenes), seed %d" % args.seed)
        + (f"; {100 * args.real_frac:.0f}% of samples real GT crops of the training scenes of muir.split"
           if args.real_frac > 0 else ""),
        "crop": f"{h}x{w}",
        "batch": str(args.batch),
        "lr": str(args.lr),
        "total_steps": str(args.steps),
    }

    def export(path, step_now, last=None):
        if not is_main:
            return
        meta = dict(meta_base, steps=str(step_now), date=datetime.datetime.now().astimezone().isoformat(timespec="seconds"))
        if last:
            meta["train_metrics"] = json.dumps(last)
        model_cpu_state = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        m2 = MUIR(cfg)
        m2.load_state_dict(model_cpu_state)
        save_model(m2, path, extra_meta=meta)

    stop = {"flag": False}

    def on_signal(signum, _frame):
        stop["flag"] = True
        print(f"signal {signum}: stopping after this step", file=sys.stderr)

    signal.signal(signal.SIGTERM, on_signal)
    signal.signal(signal.SIGINT, on_signal)

    if not (0.0 <= args.real_frac <= 1.0 and 0.0 <= args.proxy_frac <= 1.0 - args.real_frac):
        print("error: --real-frac and --proxy-frac must be in [0, 1] and sum to at most 1", file=sys.stderr)
        return 2
    if args.real_frac > 0:
        from . import split

        try:
            tr, _ = split.check()
        except (OSError, ValueError) as e:
            print(f"error: --real-frac: {e}", file=sys.stderr)
            return 2
        print(f"real GT crops: {len(tr)} training scene directories (muir.split), {100 * args.real_frac:.0f}% of samples",
              file=sys.stderr)
    ds = SynthDataset(args.seed, h, w, length=args.steps * args.batch, proxy_frac=args.proxy_frac,
                      real_frac=args.real_frac)
    loader = torch.utils.data.DataLoader(
        ds, batch_size=args.batch // world, sampler=StepSampler(step, args.steps, args.batch, world, rank),
        num_workers=args.workers, worker_init_fn=_worker_init if args.workers > 0 else None,
        pin_memory=dev.type == "cuda", drop_last=True, persistent_workers=False,
        prefetch_factor=4 if args.workers > 0 else None,
    )
    if args.workers == 0:
        synth.photo_pool()  # not before forking workers: OpenCV's thread pool would deadlock them
    # The synthetic stream depends on the texture photographs: say which ones this machine has.
    n_nogt = len(synth.photo_paths(use_skimage=False))
    print(f"textures: {len(synth.photo_paths())} photographs, {n_nogt} of them from {synth.DEFAULT_NOGT_DIR}",
          file=sys.stderr)
    if args.proxy_frac > 0:
        # Build the label cache in a child process: OpenCV's thread pool used here before the data
        # workers fork would deadlock them. This process then only reads the cached arrays.
        pkg_root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
        env = {**os.environ, "PYTHONPATH": pkg_root + os.pathsep + os.environ.get("PYTHONPATH", "")}
        if subprocess.run([sys.executable, "-m", "muir.proxy", "build"], env=env, stdout=subprocess.DEVNULL).returncode:
            print("error: --proxy-frac: building the proxy labels failed", file=sys.stderr)
            return 2
        from . import proxy

        n_src = len(proxy.pool().items)
        print(f"proxy labels: {n_src} real sources, {100 * args.proxy_frac:.0f}% of samples", file=sys.stderr)

    csv_path = os.path.join(args.out, "log.csv")
    kept_rows = []
    if state is not None and os.path.exists(csv_path):
        # Rows logged after the checkpoint we resume from will be logged again: drop them.
        kept_rows = [r for r in csv.DictReader(open(csv_path)) if int(r["step"]) <= step]
    csv_f = open(csv_path if is_main else os.devnull, "w", newline="")
    writer = csv.DictWriter(csv_f, fieldnames=CSV_FIELDS, extrasaction="ignore")
    writer.writeheader()
    writer.writerows(kept_rows)

    def fit_to_budget(step_now, s_per_step, elapsed):
        """Cut --steps to what the budget fits at the measured rate, rebuild the schedule for it."""
        nonlocal sched
        reserve = max(10.0, 0.05 * args.time_budget)  # snapshot/final exports, the last log line
        fits = step_now + int((args.time_budget - elapsed - reserve) / s_per_step)
        new_steps = max(step_now + 1, min(args.steps, fits))
        print(f"time budget {args.time_budget:.0f}s: {s_per_step:.3f}s/step measured, {elapsed:.0f}s spent -> "
              f"{new_steps} steps (upper bound {args.steps})", file=sys.stderr)
        args.steps = new_steps
        meta_base["total_steps"] = str(new_steps)
        sched = one_cycle()
        with warnings.catch_warnings():  # "scheduler stepped before optimizer": intended here
            warnings.simplefilter("ignore")
            for _ in range(step_now):  # the probe's steps are part of the new schedule's warm-up
                sched.step()
        record["steps"] = new_steps
        record["time_budget_fit"] = {"probe_steps": step_now, "s_per_step": round(s_per_step, 4),
                                     "elapsed_s": round(elapsed, 1), "steps": new_steps}
        with open(args_path, "w") as f:
            json.dump(record, f, indent=1)

    acc, n_acc, t_acc, d_acc = {}, 0, 0.0, 0.0
    qat_acc = [0.0, 0]  # sum and count of mean |d_rounded - d_float| (final) over rounded steps
    bad_steps = 0
    last = {}
    t_start = time.time()
    steps_at_start = step
    t_probe0 = None  # wall clock at the end of the budget probe's warm-up steps
    t_data0 = time.time()
    for left, right, gt in loader:
        t_data = time.time() - t_data0
        t0 = time.time()
        left, right, gt = (x.to(dev, non_blocking=True) for x in (left, right, gt))
        valid = torch.isfinite(gt) & (gt >= 0) & (gt < MAX_GT)
        # This process's slice of the step's coins (all of them in a single process).
        per = args.batch // world
        coins = binarize_coins(args.seed, step, args.batch, iters, args.binarize_p)[rank * per : (rank + 1) * per]
        denom = None
        if world > 1:
            denom = valid.float().sum()
            dist.all_reduce(denom)
            denom = denom.clamp(min=1.0)
        ref = None
        if aq is not None:
            aq.enabled = random.random() < args.qat_p
            if aq.enabled and args.qat_consistency > 0:
                # The float network's answer on the same batch, with the same mask-binarisation coins
                # (the forked RNG state is restored for the rounded pass).
                aq.enabled = False
                cuda_ids = [torch.cuda.current_device()] if dev.type == "cuda" else []
                with torch.random.fork_rng(devices=cuda_ids), torch.no_grad():
                    ref = model(left, right, iters=iters, train_out=True, binarize_coins=coins)
                aq.enabled = True
        out = net(left, right, iters=iters, train_out=True, binarize_coins=coins)
        loss, m = sequence_loss(out, gt, valid, cfg, args.gamma, denom=denom)
        if ref is not None:
            cons = consistency_loss(out, ref, args.gamma)
            loss = loss + args.qat_consistency * cons
            with torch.no_grad():
                qd = (out["disp"][-1] - ref["disp"][-1]).abs().mean().item()
            qat_acc[0] += qd
            qat_acc[1] += 1
        opt.zero_grad(set_to_none=True)
        loss_local = loss
        if world > 1:
            # Each process holds its share of the global loss and metrics: their sums are the
            # single-process figures. DistributedDataParallel averages gradients over processes,
            # hence the factor `world` on the backward pass.
            keys = sorted(m)
            t = torch.tensor([loss.item(), float(stop["flag"])] + [m[k] for k in keys], dtype=torch.float64)
            dist.all_reduce(t)
            loss = torch.tensor(t[0].item())
            stop["flag"] = stop["flag"] or t[1].item() > 0  # every process stops after the same step
            m = {k: t[2 + i].item() for i, k in enumerate(keys)}
        if not torch.isfinite(loss):
            bad_steps += 1
            print(f"step {step}: non-finite loss, skipped ({bad_steps} so far)", file=sys.stderr)
            if bad_steps > 20:
                print("error: too many non-finite losses", file=sys.stderr)
                save_ckpt(step)
                return 3
        else:
            (loss_local * world).backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.clip)
            opt.step()
        lr_used = opt.param_groups[0]["lr"]
        sched.step()  # one schedule step per data step, skipped or not, to stay aligned with the data
        step += 1
        t_step = time.time() - t0
        if tuner is not None:
            tuner.record(t_step)
        if args.time_budget is not None:
            if step == 5:
                t_probe0 = time.time()
            elif step == args.budget_probe and t_probe0 is not None:
                fit_to_budget(step, (time.time() - t_probe0) / (step - 5), time.time() - t_start)
        m["loss"] = loss.item()
        for k, v in m.items():
            acc[k] = acc.get(k, 0.0) + v
        n_acc += 1
        t_acc += t_step
        d_acc += t_data

        if step % args.log_every == 0 or step == args.steps:
            avg = {k: v / n_acc for k, v in acc.items()}
            sps = (step - steps_at_start) / (time.time() - t_start)
            eta = (args.steps - step) / max(sps, 1e-9)
            row = {"step": step, "lr": f"{lr_used:.3e}", "step_s": f"{t_acc / n_acc:.3f}",
                   "data_s": f"{d_acc / n_acc:.3f}", "time": f"{time.time():.0f}"}
            row.update({k: f"{v:.5g}" for k, v in avg.items()})
            qat_txt = ""
            if qat_acc[1]:
                row["qat_diff"] = f"{qat_acc[0] / qat_acc[1]:.5g}"
                qat_txt = f" qat |dq-df| {qat_acc[0] / qat_acc[1]:.3f}"
                qat_acc[0], qat_acc[1] = 0.0, 0
            writer.writerow(row)
            csv_f.flush()
            print(f"step {step}/{args.steps} loss {avg['loss']:.3f} epe {avg['epe']:.3f} (init {avg['epe0']:.3f}) "
                  f"bad1 {100 * avg['bad1']:.1f}% pred_err {avg.get('pred_err', float('nan')):.2f}{qat_txt} "
                  f"lr {lr_used:.2e} | {t_acc / n_acc:.2f}s/step data {d_acc / n_acc:.3f}s "
                  f"{sps:.3f} steps/s ETA {fmt_time(eta)} [{torch.get_num_threads()} thr]", file=sys.stderr, flush=True)
            last = {k: round(v, 5) for k, v in avg.items()}
            acc, n_acc, t_acc, d_acc = {}, 0, 0.0, 0.0

        if step % args.ckpt_every == 0 or step == args.steps or stop["flag"]:
            save_ckpt(step)
            if step % args.ckpt_every == 0:
                export(os.path.join(args.out, f"snapshot_{step:06d}.safetensors"), step, last)
            try:
                if is_main:
                    plot_curves(csv_path, os.path.join(args.out, "loss.png"))
            except Exception as e:  # plotting must never kill a run
                print(f"warning: loss plot failed: {e}", file=sys.stderr)
        if stop["flag"]:
            print(f"stopped at step {step}; continue with --resume", file=sys.stderr)
            csv_f.close()
            return 130
        if step >= args.steps:
            break  # a budget-fitted run ends before the loader's upper bound
        if args.time_budget is not None and time.time() - t_start > args.time_budget:
            # Slower than the probe measured: keep what was trained (lr not annealed to zero).
            print(f"time budget spent at step {step} of {args.steps}: writing the model as it is", file=sys.stderr)
            save_ckpt(step)
            args.steps = step
            meta_base["total_steps"] = f"{step} (budget ran out; schedule planned {record['steps']})"
            break
        t_data0 = time.time()

    csv_f.close()
    if world > 1:
        dist.barrier()
    if step >= args.steps:
        final = os.path.join(args.out, "model.safetensors")
        export(final, step, last)
        try:
            if is_main:
                plot_curves(csv_path, os.path.join(args.out, "loss.png"))
        except Exception as e:  # plotting must never kill a run
            print(f"warning: loss plot failed: {e}", file=sys.stderr)
        print(f"done: {step} steps in {fmt_time(time.time() - t_start)}; wrote {final}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
