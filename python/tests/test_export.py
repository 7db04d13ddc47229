"""ONNX export (muir.export): the shipped model on the shipped Teddy pair, ONNX Runtime vs the twin."""
from __future__ import annotations

import os

import numpy as np
import pytest
import torch
from PIL import Image

from muir import export

REPO = os.path.normpath(os.path.join(os.path.dirname(os.path.abspath(__file__)), "../.."))
MODEL = os.path.join(REPO, "models", "muir-slim.safetensors")
TEDDY = os.path.join(REPO, "assets", "teddy")
W, H = 160, 120  # 120 is not a multiple of 16: the graph's edge padding and crop are exercised
ITERS = 7


def teddy_crop():
    """Left/right views of Teddy (450x375) cropped to W x H around the image centre, uint8 (H, W, 3)."""
    views = []
    for name in ("left", "right"):
        a = np.asarray(Image.open(os.path.join(TEDDY, f"{name}.png")).convert("RGB"))
        y0, x0 = (a.shape[0] - H) // 2, (a.shape[1] - W) // 2
        views.append(np.ascontiguousarray(a[y0 : y0 + H, x0 : x0 + W]))
    return views


def test_onnx_matches_the_twin_on_teddy(tmp_path, capsys):
    try:
        import onnxruntime as ort
    except ImportError:
        pytest.skip("onnxruntime is not installed (pip install 'muir[export]'): ONNX export not checked")
    import onnx

    from muir.checkpoint import load_model
    from muir.evaluate import run_model

    out = tmp_path / "muir-slim.onnx"
    # The command line as a user runs it (its own post-export check off: the test does it on Teddy).
    rc = export.main(["onnx", "--model", MODEL, "--size", f"{W}x{H}", "--iters", str(ITERS), "--out", str(out),
                      "--no-check"])
    assert rc == 0
    m = onnx.load(str(out))
    meta = {p.key: p.value for p in m.metadata_props}
    assert meta["muir_iters"] == str(ITERS) and meta["muir_size"] == f"{W}x{H}"
    dims = lambda vi: [d.dim_value for d in vi.type.tensor_type.shape.dim]
    assert [(i.name, dims(i)) for i in m.graph.input] == [("left", [1, 3, H, W]), ("right", [1, 3, H, W])]
    assert [(o.name, dims(o)) for o in m.graph.output] == [("disparity", [1, 1, H, W]), ("uncertainty", [1, 1, H, W])]

    left, right = teddy_crop()
    so = ort.SessionOptions()
    so.intra_op_num_threads = 1
    so.inter_op_num_threads = 1
    sess = ort.InferenceSession(str(out), so, providers=["CPUExecutionProvider"])
    to_nchw = lambda a: np.ascontiguousarray(a.transpose(2, 0, 1)[None].astype(np.float32))
    d_onnx, u_onnx = sess.run(None, {"left": to_nchw(left), "right": to_nchw(right)})

    # The twin's eval-mode forward as muir.evaluate runs it (edge padding to 16, crop), same iterations.
    model = load_model(MODEL)
    ref = run_model(model, left, right, iters=ITERS)
    d_err = float(np.abs(d_onnx[0, 0] - ref["disp"]).max())
    u_err = float(np.abs(u_onnx[0, 0] - ref["u"]).max())
    with capsys.disabled():
        print(f"\nONNX vs twin on Teddy {W}x{H}, {ITERS} iters: max |d| diff {d_err:.2e} px, max |u| diff {u_err:.2e}")
    assert np.isfinite(d_onnx).all() and ref["disp"].max() > 5.0  # a real disparity map, not a flat one
    assert d_err <= 1e-3, d_err
    assert u_err <= 1e-3, u_err


def test_bad_arguments_give_one_line_errors(tmp_path, capsys):
    cases = [
        (["--model", str(tmp_path / "missing.safetensors"), "--size", "64x48"], "missing.safetensors"),
        (["--model", MODEL, "--size", "640"], "not WxH"),
        (["--model", MODEL, "--size", "16x16"], "sides from 32"),
        (["--model", MODEL, "--size", "64x48", "--iters", "0"], "--iters"),
    ]
    for args, needle in cases:
        with pytest.raises(SystemExit) as e:
            export.main(["onnx", *args, "--out", str(tmp_path / "x.onnx")])
        assert e.value.code == 2
        last = capsys.readouterr().err.strip().splitlines()[-1]
        assert "error:" in last and needle in last, last
    assert not (tmp_path / "x.onnx").exists()
