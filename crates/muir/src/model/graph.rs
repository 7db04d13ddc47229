//! Wiring of the quantised network: activation slots, and for each convolution the parts of its
//! (concatenated) input, its output slot(s) and its activation.
//!
//! A convolution over `cat[A, B, ...]` whose parts have different formats is computed on the raw
//! integers of the parts; the blob writer folds each part's scale into the weights ("effective
//! weights", quantised per output channel), so parts never need rescaling before a conv. The
//! context convs `context_zqr_convs.*` are merged into the GRU gate convs the same way: their
//! input (the context feature) is one more part, their bias is added to the gate bias.
#![deny(clippy::indexing_slicing)]

use super::config::Config;
use super::layers::{ConvId, MASK_CHANNELS};
use crate::arith::{FLOW_FRAC, GATE_FRAC, LOG_FRAC, QFormat, UNIT_FRAC};

macro_rules! acts {
    ($($id:ident = $name:literal $ty:ident $(fixed $frac:expr)?,)*) => {
        /// An activation slot: a tensor (or family of same-format tensors) of the quantised network.
        #[allow(missing_docs)]
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        #[repr(u8)]
        pub enum Act { $($id,)* }

        impl Act {
            /// All slots, in blob order.
            pub const ALL: &'static [Act] = &[$(Act::$id,)*];
            /// Number of slots.
            pub const COUNT: usize = Self::ALL.len();
            /// Name (calibration traces record `q.<name>`).
            pub const fn name(self) -> &'static str {
                match self { $(Act::$id => $name,)* }
            }
            /// Storage type (`i8`, `u8` or `i16`) as a format with 0 fraction bits.
            pub const fn storage(self) -> QFormat {
                match self { $(Act::$id => QFormat::$ty(0),)* }
            }
            /// Storage type in a model of `cfg`: [`Act::storage`], or `i16` for the trunk slots
            /// [`Config::wide_trunk`] widens.
            pub const fn storage_in(self, cfg: &Config) -> QFormat {
                if cfg.wide_trunk && self.in_wide_trunk() { QFormat::i16(0) } else { self.storage() }
            }
            /// Storage width (8 or 16 bits).
            pub const fn bits(self) -> u8 {
                self.storage().bits
            }
            /// Unsigned storage (`u8`): the slot follows a ReLU.
            pub const fn unsigned(self) -> bool {
                self.storage().unsigned
            }
            /// The format when fixed by the arithmetic spec; `None` when chosen by calibration.
            pub const fn fixed_format(self) -> Option<QFormat> {
                #[allow(unreachable_patterns)]
                match self {
                    $($(Act::$id => Some(QFormat::$ty($frac as i8)),)?)*
                    _ => None,
                }
            }
            /// Index in [`Act::ALL`].
            pub const fn index(self) -> usize {
                self as usize
            }
        }
    };
}

acts! {
    // Input image: 2 * pixel - 255 as i16 (scale 1/255, folded into conv1's weights), so that the
    // zero padding of conv1 is the normalised image's 0 as in the float network.
    Image = "image" i16 fixed 0,
    // Backbone: every tensor follows a ReLU, so u8 (twice the codes of i8 for the same range).
    C1 = "c1" u8,
    L1b0m = "l1b0m" u8, L1b0o = "l1b0o" u8, L1b1m = "l1b1m" u8, L1b1o = "l1b1o" u8,
    L2b0m = "l2b0m" u8, L2b0o = "l2b0o" u8, L2b1m = "l2b1m" u8, L2b1o = "l2b1o" u8,
    L3b0m = "l3b0m" u8, L3b0o = "l3b0o" u8, L3b1m = "l3b1m" u8, L3b1o = "l3b1o" u8,
    L4b0m = "l4b0m" u8, L4b0o = "l4b0o" u8, L4b1m = "l4b1m" u8, L4b1o = "l4b1o" u8,
    H08nm = "h08nm" u8, H08no = "h08no" u8, H08cm = "h08cm" u8, H08co = "h08co" u8,
    H16nm = "h16nm" u8, H16no = "h16no" u8, H16cm = "h16cm" u8, H16co = "h16co" u8,
    // Matching features: conv outputs before InstanceNorm are i16, the normalised (ReLU) ones u8,
    // the features themselves (no ReLU) i8.
    FmapRaw1 = "fmap_raw1" i16, FmapMid = "fmap_mid" u8, FmapRaw2 = "fmap_raw2" i16, FmapBlk = "fmap_blk" u8,
    Fmap = "fmap" i8,
    // Fixed formats of the update block.
    Gate = "gate" i16 fixed GATE_FRAC,
    Unit = "unit" i16 fixed UNIT_FRAC,
    Flow = "flow" i16 fixed FLOW_FRAC,
    Log = "log" i16 fixed LOG_FRAC,
    // Context: u8 storage (frame-long, the largest tensors after the features; after a ReLU);
    // widened to i16 rows where an i16 conv reads it.
    Inp08 = "inp08" u8, Inp16 = "inp16" u8,
    // Update block, i16.
    Corr = "corr" i16,
    MotC1 = "mot_c1" i16, MotC2 = "mot_c2" i16, MotF1 = "mot_f1" i16, MotF2 = "mot_f2" i16, MotOut = "mot_out" i16,
    FlowMid = "flow_mid" i16, MaskMid = "mask_mid" i16, MaskLogit = "mask_logit" i16,
    Mud1 = "mud1" i16, Mud2 = "mud2" i16,
    UfiC = "ufi_c" i16, UfiF = "ufi_f" i16, UfiFeat = "ufi_feat" i16, UfiHead = "ufi_head" i16,
    MgaQ = "mga_q" i16, MgaK = "mga_k" i16, MgaV = "mga_v" i16, Glb = "glb" i16,
}

impl Act {
    /// conv1, layer1 and layer2 outputs (block inputs, mids and outputs at 1/2 and 1/4
    /// resolution): the slots [`Config::wide_trunk`] stores in `i16`. Their 8-bit noise is most of
    /// what reaches the matching features (README, "Accuracy"); layer3 and later stay `u8`.
    pub const fn in_wide_trunk(self) -> bool {
        use Act::*;
        matches!(self, C1 | L1b0m | L1b0o | L1b1m | L1b1o | L2b0m | L2b0o | L2b1m | L2b1o)
    }
}

/// What follows the requantisation of a conv output.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
#[repr(u8)]
pub enum PostOp {
    /// Saturate only.
    None = 0,
    /// `max(0, .)`.
    Relu = 1,
    /// Requantise to Q3.12, then sigmoid to Q0.15.
    Sigmoid = 2,
    /// Requantise to Q3.12, then tanh to Q0.15.
    Tanh = 3,
}

/// One part of a conv input: a slot and a channel count.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Part {
    /// Activation slot (its format scales the part's weights).
    pub act: Act,
    /// Channels of this part.
    pub channels: usize,
}

/// Largest number of input parts of any conv.
pub const MAX_PARTS: usize = 6;

/// Wiring of one quantised conv.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct QLayer {
    /// Input parts in channel order (the float weights' `cin` axis, then the merged context).
    pub parts: [Option<Part>; MAX_PARTS],
    /// Output slot of channels `[0, split)` and of `[split, cout)`.
    pub out: [Act; 2],
    /// First channel written in `out[1]`'s format (= cout when all use `out[0]`).
    pub split: usize,
    /// Activation after requantisation.
    pub post: PostOp,
    /// Context conv merged into this gate conv: (layer, chunk of `hidden_dim` output channels).
    pub merged: Option<(ConvId, usize)>,
    /// Extra factor on the real output (0.25 of the upsampling mask).
    pub out_factor: f32,
}

const fn p(act: Act, channels: usize) -> Option<Part> {
    Some(Part { act, channels })
}

const fn q(parts: [Option<Part>; MAX_PARTS], out: Act, post: PostOp) -> QLayer {
    QLayer { parts, out: [out, out], split: usize::MAX, post, merged: None, out_factor: 1.0 }
}

const N: Option<Part> = None;

impl QLayer {
    /// Sum of the parts' channels (the conv's `cin` including a merged context).
    pub const fn cin(&self) -> usize {
        let mut c = 0;
        let mut rest: &[Option<Part>] = &self.parts;
        while let [part, tail @ ..] = rest {
            if let Some(p) = part {
                c += p.channels;
            }
            rest = tail;
        }
        c
    }

    /// Output slot of channel `c`.
    pub const fn out_act(&self, c: usize) -> Act {
        if c < self.split { self.out[0] } else { self.out[1] }
    }

    /// Wiring of `id` under `cfg`; `None` for layers that are not computed on their own
    /// (checkpoint-only layers, and the context convs merged into the GRUs).
    pub const fn of(id: ConvId, cfg: &Config) -> Option<QLayer> {
        use Act as A;
        use ConvId::*;
        use PostOp::{None as Id, Relu, Sigmoid, Tanh};
        if !id.is_computed(cfg) {
            return None;
        }
        let [d1, d2, d3] = cfg.backbone_dims;
        let h = cfg.hidden_dim;
        let ctx = cfg.context_dim;
        let fc = cfg.flow_channels;
        let cc = cfg.corr_channels();
        let l = match id {
            Conv1 => q([p(A::Image, 3), N, N, N, N, N], A::C1, Relu),
            L1b0c1 => q([p(A::C1, d1), N, N, N, N, N], A::L1b0m, Relu),
            L1b0c2 => q([p(A::L1b0m, d1), N, N, N, N, N], A::L1b0o, Relu),
            L1b1c1 => q([p(A::L1b0o, d1), N, N, N, N, N], A::L1b1m, Relu),
            L1b1c2 => q([p(A::L1b1m, d1), N, N, N, N, N], A::L1b1o, Relu),
            L2b0c1 => q([p(A::L1b1o, d1), N, N, N, N, N], A::L2b0m, Relu),
            L2b0c2 => q([p(A::L2b0m, d2), N, N, N, N, N], A::L2b0o, Relu),
            L2b0ds => q([p(A::L1b1o, d1), N, N, N, N, N], A::L2b0o, Id),
            L2b1c1 => q([p(A::L2b0o, d2), N, N, N, N, N], A::L2b1m, Relu),
            L2b1c2 => q([p(A::L2b1m, d2), N, N, N, N, N], A::L2b1o, Relu),
            L3b0c1 => q([p(A::L2b1o, d2), N, N, N, N, N], A::L3b0m, Relu),
            L3b0c2 => q([p(A::L3b0m, d3), N, N, N, N, N], A::L3b0o, Relu),
            L3b0ds => q([p(A::L2b1o, d2), N, N, N, N, N], A::L3b0o, Id),
            L3b1c1 => q([p(A::L3b0o, d3), N, N, N, N, N], A::L3b1m, Relu),
            L3b1c2 => q([p(A::L3b1m, d3), N, N, N, N, N], A::L3b1o, Relu),
            L4b0c1 => q([p(A::L3b1o, d3), N, N, N, N, N], A::L4b0m, Relu),
            L4b0c2 => q([p(A::L4b0m, d3), N, N, N, N, N], A::L4b0o, Relu),
            L4b0ds => q([p(A::L3b1o, d3), N, N, N, N, N], A::L4b0o, Id),
            L4b1c1 => q([p(A::L4b0o, d3), N, N, N, N, N], A::L4b1m, Relu),
            L4b1c2 => q([p(A::L4b1m, d3), N, N, N, N, N], A::L4b1o, Relu),
            H08nC1 => q([p(A::L3b1o, d3), N, N, N, N, N], A::H08nm, Relu),
            H08nC2 => q([p(A::H08nm, d3), N, N, N, N, N], A::H08no, Relu),
            H08nOut => q([p(A::H08no, d3), N, N, N, N, N], A::Unit, Tanh),
            H08cC1 => q([p(A::L3b1o, d3), N, N, N, N, N], A::H08cm, Relu),
            H08cC2 => q([p(A::H08cm, d3), N, N, N, N, N], A::H08co, Relu),
            H08cOut => q([p(A::H08co, d3), N, N, N, N, N], A::Inp08, Relu),
            H16nC1 => q([p(A::L4b1o, d3), N, N, N, N, N], A::H16nm, Relu),
            H16nC2 => q([p(A::H16nm, d3), N, N, N, N, N], A::H16no, Relu),
            H16nOut => q([p(A::H16no, d3), N, N, N, N, N], A::Unit, Tanh),
            H16cC1 => q([p(A::L4b1o, d3), N, N, N, N, N], A::H16cm, Relu),
            H16cC2 => q([p(A::H16cm, d3), N, N, N, N, N], A::H16co, Relu),
            H16cOut => q([p(A::H16co, d3), N, N, N, N, N], A::Inp16, Relu),
            FmapC1 => q([p(A::L3b1o, d3), N, N, N, N, N], A::FmapRaw1, Id),
            FmapC2 => q([p(A::FmapMid, d3), N, N, N, N, N], A::FmapRaw2, Id),
            FmapOut => q([p(A::FmapBlk, d3), N, N, N, N, N], A::Fmap, Id),
            Czqr08 | Czqr16 => return None,
            MotC1 => {
                if cfg.mud {
                    q([p(A::Corr, cc), p(A::Corr, cc), p(A::Unit, 1), N, N, N], A::MotC1, Relu)
                } else {
                    q([p(A::Corr, cc), N, N, N, N, N], A::MotC1, Relu)
                }
            }
            MotC2 => q([p(A::MotC1, cfg.motion_corr_dims[0]), N, N, N, N, N], A::MotC2, Relu),
            MotF1 => q([p(A::Flow, fc), N, N, N, N, N], A::MotF1, Relu),
            MotF2 => q([p(A::MotF1, cfg.motion_flow_dims[0]), N, N, N, N, N], A::MotF2, Relu),
            MotOut => q(
                [p(A::MotC2, cfg.motion_corr_dims[1]), p(A::MotF2, cfg.motion_flow_dims[1]), N, N, N, N],
                A::MotOut,
                Relu,
            ),
            Gru08Z | Gru08R | Gru08Q => {
                let first = A::Unit; // h for the gates, r*h for the candidate: both Q0.15
                let glb = if cfg.mga { p(A::Glb, h) } else { N };
                let chunk = match id {
                    Gru08Z => 0,
                    Gru08R => 1,
                    _ => 2,
                };
                let post = if matches!(id, Gru08Q) { Tanh } else { Sigmoid };
                let mut l = q(
                    [p(first, h), p(A::MotOut, cfg.motion_dim - fc), p(A::Flow, fc), p(A::Unit, h), glb, p(A::Inp08, ctx)],
                    A::Unit,
                    post,
                );
                if !cfg.mga {
                    l.parts[4] = p(A::Inp08, ctx);
                    l.parts[5] = N;
                }
                l.merged = Some((Czqr08, chunk));
                l
            }
            Gru16Z | Gru16R | Gru16Q => {
                let chunk = match id {
                    Gru16Z => 0,
                    Gru16R => 1,
                    _ => 2,
                };
                let post = if matches!(id, Gru16Q) { Tanh } else { Sigmoid };
                let mut l = q([p(A::Unit, h), p(A::Unit, h), p(A::Inp16, ctx), N, N, N], A::Unit, post);
                l.merged = Some((Czqr16, chunk));
                l
            }
            Flow1 => q([p(A::Unit, h), N, N, N, N, N], A::FlowMid, Relu),
            Flow2 => q([p(A::FlowMid, cfg.flow_head_dim), N, N, N, N, N], A::Flow, Id),
            Mask1 => q([p(A::Unit, h), N, N, N, N, N], A::MaskMid, Relu),
            Mask2 => {
                let mut l = q([p(A::MaskMid, cfg.mask_head_dim), N, N, N, N, N], A::MaskLogit, Id);
                l.out_factor = 0.25;
                l
            }
            Mud1 => q([p(A::Unit, h), p(A::Corr, cc), p(A::Flow, 1), N, N, N], A::Mud1, Relu),
            Mud2 => q([p(A::Mud1, cfg.mud_dim), N, N, N, N, N], A::Mud2, Relu),
            Mud3 => q([p(A::Mud2, cfg.mud_dim), N, N, N, N, N], A::Log, Id),
            UfiC => q([p(A::Corr, cc), N, N, N, N, N], A::UfiC, Relu),
            UfiF => q([p(A::Flow, fc), N, N, N, N, N], A::UfiF, Relu),
            UfiConv => q([p(A::UfiC, cfg.ufi_corr_dim), p(A::UfiF, cfg.ufi_flow_dim), N, N, N, N], A::UfiFeat, Relu),
            UfiQ => q([p(A::UfiFeat, cfg.ufi_dim - fc), p(A::Flow, fc), p(A::Inp08, ctx), N, N, N], A::Unit, Tanh),
            UfiZ => q([p(A::Unit, h), p(A::Unit, h), N, N, N, N], A::Unit, Sigmoid),
            UfiHead1 => q([p(A::Unit, h), p(A::UfiFeat, cfg.ufi_dim - fc), p(A::Flow, fc), N, N, N], A::UfiHead, Relu),
            UfiHead2 => {
                let mut l = q([p(A::UfiHead, cfg.ufi_head_dim), N, N, N, N, N], A::Flow, Id);
                l.out[1] = A::Log;
                l.split = 1;
                l
            }
            MgaQuery => q([p(A::Inp08, ctx), N, N, N, N, N], A::MgaQ, Id),
            MgaKey => q([p(A::Inp08, ctx), N, N, N, N, N], A::MgaK, Id),
            MgaMask => q([p(A::Unit, h), p(A::Corr, cc), p(A::Flow, 1), p(A::Unit, 1), N, N], A::Unit, Sigmoid),
            MgaValue => q([p(A::Unit, h), N, N, N, N, N], A::MgaV, Id),
            _ => return None,
        };
        Some(l)
    }
}

/// Output channels of the upsampling mask conv (re-exported for kernels).
pub const UPSAMPLE_MASK_CHANNELS: usize = MASK_CHANNELS;

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn wiring_matches_float_shapes() {
        for cfg in Config::PRESETS {
            for &id in ConvId::ALL {
                let Some(ql) = QLayer::of(id, &cfg) else { continue };
                let s = id.shape(&cfg).unwrap();
                let merged = ql.merged.map(|(m, _)| m.shape(&cfg).unwrap().cin).unwrap_or(0);
                assert_eq!(ql.cin(), s.cin + merged, "{} in {}", id.name(), cfg.name);
            }
        }
    }

    /// A u8 slot has no negative codes: every conv that writes it must end in a ReLU, except the
    /// residual blocks' 1x1 downsample convs, whose i16 output is added to the block's conv and
    /// clamped at 0 by the residual ReLU (`eltwise::residual_relu`).
    #[test]
    fn unsigned_slots_follow_a_relu() {
        for cfg in Config::PRESETS {
            for &id in ConvId::ALL {
                let Some(ql) = QLayer::of(id, &cfg) else { continue };
                let unsigned_out = ql.out[0].unsigned() || (ql.split < usize::MAX && ql.out[1].unsigned());
                if unsigned_out && ql.post != PostOp::Relu {
                    assert!(id.name().contains("downsample"), "{} writes a u8 slot without a ReLU", id.name());
                }
            }
        }
    }

    #[test]
    fn fixed_and_calibrated_slots() {
        assert_eq!(Act::Unit.fixed_format(), Some(QFormat::i16(15)));
        assert_eq!(Act::Fmap.fixed_format(), None);
        assert_eq!(Act::Fmap.bits(), 8);
        assert!(!Act::Fmap.unsigned() && Act::L3b1o.unsigned() && Act::Inp08.unsigned());
        for (i, a) in Act::ALL.iter().enumerate() {
            assert_eq!(a.index(), i);
        }
    }
}
