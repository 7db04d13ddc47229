//! Static memory plan: every byte of working memory for a (config, width, height), computed by
//! `const fn` so firmware can size a `static` buffer at compile time.
//!
//! The arena has two zones:
//! * **frame** (lives for the whole pair): matching features `f1`, `f2`, hidden states `net08`,
//!   `net16`, context `inp08`, `inp16`.
//! * **scratch**, reused by phase: the encoder's line buffers (a phase per image), then the
//!   refinement phases (UFI, iterations, output), which share their own long-lived part (keys and
//!   softmax statistics of MGA, masked values, disparity, mask, uncertainty) followed by per-phase
//!   line buffers.
//!
//! Sizes are in bytes, every buffer 8-byte aligned. [`Plan::ram_bytes`] is the total.
#![deny(clippy::indexing_slicing)]

pub use super::layout::{Buf, Bump};
use super::layout::{FeatureHeadLayout, TrunkLayout, refine_rings};
use crate::kernels::corr::window_len;
use crate::model::config::Config;
pub use crate::model::grid::Grid;
use crate::model::layers::{ConvId, MASK_CHANNELS};

const fn max(a: usize, b: usize) -> usize {
    if a > b { a } else { b }
}

/// Frame-long buffers.
#[derive(Clone, Copy, Debug, Default)]
pub struct FrameBufs {
    /// Left matching features, i8 `n8 x fmap`.
    pub f1: Buf,
    /// Right matching features.
    pub f2: Buf,
    /// 1/8 hidden state, i16 `n8 x hidden`.
    pub net08: Buf,
    /// 1/16 hidden state.
    pub net16: Buf,
    /// 1/8 context, u8 `n8 x context`.
    pub inp08: Buf,
    /// 1/16 context.
    pub inp16: Buf,
}

/// Encoder scratch (one image at a time).
#[derive(Clone, Copy, Debug, Default)]
pub struct EncoderBufs {
    /// layer3 output, u8 `n8 x d3` (whole).
    pub l3: Buf,
    /// layer4 output, u8 `n16 x d3` (whole).
    pub l4: Buf,
    /// Line buffers of the trunk and of the 1/8 and 1/16 heads (overlapping: trunk first).
    pub rings: Buf,
    /// InstanceNorm statistics, 2 x d3 x (mean i64, recip i64).
    pub norm: Buf,
}

/// Refinement scratch shared by UFI, the iterations and the output phase.
#[derive(Clone, Copy, Debug, Default)]
pub struct RefineBufs {
    /// Disparity state ("flow"), i16 `n8 x flow_channels`.
    pub flow: Buf,
    /// Matchability mask of the current iteration, i16 `n8`.
    pub mask: Buf,
    /// Uncertainty, i16 `n8`.
    pub u: Buf,
    /// MGA keys after RoPE, i16 `n8 x qk`.
    pub keys: Buf,
    /// MGA softmax statistics per query: max (i64), sum (i64).
    pub stats: Buf,
    /// MGA masked values of the iteration, i16 `n8 x hidden`.
    pub values: Buf,
    /// Line buffers of the current phase.
    pub rings: Buf,
}

/// Full-resolution refinement scratch (after the network: the whole arena is free again).
#[derive(Clone, Copy, Debug, Default)]
pub struct FullResBufs {
    /// Census rings of both images (u64).
    pub census: Buf,
    /// Path costs (u16).
    pub paths: Buf,
    /// Band and decision rows (i16).
    pub rows: Buf,
    /// Grey rows (u8).
    pub grey: Buf,
}

/// Per-pixel scratch shared by all phases (patch gather, lookup window, attention accumulators).
#[derive(Clone, Copy, Debug, Default)]
pub struct PixelBufs {
    /// Conv patches, i16 `2 x max patch` (two output pixels at a time).
    pub patch: Buf,
    /// Lookup window (i32) and prefix sums (i64).
    pub window: Buf,
    /// Lookup prefix sums.
    pub prefix: Buf,
    /// Correlation row for UFI peaks, i32 `w8`.
    pub peaks_row: Buf,
    /// Attention accumulators, i64 `hidden`, and one query row, i16 `qk`.
    pub attn: Buf,
    /// Mask logits of one pixel, i16 576, and one mask-head pixel.
    pub logits: Buf,
}

/// The memory plan.
#[derive(Clone, Copy, Debug)]
pub struct Plan {
    /// Config the plan is for.
    pub config: Config,
    /// Input width the plan holds (before padding).
    pub width: usize,
    /// Input height.
    pub height: usize,
    /// Grid sizes.
    pub grid: Grid,
    /// Frame zone.
    pub frame: FrameBufs,
    /// Per-pixel scratch.
    pub pixel: PixelBufs,
    /// Encoder phase zone.
    pub encoder: EncoderBufs,
    /// Refinement zone.
    pub refine: RefineBufs,
    /// Full-resolution refinement zone (from offset 0: it runs after the network).
    pub fullres: FullResBufs,
    /// Bytes of the encoder's line buffers.
    pub encoder_rings: usize,
    /// Bytes of the refinement phases' line buffers.
    pub refine_rings: usize,
    /// Total bytes.
    pub ram_bytes: usize,
}

/// Stack to reserve beside the arena on Cortex-M (bytes). The engine keeps all its working memory in
/// the arena; the stack holds only locals and call frames, which do not depend on the image size.
/// Measured by the QEMU firmware (painted stack, `boards/*/run-tests.sh`, `MUIR-STACK` line):
/// 20.0-22.3 KiB (20,516-22,800 B) on the Cortex-M7 and Cortex-M55 builds (firmware `main` included), at
/// 64x48 and 160x120 alike; the firmware fails if a frame exceeds this budget.
pub const STACK_BUDGET: usize = 24 * 1024;

/// Largest conv patch (elements) of a config.
pub const fn max_patch(cfg: &Config) -> usize {
    let mut m = 0;
    let mut ids = ConvId::ALL;
    while let [id, rest @ ..] = ids {
        if let Some(q) = crate::model::graph::QLayer::of(*id, cfg)
            && let Some(s) = id.shape(cfg)
        {
            m = max(m, s.k * s.k * q.cin());
        }
        ids = rest;
    }
    m
}

/// Bytes of the patch scratch: two i16 patches of the largest layer (`4 max_patch`), or, where
/// larger, what the DSP build's widened-weight path (`kernels::conv::conv_row_w16`) needs to
/// widen a channel pair's weights once for a whole 1/8-grid row of the 3x3 layers over `c =
/// max(d3, hidden, context)` channels (the context heads, the motion encoder's output, the flow
/// and mask heads): the widened weights (`4 P` bytes, `P = 9 c` values), one i16 patch (`2 P`)
/// and the row's pixel pairs (`4 P` each). Grows with the width: +1,152 B at 64x48, +14,976 B at
/// 160x120 for muir-slim.
pub const fn patch_bytes(cfg: &Config, g: &Grid) -> usize {
    let p = 9 * max(cfg.backbone_dims[2], max(cfg.hidden_dim, cfg.context_dim));
    max(4 * max_patch(cfg), 6 * p + 4 * p * g.w8.div_ceil(2))
}

impl Plan {
    /// The plan for `cfg` and an input of `width x height`.
    pub const fn new(cfg: &Config, width: usize, height: usize) -> Plan {
        let g = Grid::new(width, height);
        let n8 = g.n8();
        let n16 = g.n16();
        let h = cfg.hidden_dim;
        let d3 = cfg.backbone_dims[2];
        let mut b = Bump::new(0);
        let frame = FrameBufs {
            f1: b.take(n8 * cfg.fmap_dim),
            f2: b.take(n8 * cfg.fmap_dim),
            net08: b.take(2 * n8 * h),
            net16: b.take(2 * n16 * h),
            inp08: b.take(n8 * cfg.context_dim),
            inp16: b.take(n16 * cfg.context_dim),
        };
        let qk = if cfg.mga { cfg.mga_qk_dim } else { 0 };
        let pixel = PixelBufs {
            // two i16 patches: convolutions run on pairs of output pixels (kernels::conv)
            patch: b.take(patch_bytes(cfg, &g)),
            window: b.take(4 * window_len(cfg.corr_levels, cfg.corr_radius)),
            prefix: b.take(8 * (window_len(cfg.corr_levels, cfg.corr_radius) + 1)),
            peaks_row: b.take(4 * g.w8),
            attn: b.take(8 * h + 2 * qk),
            logits: b.take(2 * MASK_CHANNELS + 2 * cfg.mask_head_dim),
        };
        let scratch = b.at;
        let encoder_rings = max(TrunkLayout::new(cfg, &g).total, FeatureHeadLayout::new(cfg, &g).total);
        let mut e = Bump::new(scratch);
        let encoder = EncoderBufs {
            l3: e.take(n8 * d3),
            l4: e.take(n16 * d3),
            norm: e.take(2 * 16 * d3),
            rings: e.take(encoder_rings),
        };
        let refine_rings = refine_rings(cfg, &g);
        let mut r = Bump::new(scratch);
        let refine = RefineBufs {
            flow: r.take(2 * n8 * cfg.flow_channels),
            mask: r.take(2 * n8),
            u: r.take(2 * n8),
            keys: r.take(2 * n8 * qk),
            stats: r.take(if cfg.mga { 16 * n8 } else { 0 }),
            values: r.take(if cfg.mga { 2 * n8 * h } else { 0 }),
            rings: r.take(refine_rings),
        };
        let mut f = Bump::new(0);
        let n = crate::kernels::fullres::ScratchLen::new(width);
        let fullres = FullResBufs { census: f.take(8 * n.census), paths: f.take(2 * n.paths), rows: f.take(2 * n.rows), grey: f.take(n.grey) };
        let ram_bytes = max(max(e.at, r.at), f.at);
        Plan { config: *cfg, width, height, grid: g, frame, pixel, encoder, refine, fullres, encoder_rings, refine_rings, ram_bytes }
    }

    /// Bytes of the frame zone.
    pub const fn frame_bytes(&self) -> usize {
        self.frame.inp16.end()
    }

    /// Output buffer sizes (not part of the arena): disparity and uncertainty, i16 each.
    pub const fn output_bytes(&self) -> usize {
        2 * 2 * self.width * self.height
    }
}

/// Working memory in bytes for `cfg` at `width x height`.
pub const fn ram_bytes(cfg: &Config, width: usize, height: usize) -> usize {
    Plan::new(cfg, width, height).ram_bytes
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn grids() {
        let g = Grid::new(160, 120);
        assert_eq!((g.w, g.h, g.w8, g.h8, g.w16, g.h16), (160, 128, 20, 16, 10, 8));
        let g = Grid::new(321, 240);
        assert_eq!((g.w, g.w8), (336, 42));
    }

    #[test]
    fn plan_is_const() {
        const P: Plan = Plan::new(&Config::MUIR_SLIM, 160, 120);
        const N: usize = P.ram_bytes;
        static BUF: [u8; N] = [0; N];
        assert!(!BUF.is_empty());
        assert!(P.encoder.rings.end() <= P.ram_bytes && P.refine.rings.end() <= P.ram_bytes);
    }
}
