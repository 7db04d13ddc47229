"""The committed resume state: AdamW moments in bf16 load back into float32 optimizer state, the rest
of the checkpoint is unchanged, and the command writes the files --resume reads."""

import json
import os

import torch

from muir import resume_state


def _state():
    torch.manual_seed(0)
    net = torch.nn.Linear(8, 4)
    opt = torch.optim.AdamW(net.parameters(), lr=1e-3)
    for _ in range(3):
        opt.zero_grad()
        net(torch.randn(5, 8)).square().mean().backward()
        opt.step()
    return net, opt, {"model": net.state_dict(), "optimizer": opt.state_dict(), "step": 3, "args": {"lr": 1e-3}}


def test_compact_moments_load_back_as_float32():
    net, opt, st = _state()
    small = resume_state.compact(st)
    for pid, s in small["optimizer"]["state"].items():
        assert s["exp_avg"].dtype == torch.bfloat16 and s["exp_avg_sq"].dtype == torch.bfloat16
        assert s["step"].dtype == st["optimizer"]["state"][pid]["step"].dtype  # counters untouched
    assert small["model"] is st["model"] and small["step"] == 3
    opt2 = torch.optim.AdamW(net.parameters(), lr=1e-3)
    opt2.load_state_dict(small["optimizer"])
    for pid, s in opt2.state_dict()["state"].items():
        ref = st["optimizer"]["state"][pid]["exp_avg"]
        assert s["exp_avg"].dtype == torch.float32
        assert torch.allclose(s["exp_avg"], ref, rtol=1e-2, atol=1e-6)


def test_command_writes_what_resume_reads(tmp_path):
    _, _, st = _state()
    run = tmp_path / "run"
    run.mkdir()
    torch.save(st, run / "ckpt_last.pt")
    (run / "args.json").write_text(json.dumps({"steps": 10}))
    dest = tmp_path / "resume"
    assert resume_state.main([str(run), str(dest)]) == 0
    assert sorted(os.listdir(dest)) == ["args.json", "ckpt.pt"]
    back = torch.load(dest / "ckpt.pt", map_location="cpu", weights_only=False)
    assert back["step"] == 3
    assert resume_state.main([str(tmp_path / "missing"), str(dest)]) == 2
