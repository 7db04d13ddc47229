//! Every convolution of the network, by identity: parameter names, shapes and normalisation.
//!
//! This table is the single description of the weights. The float reference loads safetensors by
//! these names, the quantised blob stores layers in [`ConvId::ALL`] order, MAC counts and the memory
//! plan read the shapes from here. Names are the PyTorch twin's state_dict keys (those of the public
//! RAFT-Stereo checkpoint for the shared parts), without the `.weight` / `.bias` suffix.
#![deny(clippy::indexing_slicing)]

use super::config::Config;

/// Normalisation applied right after a convolution.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum Norm {
    /// Plain convolution (bias only).
    None,
    /// BatchNorm with stored statistics; the parameter prefix (e.g. `cnet.layer1.0.norm1`). A
    /// downsample's norm is also stored under `<block>.downsample.1` (same module, two names).
    Batch(&'static str),
    /// InstanceNorm without affine parameters (per-image statistics).
    Instance,
}

/// Shape and wiring of one convolution. Padding is `k / 2` (same padding) for every layer.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ConvShape {
    /// Input channels.
    pub cin: usize,
    /// Output channels.
    pub cout: usize,
    /// Square kernel size.
    pub k: usize,
    /// Stride (1 or 2).
    pub stride: usize,
    /// Normalisation after the conv.
    pub norm: Norm,
}

impl ConvShape {
    const fn new(cin: usize, cout: usize, k: usize, stride: usize, norm: Norm) -> Self {
        Self { cin, cout, k, stride, norm }
    }
    /// Number of weights (`cout * cin * k * k`).
    pub const fn weight_len(&self) -> usize {
        self.cout * self.cin * self.k * self.k
    }
    /// Multiply-accumulates per output pixel.
    pub const fn macs_per_pixel(&self) -> usize {
        self.weight_len()
    }
}

macro_rules! conv_ids {
    ($($id:ident = $name:literal,)*) => {
        /// Identity of a convolution layer; variant names abbreviate the parameter names
        /// ([`ConvId::name`]).
        #[allow(missing_docs)]
        #[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash)]
        #[cfg_attr(feature = "defmt", derive(defmt::Format))]
        #[repr(u8)]
        pub enum ConvId { $($id,)* }

        impl ConvId {
            /// All layers in storage order.
            pub const ALL: &'static [ConvId] = &[$(ConvId::$id,)*];
            /// Number of layer identities.
            pub const COUNT: usize = Self::ALL.len();
            /// Parameter name prefix (`<name>.weight`, `<name>.bias`).
            pub const fn name(self) -> &'static str {
                match self { $(ConvId::$id => $name,)* }
            }
            /// Index in [`ConvId::ALL`].
            pub const fn index(self) -> usize {
                self as usize
            }
        }
    };
}

conv_ids! {
    Conv1 = "cnet.conv1",
    L1b0c1 = "cnet.layer1.0.conv1", L1b0c2 = "cnet.layer1.0.conv2",
    L1b1c1 = "cnet.layer1.1.conv1", L1b1c2 = "cnet.layer1.1.conv2",
    L2b0c1 = "cnet.layer2.0.conv1", L2b0c2 = "cnet.layer2.0.conv2", L2b0ds = "cnet.layer2.0.downsample.0",
    L2b1c1 = "cnet.layer2.1.conv1", L2b1c2 = "cnet.layer2.1.conv2",
    L3b0c1 = "cnet.layer3.0.conv1", L3b0c2 = "cnet.layer3.0.conv2", L3b0ds = "cnet.layer3.0.downsample.0",
    L3b1c1 = "cnet.layer3.1.conv1", L3b1c2 = "cnet.layer3.1.conv2",
    L4b0c1 = "cnet.layer4.0.conv1", L4b0c2 = "cnet.layer4.0.conv2", L4b0ds = "cnet.layer4.0.downsample.0",
    L4b1c1 = "cnet.layer4.1.conv1", L4b1c2 = "cnet.layer4.1.conv2",
    H08nC1 = "cnet.outputs08.0.0.conv1", H08nC2 = "cnet.outputs08.0.0.conv2", H08nOut = "cnet.outputs08.0.1",
    H08cC1 = "cnet.outputs08.1.0.conv1", H08cC2 = "cnet.outputs08.1.0.conv2", H08cOut = "cnet.outputs08.1.1",
    H16nC1 = "cnet.outputs16.0.0.conv1", H16nC2 = "cnet.outputs16.0.0.conv2", H16nOut = "cnet.outputs16.0.1",
    H16cC1 = "cnet.outputs16.1.0.conv1", H16cC2 = "cnet.outputs16.1.0.conv2", H16cOut = "cnet.outputs16.1.1",
    FmapC1 = "conv2.0.conv1", FmapC2 = "conv2.0.conv2", FmapOut = "conv2.1",
    Czqr08 = "context_zqr_convs.0", Czqr16 = "context_zqr_convs.1",
    MotC1 = "update_block.encoder.convc1", MotC2 = "update_block.encoder.convc2",
    MotF1 = "update_block.encoder.convf1", MotF2 = "update_block.encoder.convf2",
    MotOut = "update_block.encoder.conv",
    Gru08Z = "update_block.gru08.convz", Gru08R = "update_block.gru08.convr", Gru08Q = "update_block.gru08.convq",
    Gru16Z = "update_block.gru16.convz", Gru16R = "update_block.gru16.convr", Gru16Q = "update_block.gru16.convq",
    Flow1 = "update_block.flow_head.conv1", Flow2 = "update_block.flow_head.conv2",
    Mask1 = "update_block.mask.0", Mask2 = "update_block.mask.2",
    Mud1 = "mud.conv1", Mud2 = "mud.conv2", Mud3 = "mud.conv3",
    UfiC = "ufi.convc", UfiF = "ufi.convf", UfiConv = "ufi.conv", UfiQ = "ufi.convq", UfiZ = "ufi.convz",
    UfiHead1 = "ufi.head1", UfiHead2 = "ufi.head2",
    MgaQuery = "mga.query", MgaKey = "mga.key", MgaMask = "mga.mask", MgaValue = "mga.value",
    // Held by the public realtime checkpoint, never run with two GRU levels.
    X5b0c1 = "cnet.layer5.0.conv1", X5b0c2 = "cnet.layer5.0.conv2", X5b0ds = "cnet.layer5.0.downsample.0",
    X5b1c1 = "cnet.layer5.1.conv1", X5b1c2 = "cnet.layer5.1.conv2",
    X32n = "cnet.outputs32.0", X32c = "cnet.outputs32.1",
    XGru32Z = "update_block.gru32.convz", XGru32R = "update_block.gru32.convr", XGru32Q = "update_block.gru32.convq",
}

/// Upsampling mask channels: 9 neighbours x 8 x 8 sub-pixels.
pub const MASK_CHANNELS: usize = 9 * 64;

impl ConvId {
    /// True for layers that exist only to load the public checkpoint (never computed).
    pub const fn checkpoint_only(self) -> bool {
        (self as u8) >= (ConvId::X5b0c1 as u8)
    }

    /// Shape of this layer under `cfg`, or `None` when the layer is not part of that network.
    pub const fn shape(self, cfg: &Config) -> Option<ConvShape> {
        use ConvId::*;
        use Norm::{Batch as B, Instance as I, None as N};
        let [d1, d2, d3] = cfg.backbone_dims;
        let h = cfg.hidden_dim;
        let ctx = cfg.context_dim;
        let fc = cfg.flow_channels;
        let s = ConvShape::new;
        let shape = match self {
            Conv1 => s(3, d1, 7, 2, B("cnet.norm1")),
            L1b0c1 => s(d1, d1, 3, 1, B("cnet.layer1.0.norm1")),
            L1b0c2 => s(d1, d1, 3, 1, B("cnet.layer1.0.norm2")),
            L1b1c1 => s(d1, d1, 3, 1, B("cnet.layer1.1.norm1")),
            L1b1c2 => s(d1, d1, 3, 1, B("cnet.layer1.1.norm2")),
            L2b0c1 => s(d1, d2, 3, 2, B("cnet.layer2.0.norm1")),
            L2b0c2 => s(d2, d2, 3, 1, B("cnet.layer2.0.norm2")),
            L2b0ds => s(d1, d2, 1, 2, B("cnet.layer2.0.norm3")),
            L2b1c1 => s(d2, d2, 3, 1, B("cnet.layer2.1.norm1")),
            L2b1c2 => s(d2, d2, 3, 1, B("cnet.layer2.1.norm2")),
            L3b0c1 => s(d2, d3, 3, 2, B("cnet.layer3.0.norm1")),
            L3b0c2 => s(d3, d3, 3, 1, B("cnet.layer3.0.norm2")),
            L3b0ds => s(d2, d3, 1, 2, B("cnet.layer3.0.norm3")),
            L3b1c1 => s(d3, d3, 3, 1, B("cnet.layer3.1.norm1")),
            L3b1c2 => s(d3, d3, 3, 1, B("cnet.layer3.1.norm2")),
            L4b0c1 => s(d3, d3, 3, 2, B("cnet.layer4.0.norm1")),
            L4b0c2 => s(d3, d3, 3, 1, B("cnet.layer4.0.norm2")),
            L4b0ds => s(d3, d3, 1, 2, B("cnet.layer4.0.norm3")),
            L4b1c1 => s(d3, d3, 3, 1, B("cnet.layer4.1.norm1")),
            L4b1c2 => s(d3, d3, 3, 1, B("cnet.layer4.1.norm2")),
            H08nC1 => s(d3, d3, 3, 1, B("cnet.outputs08.0.0.norm1")),
            H08nC2 => s(d3, d3, 3, 1, B("cnet.outputs08.0.0.norm2")),
            H08nOut => s(d3, h, 3, 1, N),
            H08cC1 => s(d3, d3, 3, 1, B("cnet.outputs08.1.0.norm1")),
            H08cC2 => s(d3, d3, 3, 1, B("cnet.outputs08.1.0.norm2")),
            H08cOut => s(d3, ctx, 3, 1, N),
            H16nC1 => s(d3, d3, 3, 1, B("cnet.outputs16.0.0.norm1")),
            H16nC2 => s(d3, d3, 3, 1, B("cnet.outputs16.0.0.norm2")),
            H16nOut => s(d3, h, 3, 1, N),
            H16cC1 => s(d3, d3, 3, 1, B("cnet.outputs16.1.0.norm1")),
            H16cC2 => s(d3, d3, 3, 1, B("cnet.outputs16.1.0.norm2")),
            H16cOut => s(d3, ctx, 3, 1, N),
            FmapC1 => s(d3, d3, 3, 1, I),
            FmapC2 => s(d3, d3, 3, 1, I),
            FmapOut => s(d3, cfg.fmap_dim, 3, 1, N),
            Czqr08 | Czqr16 => s(ctx, 3 * h, 3, 1, N),
            MotC1 => s(cfg.motion_corr_in(), cfg.motion_corr_dims[0], 1, 1, N),
            MotC2 => s(cfg.motion_corr_dims[0], cfg.motion_corr_dims[1], 3, 1, N),
            MotF1 => s(fc, cfg.motion_flow_dims[0], 7, 1, N),
            MotF2 => s(cfg.motion_flow_dims[0], cfg.motion_flow_dims[1], 3, 1, N),
            MotOut => s(cfg.motion_corr_dims[1] + cfg.motion_flow_dims[1], cfg.motion_dim - fc, 3, 1, N),
            Gru08Z | Gru08R | Gru08Q => s(h + cfg.gru08_input_dim(), h, 3, 1, N),
            Gru16Z | Gru16R | Gru16Q => s(2 * h, h, 3, 1, N),
            Flow1 => s(h, cfg.flow_head_dim, 3, 1, N),
            Flow2 => s(cfg.flow_head_dim, fc, 3, 1, N),
            Mask1 => s(h, cfg.mask_head_dim, 3, 1, N),
            Mask2 => s(cfg.mask_head_dim, MASK_CHANNELS, 1, 1, N),
            Mud1 | Mud2 | Mud3 if !cfg.mud => return None,
            Mud1 => s(cfg.mud_in(), cfg.mud_dim, 3, 1, N),
            Mud2 => s(cfg.mud_dim, cfg.mud_dim, 3, 1, N),
            Mud3 => s(cfg.mud_dim, 2, 3, 1, N),
            UfiC | UfiF | UfiConv | UfiQ | UfiZ | UfiHead1 | UfiHead2 if !cfg.ufi => return None,
            UfiC => s(cfg.corr_channels(), cfg.ufi_corr_dim, 1, 1, N),
            UfiF => s(fc, cfg.ufi_flow_dim, 3, 1, N),
            UfiConv => s(cfg.ufi_corr_dim + cfg.ufi_flow_dim, cfg.ufi_dim - fc, 3, 1, N),
            UfiQ => s(cfg.ufi_dim + ctx, h, 3, 1, N),
            UfiZ => s(2 * h, h, 3, 1, N),
            UfiHead1 => s(h + cfg.ufi_dim, cfg.ufi_head_dim, 3, 1, N),
            UfiHead2 => s(cfg.ufi_head_dim, 2, 3, 1, N),
            MgaQuery | MgaKey | MgaMask | MgaValue if !cfg.mga => return None,
            MgaQuery | MgaKey => s(ctx, cfg.mga_qk_dim, 1, 1, N),
            MgaMask => s(cfg.mga_mask_in(), 1, 3, 1, N),
            MgaValue => s(h, h, 1, 1, N),
            _ if !cfg.checkpoint_extras => return None,
            X5b0c1 => s(d3, d3, 3, 2, B("cnet.layer5.0.norm1")),
            X5b0c2 => s(d3, d3, 3, 1, B("cnet.layer5.0.norm2")),
            X5b0ds => s(d3, d3, 1, 2, B("cnet.layer5.0.norm3")),
            X5b1c1 => s(d3, d3, 3, 1, B("cnet.layer5.1.norm1")),
            X5b1c2 => s(d3, d3, 3, 1, B("cnet.layer5.1.norm2")),
            X32n => s(d3, h, 3, 1, N),
            X32c => s(d3, ctx, 3, 1, N),
            XGru32Z | XGru32R | XGru32Q => s(2 * h, h, 3, 1, N),
        };
        Some(shape)
    }

    /// True when this layer is computed by the network under `cfg`.
    pub const fn is_computed(self, cfg: &Config) -> bool {
        !self.checkpoint_only() && self.shape(cfg).is_some()
    }

    /// A downsample conv's BatchNorm is also stored as `<block>.downsample.1`.
    pub const fn bn_alias(self) -> Option<&'static str> {
        use ConvId::*;
        match self {
            L2b0ds => Some("cnet.layer2.0.downsample.1"),
            L3b0ds => Some("cnet.layer3.0.downsample.1"),
            L4b0ds => Some("cnet.layer4.0.downsample.1"),
            X5b0ds => Some("cnet.layer5.0.downsample.1"),
            _ => None,
        }
    }
}

/// Number of weights of the layers computed under `cfg`.
pub fn parameter_count(cfg: &Config) -> usize {
    ConvId::ALL
        .iter()
        .filter(|id| id.is_computed(cfg))
        .filter_map(|id| id.shape(cfg))
        .map(|s| s.weight_len() + s.cout)
        .sum()
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn ids_are_dense() {
        for (i, id) in ConvId::ALL.iter().enumerate() {
            assert_eq!(id.index(), i);
        }
    }

    #[test]
    fn realtime_has_all_checkpoint_layers() {
        let c = Config::RAFT_STEREO_REALTIME;
        assert!(ConvId::ALL.iter().filter(|id| id.checkpoint_only()).all(|id| id.shape(&c).is_some()));
        assert!(ConvId::Mud1.shape(&c).is_none());
        assert!(ConvId::X32n.shape(&Config::MUIR_FAST).is_none());
    }
}
