"""Golden parity fixtures: the twin's intermediate tensors on a real stereo crop, seeded weights.

    PYTHONPATH=python python -m muir.golden            # writes host-tests/fixtures/golden/*.safetensors

Each fixture holds the input crop (`input.left`, `input.right`, 3 x H x W, 0..255) and every tensor
the twin records (see `MUIR.forward(trace=...)`), batch dimension dropped, plus metadata: the config
JSON, the weight seed (python/muir/seeded.py) and the crop's source. The Rust tests
(host-tests/float_parity.rs) rebuild the weights from the seed, run the float reference and compare
every tensor. Backbone tensors above 1/8 resolution are left out to keep the fixtures small.
"""
import argparse
import json
import os
import sys

import numpy as np
import torch
from PIL import Image
from safetensors.torch import save_file

from . import seeded
from .config import PRESETS, preset
from .model import MUIR

DEFAULT_SOURCE = "middlebury2003/cones"
SKIP = ("backbone.conv1", "backbone.layer1", "backbone.layer2")

# (config, seed, crop height, crop width, crop y0, crop x0)
FIXTURES = [
    ("muir-fast", 1, 64, 128, 150, 200),
    ("muir-slim", 2, 64, 128, 220, 120),
    ("raft-stereo-realtime", 3, 48, 96, 100, 260),
]


def load_crop(data_root, scene, h, w, y0, x0):
    return load_crop_scene(data_root, scene, h, w, y0, x0)


def make(cfg_name, seed, h, w, y0, x0, data_root, out_dir):
    cfg = preset(cfg_name)
    model = MUIR(cfg)
    model.load_state_dict(seeded.state_dict(model, seed), strict=True)
    model.eval()
    left, right = load_crop(data_root, DEFAULT_SOURCE, h, w, y0, x0)
    trace = {}
    with torch.no_grad():
        model(left[None], right[None], trace=trace)
    tensors = {"input.left": left.contiguous(), "input.right": right.contiguous()}
    for k, v in trace.items():
        if k in SKIP:
            continue
        v = v.float()
        tensors[k] = (v[0] if v.shape[0] == 1 else v).contiguous()
    meta = {
        "muir_config": cfg.to_json(),
        "seed": str(seed),
        "source": f"{DEFAULT_SOURCE} crop y={y0} x={x0} {h}x{w} (Scharstein & Szeliski, CVPR 2003)",
        "generator": "python -m muir.golden",
        "torch": torch.__version__,
    }
    path = os.path.join(out_dir, f"{cfg_name}.safetensors")
    save_file(tensors, path, metadata=meta)
    size = os.path.getsize(path)
    print(f"{path}: {len(tensors)} tensors, {size / 1e6:.2f} MB", file=sys.stderr)


# The shipped model's output on one real pair (issue: Rust float reproduces the twin within 0.01 px).
SHIPPED_SCENE = ("middlebury2006/Aloe", 160, 224, 120, 100)  # scene, crop h, crop w, y0, x0


def make_shipped(model_path, data_root, out_dir):
    from .checkpoint import load_model

    model = load_model(model_path)
    scene, h, w, y0, x0 = SHIPPED_SCENE
    left, right = load_crop_scene(data_root, scene, h, w, y0, x0)
    with torch.no_grad():
        disp, u = model(left[None], right[None])
    tensors = {"input.left": left, "input.right": right, "up.disp": disp[0].contiguous()}
    if u is not None:
        tensors["up.u"] = u[0].contiguous()
    meta = {
        "muir_config": model.cfg.to_json(),
        "model": os.path.basename(model_path),
        "source": f"{scene} crop y={y0} x={x0} {h}x{w} (Scharstein & Pal, CVPR 2007; Hirschmueller & Scharstein, CVPR 2007)",
        "generator": "python -m muir.golden --shipped " + os.path.basename(model_path),
        "torch": torch.__version__,
    }
    path = os.path.join(out_dir, "shipped-" + os.path.basename(model_path))
    save_file(tensors, path, metadata=meta)
    print(f"{path}: {os.path.getsize(path) / 1e6:.2f} MB", file=sys.stderr)


# The full-resolution refinement's integer stage on a real crop (host-tests/float_parity.rs checks
# that the Rust stage gives the same integers as python/muir/fullres.py).
FULLRES_CROP = ("assets/teddy", 128, 192, 150, 180)  # repository folder, crop h, crop w, y0, x0


def make_fullres(model_path, out_dir):
    from . import fullres
    from .checkpoint import load_model

    repo = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))
    folder, h, w, y0, x0 = FULLRES_CROP
    left, right = load_crop_scene(repo, folder, h, w, y0, x0)
    model = load_model(model_path)
    with torch.no_grad():
        disp, u = model(left[None], right[None])
    lu8 = left.permute(1, 2, 0).numpy().astype(np.uint8)
    ru8 = right.permute(1, 2, 0).numpy().astype(np.uint8)
    dq = fullres.quantize_disp(disp[0, 0].numpy())
    uq = fullres.quantize_u(u[0, 0].numpy())
    out, ok = fullres.refine_q(lu8, ru8, dq, uq)
    f = lambda a: torch.from_numpy(a.astype(np.float32))  # i16 values, exact in f32
    tensors = {"fullres.d0": f(dq), "fullres.u": f(uq), "fullres.out": f(out)}
    meta = {
        "source": f"{folder} crop y={y0} x={x0} {h}x{w}",
        "model": os.path.basename(model_path),
        "refined": str(int(ok.sum())),
        "generator": "python -m muir.golden --fullres " + os.path.basename(model_path),
    }
    path = os.path.join(out_dir, "fullres-teddy.safetensors")
    save_file(tensors, path, metadata=meta)
    print(f"{path}: {os.path.getsize(path) / 1e6:.2f} MB, {int(ok.sum())} of {h * w} pixels refined", file=sys.stderr)


def load_crop_scene(data_root, scene, h, w, y0, x0):
    def rd(name):
        im = np.asarray(Image.open(os.path.join(data_root, scene, name)).convert("RGB"), dtype=np.float32)
        return torch.from_numpy(im[y0 : y0 + h, x0 : x0 + w].transpose(2, 0, 1).copy())

    return rd("left.png"), rd("right.png")


def main(argv=None):
    p = argparse.ArgumentParser(prog="python -m muir.golden", description="Write golden parity fixtures.")
    p.add_argument("--data", default=os.path.join(os.path.dirname(__file__), "../../../shared/data"))
    p.add_argument("--out", default=os.path.join(os.path.dirname(__file__), "../../host-tests/fixtures/golden"))
    p.add_argument("--shipped", metavar="MODEL", help="only write the shipped model's fixture (models/*.safetensors)")
    p.add_argument("--fullres", metavar="MODEL", help="only write the full-resolution refinement's fixture")
    a = p.parse_args(argv)
    torch.set_num_threads(max(1, torch.get_num_threads()))
    os.makedirs(a.out, exist_ok=True)
    if a.shipped:
        make_shipped(a.shipped, a.data, a.out)
        return 0
    if a.fullres:
        make_fullres(a.fullres, a.out)
        return 0
    for f in FIXTURES:
        make(*f, a.data, a.out)
    # Preset configs as the twin serialises them (host-tests/model_files.rs parses them in Rust).
    presets = {k: json.loads(v.to_json()) for k, v in PRESETS.items()}
    with open(os.path.join(a.out, "..", "python-presets.json"), "w") as f:
        json.dump(presets, f, indent=1, sort_keys=True)
        f.write("\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
