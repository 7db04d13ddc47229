//! Multiply-accumulates (MACs) per frame, itemised by stage, computed from the layer table
//! ([`ConvId::shape`], [`QLayer::of`]) on the engine's padded grids ([`Grid`]). `const fn`, no
//! heap: usable on the device and in `const` items.
//!
//! Two kinds of items:
//! * **network** items: the work of the quantised network computed once per tensor, as the float
//!   reference and the plain fixed engine (`crate::reference`) do. The GRU gate convs include the
//!   context convs merged into them ([`QLayer::merged`]): the quantised network evaluates the
//!   context part inside every gate call, the float network once per frame (`context_zqr_convs`).
//!   The merged share is reported on its own ([`Macs::gru08_context`], [`Macs::gru16_context`]).
//! * **recompute** items: extra work of the streaming engine, which recomputes instead of holding
//!   whole tensors (InstanceNorm passes, UFI proposal features, one correlation lookup per pass,
//!   MGA queries and logits per iteration). [`Macs::engine_total`] = network + recompute.
//!
//! What is counted: convolution MACs (`out pixels x k^2 x cin x cout`, `cin` including merged
//! parts); correlation dot products of `fmap_dim` (lookups, UFI peaks, MGA logits `qk` and value
//! aggregation `hidden` per query-key pair); the 9 weighted terms per sub-pixel and output of the
//! convex upsampler. Not counted (each below 0.1 % of a frame): requantisation, activations,
//! InstanceNorm statistics, pooling and bilinear resizing between the 1/8 and 1/16 grids, RoPE,
//! the lookup's interpolation and box sums, element-wise gate products.
//!
//! Correlation lookups: the tiled kernel (`crate::kernels::corr::lookup_pixel`) computes one dot
//! product per right column of its window (`span`) that lies inside the row. The count here is
//! exact for a zero disparity state (window centred on `x`); a non-zero disparity moves the window
//! and changes the count only where it reaches past the row ends, never above
//! `min(window_len, w8)` per pixel. At 320x240 (`w8 = 40`, window 74 columns post-pooled, 80 for
//! the RAFT pyramid) the window covers almost the whole row: 1588 dot products per row for
//! post-pooling (1600 is the bound).
#![deny(clippy::indexing_slicing)]

use super::config::Config;
use super::graph::QLayer;
use super::layers::ConvId::{self, *};
use crate::model::grid::Grid;

/// MACs of conv `id` under `cfg` producing `pixels` output pixels (0 when the layer is not
/// computed under `cfg`). `cin` counts every quantised input part, merged context included.
pub const fn conv_macs(id: ConvId, cfg: &Config, pixels: usize) -> u64 {
    if !id.is_computed(cfg) {
        return 0;
    }
    let Some(s) = id.shape(cfg) else { return 0 };
    let cin = match QLayer::of(id, cfg) {
        Some(q) => q.cin(),
        None => s.cin,
    };
    pixels as u64 * (s.k * s.k) as u64 * cin as u64 * s.cout as u64
}

/// The part of [`conv_macs`] spent on a merged context conv's input (0 when nothing is merged).
pub const fn merged_macs(id: ConvId, cfg: &Config, pixels: usize) -> u64 {
    let Some(q) = QLayer::of(id, cfg) else { return 0 };
    let Some((ctx, _)) = q.merged else { return 0 };
    let (Some(s), Some(c)) = (id.shape(cfg), ctx.shape(cfg)) else { return 0 };
    pixels as u64 * (s.k * s.k) as u64 * c.cin as u64 * s.cout as u64
}

/// Sum of [`conv_macs`] over `ids`, each with `pixels` output pixels.
const fn convs(ids: &[ConvId], cfg: &Config, pixels: usize) -> u64 {
    let mut t = 0;
    let mut rest = ids;
    while let [id, tail @ ..] = rest {
        t += conv_macs(*id, cfg, pixels);
        rest = tail;
    }
    t
}

/// Sum of [`merged_macs`] over `ids`.
const fn merged(ids: &[ConvId], cfg: &Config, pixels: usize) -> u64 {
    let mut t = 0;
    let mut rest = ids;
    while let [id, tail @ ..] = rest {
        t += merged_macs(*id, cfg, pixels);
        rest = tail;
    }
    t
}

const fn min(a: i64, b: i64) -> i64 {
    if a < b { a } else { b }
}

const fn max(a: i64, b: i64) -> i64 {
    if a > b { a } else { b }
}

/// Correlation dot products of one lookup over a row of `w` pixels at zero disparity: the columns
/// of the tiled kernel's window (`corr::span`, same formulas) that lie inside the row.
pub const fn lookup_dots_per_row(cfg: &Config, w: usize) -> u64 {
    let l = cfg.corr_levels as u32 - 1;
    let s = 1i64 << l;
    let r = cfg.corr_radius as i64;
    let wi = w as i64;
    let mut n = 0u64;
    let mut x = 0;
    while x < w {
        let centre = (x as i64) << 8;
        let (lo, hi) = if cfg.post_pool {
            let reach = (r << (8 + l)) + ((s - 1) << 7);
            ((centre - reach) >> 8, ((centre + reach) >> 8) + 2)
        } else {
            let q = centre >> (8 + l);
            ((q - r) * s, (q + r + 2) * s)
        };
        n += max(0, min(hi, wi) - max(lo, 0)) as u64;
        x += 1;
    }
    n
}

/// MACs of one correlation lookup over the 1/8 grid (dot products of `fmap_dim`).
pub const fn lookup_macs(cfg: &Config, g: &Grid) -> u64 {
    g.h8 as u64 * lookup_dots_per_row(cfg, g.w8) * cfg.fmap_dim as u64
}

/// One stage of a MAC breakdown.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Stage {
    /// Short name.
    pub name: &'static str,
    /// What it covers.
    pub what: &'static str,
    /// MACs per frame.
    pub macs: u64,
}

/// Multiply-accumulates per frame (one image pair), itemised. Per-iteration items are summed over
/// the iterations.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Macs {
    /// Iterations counted.
    pub iters: usize,
    /// Backbone `conv1` (7x7 stride 2), both images.
    pub conv1: u64,
    /// Backbone layer1 (two blocks at 1/2), both images.
    pub layer1: u64,
    /// Backbone layer2 (1/4), both images.
    pub layer2: u64,
    /// Backbone layer3 (1/8), both images.
    pub layer3: u64,
    /// layer4 (1/16), left image.
    pub layer4: u64,
    /// Context heads (hidden state and context at 1/8 and 1/16), left image.
    pub context_heads: u64,
    /// Matching features (InstanceNorm block + conv), both images, each conv once.
    pub features: u64,
    /// UFI correlation peaks: `x + 1` dot products per pixel.
    pub ufi_peaks: u64,
    /// UFI: one lookup per proposal (3).
    pub ufi_lookups: u64,
    /// UFI convs: proposal encoders and gated initializer (3 proposals), decoder (3).
    pub ufi_convs: u64,
    /// MGA once per frame: keys, queries, `N^2 x qk` logits for the softmax statistics.
    pub mga_setup: u64,
    /// Correlation lookups, one per iteration.
    pub lookups: u64,
    /// MUD convs, every iteration.
    pub mud: u64,
    /// MGA per iteration: mask and value convs, `N^2 x hidden` aggregation.
    pub mga: u64,
    /// 1/16 ConvGRU, twice per iteration, merged context included.
    pub gru16: u64,
    /// Motion encoder, every iteration.
    pub motion: u64,
    /// 1/8 ConvGRU, every iteration, merged context included.
    pub gru08: u64,
    /// Disparity head, every iteration.
    pub flow_head: u64,
    /// Final MUD: one lookup and the MUD convs.
    pub final_mud: u64,
    /// Upsampling mask head, once.
    pub mask_head: u64,
    /// Convex upsampling (9 terms per full-resolution pixel and output).
    pub upsample: u64,
    /// Streaming engine: matching features recomputed for the InstanceNorm statistics
    /// (`FmapC1` three times, `FmapC2` twice per image).
    pub features_recompute: u64,
    /// Streaming engine: the UFI decoder pass recomputes each proposal's lookup and features.
    pub ufi_recompute: u64,
    /// Streaming engine: the MUD and MGA-value passes look the correlation up again.
    pub lookups_recompute: u64,
    /// Streaming engine: second logit pass of the softmax statistics; per iteration the queries
    /// and `N^2 x qk` logits again.
    pub mga_recompute: u64,
    /// Share of [`Macs::gru16`] spent on the merged context (`context_zqr_convs.1` inside every
    /// gate call).
    pub gru16_context: u64,
    /// Share of [`Macs::gru08`] spent on the merged context (`context_zqr_convs.0`).
    pub gru08_context: u64,
    /// MGA attention's query-key logits and weighted value sums (engine: statistics in two
    /// passes, logits again per iteration), part of `mga_setup`, `mga` and `mga_recompute`.
    pub attention: u64,
    /// Correlation dot products (UFI peaks, every lookup, recomputed ones included).
    pub correlation: u64,
}

/// MACs per frame of `cfg` on a `width x height` pair with `iters` iterations.
pub const fn macs(cfg: &Config, width: usize, height: usize, iters: usize) -> Macs {
    Macs::new(cfg, width, height, iters)
}

impl Macs {
    /// MACs per frame of `cfg` on a `width x height` pair (padded as the engine pads) with
    /// `iters` iterations.
    pub const fn new(cfg: &Config, width: usize, height: usize, iters: usize) -> Macs {
        let g = Grid::new(width, height);
        let (n2, n4, n8, n16) = (g.w2 * g.h2, g.w4 * g.h4, g.n8(), g.n16());
        let it = iters as u64;
        let n8l = n8 as u64;
        let (hd, qk) = (cfg.hidden_dim as u64, cfg.mga_qk_dim as u64);
        let look = lookup_macs(cfg, &g);

        let conv1 = 2 * conv_macs(Conv1, cfg, n2);
        let layer1 = 2 * convs(&[L1b0c1, L1b0c2, L1b1c1, L1b1c2], cfg, n2);
        let layer2 = 2 * convs(&[L2b0c1, L2b0c2, L2b0ds, L2b1c1, L2b1c2], cfg, n4);
        let layer3 = 2 * convs(&[L3b0c1, L3b0c2, L3b0ds, L3b1c1, L3b1c2], cfg, n8);
        let layer4 = convs(&[L4b0c1, L4b0c2, L4b0ds, L4b1c1, L4b1c2], cfg, n16);
        let context_heads = convs(&[H08nC1, H08nC2, H08nOut, H08cC1, H08cC2, H08cOut], cfg, n8)
            + convs(&[H16nC1, H16nC2, H16nOut, H16cC1, H16cC2, H16cOut], cfg, n16);
        let features = 2 * convs(&[FmapC1, FmapC2, FmapOut], cfg, n8);
        let features_recompute = 2 * (2 * conv_macs(FmapC1, cfg, n8) + conv_macs(FmapC2, cfg, n8));

        let (mut ufi_peaks, mut ufi_lookups, mut ufi_convs, mut ufi_recompute) = (0, 0, 0, 0);
        if cfg.ufi {
            let w8 = g.w8 as u64;
            ufi_peaks = g.h8 as u64 * (w8 * (w8 + 1) / 2) * cfg.fmap_dim as u64;
            ufi_lookups = 3 * look;
            let encoder = convs(&[UfiC, UfiF, UfiConv], cfg, n8);
            ufi_convs = 3 * (encoder + convs(&[UfiQ, UfiZ, UfiHead1, UfiHead2], cfg, n8));
            ufi_recompute = 3 * (look + encoder);
        }

        let (mut mga_setup, mut mga, mut mga_recompute, mut attention) = (0, 0, 0, 0);
        if cfg.mga {
            let pairs = n8l * n8l;
            let query = conv_macs(MgaQuery, cfg, n8);
            mga_setup = conv_macs(MgaKey, cfg, n8) + query + pairs * qk;
            mga = it * (convs(&[MgaMask, MgaValue], cfg, n8) + pairs * hd);
            mga_recompute = pairs * qk + it * (query + pairs * qk);
            attention = pairs * (2 * qk + it * (qk + hd));
        }

        let mud_convs = convs(&[Mud1, Mud2, Mud3], cfg, n8);
        let passes_with_lookup = 1 + cfg.mud as u64 + cfg.mga as u64;
        let gru16_ids = [Gru16Z, Gru16R, Gru16Q];
        let gru08_ids = [Gru08Z, Gru08R, Gru08Q];
        Macs {
            iters,
            conv1,
            layer1,
            layer2,
            layer3,
            layer4,
            context_heads,
            features,
            ufi_peaks,
            ufi_lookups,
            ufi_convs,
            mga_setup,
            lookups: it * look,
            mud: it * mud_convs,
            mga,
            gru16: it * 2 * convs(&gru16_ids, cfg, n16),
            motion: it * convs(&[MotC1, MotC2, MotF1, MotF2, MotOut], cfg, n8),
            gru08: it * convs(&gru08_ids, cfg, n8),
            flow_head: it * convs(&[Flow1, Flow2], cfg, n8),
            final_mud: if cfg.mud { look + mud_convs } else { 0 },
            mask_head: convs(&[Mask1, Mask2], cfg, n8),
            upsample: n8l * 64 * 9 * (1 + cfg.mud as u64),
            features_recompute,
            ufi_recompute,
            lookups_recompute: it * (passes_with_lookup - 1) * look,
            mga_recompute,
            gru16_context: it * 2 * merged(&gru16_ids, cfg, n16),
            gru08_context: it * merged(&gru08_ids, cfg, n8),
            attention,
            correlation: ufi_peaks
                + ufi_lookups
                + if cfg.ufi { 3 * look } else { 0 }
                + it * passes_with_lookup * look
                + if cfg.mud { look } else { 0 },
        }
    }

    /// The engine's MACs by kernel family (what a per-function profile of the firmware can be
    /// set against): convolutions (everything not in the other three), attention, correlation,
    /// convex upsampling. They sum to [`Macs::engine_total`].
    pub const fn families(&self) -> [Stage; 4] {
        let other = self.attention + self.correlation + self.upsample;
        [
            Stage { name: "convolutions", what: "every conv layer, recomputed ones included", macs: self.engine_total() - other },
            Stage { name: "attention", what: "MGA logits and weighted value sums", macs: self.attention },
            Stage { name: "correlation", what: "UFI peaks and every correlation lookup", macs: self.correlation },
            Stage { name: "upsampling", what: "convex upsampling", macs: self.upsample },
        ]
    }

    /// Backbone conv1 .. layer3, both images.
    pub const fn backbone(&self) -> u64 {
        self.conv1 + self.layer1 + self.layer2 + self.layer3
    }

    /// Network items (see the module doc), in the order of a frame.
    pub const fn network(&self) -> [Stage; 21] {
        const fn s(name: &'static str, what: &'static str, macs: u64) -> Stage {
            Stage { name, what, macs }
        }
        [
            s("conv1", "backbone conv1, both images", self.conv1),
            s("layer1", "backbone layer1, both images", self.layer1),
            s("layer2", "backbone layer2, both images", self.layer2),
            s("layer3", "backbone layer3, both images", self.layer3),
            s("layer4", "layer4, left image", self.layer4),
            s("context heads", "hidden state and context heads, 1/8 and 1/16", self.context_heads),
            s("features", "matching features, both images", self.features),
            s("ufi peaks", "UFI correlation peaks", self.ufi_peaks),
            s("ufi lookups", "UFI proposal lookups (3)", self.ufi_lookups),
            s("ufi convs", "UFI encoders, initializer, decoder (3 proposals)", self.ufi_convs),
            s("mga setup", "MGA keys, queries, softmax statistics", self.mga_setup),
            s("lookups", "correlation lookup, per iteration", self.lookups),
            s("mud", "MUD, per iteration", self.mud),
            s("mga", "MGA mask, values, aggregation, per iteration", self.mga),
            s("gru16", "1/16 ConvGRU x2 (merged context), per iteration", self.gru16),
            s("motion", "motion encoder, per iteration", self.motion),
            s("gru08", "1/8 ConvGRU (merged context), per iteration", self.gru08),
            s("flow head", "disparity head, per iteration", self.flow_head),
            s("final mud", "final lookup and MUD", self.final_mud),
            s("mask head", "upsampling mask head, once", self.mask_head),
            s("upsample", "convex upsampling", self.upsample),
        ]
    }

    /// Recompute items of the streaming engine.
    pub const fn recompute(&self) -> [Stage; 4] {
        [
            Stage { name: "features recompute", what: "InstanceNorm passes (FmapC1 x3, FmapC2 x2)", macs: self.features_recompute },
            Stage { name: "ufi recompute", what: "decoder pass: proposal lookups and encoders again", macs: self.ufi_recompute },
            Stage { name: "lookups recompute", what: "MUD and MGA-value passes look up again", macs: self.lookups_recompute },
            Stage { name: "mga recompute", what: "statistics second pass, per-iteration queries and logits", macs: self.mga_recompute },
        ]
    }

    /// Sum of the network items.
    pub const fn total(&self) -> u64 {
        let n = self.network();
        let mut t = 0;
        let mut rest: &[Stage] = &n;
        while let [stage, tail @ ..] = rest {
            t += stage.macs;
            rest = tail;
        }
        t
    }

    /// Sum of the recompute items.
    pub const fn recompute_total(&self) -> u64 {
        self.features_recompute + self.ufi_recompute + self.lookups_recompute + self.mga_recompute
    }

    /// What the streaming engine computes: network + recompute.
    pub const fn engine_total(&self) -> u64 {
        self.total() + self.recompute_total()
    }

    /// The engine's MACs of one iteration (MUD, MGA, lookups, GRUs, motion, head), recompute
    /// included: `(frame(iters) - frame(0)) / iters`.
    pub const fn per_iteration(cfg: &Config, width: usize, height: usize) -> u64 {
        Macs::new(cfg, width, height, 1).engine_total() - Macs::new(cfg, width, height, 0).engine_total()
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    const G: f64 = 1e9;

    fn close(what: &str, got: u64, want_g: f64, tol: f64) {
        let g = got as f64 / G;
        assert!((g - want_g).abs() <= tol * want_g, "{what}: {g:.3} G, expected {want_g} G within {}%", tol * 100.0);
    }

    /// The public realtime model at 320x240, 7 iterations, against the PyTorch count in
    /// `shared/reference/raft-stereo-realtime-forward.md`: 36.95 G with the mask head every
    /// iteration; gru08 11.15, layer1 5.66, gru16 3.72, mask head 3.72, layer2 2.98, flow head
    /// 2.52, motion encoder 1.91, layer3 1.36.
    ///
    /// Their GRU figures exclude `context_zqr_convs` (computed once per pair there):
    /// gru08 = 7 x 1200 px x 3 gates x 9 x 384 x 128 = 11.15 G exactly, while the quantised
    /// network's gates read 128 more (context) input channels, 14.86 G. So the comparison subtracts
    /// the merged share; the float network's once-per-frame context convs (0.66 G) are part of
    /// their total. Their total also holds a full correlation volume (h8 x w8 x w8 x 256, 0.012 G)
    /// instead of our 7 tiled lookups.
    #[test]
    fn realtime_matches_the_pytorch_count() {
        let cfg = Config::RAFT_STEREO_REALTIME;
        let m = Macs::new(&cfg, 320, 240, 7);
        close("gru08", m.gru08 - m.gru08_context, 11.15, 0.02);
        close("gru16", m.gru16 - m.gru16_context, 3.72, 0.02);
        close("layer1", m.layer1, 5.66, 0.02);
        close("layer2", m.layer2, 2.98, 0.02);
        close("layer3", m.layer3, 1.36, 0.02);
        close("flow head", m.flow_head, 2.52, 0.02);
        close("motion", m.motion, 1.91, 0.02);
        close("mask head x7", 7 * m.mask_head, 3.72, 0.02);
        // The merged context is exactly the context conv per gate call.
        assert_eq!(m.gru08_context, 7 * conv_macs(Czqr08, &cfg, 1200));
        assert_eq!(m.gru16_context, 14 * conv_macs(Czqr16, &cfg, 300));
        let g = Grid::new(320, 240);
        let pytorch_like = m.total() - m.gru08_context - m.gru16_context
            + conv_macs(Czqr08, &cfg, g.n8())
            + conv_macs(Czqr16, &cfg, g.n16())
            + 6 * m.mask_head
            - m.lookups
            - m.upsample
            + (g.n8() * g.w8 * cfg.fmap_dim) as u64;
        close("total", pytorch_like, 36.95, 0.01);
        // No MUIR module: nothing of UFI, MGA, MUD; the engine recomputes the features only.
        assert_eq!(m.ufi_convs + m.mga_setup + m.mga + m.mud + m.final_mud, 0);
        assert_eq!(m.recompute_total(), m.features_recompute);
    }

    #[test]
    fn lookup_window_counts() {
        // post-pooled 4 levels radius 4: window [x - 36, x + 37) clipped to 40 columns
        assert_eq!(lookup_dots_per_row(&Config::MUIR_FAST, 40), 40 * 40 - 2 * (3 + 2 + 1));
        // wide rows: 73 columns per pixel, 1..36 fewer towards either end
        let wide = lookup_dots_per_row(&Config::MUIR_FAST, 400);
        assert_eq!(wide, 400 * 73 - 2 * (1..=36).sum::<u64>());
        assert!(wide <= 400 * crate::kernels::corr::window_len(4, 4) as u64);
        // RAFT pyramid: blocks of 8, window (q - 4) * 8 .. (q + 6) * 8
        assert_eq!(lookup_dots_per_row(&Config::RAFT_STEREO_REALTIME, 16), 16 * 16);
    }

    #[test]
    fn muir_items_and_totals() {
        for cfg in [Config::MUIR_FAST, Config::MUIR_SLIM] {
            let m = Macs::new(&cfg, 320, 240, 7);
            let n8 = 1200u64;
            assert_eq!(m.ufi_peaks, 30 * (40 * 41 / 2) * cfg.fmap_dim as u64);
            assert_eq!(m.ufi_lookups, 3 * m.lookups / 7);
            assert_eq!(m.lookups_recompute, 2 * m.lookups);
            assert_eq!(m.mga_setup, 2 * n8 * (cfg.context_dim * cfg.mga_qk_dim) as u64 + n8 * n8 * cfg.mga_qk_dim as u64);
            assert_eq!(m.engine_total(), m.total() + m.recompute_total());
            assert_eq!(Macs::per_iteration(&cfg, 320, 240) * 7, m.engine_total() - Macs::new(&cfg, 320, 240, 0).engine_total());
            assert!(m.features_recompute > m.features / 2 && m.features_recompute < m.features);
            // Families: attention = statistics (two passes) + per-iteration logits and sums.
            let (qk, hd) = (cfg.mga_qk_dim as u64, cfg.hidden_dim as u64);
            assert_eq!(m.attention, n8 * n8 * (2 * qk + 7 * (qk + hd)));
            assert_eq!(m.correlation, m.ufi_peaks + 2 * m.ufi_lookups + 3 * m.lookups + m.lookups / 7);
            assert_eq!(m.families().iter().map(|f| f.macs).sum::<u64>(), m.engine_total());
            assert!(m.families()[0].macs > m.engine_total() / 2);
        }
        // slim has half the widths: about a quarter of the conv MACs
        let (f, s) = (Macs::new(&Config::MUIR_FAST, 320, 240, 7), Macs::new(&Config::MUIR_SLIM, 320, 240, 7));
        assert_eq!(4 * s.gru08, f.gru08);
        assert_eq!(4 * s.layer1, f.layer1);
        // padding: 321 wide is computed as 336
        assert_eq!(Macs::new(&Config::MUIR_SLIM, 321, 240, 7), Macs::new(&Config::MUIR_SLIM, 336, 240, 7));
    }

    #[test]
    fn usable_in_const() {
        const M: Macs = macs(&Config::MUIR_SLIM, 160, 120, 7);
        const T: u64 = M.engine_total();
        assert!(T > M.total());
    }
}
