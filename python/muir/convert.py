"""Convert a PyTorch checkpoint (.pth: a state_dict, or a dict holding one) to a muir safetensors file.

    python -m muir.convert raftstereo-realtime.pth raft-stereo-realtime.safetensors --config raft-stereo-realtime

The state_dict is loaded into the twin with strict=True first (a leading `module.` is stripped), so a
file that does not fit the config fails here, not on the device.
"""
import argparse
import sys

import torch

from .checkpoint import save_model
from .config import PRESETS, preset
from .model import MUIR, strip_module_prefix


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m muir.convert", description=__doc__.splitlines()[0])
    p.add_argument("checkpoint", help="input .pth")
    p.add_argument("output", help="output .safetensors")
    p.add_argument("--config", required=True, choices=sorted(PRESETS), help="model config of the checkpoint")
    a = p.parse_args(argv)
    obj = torch.load(a.checkpoint, map_location="cpu", weights_only=True)
    if isinstance(obj, dict) and "state_dict" in obj and isinstance(obj["state_dict"], dict):
        obj = obj["state_dict"]
    elif isinstance(obj, dict) and "model" in obj and isinstance(obj["model"], dict):
        obj = obj["model"]
    model = MUIR(preset(a.config))
    try:
        model.load_state_dict(strip_module_prefix(obj), strict=True)
    except RuntimeError as e:
        print(f"error: {a.checkpoint} does not match config {a.config}:\n{e}", file=sys.stderr)
        return 2
    save_model(model, a.output, {"source": a.checkpoint})
    print(f"wrote {a.output} ({sum(v.numel() for v in model.state_dict().values())} values)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
