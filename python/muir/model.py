"""PyTorch twin of the MUIR network (and of the RAFT-Stereo realtime baseline).

Parameter names of the shared parts are those of the public RAFT-Stereo checkpoint (`cnet.*`, `conv2.*`,
`context_zqr_convs.*`, `update_block.*`), so `load_state_dict(strict=True)` of `raftstereo-realtime.pth`
works with the `raft-stereo-realtime` config. MUIR modules live under `mud.*`, `ufi.*` and `mga.*`.

Conventions (shared with the Rust reference, `src/float/`):
- The disparity state is RAFT's x-"flow" at 1/8 resolution: flow = -disparity / 8 (1/8-grid pixels).
- Uncertainty u = log(beta^2) with beta in full-resolution pixels; predicted error = exp(u / 2).
- BatchNorm always runs with its stored statistics (frozen, as RAFT-Stereo trains), InstanceNorm with
  per-image statistics (eps 1e-5, biased variance).

`forward(..., trace=dict)` records every intermediate tensor under a stable name; the golden-fixture
script and the Rust parity tests use those names.
"""
from __future__ import annotations

import math

import torch
import torch.nn as nn
import torch.nn.functional as F

from .config import Config


# ------------------------------------------------------------------------------------------------
# Building blocks (RAFT-Stereo core/extractor.py, core/update.py)
# ------------------------------------------------------------------------------------------------
class ResidualBlock(nn.Module):
    def __init__(self, cin: int, cout: int, norm: str, stride: int = 1):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1, stride=stride)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.relu = nn.ReLU(inplace=False)
        shape_change = not (stride == 1 and cin == cout)
        if norm == "batch":
            self.norm1 = nn.BatchNorm2d(cout)
            self.norm2 = nn.BatchNorm2d(cout)
            if shape_change:
                self.norm3 = nn.BatchNorm2d(cout)
        elif norm == "instance":
            self.norm1 = nn.InstanceNorm2d(cout)
            self.norm2 = nn.InstanceNorm2d(cout)
            if shape_change:
                self.norm3 = nn.InstanceNorm2d(cout)
        else:
            raise ValueError(norm)
        # `downsample.1` and `norm3` are the same module: the checkpoint holds both names.
        self.downsample = nn.Sequential(nn.Conv2d(cin, cout, 1, stride=stride), self.norm3) if shape_change else None
        # Quantisation-aware training (muir.qat.attach): the engine's slot names and rounding.
        self.slots = None
        self.aq = None

    def forward(self, x):
        if self.aq is not None and self.aq.enabled:
            return self._forward_quantised(x)
        y = self.relu(self.norm1(self.conv1(x)))
        y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        return self.relu(x + y)

    def _forward_quantised(self, x):
        """As `forward`, each tensor the engine stores rounded to its slot (crates/muir/src/engine/encoder.rs)."""
        q = self.aq
        if len(self.slots) == 4:  # InstanceNorm block of the feature head: raw conv outputs are slots
            raw1, mid, raw2, out = self.slots
            y = q(mid, self.relu(self.norm1(q(raw1, self.conv1(x)))))
            y = self.relu(self.norm2(q(raw2, self.conv2(y))))
        else:
            mid, out = self.slots
            y = q(mid, self.relu(self.norm1(self.conv1(x))))
            y = self.relu(self.norm2(self.conv2(y)))
        if self.downsample is not None:
            x = self.downsample(x)
        # Both branches on the output slot's grid (i16), then the saturating add + ReLU.
        s = q.scale(out, self.relu(x + y))
        return q(out, self.relu(q(out, x, saturate=False, scale=s) + q(out, y, saturate=False, scale=s)), scale=s)


class MultiBasicEncoder(nn.Module):
    """`cnet`: shared backbone (both images to 1/8) + context heads (left image, 1/8 and 1/16)."""

    def __init__(self, cfg: Config):
        super().__init__()
        d1, d2, d3 = cfg.backbone_dims
        self.conv1 = nn.Conv2d(3, d1, 7, stride=2, padding=3)
        self.norm1 = nn.BatchNorm2d(d1)
        self.relu1 = nn.ReLU(inplace=False)
        self.layer1 = nn.Sequential(ResidualBlock(d1, d1, "batch", 1), ResidualBlock(d1, d1, "batch", 1))
        self.layer2 = nn.Sequential(ResidualBlock(d1, d2, "batch", 2), ResidualBlock(d2, d2, "batch", 1))
        self.layer3 = nn.Sequential(ResidualBlock(d2, d3, "batch", 2), ResidualBlock(d3, d3, "batch", 1))
        self.layer4 = nn.Sequential(ResidualBlock(d3, d3, "batch", 2), ResidualBlock(d3, d3, "batch", 1))
        heads = (cfg.hidden_dim, cfg.context_dim)
        self.outputs08 = nn.ModuleList(
            [nn.Sequential(ResidualBlock(d3, d3, "batch", 1), nn.Conv2d(d3, c, 3, padding=1)) for c in heads]
        )
        self.outputs16 = nn.ModuleList(
            [nn.Sequential(ResidualBlock(d3, d3, "batch", 1), nn.Conv2d(d3, c, 3, padding=1)) for c in heads]
        )
        if cfg.checkpoint_extras:  # present in the public checkpoint, unused with two GRU levels
            self.layer5 = nn.Sequential(ResidualBlock(d3, d3, "batch", 2), ResidualBlock(d3, d3, "batch", 1))
            self.outputs32 = nn.ModuleList([nn.Conv2d(d3, c, 3, padding=1) for c in heads])

    def trunk(self, x, trace=None, prefix="", aq=None):
        x = self.relu1(self.norm1(self.conv1(x)))
        if aq is not None:
            x = aq("c1", x)
        _rec(trace, prefix + "conv1", x)
        x = self.layer1(x)
        _rec(trace, prefix + "layer1", x)
        x = self.layer2(x)
        _rec(trace, prefix + "layer2", x)
        x = self.layer3(x)
        _rec(trace, prefix + "layer3", x)
        return x


class ConvGRU(nn.Module):
    def __init__(self, hidden: int, inp: int):
        super().__init__()
        self.convz = nn.Conv2d(hidden + inp, hidden, 3, padding=1)
        self.convr = nn.Conv2d(hidden + inp, hidden, 3, padding=1)
        self.convq = nn.Conv2d(hidden + inp, hidden, 3, padding=1)

    def forward(self, h, cz, cr, cq, *x_list):
        x = torch.cat(x_list, dim=1)
        hx = torch.cat([h, x], dim=1)
        z = torch.sigmoid(self.convz(hx) + cz)
        r = torch.sigmoid(self.convr(hx) + cr)
        q = torch.tanh(self.convq(torch.cat([r * h, x], dim=1)) + cq)
        return (1 - z) * h + z * q


class MotionEncoder(nn.Module):
    """RAFT-Stereo BasicMotionEncoder; with MUD the corr input is cat[C, C*m, m] (Eq. 2)."""

    def __init__(self, cfg: Config):
        super().__init__()
        c1, c2 = cfg.motion_corr_dims
        f1, f2 = cfg.motion_flow_dims
        self.convc1 = nn.Conv2d(cfg.motion_corr_in, c1, 1)
        self.convc2 = nn.Conv2d(c1, c2, 3, padding=1)
        self.convf1 = nn.Conv2d(cfg.flow_channels, f1, 7, padding=3)
        self.convf2 = nn.Conv2d(f1, f2, 3, padding=1)
        self.conv = nn.Conv2d(c2 + f2, cfg.motion_dim - cfg.flow_channels, 3, padding=1)

    def forward(self, flow, corr):
        cor = F.relu(self.convc2(F.relu(self.convc1(corr))))
        flo = F.relu(self.convf2(F.relu(self.convf1(flow))))
        out = F.relu(self.conv(torch.cat([cor, flo], dim=1)))
        return torch.cat([out, flow], dim=1)


class FlowHead(nn.Module):
    def __init__(self, cin: int, mid: int, cout: int):
        super().__init__()
        self.conv1 = nn.Conv2d(cin, mid, 3, padding=1)
        self.conv2 = nn.Conv2d(mid, cout, 3, padding=1)

    def forward(self, x):
        return self.conv2(F.relu(self.conv1(x)))


class UpdateBlock(nn.Module):
    def __init__(self, cfg: Config):
        super().__init__()
        h = cfg.hidden_dim
        self.encoder = MotionEncoder(cfg)
        self.gru08 = ConvGRU(h, cfg.gru08_input_dim)
        self.gru16 = ConvGRU(h, h)
        if cfg.checkpoint_extras:
            self.gru32 = ConvGRU(h, h)
        self.flow_head = FlowHead(h, cfg.flow_head_dim, cfg.flow_channels)
        self.mask = nn.Sequential(
            nn.Conv2d(h, cfg.mask_head_dim, 3, padding=1), nn.ReLU(inplace=False), nn.Conv2d(cfg.mask_head_dim, 64 * 9, 1)
        )


class MUD(nn.Module):
    """Matchability and uncertainty decoder: (H, C(D), flow) -> (m, u), Eq. 2, 8, 9."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.conv1 = nn.Conv2d(cfg.mud_in, cfg.mud_dim, 3, padding=1)
        self.conv2 = nn.Conv2d(cfg.mud_dim, cfg.mud_dim, 3, padding=1)
        self.conv3 = nn.Conv2d(cfg.mud_dim, 2, 3, padding=1)

    def forward(self, h, corr, flow, cfg: Config):
        x = F.relu(self.conv1(torch.cat([h, corr, flow[:, :1]], dim=1)))
        x = F.relu(self.conv2(x))
        ab = self.conv3(x)
        m = torch.sigmoid(ab[:, 0:1])
        u = uncertainty_from_logit(ab[:, 1:2], cfg)
        return m, u


def uncertainty_from_logit(v, cfg: Config):
    """Eq. 8: u = log(eps_min^2 + (eps_max^2 - eps_min^2) * sigmoid(v))."""
    lo, hi = cfg.eps_min**2, cfg.eps_max**2
    return torch.log(lo + (hi - lo) * torch.sigmoid(v))


class UFI(nn.Module):
    """Uncertainty-preferred field initialisation (Eq. 10) over proposals {0, peak1, peak2}."""

    def __init__(self, cfg: Config):
        super().__init__()
        fc = cfg.flow_channels
        self.convc = nn.Conv2d(cfg.corr_channels, cfg.ufi_corr_dim, 1)
        self.convf = nn.Conv2d(fc, cfg.ufi_flow_dim, 3, padding=1)
        self.conv = nn.Conv2d(cfg.ufi_corr_dim + cfg.ufi_flow_dim, cfg.ufi_dim - fc, 3, padding=1)
        self.convq = nn.Conv2d(cfg.ufi_dim + cfg.context_dim, cfg.hidden_dim, 3, padding=1)
        self.convz = nn.Conv2d(2 * cfg.hidden_dim, cfg.hidden_dim, 3, padding=1)
        self.head1 = nn.Conv2d(cfg.hidden_dim + cfg.ufi_dim, cfg.ufi_head_dim, 3, padding=1)
        self.head2 = nn.Conv2d(cfg.ufi_head_dim, 2, 3, padding=1)

    def encode(self, flow, corr):
        c = F.relu(self.convc(corr))
        f = F.relu(self.convf(flow))
        return torch.cat([F.relu(self.conv(torch.cat([c, f], dim=1))), flow], dim=1)


class MGA(nn.Module):
    """Masked global aggregation (Eq. 11, 12). query/key from context, value from the hidden state."""

    def __init__(self, cfg: Config):
        super().__init__()
        self.query = nn.Conv2d(cfg.context_dim, cfg.mga_qk_dim, 1)
        self.key = nn.Conv2d(cfg.context_dim, cfg.mga_qk_dim, 1)
        self.mask = nn.Conv2d(cfg.mga_mask_in, 1, 3, padding=1)
        self.value = nn.Conv2d(cfg.hidden_dim, cfg.hidden_dim, 1)


# ------------------------------------------------------------------------------------------------
# Functional pieces shared by the network (each has a Rust twin in src/float/)
# ------------------------------------------------------------------------------------------------
def pool2x(x):
    return F.avg_pool2d(x, 3, stride=2, padding=1)


def interp(x, dest):
    return F.interpolate(x, dest.shape[2:], mode="bilinear", align_corners=True)


def normalize_image(img):
    """uint8-range RGB (B,3,H,W) float -> [-1, 1]."""
    return 2.0 * (img / 255.0) - 1.0


def corr_volume(f1, f2):
    """C(b, y, x1, x2) = <f1(:, y, x1), f2(:, y, x2)> / sqrt(c). (B, H, W, W)"""
    c = f1.shape[1]
    return torch.einsum("bchi,bchj->bhij", f1, f2) / math.sqrt(c)


def sample_rows(rows, pos):
    """Linear interpolation of rows (N, W) at positions pos (N, K); zero outside [0, W-1]."""
    n, w = rows.shape
    padded = F.pad(rows, (1, 1))
    i0 = torch.floor(pos)
    a = pos - i0
    i0 = i0.long()
    lo = torch.clamp(i0 + 1, 0, w + 1)
    hi = torch.clamp(i0 + 2, 0, w + 1)
    v0 = torch.gather(padded, 1, lo)
    v1 = torch.gather(padded, 1, hi)
    return (1 - a) * v0 + a * v1


def lookup(vol, flow, cfg: Config):
    """Correlation lookup at disparity -flow. vol (B,H,W,W), flow (B,>=1,H,W) -> (B, L*(2r+1), H, W).

    RAFT pyramid (post_pool=False): level l averages the volume over x2 in blocks of 2^l (floor), then
    samples at (x + flow)/2^l + j.  Post-pooling (post_pool=True): level l samples at x + flow + j*2^l,
    each sample the mean of the linearly interpolated correlation at the 2^l positions centred there.
    """
    b, h, w1, w2 = vol.shape
    r = cfg.corr_radius
    k = 2 * r + 1
    x = torch.arange(w1, dtype=vol.dtype, device=vol.device).view(1, 1, w1)
    centre = (x + flow[:, 0]).reshape(b * h * w1, 1)
    j = torch.arange(-r, r + 1, dtype=vol.dtype, device=vol.device).view(1, k)
    rows = vol.reshape(b * h * w1, w2)
    out = []
    if not cfg.post_pool:
        for lvl in range(cfg.corr_levels):
            if lvl > 0:
                rows = F.avg_pool1d(rows.unsqueeze(1), 2, stride=2).squeeze(1)
            out.append(sample_rows(rows, centre / 2**lvl + j))
    else:
        for lvl in range(cfg.corr_levels):
            s = 2**lvl
            offs = torch.arange(s, dtype=vol.dtype, device=vol.device) - (s - 1) / 2.0
            pos = (centre + j * s).unsqueeze(-1) + offs.view(1, 1, s)  # (N, k, s)
            v = sample_rows(rows, pos.reshape(-1, k * s)).reshape(-1, k, s).mean(-1)
            out.append(v)
    c = torch.cat(out, dim=1)  # (N, L*k), level-major
    return c.view(b, h, w1, -1).permute(0, 3, 1, 2).contiguous()


# Largest proposal disparity on the 1/8 grid (Rust: arith::MAX_PROPOSAL_D8): the largest whole
# disparity the engine's Q7.8 flow state holds (i16::MAX >> 8 = 127, 1016 px at full resolution).
# Only inputs wider than 1024 px reach it.
MAX_PROPOSAL_D8 = 127
# Default largest disparity (px, full resolution) of the proposal search (Rust:
# model::config::MaxDisparity::DEFAULT): a run-time setting of every engine, `MUIR.max_disparity`
# here. Searching the whole row lets far, spurious correlation peaks win on near-ties, where the
# fixed-point engine's 8-bit features then pick another peak than the float model.
DEFAULT_MAX_DISPARITY = 256


def correlation_peaks(vol, separation: int, max_d8: int = MAX_PROPOSAL_D8):
    """UFI proposals: per left pixel, the two highest correlations over d in [0, min(x, max_d8, 127)] (d
    integer, 1/8 grid), the second at least `separation` away from the first (the first again if none
    is). Ties go to the smaller d. Returns disparities (B, 2, H, W) as float."""
    b, h, w1, w2 = vol.shape
    x = torch.arange(w1, device=vol.device).view(w1, 1)
    d = torch.arange(w2, device=vol.device).view(1, w2)
    x2 = x - d  # (w1, w2): column index for disparity d
    valid = (x2 >= 0) & (d <= min(max_d8, MAX_PROPOSAL_D8))
    idx = x2.clamp(min=0).view(1, 1, w1, w2).expand(b, h, w1, w2)
    cd = torch.gather(vol, 3, idx)
    neg = torch.finfo(vol.dtype).min
    cd = torch.where(valid.view(1, 1, w1, w2), cd, torch.full_like(cd, neg))
    d1 = torch.argmax(cd, dim=3, keepdim=True)
    far = (d.view(1, 1, 1, w2) - d1).abs() >= separation
    ok2 = far & valid.view(1, 1, w1, w2)
    cd2 = torch.where(ok2, cd, torch.full_like(cd, neg))
    d2 = torch.argmax(cd2, dim=3, keepdim=True)
    d2 = torch.where(ok2.any(dim=3, keepdim=True), d2, d1)
    return torch.cat([d1, d2], dim=3).permute(0, 3, 1, 2).to(vol.dtype)


def rope_2d(x, base: float):
    """2D rotary embedding of (B, C, H, W): channel pairs (2i, 2i+1); the first half of the pairs
    rotates with the column x, the second half with the row y; pair i of a half turns by pos * base^(-i/n)."""
    b, c, h, w = x.shape
    pairs = c // 2
    n = pairs // 2
    freq = base ** (-torch.arange(n, dtype=torch.float64) / n)
    ys = torch.arange(h, dtype=torch.float64).view(h, 1).expand(h, w)
    xs = torch.arange(w, dtype=torch.float64).view(1, w).expand(h, w)
    ang = torch.cat([xs.unsqueeze(0) * freq.view(n, 1, 1), ys.unsqueeze(0) * freq.view(n, 1, 1)], dim=0)
    cos = torch.cos(ang).to(x.dtype).to(x.device)
    sin = torch.sin(ang).to(x.dtype).to(x.device)
    a = x[:, 0::2]
    bb = x[:, 1::2]
    ra = a * cos - bb * sin
    rb = a * sin + bb * cos
    return torch.stack([ra, rb], dim=2).reshape(b, c, h, w)


def convex_upsample(x, mask):
    """RAFT convex upsampling by 8: x (B,D,H,W), mask (B,576,H,W) -> (B,D,8H,8W). Zero padding."""
    n, dch, h, w = x.shape
    mask = torch.softmax(mask.view(n, 1, 9, 8, 8, h, w), dim=2)
    up = F.unfold(x, [3, 3], padding=1).view(n, dch, 9, 1, 1, h, w)
    up = torch.sum(mask * up, dim=2)
    return up.permute(0, 1, 4, 2, 5, 3).reshape(n, dch, 8 * h, 8 * w)


def _rec(trace, name, t):
    if trace is not None:
        trace[name] = t.detach().clone()


# ------------------------------------------------------------------------------------------------
# The network
# ------------------------------------------------------------------------------------------------
class MUIR(nn.Module):
    def __init__(self, cfg: Config):
        super().__init__()
        self.cfg = cfg
        # Largest disparity (px) of UFI's proposal search; 8 ..= 1016, a run-time setting.
        self.max_disparity = DEFAULT_MAX_DISPARITY
        self.cnet = MultiBasicEncoder(cfg)
        d3 = cfg.backbone_dims[2]
        self.conv2 = nn.Sequential(ResidualBlock(d3, d3, "instance", 1), nn.Conv2d(d3, cfg.fmap_dim, 3, padding=1))
        self.context_zqr_convs = nn.ModuleList(
            [nn.Conv2d(cfg.context_dim, 3 * cfg.hidden_dim, 3, padding=1) for _ in range(2)]
        )
        self.update_block = UpdateBlock(cfg)
        if cfg.mud:
            self.mud = MUD(cfg)
        if cfg.ufi:
            self.ufi = UFI(cfg)
        if cfg.mga:
            self.mga = MGA(cfg)
        self.aq = None  # muir.qat.ActQuant when training with the engine's rounding simulated

    def freeze_bn(self):
        """BatchNorm keeps its stored statistics in training too (as RAFT-Stereo trains)."""
        for m in self.modules():
            if isinstance(m, nn.BatchNorm2d):
                m.eval()
        return self

    def train(self, mode: bool = True):
        super().train(mode)
        return self.freeze_bn()

    # -- stages ------------------------------------------------------------------------------------
    def encode(self, left, right, trace=None):
        cfg = self.cfg
        aq = self.aq
        x = self.cnet.trunk(normalize_image(torch.cat([left, right], dim=0)), trace, "backbone.", aq)
        bsz = left.shape[0]
        xl = x[:bsz]
        fm = self.conv2(x)
        if aq is not None:
            fm = aq("fmap", fm)
        f1, f2 = fm[:bsz], fm[bsz:]
        _rec(trace, "fmap1", f1)
        _rec(trace, "fmap2", f2)
        c08 = [head(xl) for head in self.cnet.outputs08]
        y = self.cnet.layer4(xl)
        c16 = [head(y) for head in self.cnet.outputs16]
        net08, net16 = torch.tanh(c08[0]), torch.tanh(c16[0])
        inp08, inp16 = F.relu(c08[1]), F.relu(c16[1])
        if aq is not None:
            inp08, inp16 = aq("inp08", inp08), aq("inp16", inp16)
        _rec(trace, "net08.init", net08)
        _rec(trace, "net16.init", net16)
        _rec(trace, "inp08", inp08)
        _rec(trace, "inp16", inp16)
        zqr08 = self.context_zqr_convs[0](inp08)
        zqr16 = self.context_zqr_convs[1](inp16)
        _rec(trace, "czqr08", zqr08)
        _rec(trace, "czqr16", zqr16)
        h = cfg.hidden_dim
        ctx08 = list(zqr08.split(h, dim=1))
        ctx16 = list(zqr16.split(h, dim=1))
        return f1, f2, net08, net16, inp08, ctx08, ctx16

    def ufi_init(self, vol, net08, inp08, trace=None):
        """Returns (flow0, u0, candidate flows (B,3,H,W), candidate u (B,3,H,W), net08)."""
        cfg = self.cfg
        b, _, h, w = net08.shape
        if not 8 <= self.max_disparity <= 8 * MAX_PROPOSAL_D8:
            raise ValueError(f"max_disparity {self.max_disparity} outside 8 ..= {8 * MAX_PROPOSAL_D8} px")
        peaks = correlation_peaks(vol, cfg.ufi_peak_separation, int(self.max_disparity) // 8)
        _rec(trace, "ufi.peaks", peaks)
        props = torch.cat([torch.zeros_like(peaks[:, :1]), peaks], dim=1)  # disparities (B,3,H,W)
        feats = []
        hid = net08
        for k in range(3):
            flow_k = -props[:, k : k + 1]
            if cfg.flow_channels == 2:
                flow_k = torch.cat([flow_k, torch.zeros_like(flow_k)], dim=1)
            corr_k = lookup(vol, flow_k, cfg)
            _rec(trace, f"ufi.corr{k}", corr_k)
            fk = self.ufi.encode(flow_k, corr_k)
            feats.append(fk)
            q = torch.tanh(self.ufi.convq(torch.cat([fk, inp08], dim=1)))
            z = torch.sigmoid(self.ufi.convz(torch.cat([hid, q], dim=1)))
            hid = hid + (q - hid) * z
            _rec(trace, f"ufi.hidden{k}", hid)
        cand_flow, cand_u = [], []
        for k in range(3):
            out = self.ufi.head2(F.relu(self.ufi.head1(torch.cat([hid, feats[k]], dim=1))))
            cand_flow.append(-props[:, k : k + 1] + out[:, 0:1])
            cand_u.append(uncertainty_from_logit(out[:, 1:2], cfg))
        cand_flow = torch.cat(cand_flow, dim=1)
        cand_u = torch.cat(cand_u, dim=1)
        _rec(trace, "ufi.cand_flow", cand_flow)
        _rec(trace, "ufi.cand_u", cand_u)
        best = torch.argmin(cand_u, dim=1, keepdim=True)
        flow0 = torch.gather(cand_flow, 1, best)
        u0 = torch.gather(cand_u, 1, best)
        _rec(trace, "ufi.choice", best.to(flow0.dtype))
        return flow0, u0, cand_flow, cand_u, hid

    def attention(self, inp08):
        cfg = self.cfg
        q = rope_2d(self.mga.query(inp08), cfg.mga_rope_base)
        k = rope_2d(self.mga.key(inp08), cfg.mga_rope_base)
        b, c, h, w = q.shape
        logits = torch.einsum("bci,bcj->bij", q.reshape(b, c, h * w), k.reshape(b, c, h * w)) / math.sqrt(c)
        return torch.softmax(logits, dim=-1), q, k

    # -- forward -------------------------------------------------------------------------------------
    def forward(self, left, right, iters=None, trace=None, train_out=False, binarize_p=0.0, binarize_coins=None):
        """left/right: (B,3,H,W) float in [0, 255], H and W multiples of 16.

        Inference (train_out=False): returns (disparity (B,1,H,W) px, uncertainty u (B,1,H,W) or None).
        Training (train_out=True): returns a dict with per-iteration full-resolution predictions.
        binarize_p: probability, per sample and iteration, of rounding the mask (Eq. 3; training only).
        binarize_coins: (B, iters) tensor of 0/1 drawn by the caller instead (training only), so that
            the coins are a function of the data, not of the process (data-parallel runs).
        """
        cfg = self.cfg
        iters = cfg.iters if iters is None else iters
        b, _, hh, ww = left.shape
        if hh % cfg.pad_multiple or ww % cfg.pad_multiple:
            raise ValueError(f"image sides must be multiples of {cfg.pad_multiple} (pad first), got {hh}x{ww}")
        f1, f2, net08, net16, inp08, ctx08, ctx16 = self.encode(left, right, trace)
        vol = corr_volume(f1, f2)
        h8, w8 = net08.shape[2:]
        fc = cfg.flow_channels
        # Training outputs: full-resolution disparity of the initial field (UFI) and after each
        # iteration, each with the MUD uncertainty decoded for it (at the start of the next iteration,
        # or by the final MUD), plus every UFI candidate with its own uncertainty.
        masks, flows, us = [], [], []
        cand = None
        if cfg.ufi:
            flow0, u0, cand_flow, cand_u, net08 = self.ufi_init(vol, net08, inp08, trace)
            flow = flow0 if fc == 1 else torch.cat([flow0, torch.zeros_like(flow0)], dim=1)
            if train_out:
                masks.append(0.25 * self.update_block.mask(net08))
                flows.append(flow0)
                cand = (cand_flow, cand_u)
        else:
            flow = torch.zeros(b, fc, h8, w8, dtype=f1.dtype, device=f1.device)
        _rec(trace, "init.flow", flow[:, :1])
        _rec(trace, "init.net08", net08)

        if cfg.mga:
            attn, q, k = self.attention(inp08)
            _rec(trace, "mga.query", q)
            _rec(trace, "mga.key", k)

        ub = self.update_block
        for itr in range(iters):
            flow = flow.detach()
            corr = lookup(vol, flow, cfg)
            _rec(trace, f"iter{itr}.corr", corr)
            if cfg.mud:
                m, u = self.mud(net08, corr, flow, cfg)
                _rec(trace, f"iter{itr}.mud_m", m)
                _rec(trace, f"iter{itr}.mud_u", u)
                if train_out and (itr > 0 or cfg.ufi):
                    us.append(u)
                if binarize_coins is not None and self.training:
                    coin = binarize_coins[:, itr].view(b, 1, 1, 1).to(device=m.device, dtype=m.dtype)
                    m = coin * torch.round(m) + (1 - coin) * m
                elif binarize_p > 0 and self.training:
                    coin = (torch.rand(b, 1, 1, 1, device=m.device) < binarize_p).to(m.dtype)
                    m = coin * torch.round(m) + (1 - coin) * m
                corr_in = torch.cat([corr, corr * m, m], dim=1)
            else:
                corr_in = corr
            if cfg.mga:
                hm = torch.sigmoid(self.mga.mask(torch.cat([net08, corr, flow[:, :1], m], dim=1)))
                v = self.mga.value(net08) * hm
                glb = torch.einsum("bij,bcj->bci", attn, v.reshape(b, -1, h8 * w8)).reshape(b, -1, h8, w8)
                _rec(trace, f"iter{itr}.mga_mask", hm)
                _rec(trace, f"iter{itr}.mga", glb)
            net16 = ub.gru16(net16, *ctx16, pool2x(net08))
            net16 = ub.gru16(net16, *ctx16, pool2x(net08))
            motion = ub.encoder(flow, corr_in)
            _rec(trace, f"iter{itr}.motion", motion)
            xs = [motion, interp(net16, net08)]
            if cfg.mga:
                xs.append(glb)
            net08 = ub.gru08(net08, *ctx08, *xs)
            delta = ub.flow_head(net08)
            if fc == 2:
                delta = torch.cat([delta[:, :1], torch.zeros_like(delta[:, 1:])], dim=1)
            flow = flow + delta
            _rec(trace, f"iter{itr}.net16", net16)
            _rec(trace, f"iter{itr}.net08", net08)
            _rec(trace, f"iter{itr}.flow", flow[:, :1])
            if train_out:
                masks.append(0.25 * ub.mask(net08))
                flows.append(flow[:, :1])

        u_final = None
        if cfg.mud:
            # Detached like every in-loop MUD call: the uncertainty loss must not train the disparity.
            corr = lookup(vol, flow.detach(), cfg)
            m, u_final = self.mud(net08, corr, flow.detach(), cfg)
            _rec(trace, "final.corr", corr)
            _rec(trace, "final.mud_m", m)
            _rec(trace, "final.mud_u", u_final)
        if train_out:
            out = {
                "disp": [-convex_upsample(8.0 * f, mk) for f, mk in zip(flows, masks)],
                "u": [convex_upsample(u, mk) for u, mk in zip(us + [u_final], masks)] if cfg.mud else None,
                "has_init": cfg.ufi,
                "cand_disp": None,
                "cand_u": None,
            }
            if cand is not None:
                out["cand_disp"] = -convex_upsample(8.0 * cand[0], masks[0])
                out["cand_u"] = convex_upsample(cand[1], masks[0])
            return out
        mask = 0.25 * ub.mask(net08)
        _rec(trace, "up_mask", mask)
        disp = -convex_upsample(8.0 * flow[:, :1], mask)
        _rec(trace, "up.disp", disp)
        u_up = None
        if cfg.mud:
            u_up = convex_upsample(u_final, mask)
            _rec(trace, "up.u", u_up)
        return disp, u_up


def strip_module_prefix(state_dict):
    return {(k[7:] if k.startswith("module.") else k): v for k, v in state_dict.items()}
