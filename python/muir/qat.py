"""Quantisation-aware training: the integer engine's encoder rounding, simulated in the twin.

The fixed-point engine stores the encoder's activations in 8 bits (`u8` after a ReLU, the matching
features `i8`), each slot with a power-of-two scale chosen by calibration (`muir quantize`, whose
report lists `slot | bits | frac`), and its weights in int8 per output channel. That noise flips
near-tied matches and separates the two engines on ambiguous pixels (README, "Accuracy").
`ActQuant` rounds the same tensors to the same grids in the forward pass, with a straight-through
gradient, so that a model can be fine-tuned against it (`python -m muir.train --qat dynamic`, see
docs/training.md; the trials and what they bought: docs/experiments/qat-trial/).

Slots simulated (crates/muir/src/model/graph.rs): the backbone (`c1`, `l*b*m/o`), the context/hidden heads
(`h08*`, `h16*`, `inp08`, `inp16`) and the matching-feature head (`fmap_raw1`, `fmap_mid`, `fmap_raw2`,
`fmap_blk`, `fmap`). The update block's slots are 16-bit and its weights several-part, and are left
in float.
"""
from __future__ import annotations

import json
import math
import os

import torch

# The slots the twin simulates (the tensors it can hook). Their storage (width, signedness) and,
# for a given blob, their fraction bits come from the Rust side's one table (`crates/muir/src/model/graph.rs`),
# exported by `muir info --model BLOB.muirq --json` (`models/muir-slim.formats.json` for the shipped
# blob; a test checks that file against the blob), never repeated or parsed out of Markdown here.
ENCODER_SLOT_NAMES = (
    "c1",
    *(f"l{l}b{b}{k}" for l in range(1, 5) for b in range(2) for k in "mo"),
    *(f"h{r}{h}{k}" for r in ("08", "16") for h in "nc" for k in "mo"),
    "fmap_raw1", "fmap_mid", "fmap_raw2", "fmap_blk", "fmap",
    "inp08", "inp16",
)
FORMATS_FILE = os.path.join(os.path.dirname(__file__), "..", "..", "models", "muir-slim.formats.json")


def read_formats(path: str) -> dict[str, dict]:
    """Every encoder slot's `{"bits", "unsigned", "frac"}` from `muir info --json` output of a blob;
    a ValueError naming the file if it is not one or lacks a slot."""
    try:
        with open(path) as f:
            j = json.load(f)
    except json.JSONDecodeError as e:
        raise ValueError(f"{path}: not JSON ({e}); write it with `muir info --model BLOB.muirq --json`") from None
    if not isinstance(j, dict) or j.get("kind") != "muirq" or not isinstance(j.get("slots"), list):
        raise ValueError(f"{path}: not the `muir info --json` output of a .muirq blob")
    slots = {e["name"]: e for e in j["slots"] if isinstance(e, dict) and "name" in e}
    missing = [s for s in ENCODER_SLOT_NAMES if s not in slots]
    if missing:
        raise ValueError(f"{path}: no format for slot(s) {', '.join(missing)}")
    return {s: {k: slots[s][k] for k in ("bits", "unsigned", "frac")} for s in ENCODER_SLOT_NAMES}


def encoder_storage(path: str = FORMATS_FILE) -> dict[str, tuple[int, bool]]:
    """(bits, unsigned) of each simulated slot in the u8-trunk engine (the shipped blob's table)."""
    return {s: (f["bits"], f["unsigned"]) for s, f in read_formats(path).items()}


def read_report(path: str) -> dict[str, int]:
    """Fraction bits per slot of a blob's `muir info --json` output."""
    return {slot: f["frac"] for slot, f in read_formats(path).items()}


def read_report_formats(path: str) -> dict[str, tuple[int, int]]:
    """(bits, fraction bits) per slot of a blob's `muir info --json` output; a wide-trunk blob
    (`muir quantize --wide-trunk`) gives 16 bits for conv1 .. layer2."""
    return {slot: (f["bits"], f["frac"]) for slot, f in read_formats(path).items()}


def dynamic_frac(x: torch.Tensor, qmax: int, percentile: float = 99.99) -> int:
    """The calibration's rule (`QFormat::for_range`, `muir quantize --method percentile`) on one
    tensor: the most fraction bits whose range still holds the given percentile of |x|."""
    a = x.detach().abs().flatten()
    k = max(1, int(a.numel() * (1.0 - percentile / 100.0)))
    p = float(a.topk(k).values[-1]) if a.numel() > k else float(a.max())
    return int(math.floor(math.log2(qmax / max(p, 1e-12))))


class ActQuant:
    """Rounds a slot's tensor to the engine's grid (round to nearest, saturate), straight-through;
    with `weights`, the encoder convs' weights too (see `attach`).

    With `fracs` the grids are fixed (those of a blob: `python -m muir.qat` compares with the engine);
    without, each call re-derives its slot's grid from the tensor by the calibration rule, so that
    training follows the formats a re-calibration of the trained weights will choose (fixed grids let
    the float steps grow activations past the range, where saturation then breaks the rounded steps).
    """

    def __init__(self, fracs: dict[str, int] | None = None, weights: bool = True,
                 bits: dict[str, int] | None = None):
        """`bits`: storage width per slot from a blob's formats (`read_report_formats`); a slot a
        wide-trunk blob (`muir quantize --wide-trunk`) widens to 16 bits holds i16 codes [0, 32767]."""
        self.grid = {}
        for slot, (width, unsigned) in encoder_storage().items():
            if bits is not None and bits.get(slot, width) == 16 and width == 8 and unsigned:
                lo, hi = 0, 2**15 - 1
            else:
                lo, hi = (0, 2**width - 1) if unsigned else (-(2 ** (width - 1)), 2 ** (width - 1) - 1)
            self.grid[slot] = (None if fracs is None else 2.0 ** fracs[slot], lo, hi)
        self.enabled = False
        self.weights = weights

    def scale(self, slot: str, x: torch.Tensor) -> float:
        """2^frac of `slot` (fixed, or derived from `x`, the slot's float value)."""
        s, _, hi = self.grid[slot]
        return 2.0 ** dynamic_frac(x, hi) if s is None else s

    def __call__(self, slot: str, x: torch.Tensor, saturate: bool = True, scale: float | None = None) -> torch.Tensor:
        """`saturate=False` for an i16 intermediate on the slot's grid (a residual branch before the
        add, with `scale` = the slot's, from the sum)."""
        if not self.enabled:
            return x
        _, lo, hi = self.grid[slot]
        s = self.scale(slot, x) if scale is None else scale
        q = torch.round(x * s)
        if saturate:
            q = torch.clamp(q, lo, hi)
        return x + (q / s - x).detach()


def _quantised_conv_forward(conv, aq):
    """`conv.forward` with its weight rounded as the blob stores it when `aq` is enabled: int8,
    symmetric, one scale per output channel (BatchNorm and the input slot's scale fold into that
    per-channel scale, so rounding the raw weight per channel is the same grid)."""

    def forward(x):
        w = conv.weight
        if aq is not None and aq.enabled and aq.weights:
            s = w.detach().abs().amax(dim=(1, 2, 3), keepdim=True).clamp(min=1e-12) / 127.0
            w = w + (torch.round(w / s) * s - w).detach()
        return conv._conv_forward(x, w, conv.bias)

    return forward


def attach(model, aq: ActQuant | None):
    """Wires `aq` into `model`'s encoder (None detaches): names each residual block's slots."""
    enc = model.cnet
    named = [(enc.layer1, "l1"), (enc.layer2, "l2"), (enc.layer3, "l3"), (enc.layer4, "l4")]
    for seq, name in named:
        for b, blk in enumerate(seq):
            blk.slots = (f"{name}b{b}m", f"{name}b{b}o")
            blk.aq = aq
    for heads, r in ((enc.outputs08, "08"), (enc.outputs16, "16")):
        for head, h in zip(heads, "nc"):
            head[0].slots = (f"h{r}{h}m", f"h{r}{h}o")
            head[0].aq = aq
    model.conv2[0].slots = ("fmap_raw1", "fmap_mid", "fmap_raw2", "fmap_blk")
    model.conv2[0].aq = aq
    model.aq = aq
    # Weights of the encoder's convs (single-input-part layers; the update block's convs read
    # several slots, each with its own weight scale in the blob, and are not simulated).
    for mod in list(enc.modules()) + list(model.conv2.modules()):
        if isinstance(mod, torch.nn.Conv2d):
            if aq is None:
                mod.__dict__.pop("forward", None)
            else:
                mod.forward = _quantised_conv_forward(mod, aq)


CROPS_FILE = os.path.join(os.path.dirname(__file__), "..", "..", "host-tests", "fixtures", "crops.txt")


def read_crops(path=CROPS_FILE):
    """The fixed_vs_float crops, as host-tests/support/crops.rs reads them: ((w, h), [(scene, x, y)])."""
    size, crops = None, []
    with open(path) as f:
        for line in f:
            fields = line.split("#")[0].split()
            if not fields:
                continue
            if fields[0] == "size" and len(fields) == 3:
                size = (int(fields[1]), int(fields[2]))
            elif len(fields) == 3:
                crops.append((fields[0], int(fields[1]), int(fields[2])))
            else:
                raise ValueError(f"{path}: bad line {line.strip()!r}")
    if size is None:
        raise ValueError(f"{path}: no size line")
    return size, crops


def main(argv=None):
    """Simulated fixed vs float on the fixed_vs_float crops: checks that the simulation tracks the
    engine (compare with `cargo test --release --test fixed_vs_float -- --nocapture`)."""
    import argparse

    import sys

    import numpy as np
    from PIL import Image

    from .checkpoint import load_model

    ap = argparse.ArgumentParser(prog="python -m muir.qat", description=main.__doc__)
    ap.add_argument("--model", default="models/muir-slim.safetensors")
    ap.add_argument("--report", default="models/muir-slim.formats.json",
                    help="the blob's slot formats, `muir info --model BLOB.muirq --json` "
                         "(models/muir-slim-wide.formats.json for the wide trunk)")
    ap.add_argument("--data", default="../shared/data")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
    ap.add_argument("--activations-only", action="store_true", help="do not round the encoder's weights")
    args = ap.parse_args(argv)
    if args.threads > 0:
        torch.set_num_threads(args.threads)
    try:
        m = load_model(args.model, "muir-slim")
        formats = read_report_formats(args.report)
        aq = ActQuant({k: f for k, (_, f) in formats.items()}, weights=not args.activations_only,
                      bits={k: b for k, (b, _) in formats.items()})
    except (OSError, ValueError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    attach(m, aq)

    (cw, ch), crops = read_crops()

    def tensor(path, x, y):
        a = np.asarray(Image.open(path).convert("RGB"))[y : y + ch, x : x + cw]
        return torch.from_numpy(a.copy()).permute(2, 0, 1)[None].float()

    diffs = []
    print("| pair | mean |d_rounded - d_float| px | within 1 px % |")
    print("|---|---:|---:|")
    for name, x, y in crops:
        d = os.path.join(args.data, name)
        left, right = tensor(os.path.join(d, "left.png"), x, y), tensor(os.path.join(d, "right.png"), x, y)
        with torch.no_grad():
            aq.enabled = False
            d0, _ = m(left, right)
            aq.enabled = True
            d1, _ = m(left, right)
        e = (d0 - d1).abs().flatten()
        diffs.append(e)
        print(f"| {name} | {e.mean():.4f} | {100 * (e < 1).float().mean():.2f} |", flush=True)
    e = torch.cat(diffs)
    print(f"| all five | {e.mean():.4f} | {100 * (e < 1).float().mean():.2f} |")
    return 0


if __name__ == "__main__":
    import sys

    sys.exit(main())
