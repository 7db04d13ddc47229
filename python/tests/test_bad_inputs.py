"""Bad input to the training and evaluation scripts gets a one-line error naming the file."""
from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
from PIL import Image
from safetensors import safe_open
from safetensors.torch import load_file, save_file

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))
MODEL = os.path.join(REPO, "models", "muir-slim.safetensors")


def run(*args):
    env = {**os.environ, "PYTHONPATH": os.path.join(REPO, "python")}
    r = subprocess.run([sys.executable, "-m", *args], env=env, cwd=REPO, capture_output=True, text=True, timeout=300)
    lines = [l for l in r.stderr.strip().splitlines() if l.strip()]
    assert r.returncode != 0
    assert "Traceback" not in r.stderr, r.stderr[-2000:]
    return lines[-1]


def test_truncated_and_nan_models(tmp_path):
    trunc = tmp_path / "trunc.safetensors"
    trunc.write_bytes(open(MODEL, "rb").read()[:1000])
    assert str(trunc) in run("muir.evaluate", "--model", str(trunc), "--out", str(tmp_path / "o"))
    t = load_file(MODEL)
    k = next(k for k, v in t.items() if v.dim() > 1)
    t[k].view(-1)[0] = float("nan")
    with safe_open(MODEL, "pt") as f:
        meta = f.metadata()
    nan = tmp_path / "nan.safetensors"
    save_file(t, str(nan), metadata=meta)
    for cmd in (("muir.evaluate", "--model", str(nan), "--out", str(tmp_path / "o")),
                ("muir.train", "--out", str(tmp_path / "t"), "--init", str(nan), "--steps", "1")):
        line = run(*cmd)
        assert str(nan) in line and "NaN" in line, line


def test_unreadable_checkpoint(tmp_path):
    (tmp_path / "ckpt_last.pt").write_bytes(b"garbage")
    line = run("muir.train", "--out", str(tmp_path), "--resume")
    assert "ckpt_last.pt" in line and "unreadable" in line, line


def test_missing_view_and_gt_of_another_size(tmp_path):
    sc = tmp_path / "ds" / "sc"
    sc.mkdir(parents=True)
    img = np.zeros((40, 60, 3), np.uint8)
    Image.fromarray(img).save(sc / "left.png")
    Image.fromarray(np.zeros((10, 10), np.uint8)).save(sc / "disp2.png")
    args = ("muir.evaluate", "--datasets", "ds", "--root", str(tmp_path), "--sgbm", "--out", str(tmp_path / "o"))
    assert str(sc / "right.png") in run(*args)
    Image.fromarray(img).save(sc / "right.png")
    line = run(*args)
    assert str(sc / "disp2.png") in line and "10x10" in line, line
