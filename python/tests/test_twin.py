"""The twin against its committed golden file, the synthetic stream's determinism, a checkpoint
round trip, and the evaluation metrics on tiny arrays with known answers."""
from __future__ import annotations

import os

import numpy as np
import torch
from safetensors.torch import load_file

from muir import evaluate, seeded, synth
from muir.checkpoint import load_model, read_config, save_model
from muir.config import preset
from muir.model import MUIR

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))


def test_shipped_model_reproduces_its_golden_file():
    """host-tests/fixtures/golden/shipped-muir-slim.safetensors (python -m muir.golden --shipped,
    the file the Rust float engine is checked against) is what the twin computes today."""
    g = load_file(os.path.join(REPO, "host-tests", "fixtures", "golden", "shipped-muir-slim.safetensors"))
    model = load_model(os.path.join(REPO, "models", "muir-slim.safetensors")).eval()
    torch.set_num_threads(1)
    with torch.no_grad():
        disp, u = model(g["input.left"][None], g["input.right"][None])
    assert disp[0].shape == g["up.disp"].shape
    assert float((disp[0] - g["up.disp"]).abs().max()) < 1e-3
    assert float((u[0] - g["up.u"]).abs().max()) < 1e-3


def test_synthetic_stream_is_deterministic():
    photos = synth.PhotoPool(nogt_dir=None, use_skimage=False)
    a = synth.sample(7, 3, h=48, w=96, photos=photos)
    b = synth.sample(7, 3, h=48, w=96, photos=photos)
    c = synth.sample(7, 4, h=48, w=96, photos=photos)
    for k in ("left", "right", "disp"):
        assert np.array_equal(a[k], b[k]), k
    assert a["left"].shape == (48, 96, 3) and a["left"].dtype == np.uint8 and a["disp"].dtype == np.float32
    assert not np.array_equal(a["left"], c["left"])  # another index, another scene


def test_checkpoint_round_trip(tmp_path):
    cfg = preset("muir-slim")
    model = MUIR(cfg)
    model.load_state_dict(seeded.state_dict(model, 5), strict=True)
    path = str(tmp_path / "m.safetensors")
    save_model(model, path, {"note": "round trip"})
    assert read_config(path) == cfg
    back = load_model(path)
    want, got = model.state_dict(), back.state_dict()
    assert want.keys() == got.keys()
    for k in want:
        assert torch.equal(want[k].float(), got[k].float()), k


def test_error_metrics_on_known_arrays():
    gt = np.array([[10.0, 10.0, 10.0, 100.0]], np.float32)
    pred = np.array([[10.0, 11.5, 12.5, 104.0]], np.float32)  # errors 0, 1.5, 2.5, 4
    m = evaluate.error_metrics(pred, gt, np.ones_like(gt, bool))
    assert m["n"] == 4
    assert np.isclose(m["epe"], 2.0) and np.isclose(m["a50"], 2.0)
    assert m["bad1"] == 75.0 and m["bad2"] == 50.0
    assert m["d1"] == 0.0  # 4 px > 3 px but not > 5 % of 100 px
    # a region selects pixels; an empty one has no figures
    assert evaluate.error_metrics(pred, gt, np.array([[True, False, False, False]]))["epe"] == 0.0
    assert evaluate.error_metrics(pred, gt, np.zeros_like(gt, bool)) is None


def test_sparsification_on_known_arrays():
    err = np.array([4.0, 3.0, 2.0, 1.0] * 25)
    # sigma ordered as the error: the model curve is the oracle's, AUSE 0
    model, oracle = evaluate.sparsification(err, err.copy())
    assert np.allclose(model, oracle) and np.isclose(model[0], 1.0)
    # removing the largest 25 % of errors leaves mean (3 + 2 + 1) / 3 = 2 of a full mean 2.5
    assert np.isclose(oracle[25], 2.0 / 2.5)
    # sigma ordered against the error: the model curve rises above 1
    model, _ = evaluate.sparsification(err, -err)
    assert model[25] > 1.0
