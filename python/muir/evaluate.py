"""Evaluate MUIR models and OpenCV StereoSGBM on the real scenes with GT, at the stored resolution.

    PYTHONPATH=python python -m muir.evaluate --model runs/slim/model.safetensors --sgbm --out runs/eval
    PYTHONPATH=python python -m muir.evaluate --tune-sgbm --out runs/eval      # once: SGBM parameters
    cargo build --release --bin muir && PYTHONPATH=python python -m muir.evaluate \
        --blob models/muir-slim.muirq --out runs/eval/fixed               # the device's fixed-point engine

Default scene set: the 11 held-out scenes of muir.split (Middlebury 2003 and 2005 at quarter/third
size, ETH3D, KITTI 2015), never trained on; --set train / middlebury28 and --datasets pick others. Network input: RGB float 0..255 (gray views replicated), padded to a
multiple of 16 by edge replication on the right/bottom, output cropped back.

Metrics per scene over all valid GT pixels ("all"), and where a non-occlusion mask exists (tsukuba's
official one, else the left-right GT check, see muir.data) over non-occluded ("noc") and occluded ("occ")
pixels: EPE, A50 (median abs error), Bad1.0, Bad2.0, D1 (error > 3 px and > 5 % of GT), all in px / %.
Means are over scenes. Uncertainty (models with MUD): predicted error sigma = exp(u/2); AUSE of EPE
(sparsification by sigma vs oracle by true error, both curves normalised by the full EPE, removal
fractions 0..0.99 in steps of 0.01) with the random-order baseline (normalised curve = 1), and EPE /
kept fraction after rejecting sigma > 1 px and sigma > 3 px.

SGBM: fixed parameters (tuned with --tune-sgbm on Middlebury 2001 scenes only), search range from the
data set's disparity budget (muir.data.MAX_DISP), left border padded by the search range so border
pixels get a match; invalid pixels (speckle filter, uniqueness, left-right check) are filled from the
nearest valid pixel on the same row, taking the smaller (background) of the left and right neighbours;
metrics are over all GT pixels after filling; raw density and EPE on raw-valid pixels are reported too.

Outputs in --out: <method>.json (per scene and mean figures), results.md (tables), vis/<method>/*.png.
"""
from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import subprocess
import sys
import tempfile
import time

import cv2
import numpy as np
import torch
import torch.nn.functional as F

from . import data as D
from . import fullres

# Tuned once on middlebury2001 {barn1, sawtooth, venus} with --tune-sgbm (512 settings, objective: mean
# EPE over all GT pixels after filling; see docs/training.md). P1/P2 are multiplied by 3 * blockSize^2
# (colour input); numDisparities comes from the data set's budget.
SGBM_PARAMS = {
    "blockSize": 5, "P1": 8, "P2": 32, "uniquenessRatio": 15, "speckleWindowSize": 100, "speckleRange": 2,
    "disp12MaxDiff": 1, "preFilterCap": 63, "mode": "HH",
}
SGBM_TUNE_SCENES = ("middlebury2001/barn1", "middlebury2001/sawtooth", "middlebury2001/venus")
MODES = {"SGBM": cv2.STEREO_SGBM_MODE_SGBM, "HH": cv2.STEREO_SGBM_MODE_HH,
         "SGBM_3WAY": cv2.STEREO_SGBM_MODE_SGBM_3WAY, "HH4": cv2.STEREO_SGBM_MODE_HH4}


# ------------------------------------------------------------------------------------------------
# Methods
# ------------------------------------------------------------------------------------------------
def run_model(model, left: np.ndarray, right: np.ndarray, iters=None, device="cpu"):
    """Returns dict(disp (H,W), u (H,W) or None, mask (H,W) matchability at 1/8 upsampled, or None)."""
    h, w = left.shape[:2]
    m = model.cfg.pad_multiple
    ph, pw = (-h) % m, (-w) % m

    def prep(img):
        t = torch.from_numpy(img).permute(2, 0, 1)[None].float().to(device)
        return F.pad(t, (0, pw, 0, ph), mode="replicate") if (ph or pw) else t

    trace = {}
    with torch.inference_mode():
        disp, u = model(prep(left), prep(right), iters=iters, trace=trace)
    out = {"disp": disp[0, 0, :h, :w].float().cpu().numpy(), "u": None, "mask": None}
    if u is not None:
        out["u"] = u[0, 0, :h, :w].float().cpu().numpy()
    if "final.mud_m" in trace:
        mm = trace["final.mud_m"][0, 0].float().cpu().numpy()
        out["mask"] = np.kron(mm, np.ones((8, 8), np.float32))[:h, :w]  # one value per 8x8 cell
    return out


def run_fixed_engine(muir_bin: str, blob: str, scene_dir: str, iters=None, refine=True, early_stop=None,
                     max_disparity=None):
    """The Rust fixed-point engine on a scene's left.png/right.png (the files, as a user would run it):
    (disparity (H,W), dict(u=log-variance from the predicted error exp(u/2) the CLI writes))."""
    with tempfile.TemporaryDirectory() as tmp:
        disp, err = os.path.join(tmp, "d.pfm"), os.path.join(tmp, "e.pfm")
        cmd = [muir_bin, "run", "--engine", "fixed", "--model", blob,
               "--left", os.path.join(scene_dir, "left.png"), "--right", os.path.join(scene_dir, "right.png"),
               "--disparity", disp, "--uncertainty", err]
        if iters:
            cmd += ["--iters", str(iters)]
        if not refine:
            cmd += ["--no-refine"]
        if max_disparity is not None:
            cmd += ["--max-disparity", str(max_disparity)]
        if early_stop is not None:
            cmd += ["--early-stop", str(early_stop[0]), "--settled", str(early_stop[1])]
        r = subprocess.run(cmd, capture_output=True, text=True)
        if r.returncode != 0:
            raise RuntimeError(f"{' '.join(cmd)} failed ({r.returncode}): {r.stderr.strip()}")
        d, e = D.read_pfm(disp), D.read_pfm(err)
    import re

    m = re.search(r"(\d+)(?: of (\d+))? iters", r.stderr)
    used = int(m.group(1)) if m else None
    return d, {"disp": d, "u": 2 * np.log(np.maximum(e, 1e-6)), "mask": None, "iters_used": used}


def sgbm_num_disp(dataset: str) -> int:
    return int(16 * math.ceil(1.1 * D.MAX_DISP.get(dataset, 128) / 16))


def run_sgbm(left: np.ndarray, right: np.ndarray, num_disp: int, p: dict):
    """Raw SGBM disparity (NaN = invalid) at the input size."""
    cn = 3
    bs = p["blockSize"]
    sg = cv2.StereoSGBM_create(
        minDisparity=0, numDisparities=num_disp, blockSize=bs, P1=p["P1"] * cn * bs * bs, P2=p["P2"] * cn * bs * bs,
        disp12MaxDiff=p["disp12MaxDiff"], uniquenessRatio=p["uniquenessRatio"],
        speckleWindowSize=p["speckleWindowSize"], speckleRange=p["speckleRange"], preFilterCap=p["preFilterCap"],
        mode=MODES[p["mode"]],
    )
    # SGBM leaves the first numDisparities columns empty: pad both views on the left so they get a match.
    lp = cv2.copyMakeBorder(left, 0, 0, num_disp, 0, cv2.BORDER_REPLICATE)
    rp = cv2.copyMakeBorder(right, 0, 0, num_disp, 0, cv2.BORDER_REPLICATE)
    raw = sg.compute(lp[:, :, ::-1].copy(), rp[:, :, ::-1].copy())[:, num_disp:]
    d = raw.astype(np.float32) / 16.0
    d[raw < 0] = np.nan
    return d


def fill_background(d: np.ndarray) -> np.ndarray:
    """Fill NaNs from the nearest valid pixel on the row, left or right, whichever is smaller
    (background side); rows with no valid pixel get the image's median valid disparity (or 0)."""
    h, w = d.shape
    valid = np.isfinite(d)
    idx = np.where(valid, np.arange(w)[None], -1)
    left_idx = np.maximum.accumulate(idx, axis=1)
    idx_r = np.where(valid, np.arange(w)[None], w)
    right_idx = np.minimum.accumulate(idx_r[:, ::-1], axis=1)[:, ::-1]
    rows = np.arange(h)[:, None]
    lv = np.where(left_idx >= 0, d[rows, np.clip(left_idx, 0, w - 1)], np.inf)
    rv = np.where(right_idx < w, d[rows, np.clip(right_idx, 0, w - 1)], np.inf)
    fill = np.minimum(lv, rv)
    out = np.where(valid, d, fill)
    if not np.isfinite(out).all():
        med = float(np.nanmedian(d)) if valid.any() else 0.0
        out[~np.isfinite(out)] = med
    return out.astype(np.float32)


# ------------------------------------------------------------------------------------------------
# Metrics
# ------------------------------------------------------------------------------------------------
def error_metrics(pred, gt, region):
    e = np.abs(pred[region] - gt[region])
    if e.size == 0:
        return None
    g = gt[region]
    return {
        "epe": float(e.mean()),
        "a50": float(np.median(e)),
        "bad1": float((e > 1).mean() * 100),
        "bad2": float((e > 2).mean() * 100),
        "d1": float(((e > 3) & (e > 0.05 * g)).mean() * 100),
        "n": int(e.size),
    }


FRACTIONS = np.arange(100) / 100.0


def sparsification(err: np.ndarray, sigma: np.ndarray):
    """Normalised sparsification curves: EPE of the remaining pixels / full EPE, removing the fraction
    f of pixels with the largest sigma (model) or largest error (oracle)."""
    n = err.size
    full = err.mean()
    keep = n - np.floor(FRACTIONS * n).astype(np.int64)

    def curve(order):
        c = np.cumsum(err[order], dtype=np.float64)
        return c[keep - 1] / keep / max(full, 1e-12)

    model = curve(np.argsort(sigma, kind="stable"))
    oracle = curve(np.argsort(err, kind="stable"))
    return model, oracle


def uncertainty_metrics(pred, gt, u, region):
    err = np.abs(pred[region] - gt[region]).astype(np.float64)
    sigma = np.exp(u[region].astype(np.float64) / 2)
    model, oracle = sparsification(err, sigma)
    ause = float(np.trapezoid(model - oracle, FRACTIONS))
    ause_rand = float(np.trapezoid(1.0 - oracle, FRACTIONS))
    out = {"ause": ause, "ause_random": ause_rand, "mean_sigma": float(sigma.mean()),
           "corr_log": float(np.corrcoef(np.log(sigma), np.log(err + 1e-3))[0, 1])}
    for t in (1, 3):
        k = sigma <= t
        out[f"kept_s{t}"] = float(k.mean() * 100)
        out[f"epe_s{t}"] = float(err[k].mean()) if k.any() else float("nan")
    # EPE of the kept pixels after removing FRACTIONS of them by sigma (not normalised): read at
    # another method's density (StereoSGBM's after its checks) by `at_density`.
    out["epe_curve"] = [float(v) for v in model * err.mean()]
    return out, (model, oracle)


def at_density(curve, density_pct: float) -> float:
    """EPE of the pixels a model keeps by its uncertainty at `density_pct` % kept (from epe_curve)."""
    i = int(round(100.0 - density_pct))
    return float(curve[min(max(i, 0), len(curve) - 1)])


def add_sgbm_density_comparison(results):
    """For every method with an uncertainty: mean over scenes of the EPE of its pixels kept at the
    density StereoSGBM keeps on that scene (raw, after its uniqueness/left-right/speckle checks),
    beside SGBM's EPE on those pixels (`sgbm.epe_raw_valid`)."""
    sg = next((r for r in results if r["method"] == "sgbm"), None)
    if sg is None:
        return
    for r in results:
        if r is sg:
            continue
        vals = []
        for k, sc in r["scenes"].items():
            dens = sg["scenes"].get(k, {}).get("sgbm", {}).get("density")
            curve = sc.get("unc", {}).get("epe_curve")
            if dens is not None and curve:
                sc["unc"]["epe_at_sgbm_density"] = at_density(curve, dens)
                vals.append(sc["unc"]["epe_at_sgbm_density"])
        if vals:
            for g, summ in r["mean"].items():
                keys = [k for k in r["scenes"] if g in ("all", "headline") or k.startswith(g + "/")]
                v = [r["scenes"][k]["unc"]["epe_at_sgbm_density"] for k in keys if "epe_at_sgbm_density" in r["scenes"][k].get("unc", {})]
                if v:
                    summ["unc.epe_at_sgbm_density"] = float(np.mean(v))


def scene_metrics(pred, sc: D.Scene):
    valid = sc.valid
    gt = np.nan_to_num(sc.disp)
    res = {"all": error_metrics(pred, gt, valid)}
    if sc.nonocc is not None:
        res["noc"] = error_metrics(pred, gt, valid & sc.nonocc)
        res["occ"] = error_metrics(pred, gt, valid & ~sc.nonocc)
    return res


def mean_over(scenes: dict, path):
    """Mean of a nested metric over scenes that have it."""
    vals = []
    for r in scenes.values():
        v = r
        for k in path:
            v = v.get(k) if isinstance(v, dict) else None
            if v is None:
                break
        if isinstance(v, (int, float)) and math.isfinite(v):
            vals.append(v)
    return (float(np.mean(vals)), len(vals)) if vals else (float("nan"), 0)


def summarise(per_scene: dict):
    summ = {}
    groups = {"headline" if set(D.HEADLINE) >= {k.split("/")[0] for k in per_scene} else "all": per_scene}
    for ds in sorted({k.split("/")[0] for k in per_scene}):
        groups[ds] = {k: v for k, v in per_scene.items() if k.startswith(ds + "/")}
    for g, sub in groups.items():
        s = {"scenes": len(sub)}
        for region in ("all", "noc", "occ"):
            for m in ("epe", "a50", "bad1", "bad2", "d1"):
                v, n = mean_over(sub, (region, m))
                if n:
                    s[f"{region}.{m}"] = v
        for m in ("ause", "ause_random", "mean_sigma", "corr_log", "kept_s1", "epe_s1", "kept_s3", "epe_s3"):
            v, n = mean_over(sub, ("unc", m))
            if n:
                s[f"unc.{m}"] = v
        for m in ("density", "epe_raw_valid"):
            v, n = mean_over(sub, ("sgbm", m))
            if n:
                s[f"sgbm.{m}"] = v
        v, n = mean_over(sub, ("time_s",))
        s["time_s"] = v
        v, n = mean_over(sub, ("iters_used",))
        if n:
            s["iters_used"] = v
        summ[g] = s
    return summ


# ------------------------------------------------------------------------------------------------
# Visualisation
# ------------------------------------------------------------------------------------------------
def save_vis(path, sc: D.Scene, pred, out=None, raw=None, curves=None, title=""):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    gt = sc.disp
    vmax = float(np.nanmax(gt)) * 1.05
    err = np.abs(pred - np.nan_to_num(gt))
    err[~sc.valid] = np.nan
    panels = [("left", sc.left, None), ("GT disparity", gt, "turbo"), ("prediction", pred, "turbo"),
              ("|error| (0..5 px)", err, "inferno")]
    if raw is not None:
        panels.append((f"SGBM raw (density {np.isfinite(raw).mean() * 100:.0f} %)", raw, "turbo"))
    if out is not None and out.get("mask") is not None:
        panels.append(("matchability mask (1/8)", out["mask"], "gray"))
    if out is not None and out.get("u") is not None:
        sig = np.exp(out["u"] / 2)
        panels.append(("predicted error exp(u/2), log", np.log10(sig), "magma"))
        rej = np.zeros(sc.left.shape, np.float32)
        rej[:] = sc.left.astype(np.float32) / 255 * 0.5
        rej[sig > 3] = (1.0, 0.0, 0.0)
        rej[(sig > 1) & (sig <= 3)] = (1.0, 0.7, 0.0)
        panels.append(("rejected: sigma>3 red, 1..3 orange", rej, None))
    n = len(panels) + (1 if curves is not None else 0)
    cols = 4
    rows = (n + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(4.2 * cols, 3.6 * rows))
    axes = np.atleast_1d(axes).ravel()
    for ax, (t, im, cmap) in zip(axes, panels):
        if cmap == "turbo":
            ax.imshow(im, cmap=cmap, vmin=0, vmax=vmax)
        elif cmap == "inferno":
            ax.imshow(im, cmap=cmap, vmin=0, vmax=5)
        elif cmap == "gray":
            ax.imshow(im, cmap=cmap, vmin=0, vmax=1)
        elif cmap == "magma":
            ax.imshow(im, cmap=cmap, vmin=math.log10(0.25), vmax=math.log10(32))
        else:
            ax.imshow(im)
        ax.set_title(t, fontsize=9)
        ax.axis("off")
    k = len(panels)
    if curves is not None:
        ax = axes[k]
        ax.plot(FRACTIONS, curves[0], label="by predicted sigma")
        ax.plot(FRACTIONS, curves[1], label="oracle")
        ax.axhline(1.0, color="gray", ls="--", label="random")
        ax.set_xlabel("fraction removed")
        ax.set_ylabel("EPE / EPE(all)")
        ax.set_title("sparsification", fontsize=9)
        ax.legend(fontsize=7)
        k += 1
    for ax in axes[k:]:
        ax.axis("off")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


# ------------------------------------------------------------------------------------------------
# Drivers
# ------------------------------------------------------------------------------------------------
def evaluate_method(name, scenes, root, predict, out_dir, vis_keys, info):
    """predict(scene) -> (pred (H,W), extras dict). Returns the result dict (also written as JSON)."""
    per_scene = {}
    t_all = time.time()
    for i, (ds, s) in enumerate(scenes):
        try:
            sc = D.load_scene(root, ds, s)
        except (OSError, ValueError) as e:
            raise SceneError(str(e)) from None
        t0 = time.time()
        pred, extra = predict(sc)
        dt = time.time() - t0
        r = scene_metrics(pred, sc)
        r["time_s"] = dt
        if extra.get("iters_used") is not None:
            r["iters_used"] = extra["iters_used"]
        r["size"] = f"{sc.left.shape[1]}x{sc.left.shape[0]}"
        r["mask_source"] = sc.mask_source
        curves = None
        if extra.get("u") is not None:
            r["unc"], curves = uncertainty_metrics(pred, np.nan_to_num(sc.disp), extra["u"], sc.valid)
        if extra.get("raw") is not None:
            raw = extra["raw"]
            ok = np.isfinite(raw) & sc.valid
            r["sgbm"] = {"density": float(np.isfinite(raw).mean() * 100),
                         "epe_raw_valid": float(np.abs(raw[ok] - sc.disp[ok]).mean()) if ok.any() else float("nan")}
        per_scene[sc.key] = r
        a = r["all"]
        # progress: share done and the time left at the rate so far (plain lines, for logs too)
        done, elapsed = i + 1, time.time() - t_all
        left = elapsed / done * (len(scenes) - done)
        msg = (f"[{name}] {done}/{len(scenes)} ({100 * done / len(scenes):.0f}%, ETA {left:.0f} s) {sc.key} {r['size']}: "
               f"EPE {a['epe']:.2f} bad2 {a['bad2']:.1f}% D1 {a['d1']:.1f}%")
        if "noc" in r:
            msg += f" | noc EPE {r['noc']['epe']:.2f}"
        if "unc" in r:
            msg += f" | AUSE {r['unc']['ause']:.3f} (rand {r['unc']['ause_random']:.3f})"
        if "sgbm" in r:
            msg += f" | density {r['sgbm']['density']:.1f}%"
        print(msg + f" ({dt:.1f}s)", file=sys.stderr, flush=True)
        if sc.key in vis_keys:
            os.makedirs(os.path.join(out_dir, "vis", name), exist_ok=True)
            save_vis(os.path.join(out_dir, "vis", name, sc.key.replace("/", "_") + ".png"), sc, pred,
                     out=extra, raw=extra.get("raw"), curves=curves, title=f"{name}: {sc.key}  EPE {a['epe']:.2f}")
    result = {"method": name, **info, "date": datetime.datetime.now().astimezone().isoformat(timespec="seconds"),
              "scenes": per_scene, "mean": summarise(per_scene), "total_time_s": time.time() - t_all}
    with open(os.path.join(out_dir, f"{name}.json"), "w") as f:
        json.dump(result, f, indent=1)
    return result


class SceneError(RuntimeError):
    """A scene that cannot be read (missing file, GT of another size): the message names it."""


def fmt(v, nd=2):
    return "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else f"{v:.{nd}f}"


def markdown(results, groups=None):
    lines = []
    if not results:
        return ""
    gnames = list(results[0]["mean"].keys())
    for g in gnames:
        lines.append(f"### {g} (mean over {results[0]['mean'][g]['scenes']} scenes)\n")
        lines.append("| method | EPE all | EPE noc | EPE occ | A50 | Bad1.0 % | Bad2.0 % | D1 % | Bad1.0 occ % | "
                     "AUSE (random) | EPE / kept % at sigma<=1 | at sigma<=3 | SGBM density % / EPE on raw-valid | "
                     "EPE kept by sigma at SGBM's density |")
        lines.append("|---|---|---|---|---|---|---|---|---|---|---|---|---|---|")
        for r in results:
            s = r["mean"].get(g, {})
            unc = (f"{fmt(s.get('unc.ause'), 3)} ({fmt(s.get('unc.ause_random'), 3)})" if "unc.ause" in s else "–")
            k1 = f"{fmt(s.get('unc.epe_s1'))} / {fmt(s.get('unc.kept_s1'), 1)}" if "unc.ause" in s else "–"
            k3 = f"{fmt(s.get('unc.epe_s3'))} / {fmt(s.get('unc.kept_s3'), 1)}" if "unc.ause" in s else "–"
            sg = (f"{fmt(s.get('sgbm.density'), 1)} / {fmt(s.get('sgbm.epe_raw_valid'))}" if "sgbm.density" in s else "–")
            lines.append(f"| {r['method']} | {fmt(s.get('all.epe'))} | {fmt(s.get('noc.epe'))} | {fmt(s.get('occ.epe'))} | "
                         f"{fmt(s.get('all.a50'))} | {fmt(s.get('all.bad1'), 1)} | {fmt(s.get('all.bad2'), 1)} | "
                         f"{fmt(s.get('all.d1'), 1)} | {fmt(s.get('occ.bad1'), 1)} | {unc} | {k1} | {k3} | {sg} | "
                         f"{fmt(s.get('unc.epe_at_sgbm_density'))} |")
        lines.append("")
    lines.append("### per scene: EPE all / Bad2.0 % / D1 %\n")
    keys = list(results[0]["scenes"].keys())
    lines.append("| scene | " + " | ".join(r["method"] for r in results) + " |")
    lines.append("|---|" + "---|" * len(results))
    for k in keys:
        cells = []
        for r in results:
            a = r["scenes"].get(k, {}).get("all")
            cells.append(f"{fmt(a['epe'])} / {fmt(a['bad2'], 1)} / {fmt(a['d1'], 1)}" if a else "–")
        lines.append(f"| {k} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def tune_sgbm(root, out_dir):
    """Grid search on the Middlebury 2001 tuning scenes; objective: mean EPE over all GT pixels after
    background filling (the reported metric)."""
    import itertools

    scenes = [D.load_scene(root, *k.split("/")) for k in SGBM_TUNE_SCENES]
    grid = {
        "blockSize": [3, 5, 7, 9],
        "P": [(8, 32), (4, 32), (8, 64), (2, 64)],
        "uniquenessRatio": [0, 5, 10, 15],
        "speckleWindowSize": [0, 100],
        "disp12MaxDiff": [1, -1],
        "mode": ["SGBM_3WAY", "HH"],
    }
    best = None
    trials = []
    combos = list(itertools.product(*grid.values()))
    t0 = time.time()
    for j, vals in enumerate(combos):
        c = dict(zip(grid.keys(), vals))
        p = {"blockSize": c["blockSize"], "P1": c["P"][0], "P2": c["P"][1], "uniquenessRatio": c["uniquenessRatio"],
             "speckleWindowSize": c["speckleWindowSize"], "speckleRange": 2, "disp12MaxDiff": c["disp12MaxDiff"],
             "preFilterCap": 63, "mode": c["mode"]}
        epes, d1s = [], []
        for sc in scenes:
            raw = run_sgbm(sc.left, sc.right, sgbm_num_disp(sc.dataset), p)
            m = error_metrics(fill_background(raw), np.nan_to_num(sc.disp), sc.valid)
            epes.append(m["epe"])
            d1s.append(m["bad2"])
        score = float(np.mean(epes))
        trials.append({**p, "epe": score, "bad2": float(np.mean(d1s))})
        if best is None or score < best[0]:
            best = (score, p, float(np.mean(d1s)))
        if (j + 1) % 32 == 0:
            print(f"tune-sgbm {j + 1}/{len(combos)} best EPE {best[0]:.3f} bad2 {best[2]:.1f}% {best[1]} "
                  f"({time.time() - t0:.0f}s)", file=sys.stderr, flush=True)
    os.makedirs(out_dir, exist_ok=True)
    res = {"scenes": list(SGBM_TUNE_SCENES), "objective": "mean EPE (all GT pixels, background-filled)",
           "best": best[1], "best_epe": best[0], "best_bad2": best[2], "grid": {k: [list(v) if isinstance(v, tuple) else v for v in vs] for k, vs in grid.items()},
           "trials": sorted(trials, key=lambda t: t["epe"])[:20]}
    path = os.path.join(out_dir, "sgbm_params.json")
    with open(path, "w") as f:
        json.dump(res, f, indent=1)
    print(f"best SGBM parameters {best[1]} (EPE {best[0]:.3f}, bad2 {best[2]:.1f}%) -> {path}", file=sys.stderr)
    return best[1]


def main(argv=None):
    try:
        return _main(argv)
    except SceneError as e:
        print(f"error: {e}", file=sys.stderr)
        return 1


def _main(argv=None):
    p = argparse.ArgumentParser(prog="python -m muir.evaluate", description=__doc__.splitlines()[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--model", action="append", default=[], help="model .safetensors (repeatable)")
    p.add_argument("--name", action="append", default=[], help="method name per --model (default: file stem)")
    p.add_argument("--config", default=None, help="config preset for files without config metadata")
    p.add_argument("--blob", action="append", default=[],
                   help="quantised model .muirq (repeatable): the Rust fixed-point engine, the one the firmware "
                        "runs, through `muir run --engine fixed` (build it first: cargo build --release --bin muir)")
    p.add_argument("--blob-name", action="append", default=[], help="method name per --blob (default: file stem + '-fixed')")
    p.add_argument("--muir-bin", default="target/release/muir", help="the muir CLI used for --blob")
    p.add_argument("--sgbm", action="store_true", help="also evaluate OpenCV StereoSGBM")
    p.add_argument("--sgbm-params", default=None, help="JSON from --tune-sgbm (default: the built-in tuned values)")
    p.add_argument("--tune-sgbm", action="store_true", help="grid-search SGBM on Middlebury 2001 scenes and exit")
    p.add_argument("--root", default=D.DEFAULT_ROOT)
    p.add_argument("--set", default="heldout", choices=("heldout", "train", "middlebury28"),
                   help="scene set: the 11 held-out headline scenes of muir.split (default), the training side, "
                        "or the 28 Middlebury 2003/2005/2006 scenes reported before the split existed")
    p.add_argument("--datasets", default=None, help="comma list of data sets (overrides --set)")
    p.add_argument("--scenes", default=None, help="comma list of dataset/scene or scene names to keep")
    p.add_argument("--iters", type=int, default=None, help="refinement iterations (default: the config's)")
    p.add_argument("--early-stop", type=int, default=None, metavar="PER_MILLE",
                   help="--blob runs: adaptive iterations (muir run --early-stop), stop when at most this many "
                        "per mille of the 1/8-grid pixels move by more than --settled px")
    p.add_argument("--settled", type=float, default=0.25, help="with --early-stop: px at full resolution")
    p.add_argument("--no-refine", action="store_true",
                   help="the network's disparity without the full-resolution refinement (muir.fullres)")
    p.add_argument("--max-disparity", type=int, default=None, metavar="PX",
                   help="largest disparity of UFI's proposal search, 8..1016 px (default: the engines' 256)")
    p.add_argument("--device", default="cpu")
    p.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    p.add_argument("--vis", default="4", help="number of scenes to draw (first N) or comma list of scene keys")
    p.add_argument("--out", required=True, help="output directory")
    a = p.parse_args(argv)
    if a.threads > 0:
        torch.set_num_threads(a.threads)
    cv2.setNumThreads(max(1, a.threads) if a.threads else 2)
    os.makedirs(a.out, exist_ok=True)
    if a.tune_sgbm:
        tune_sgbm(a.root, a.out)
        return 0
    if not a.model and not a.blob and not a.sgbm:
        p.error("nothing to evaluate: give --model, --blob and/or --sgbm")
    from .model import MAX_PROPOSAL_D8

    if a.max_disparity is not None and not 8 <= a.max_disparity <= 8 * MAX_PROPOSAL_D8:
        p.error(f"--max-disparity {a.max_disparity}: must be 8 ..= {8 * MAX_PROPOSAL_D8} px")
    # Every input is checked before the first (minutes-long) evaluation starts.
    for path in a.model + a.blob:
        if not os.path.exists(path):
            p.error(f"no model file {path}")
    if a.blob and not os.access(a.muir_bin, os.X_OK):
        p.error(f"--blob needs the muir CLI at {a.muir_bin} (cargo build --release --bin muir, or --muir-bin)")
    from . import split

    try:
        if a.datasets:
            scenes = D.list_scenes(a.root, [d for d in a.datasets.split(",") if d])
        elif a.set == "heldout":
            split.check(a.root)
            scenes = [tuple(k.split("/", 1)) for k in split.HELDOUT_HEADLINE]
        elif a.set == "train":
            scenes = split.train_scenes(a.root)
        else:
            scenes = D.list_scenes(a.root, D.HEADLINE)
    except (FileNotFoundError, ValueError) as e:
        p.error(str(e))
    a.datasets = a.datasets or {"heldout": "held-out scenes of muir.split", "train": "training scenes of muir.split",
                                "middlebury28": ",".join(D.HEADLINE)}[a.set]
    if a.scenes:
        keep = set(a.scenes.split(","))
        scenes = [(ds, s) for ds, s in scenes if f"{ds}/{s}" in keep or s in keep]
    if not scenes:
        p.error("no scenes selected")
    if a.vis.isdigit():
        vis_keys = {f"{ds}/{s}" for ds, s in scenes[: int(a.vis)]}
    else:
        vis_keys = set(a.vis.split(","))
    print(f"{len(scenes)} scenes from {a.datasets}", file=sys.stderr)

    results = []
    from .checkpoint import load_model, read_config

    for i, path in enumerate(a.model):
        name = a.name[i] if i < len(a.name) else os.path.splitext(os.path.basename(path))[0]
        try:
            model = load_model(path, a.config).to(a.device).eval()
        except ValueError as e:  # ModelFileError: names the file and the reason
            p.error(str(e))
        from safetensors import safe_open

        with safe_open(path, framework="pt") as f:
            meta = f.metadata() or {}
        if a.max_disparity is not None:
            model.max_disparity = a.max_disparity
        info = {"model": os.path.abspath(path), "config": model.cfg.name, "iters": a.iters or model.cfg.iters,
                "max_disparity": model.max_disparity,
                "full_res_refinement": not a.no_refine,
                "train_steps": meta.get("steps"), "train_command": meta.get("command")}

        def predict(sc, model=model):
            o = run_model(model, sc.left, sc.right, a.iters, a.device)
            if not a.no_refine:
                o["disp"], _ = fullres.refine(sc.left, sc.right, o["disp"], o["u"])
            return o["disp"], o

        results.append(evaluate_method(name, scenes, a.root, predict, a.out, vis_keys, info))

    for i, path in enumerate(a.blob):
        name = a.blob_name[i] if i < len(a.blob_name) else os.path.splitext(os.path.basename(path))[0] + "-fixed"
        info = {"model": os.path.abspath(path), "engine": "fixed (muir run --engine fixed)",
                "iters": a.iters or "the blob's config", "full_res_refinement": not a.no_refine}

        def predict_fixed(sc, path=path):
            es = None if a.early_stop is None else (a.early_stop, a.settled)
            return run_fixed_engine(a.muir_bin, path, os.path.join(a.root, sc.dataset, sc.name), a.iters, not a.no_refine, es,
                                    a.max_disparity)

        try:
            results.append(evaluate_method(name, scenes, a.root, predict_fixed, a.out, vis_keys, info))
        except RuntimeError as e:  # the CLI refused the blob or a pair; its message says why
            print(f"error: {e}", file=sys.stderr)
            return 1

    if a.sgbm:
        params = dict(SGBM_PARAMS)
        if a.sgbm_params:
            with open(a.sgbm_params) as f:
                params = json.load(f)["best"]
        info = {"params": params, "num_disparities": "16*ceil(1.1*budget/16) per data set: "
                + ", ".join(f"{ds} {sgbm_num_disp(ds)}" for ds in sorted({d for d, _ in scenes})),
                "fill": "invalid -> nearest valid pixel on the row, smaller (background) of left/right neighbours",
                "left_pad": "both views padded on the left by numDisparities (edge replication), then cropped"}

        def predict_sgbm(sc):
            raw = run_sgbm(sc.left, sc.right, sgbm_num_disp(sc.dataset), params)
            return fill_background(raw), {"raw": raw}

        results.append(evaluate_method("sgbm", scenes, a.root, predict_sgbm, a.out, vis_keys, info))

    add_sgbm_density_comparison(results)
    for r in results:  # rewrite the JSON with the density comparison
        with open(os.path.join(a.out, f"{r['method']}.json"), "w") as f:
            json.dump(r, f, indent=1)
    md = markdown(results)
    with open(os.path.join(a.out, "results.md"), "w") as f:
        f.write(f"# Evaluation ({a.datasets}; {len(scenes)} scenes at stored resolution)\n\n")
        for r in results:
            f.write(f"* **{r['method']}**: " + ", ".join(f"{k}={v}" for k, v in r.items()
                                                        if k in ("model", "engine", "config", "iters", "full_res_refinement", "train_steps", "params",
                                                                 "num_disparities", "fill")) + "\n")
        f.write("\n" + md)
    print(md)
    return 0


if __name__ == "__main__":
    sys.exit(main())
