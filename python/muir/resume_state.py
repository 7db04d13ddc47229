"""The small state a training run needs to continue in another session, for committing to the repo.

A run directory's `ckpt_last.pt` (model, AdamW moments, schedule, step, RNG states) is 29 MB for
muir-slim; the copy written here keeps the model in float32 and stores the AdamW moments in
bfloat16 (19 MB): `torch.optim.Optimizer.load_state_dict` casts them back to the parameters' dtype,
so `--resume` reads the copy directly. The moments lose precision (bf16 keeps 8 significant bits),
a perturbation of the step direction well below the minibatch noise; the schedule, step and data
stream continue exactly. Alongside go the run's `args.json` and `log.csv` (so the loss curve
continues). One fixed destination, overwritten: the repository holds one resume state, never a
history of them.

    python -m muir.resume_state runs/phase9 models/muir-slim.train/resume      # save
    python -m muir.train --out runs/phase9 --resume models/muir-slim.train/resume/ckpt.pt   # continue
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys

import torch


def compact(state: dict) -> dict:
    """The checkpoint with every floating optimizer tensor (except AdamW's step counters) in bf16."""
    opt = state["optimizer"]
    small = {}
    for pid, st in opt["state"].items():
        small[pid] = {k: (v.to(torch.bfloat16) if torch.is_tensor(v) and v.is_floating_point() and k != "step" else v)
                      for k, v in st.items()}
    return {**state, "optimizer": {**opt, "state": small}}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m muir.resume_state", description=__doc__.split("\n\n")[0])
    p.add_argument("run", help="run directory of muir.train (holds ckpt_last.pt, args.json, log.csv)")
    p.add_argument("dest", help="destination folder (overwritten): ckpt.pt, args.json, log.csv")
    a = p.parse_args(argv)
    src = os.path.join(a.run, "ckpt_last.pt")
    try:
        state = torch.load(src, map_location="cpu", weights_only=False)
        if not isinstance(state, dict) or "optimizer" not in state or "step" not in state:
            raise ValueError("not a muir.train checkpoint")
    except (OSError, ValueError, RuntimeError) as e:
        print(f"error: {src}: {e}", file=sys.stderr)
        return 2
    os.makedirs(a.dest, exist_ok=True)
    tmp = os.path.join(a.dest, "ckpt.pt.tmp")
    torch.save(compact(state), tmp)
    os.replace(tmp, os.path.join(a.dest, "ckpt.pt"))
    for name in ("args.json", "log.csv"):
        if os.path.exists(os.path.join(a.run, name)):
            shutil.copyfile(os.path.join(a.run, name), os.path.join(a.dest, name))
    size = os.path.getsize(os.path.join(a.dest, "ckpt.pt"))
    print(f"{a.dest}: step {state['step']}, {size / 1e6:.1f} MB; continue with "
          f"python -m muir.train --out RUN_DIR --resume {os.path.join(a.dest, 'ckpt.pt')}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
