"""Export the float twin for deployment runtimes (ONNX Runtime, TensorRT, NPU toolchains).

    python -m muir.export onnx --model models/muir-slim.safetensors --size 640x480 --out muir-slim-640x480.onnx
    python -m muir.export onnx --model models/muir-slim.safetensors --size 450x375 --iters 4 --out teddy.onnx

The ONNX model is the network of `muir.model.MUIR` in eval mode for one fixed input size and a fixed
number of refinement iterations (default: the config's), batch 1:

- inputs `left`, `right`: float32 (1, 3, H, W), RGB in 0..255 (the twin's input convention; gray
  views replicated to three channels), H x W the exported size;
- output `disparity`: float32 (1, 1, H, W), px at full resolution (left view, positive);
- output `uncertainty` (models with MUD): float32 (1, 1, H, W), u = log(beta^2) with beta in px,
  predicted error exp(u / 2) px.

Sizes that are not multiples of 16 are padded inside the graph as `muir.evaluate` and the Rust engines
pad (edge replication on the right and bottom) and the outputs are cropped back. The disparity is the
network's, before the optional full-resolution refinement (`muir.fullres`, integer census matching
in numpy, not part of the graph). The graph has no data-dependent control flow and uses standard ONNX
ops only (Conv, GatherElements, Einsum, ArgMax/ArgMin, Resize, InstanceNormalization, ...); no op of
the twin needed an export-specific rewrite (the wrapper's edge padding is written with slices so that
the graph keeps static shapes). The file carries the model config, the size and the
iterations in its metadata (`metadata_props`).

Needs the optional `export` dependencies: pip install 'muir[export]' (onnx; onnxruntime for the
post-export check).
"""
from __future__ import annotations

import argparse
import inspect
import os
import sys
import time
import warnings

import torch
import torch.nn as nn
import torch.nn.functional as F

DEFAULT_OPSET = 17
# The Rust engines' limits (crates/muir/src/model/config.rs: MIN_SIDE, MAX_IMAGE_WIDTH, MAX_IMAGE_HEIGHT).
MIN_SIDE = 32
MAX_WIDTH, MAX_HEIGHT = 1920, 1088
MAX_ITERS = 64


class OnnxMUIR(nn.Module):
    """The twin's eval-mode forward at a fixed size: pads to the network's multiple (edge replication,
    right/bottom, as muir.evaluate.run_model), runs `iters` iterations, crops the outputs back."""

    def __init__(self, model, height: int, width: int, iters: int):
        super().__init__()
        self.model = model
        self.height, self.width, self.iters = height, width, iters
        m = model.cfg.pad_multiple
        self.pad = ((-width) % m, (-height) % m)

    def forward(self, left, right):
        pw, ph = self.pad
        if pw or ph:
            left, right = pad_edge(left, pw, ph), pad_edge(right, pw, ph)
        disp, u = self.model(left, right, iters=self.iters)
        disp = disp[:, :, : self.height, : self.width]
        if u is None:
            return disp
        return disp, u[:, :, : self.height, : self.width]


def pad_edge(x, pw: int, ph: int):
    """F.pad(x, (0, pw, 0, ph), mode="replicate") written with slices, expand and cat: the same numbers,
    and the exported graph keeps static shapes (the exporter's Pad loses them)."""
    b, c, h, w = x.shape
    if pw:
        x = torch.cat([x, x[:, :, :, w - 1 :].expand(b, c, h, pw)], dim=3)
    if ph:
        x = torch.cat([x, x[:, :, h - 1 :, :].expand(b, c, ph, w + pw)], dim=2)
    return x


def output_names(model) -> list[str]:
    return ["disparity", "uncertainty"] if model.cfg.mud else ["disparity"]


def export_onnx(model, path: str, width: int, height: int, iters: int | None = None, opset: int = DEFAULT_OPSET,
                source: str | None = None) -> dict:
    """Writes the ONNX model of `model` (a MUIR; moved to the CPU as float32, eval mode) for
    (1, 3, height, width) inputs. Returns the metadata written into the file."""
    import onnx

    cfg = model.cfg
    iters = cfg.iters if iters is None else iters
    model = model.float().cpu().eval()
    if model.aq is not None:
        raise ValueError("the model has QAT rounding attached (muir.qat): export the float model")
    wrapper = OnnxMUIR(model, height, width, iters).eval()
    # Any pair traces the same graph (no data-dependent control flow); a textured one keeps the
    # tracer's single forward pass representative.
    g = torch.Generator().manual_seed(0)
    left = torch.rand(1, 3, height, width, generator=g) * 255.0
    right = torch.roll(left, -4, dims=3)
    names = output_names(model)
    with warnings.catch_warnings(), torch.no_grad():
        # Tracer notes about shapes taken as constants (the size is fixed by design) and the
        # TorchScript exporter's deprecation notice.
        warnings.simplefilter("ignore")
        # The TorchScript-based exporter (torch < 2.5 has no `dynamo` argument and uses it anyway).
        kw = {"dynamo": False} if "dynamo" in inspect.signature(torch.onnx.export).parameters else {}
        torch.onnx.export(
            wrapper, (left, right), path, opset_version=opset, input_names=["left", "right"],
            output_names=names, do_constant_folding=True, **kw,
        )
    meta = {
        "muir_config": cfg.to_json(),
        "muir_iters": str(iters),
        "muir_size": f"{width}x{height}",
        "muir_inputs": "left, right: float32 (1, 3, H, W) RGB 0..255",
        "muir_outputs": "disparity: float32 (1, 1, H, W) px (before full-resolution refinement)"
        + ("; uncertainty: float32 (1, 1, H, W) u = log(beta^2), predicted error exp(u/2) px" if cfg.mud else ""),
        "muir_padding": "inputs padded to a multiple of 16 by edge replication (right/bottom), outputs cropped",
    }
    if source:
        meta["muir_source"] = os.path.basename(source)
    m = onnx.load(path)
    for k, v in meta.items():
        p = m.metadata_props.add()
        p.key, p.value = k, v
    m.producer_name = "muir.export"
    m.doc_string = f"MUIR ({cfg.name}) stereo network, {width}x{height}, {iters} iterations"
    onnx.checker.check_model(m)
    onnx.save(m, path)
    return meta


def check_pair(width: int, height: int):
    """A deterministic textured pair at disparity 6 px (left(x) = right(x - 6)) for the post-export check."""
    g = torch.Generator().manual_seed(1)
    base = torch.rand(1, 3, (height + 3) // 4 + 1, (width + 3) // 4 + 8, generator=g) * 255.0
    big = F.interpolate(base, scale_factor=4, mode="bilinear", align_corners=False)
    left = big[:, :, :height, :width].contiguous()
    right = big[:, :, :height, 6 : 6 + width].contiguous()
    return left, right


def compare(path: str, model, iters: int, left, right, threads: int = 1) -> dict:
    """Runs the ONNX file with ONNX Runtime (CPU) and the twin on one pair: max |difference| and times."""
    import onnxruntime as ort

    so = ort.SessionOptions()
    so.intra_op_num_threads = threads
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession(path, so, providers=["CPUExecutionProvider"])
    t = time.perf_counter()
    out = sess.run(None, {"left": left.numpy(), "right": right.numpy()})
    t_ort = time.perf_counter() - t
    h, w = left.shape[2:]
    wrapper = OnnxMUIR(model.float().cpu().eval(), h, w, iters)
    t = time.perf_counter()
    with torch.inference_mode():
        ref = wrapper(left, right)
    t_torch = time.perf_counter() - t
    ref = ref if isinstance(ref, tuple) else (ref,)
    dd = (torch.from_numpy(out[0]) - ref[0]).abs()
    res = {"disparity": float(dd.max()), "disparity_mean": float(dd.mean()), "ort_s": t_ort, "torch_s": t_torch}
    if len(ref) > 1:
        res["uncertainty"] = float((torch.from_numpy(out[1]) - ref[1]).abs().max())
    return res


def parse_size(s: str):
    """WxH (width x height, as the muir CLI's --size) -> (width, height)."""
    try:
        w, h = (int(v) for v in s.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{s}' is not WxH (e.g. 640x480)") from None
    if not (MIN_SIDE <= w <= MAX_WIDTH and MIN_SIDE <= h <= MAX_HEIGHT):
        raise argparse.ArgumentTypeError(f"'{s}' is not WxH with sides from {MIN_SIDE} to {MAX_WIDTH}x{MAX_HEIGHT}")
    return w, h


def build_parser():
    p = argparse.ArgumentParser(prog="python -m muir.export", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=__doc__.split("\n", 2)[2])
    sub = p.add_subparsers(dest="cmd", required=True, metavar="{onnx}")
    o = sub.add_parser("onnx", help="ONNX model for one fixed input size and number of iterations",
                       description="ONNX model (TorchScript exporter) for one fixed input size and number of "
                                   "iterations", formatter_class=argparse.RawDescriptionHelpFormatter,
                       epilog=__doc__.split("\n", 2)[2])
    o.add_argument("--model", required=True, help="model .safetensors")
    o.add_argument("--config", default=None, help="config preset for files without config metadata")
    o.add_argument("--size", required=True, type=parse_size, metavar="WxH",
                   help=f"input width x height in px, sides {MIN_SIDE}..{MAX_WIDTH}x{MAX_HEIGHT} "
                        "(any; padded to a multiple of 16 inside the graph)")
    o.add_argument("--iters", type=int, default=None, help="refinement iterations (default: the config's)")
    o.add_argument("--opset", type=int, default=DEFAULT_OPSET, help=f"ONNX opset, 14..20 (default {DEFAULT_OPSET})")
    o.add_argument("--out", required=True, help="output .onnx file")
    o.add_argument("--no-check", action="store_true",
                   help="skip the check: ONNX Runtime vs the twin on a synthetic pair (max |difference|, times)")
    o.add_argument("--threads", type=int, default=1,
                   help="torch threads of the export, and of both runtimes in the check (default 1)")
    return p


def main(argv=None):
    p = build_parser()
    a = p.parse_args(argv)
    w, h = a.size
    if a.iters is not None and not (1 <= a.iters <= MAX_ITERS):
        p.error(f"--iters must be from 1 to {MAX_ITERS}, got {a.iters}")
    if not (14 <= a.opset <= 20):
        p.error(f"--opset must be from 14 to 20, got {a.opset}")
    if a.threads < 1:
        p.error(f"--threads must be >= 1, got {a.threads}")
    out_dir = os.path.dirname(os.path.abspath(a.out))
    if not os.path.isdir(out_dir):
        p.error(f"--out {a.out}: no directory {out_dir}")
    from .checkpoint import load_model

    try:
        model = load_model(a.model, a.config)
    except ValueError as e:  # ModelFileError: names the file and the reason
        p.error(str(e))
    try:
        import onnx  # noqa: F401
    except ImportError:
        p.error("ONNX export needs the onnx package: pip install 'muir[export]' (or pip install onnx onnxruntime)")
    iters = model.cfg.iters if a.iters is None else a.iters
    torch.set_num_threads(a.threads)
    t = time.perf_counter()
    try:
        export_onnx(model, a.out, w, h, iters, a.opset, source=a.model)
    except Exception as e:  # exporter errors are long; one line with the type and the start
        msg = " ".join(str(e).split())[:300]
        print(f"error: ONNX export of {a.model} at {w}x{h} failed ({type(e).__name__}: {msg})", file=sys.stderr)
        return 1
    size_mb = os.path.getsize(a.out) / 1e6
    print(f"{a.out}: {model.cfg.name}, {w}x{h}, {iters} iterations, opset {a.opset}, outputs "
          f"{', '.join(output_names(model))}, {size_mb:.1f} MB ({time.perf_counter() - t:.1f} s)", file=sys.stderr)
    if a.no_check:
        return 0
    try:
        import onnxruntime  # noqa: F401
    except ImportError:
        print("check skipped: onnxruntime is not installed (pip install 'muir[export]')", file=sys.stderr)
        return 0
    left, right = check_pair(w, h)
    r = compare(a.out, model, iters, left, right, a.threads)
    extra = f", uncertainty max {r['uncertainty']:.2e}" if "uncertainty" in r else ""
    print(f"check (synthetic pair, {a.threads} thread(s)): |ONNX Runtime - twin| disparity max "
          f"{r['disparity']:.2e} px, "
          f"mean {r['disparity_mean']:.1e} px{extra}; ONNX Runtime {r['ort_s']:.2f} s, PyTorch {r['torch_s']:.2f} s "
          "(first run each)", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
