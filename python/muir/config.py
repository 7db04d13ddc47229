"""Model description shared with the Rust crate (`crates/muir/src/model/config.rs`).

A config is a flat JSON object. The same field names, the same presets and the same defaults live in
`crates/muir/src/model/config.rs`; `host-tests/model_files.rs` (`python_presets_parse`) checks that every preset written here (`host-tests/fixtures/python-presets.json`) equals the Rust one. Widths are channel counts.
"""
from __future__ import annotations

import math

import dataclasses
import json
from dataclasses import dataclass, field

CONFIG_VERSION = 1


@dataclass(frozen=True)
class Config:
    name: str
    # Backbone (cnet) widths: layer1 (1/2), layer2 (1/4), layer3 and layer4 (1/8, 1/16).
    backbone_dims: tuple = (64, 96, 128)
    hidden_dim: int = 128  # ConvGRU hidden state, both levels
    context_dim: int = 128  # context input of the GRUs (and MGA query/key source)
    fmap_dim: int = 256  # matching features
    corr_levels: int = 4
    corr_radius: int = 4
    # Motion encoder (RAFT-Stereo BasicMotionEncoder).
    motion_corr_dims: tuple = (64, 64)  # convc1 (1x1), convc2 (3x3)
    motion_flow_dims: tuple = (64, 64)  # convf1 (7x7), convf2 (3x3)
    motion_dim: int = 128  # output incl. the flow channels
    flow_head_dim: int = 256
    mask_head_dim: int = 256
    # Disparity state channels: 2 = RAFT "flow" (x, y with y forced to 0), 1 = x only.
    flow_channels: int = 2
    iters: int = 7
    # Post-pooling correlation lookup (paper 3.1.1) instead of RAFT's pooled pyramid.
    post_pool: bool = False
    # MUD: matchability mask + uncertainty decoder.
    mud: bool = False
    mud_dim: int = 64
    # UFI: uncertainty-preferred multi-proposal initialisation.
    ufi: bool = False
    ufi_corr_dim: int = 64
    ufi_flow_dim: int = 32
    ufi_dim: int = 64
    ufi_head_dim: int = 64
    ufi_peak_separation: int = 2  # 1/8-resolution pixels between the two correlation peaks
    # MGA: masked global aggregation of the hidden state.
    mga: bool = False
    mga_qk_dim: int = 64
    mga_rope_base: float = 100.0
    # Uncertainty range (full-resolution pixels): u = log(eps^2), eps in [eps_min, eps_max].
    eps_min: float = 0.25
    eps_max: float = 32.0
    # Build the modules that the public realtime checkpoint holds but never uses (layer5, outputs32,
    # gru32), so that `load_state_dict(strict=True)` of that checkpoint works.
    checkpoint_extras: bool = False

    def __post_init__(self):
        problems = []
        if self.flow_channels not in (1, 2):
            problems.append("flow_channels must be 1 or 2")
        if (self.mud or self.ufi or self.mga) and self.flow_channels != 1:
            problems.append("mud, ufi and mga need flow_channels = 1")
        if self.mga and not self.mud:
            problems.append("mga needs mud (its mask input is the MUD matchability mask)")
        if self.mga and self.mga_qk_dim % 4:
            problems.append("mga_qk_dim must be a multiple of 4 (2D RoPE: pairs split between x and y)")
        if not (0 < self.eps_min < self.eps_max):
            problems.append("need 0 < eps_min < eps_max")
        if self.corr_levels < 1 or self.corr_radius < 1 or self.iters < 1:
            problems.append("corr_levels, corr_radius and iters must be >= 1")
        if len(self.backbone_dims) != 3:
            problems.append("backbone_dims has three entries")
        # The Rust crate's further limits (crates/muir/src/model/config.rs validate), so a model the twin
        # accepts is one the engines accept.
        if self.iters > 64:
            problems.append("iters exceeds the supported maximum (64)")
        if not math.isfinite(self.eps_max):
            problems.append("need 0 < eps_min < eps_max")
        if self.mga and not (math.isfinite(self.mga_rope_base) and self.mga_rope_base > 1):
            problems.append("mga_rope_base must be a finite number > 1")
        if self.ufi and not (1 <= self.ufi_peak_separation <= 127):
            problems.append("ufi_peak_separation must be in 1..=127")
        if problems:
            raise ValueError(f"invalid config '{self.name}': " + "; ".join(problems))

    # ---- derived -------------------------------------------------------------------------------
    @property
    def corr_channels(self) -> int:
        return self.corr_levels * (2 * self.corr_radius + 1)

    @property
    def motion_corr_in(self) -> int:
        """Input channels of the motion encoder's first corr conv: cat[C, C*m, m] with MUD."""
        c = self.corr_channels
        return 2 * c + 1 if self.mud else c

    @property
    def gru08_input_dim(self) -> int:
        return self.motion_dim + self.hidden_dim + (self.hidden_dim if self.mga else 0)

    @property
    def mud_in(self) -> int:
        return self.hidden_dim + self.corr_channels + 1

    @property
    def mga_mask_in(self) -> int:
        return self.hidden_dim + self.corr_channels + 1 + 1

    @property
    def pad_multiple(self) -> int:
        """Input sides are padded to this multiple (1/8 grid, and 1/16 GRU level)."""
        return 16

    def to_json(self) -> str:
        d = dataclasses.asdict(self)
        d["config_version"] = CONFIG_VERSION
        return json.dumps(d, sort_keys=True)

    @staticmethod
    def from_json(s: str) -> "Config":
        d = json.loads(s)
        v = d.pop("config_version", CONFIG_VERSION)
        if v != CONFIG_VERSION:
            raise ValueError(f"config_version {v} not supported (expected {CONFIG_VERSION})")
        known = {f.name for f in dataclasses.fields(Config)}
        unknown = set(d) - known
        if unknown:
            raise ValueError(f"unknown config fields: {sorted(unknown)}")
        for k in ("backbone_dims", "motion_corr_dims", "motion_flow_dims"):
            if k in d:
                d[k] = tuple(d[k])
        return Config(**d)

    def replace(self, **kw) -> "Config":
        return dataclasses.replace(self, **kw)


RAFT_STEREO_REALTIME = Config(name="raft-stereo-realtime", checkpoint_extras=True)

MUIR_FAST = Config(
    name="muir-fast",
    flow_channels=1,
    post_pool=True,
    mud=True,
    ufi=True,
    mga=True,
)

MUIR_SLIM = Config(
    name="muir-slim",
    backbone_dims=(32, 48, 64),
    hidden_dim=64,
    context_dim=64,
    fmap_dim=128,
    motion_corr_dims=(32, 32),
    motion_flow_dims=(32, 32),
    motion_dim=64,
    flow_head_dim=128,
    mask_head_dim=128,
    flow_channels=1,
    post_pool=True,
    mud=True,
    mud_dim=32,
    ufi=True,
    ufi_corr_dim=32,
    ufi_flow_dim=16,
    ufi_dim=32,
    ufi_head_dim=32,
    mga=True,
    mga_qk_dim=32,
)

PRESETS = {c.name: c for c in (RAFT_STEREO_REALTIME, MUIR_FAST, MUIR_SLIM)}


def preset(name: str) -> Config:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown config '{name}', expected one of {sorted(PRESETS)}") from None
