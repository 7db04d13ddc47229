"""Model files: safetensors with the config JSON in the metadata (key `muir_config`).

The Rust crate reads the same files (`src/float/weights.rs`). Tensors are stored float32, contiguous,
one copy per state_dict key (shared modules such as `norm3` / `downsample.1` are cloned, as
safetensors requires).
"""
from __future__ import annotations

import json
import os

import torch
from safetensors.torch import load_file, save_file
from safetensors import safe_open

from .config import Config, preset
from .model import MUIR, strip_module_prefix

CONFIG_KEY = "muir_config"


def save_state_dict(state_dict, cfg: Config, path: str, extra_meta: dict | None = None):
    tensors = {}
    for k, v in state_dict.items():
        t = v.detach().cpu()
        t = t.to(torch.float32) if t.is_floating_point() else t
        tensors[k] = t.contiguous().clone()
    meta = {CONFIG_KEY: cfg.to_json()}
    if extra_meta:
        meta.update({k: v if isinstance(v, str) else json.dumps(v) for k, v in extra_meta.items()})
    save_file(tensors, path, metadata=meta)


def save_model(model: MUIR, path: str, extra_meta: dict | None = None):
    save_state_dict(model.state_dict(), model.cfg, path, extra_meta)


def read_config(path: str) -> Config | None:
    with safe_open(path, framework="pt") as f:
        meta = f.metadata() or {}
    return Config.from_json(meta[CONFIG_KEY]) if CONFIG_KEY in meta else None


class ModelFileError(ValueError):
    """A model file that cannot be used; the message names the file and says why (one line)."""


def load_model(path: str, config: str | None = None) -> MUIR:
    """The model in a safetensors file. Raises ModelFileError (naming the file) for a missing,
    unreadable or truncated file, one whose tensors do not fit the config, or NaN/inf weights."""
    if not os.path.isfile(path):
        raise ModelFileError(f"{path}: no such model file")
    try:
        cfg = read_config(path)
        tensors = load_file(path)
    except Exception as e:  # safetensors raises its own error types for corrupted headers
        raise ModelFileError(f"{path}: not a readable safetensors model ({type(e).__name__}: {e})") from None
    if cfg is None:
        if config is None:
            raise ModelFileError(f"{path} carries no config metadata: name one (--config)")
        cfg = preset(config)
    bad = [k for k, v in tensors.items() if v.is_floating_point() and not torch.isfinite(v).all()]
    if bad:
        raise ModelFileError(f"{path}: NaN or infinite weights in {len(bad)} tensor(s), e.g. {bad[0]}")
    model = MUIR(cfg)
    try:
        model.load_state_dict(strip_module_prefix(tensors), strict=True)
    except RuntimeError as e:
        first = str(e).strip().splitlines()
        raise ModelFileError(f"{path}: tensors do not match config {cfg.name} ({' '.join(first[:2])[:300]})") from None
    return model.eval()
