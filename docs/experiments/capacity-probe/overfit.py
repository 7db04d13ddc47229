"""Capacity probe (issue #3): can muir-slim fit sub-pixel disparity at all?

Fine-tunes a model on a FIXED set of N synthetic crops (cycled, batch 4, the training loss of
muir.train) and reports, every --every steps, the median error (A50), Bad2.0 and EPE over the
non-occluded pixels of those same crops and of N held-out crops of the same generator. If the
fitted set's A50 falls far below the ~0.6-0.8 px the model has everywhere, the architecture can
represent sub-pixel matches and the gap is training (steps/data); if it stays, it is capacity.

PYTHONPATH=python python docs/experiments/capacity-probe/overfit.py MODEL [--n 16] [--steps 600]
"""
import argparse, os, sys, time

import numpy as np
import torch

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "../../../python"))
from muir import synth  # noqa: E402
from muir.checkpoint import load_model  # noqa: E402
from muir.train import MAX_GT, sequence_loss  # noqa: E402


def noc_mask(gl, gr):
    h, w = gl.shape
    xs = np.arange(w)[None].repeat(h, 0)
    xr = np.rint(xs - gl).astype(int)
    ok = (xr >= 0) & (xr < w) & np.isfinite(gl)
    rows = np.arange(h)[:, None].repeat(w, 1)
    noc = ok.copy()
    noc[ok] = np.abs(gl[ok] - gr[rows[ok], xr[ok]]) <= 1
    return noc


def to_t(s):
    l = torch.from_numpy(s["left"]).permute(2, 0, 1).float()[None]
    r = torch.from_numpy(s["right"]).permute(2, 0, 1).float()[None]
    return l, r


@torch.no_grad()
def measure(model, samples):
    model.eval()
    a50, bad2, epe = [], [], []
    for s in samples:
        l, r = to_t(s)
        d = model(l, r)[0][0, 0].numpy()
        e = np.abs(d - s["disp"])[s["noc"]]
        a50.append(np.median(e)); bad2.append((e > 2).mean() * 100); epe.append(e.mean())
    model.train()
    return np.mean(a50), np.mean(bad2), np.mean(epe)


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("model")
    p.add_argument("--n", type=int, default=16)
    p.add_argument("--steps", type=int, default=600)
    p.add_argument("--every", type=int, default=100)
    p.add_argument("--lr", type=float, default=2e-4)
    p.add_argument("--crop", default="128x320")
    p.add_argument("--seed", type=int, default=4242)
    a = p.parse_args()
    h, w = map(int, a.crop.split("x"))
    torch.manual_seed(0)
    mk = lambda i: synth.sample(a.seed, i, h, w, with_right_disp=True)
    fit = [mk(i) for i in range(a.n)]
    held = [mk(10_000 + i) for i in range(a.n)]
    for s in fit + held:
        s["noc"] = noc_mask(s["disp"], s["disp_right"])
    model = load_model(a.model)
    cfg = model.cfg
    opt = torch.optim.AdamW(model.parameters(), lr=a.lr, weight_decay=1e-5)
    model.train()
    print("step,fit_a50,fit_bad2,fit_epe,held_a50,held_bad2,held_epe,loss,s_per_step", flush=True)
    t0, loss_v = time.time(), float("nan")
    for step in range(a.steps + 1):
        if step % a.every == 0:
            f, g = measure(model, fit), measure(model, held)
            dt = (time.time() - t0) / max(step, 1)
            print(f"{step},{f[0]:.3f},{f[1]:.2f},{f[2]:.3f},{g[0]:.3f},{g[1]:.2f},{g[2]:.3f},{loss_v:.3f},{dt:.2f}", flush=True)
        if step == a.steps:
            break
        idx = [(step * 4 + k) % a.n for k in range(4)]
        pairs = [to_t(fit[i]) for i in idx]
        l = torch.cat([p_[0] for p_ in pairs]); r = torch.cat([p_[1] for p_ in pairs])
        gt = torch.stack([torch.from_numpy(fit[i]["disp"])[None] for i in idx])
        valid = torch.isfinite(gt) & (gt >= 0) & (gt < MAX_GT)
        for g_ in opt.param_groups:  # 50-step linear warm-up, then constant
            g_["lr"] = a.lr * min(1.0, (step + 1) / 50)
        out = model(l, r, iters=cfg.iters, train_out=True, binarize_p=0.5)
        loss, _ = sequence_loss(out, gt, valid, cfg)
        opt.zero_grad(); loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step(); loss_v = loss.item()


if __name__ == "__main__":
    main()
