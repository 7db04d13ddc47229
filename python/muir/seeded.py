"""Deterministic pseudo-random weights, identical to `src/float/seeded.rs` (see its doc for the rules).

Used for the golden parity fixtures: the fixtures carry inputs and intermediate tensors only, and both
the twin and the Rust reference rebuild the same weights from (name, shape, seed).
"""
import numpy as np
import torch

GOLDEN = np.uint64(0x9E3779B97F4A7C15)


def _fnv1a64(s: str) -> int:
    h = 0xCBF29CE484222325
    for b in s.encode():
        h ^= b
        h = (h * 0x100000001B3) & 0xFFFFFFFFFFFFFFFF
    return h


def uniform(name: str, n: int, seed: int) -> np.ndarray:
    canonical = name.replace(".downsample.1.", ".norm3.")
    s = np.uint64(_fnv1a64(canonical) ^ ((seed * 0x9E3779B97F4A7C15) & 0xFFFFFFFFFFFFFFFF))
    with np.errstate(over="ignore"):
        z = s + (np.arange(1, n + 1, dtype=np.uint64) * GOLDEN)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
        z = z ^ (z >> np.uint64(31))
    top = (z >> np.uint64(40)).astype(np.int64) - (1 << 23)
    return top.astype(np.float32) / np.float32(1 << 23)


def tensor(name: str, shape, seed: int) -> np.ndarray:
    n = int(np.prod(shape)) if len(shape) else 1
    u = uniform(name, n, seed)
    if name.endswith(".weight") and len(shape) == 4:
        fan_in = shape[1] * shape[2] * shape[3]
        scale, offset = np.float32(np.sqrt(3.0 / fan_in)), np.float32(0.0)
    elif name.endswith(".bias") or name.endswith(".running_mean"):
        scale, offset = np.float32(0.1), np.float32(0.0)
    elif name.endswith(".weight"):
        scale, offset = np.float32(0.25), np.float32(1.0)
    elif name.endswith(".running_var"):
        scale, offset = np.float32(0.5), np.float32(1.0)
    else:
        scale, offset = np.float32(0.0), np.float32(0.0)
    return (offset + scale * u).astype(np.float32).reshape(shape)


def state_dict(model: torch.nn.Module, seed: int) -> dict:
    out = {}
    for k, v in model.state_dict().items():
        if k.endswith("num_batches_tracked"):
            out[k] = torch.zeros_like(v)
        else:
            out[k] = torch.from_numpy(tensor(k, tuple(v.shape), seed).copy())
    return out
