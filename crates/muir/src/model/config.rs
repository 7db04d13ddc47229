//! Model configuration: widths, iteration count and which MUIR modules are on.
//!
//! The same fields, presets and validation rules live in the PyTorch twin (`python/muir/config.py`);
//! a model file carries its config as JSON (safetensors metadata key `muir_config`) or, in the
//! quantised blob, as a fixed binary record (`crate::format`).
#![deny(clippy::indexing_slicing)]

use core::fmt;

/// Version of the config record understood by this crate (`config_version` in JSON).
pub const CONFIG_VERSION: u32 = 1;

/// A short model name stored inline (no heap): at most [`Name::CAPACITY`] bytes of UTF-8.
#[derive(Clone, Copy, PartialEq, Eq)]
pub struct Name {
    bytes: [u8; Name::CAPACITY],
    len: u8,
}

impl Name {
    /// Longest name a config can carry.
    pub const CAPACITY: usize = 32;

    /// Builds a name; `None` if `s` is longer than [`Name::CAPACITY`] bytes.
    pub const fn new(s: &str) -> Option<Self> {
        let src = s.as_bytes();
        if src.len() > Self::CAPACITY {
            return None;
        }
        let mut bytes = [0u8; Self::CAPACITY];
        // A `const fn`: byte by byte, with slice patterns (no iterators, no indexing).
        let (mut dst, mut rest): (&mut [u8], &[u8]) = (&mut bytes, src);
        while let ([d, dt @ ..], [s, st @ ..]) = (dst, rest) {
            *d = *s;
            (dst, rest) = (dt, st);
        }
        Some(Self { bytes, len: src.len() as u8 })
    }

    /// The name as a string slice.
    pub fn as_str(&self) -> &str {
        // Built from a &str (or checked UTF-8 in the blob reader), so this cannot fail; fall back to
        // an empty name rather than panic.
        core::str::from_utf8(self.bytes.get(..self.len as usize).unwrap_or(&[])).unwrap_or("")
    }

    /// Raw bytes (fixed capacity, zero padded) for binary records.
    pub const fn raw(&self) -> (&[u8; Self::CAPACITY], u8) {
        (&self.bytes, self.len)
    }
}

impl fmt::Debug for Name {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{:?}", self.as_str())
    }
}

impl fmt::Display for Name {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

// Evaluated only in the presets' constants: a too-long name is a compile error, not a run-time one.
#[allow(clippy::panic)]
const fn name(s: &str) -> Name {
    match Name::new(s) {
        Some(n) => n,
        None => panic!("preset name too long"),
    }
}

/// Network description. Channel counts are per tensor; resolutions are fixed by the architecture
/// (features and the fine GRU at 1/8, the coarse GRU at 1/16).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Config {
    /// Preset or user name.
    pub name: Name,
    /// Backbone widths: layer1 (1/2), layer2 (1/4), layer3 and layer4 (1/8, 1/16).
    pub backbone_dims: [usize; 3],
    /// ConvGRU hidden state channels (both levels).
    pub hidden_dim: usize,
    /// Context channels (GRU context input, MGA query/key source).
    pub context_dim: usize,
    /// Matching feature channels.
    pub fmap_dim: usize,
    /// Correlation lookup levels.
    pub corr_levels: usize,
    /// Correlation lookup radius (2r+1 samples per level).
    pub corr_radius: usize,
    /// Motion encoder corr convs: convc1 (1x1), convc2 (3x3).
    pub motion_corr_dims: [usize; 2],
    /// Motion encoder disparity convs: convf1 (7x7), convf2 (3x3).
    pub motion_flow_dims: [usize; 2],
    /// Motion feature channels (including the disparity channels appended at the end).
    pub motion_dim: usize,
    /// Disparity head hidden width.
    pub flow_head_dim: usize,
    /// Upsampling-mask head hidden width.
    pub mask_head_dim: usize,
    /// Disparity state channels: 2 = RAFT "flow" (x, y with y forced to 0), 1 = x only.
    pub flow_channels: usize,
    /// Refinement iterations.
    pub iters: usize,
    /// Post-pooling correlation lookup (paper 3.1.1) instead of RAFT's pooled pyramid.
    pub post_pool: bool,
    /// MUD (matchability mask and uncertainty decoder) on.
    pub mud: bool,
    /// MUD hidden width.
    pub mud_dim: usize,
    /// UFI (multi-proposal initialisation) on.
    pub ufi: bool,
    /// UFI corr encoder width.
    pub ufi_corr_dim: usize,
    /// UFI disparity encoder width.
    pub ufi_flow_dim: usize,
    /// UFI proposal feature width (including the disparity channels).
    pub ufi_dim: usize,
    /// UFI decoder hidden width.
    pub ufi_head_dim: usize,
    /// Minimum distance (1/8-grid pixels) between the two correlation-peak proposals.
    pub ufi_peak_separation: usize,
    /// MGA (masked global aggregation) on.
    pub mga: bool,
    /// MGA query/key channels (multiple of 4: 2D RoPE pairs split between x and y).
    pub mga_qk_dim: usize,
    /// RoPE frequency base: pair i of a half turns by `pos * base^(-i/n)`.
    pub mga_rope_base: f32,
    /// Smallest predicted error (full-resolution pixels).
    pub eps_min: f32,
    /// Largest predicted error (full-resolution pixels).
    pub eps_max: f32,
    /// The public realtime checkpoint's unused modules (layer5, outputs32, gru32) are expected in
    /// float model files (checked, then ignored).
    pub checkpoint_extras: bool,
    /// Fixed-point engine only: conv1, layer1 and layer2 activations stored in `i16` instead of
    /// `u8` (the float network is the same). Lowers the engine's difference from the float
    /// reference at the cost of wider line buffers (`muir plan` lists both); set by
    /// `muir quantize --wide-trunk`, never by a float model file.
    pub wide_trunk: bool,
}

/// Why a config is rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum ConfigError {
    /// `flow_channels` is not 1 or 2.
    FlowChannels,
    /// MGA needs MUD (its mask input is the matchability mask).
    MgaWithoutMud,
    /// MUIR modules track disparity with one channel (`flow_channels = 1`).
    MuirFlowChannels,
    /// `mga_qk_dim` is not a multiple of 4.
    QkDim,
    /// `eps_min`/`eps_max` are not `0 < eps_min < eps_max`.
    EpsRange,
    /// A width, level count, radius or iteration count is zero.
    Zero,
    /// More refinement iterations than [`MAX_ITERS`].
    Iterations,
    /// `mga_rope_base` is not a finite number above 1.
    RopeBase,
    /// `ufi_peak_separation` is 0 (the two proposals could coincide) or larger than
    /// [`crate::arith::MAX_PROPOSAL_D8`].
    PeakSeparation,
    /// A width is larger than the engine supports ([`MAX_WIDTH`]).
    TooWide,
    /// Unknown preset name.
    UnknownPreset,
    /// `config_version` is not [`CONFIG_VERSION`].
    Version,
    /// A largest disparity outside [`MaxDisparity::MIN`]`..=`[`MaxDisparity::MAX`].
    MaxDisparity,
}

impl fmt::Display for ConfigError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::FlowChannels => "flow_channels must be 1 or 2",
            Self::MgaWithoutMud => "mga needs mud (its mask input is the MUD matchability mask)",
            Self::MuirFlowChannels => "mud, ufi and mga need flow_channels = 1",
            Self::QkDim => "mga_qk_dim must be a multiple of 4",
            Self::EpsRange => "need 0 < eps_min < eps_max",
            Self::Zero => "widths, corr_levels, corr_radius and iters must be >= 1",
            Self::Iterations => "iters exceeds the supported maximum (64)",
            Self::RopeBase => "mga_rope_base must be a finite number > 1",
            Self::PeakSeparation => "ufi_peak_separation must be in 1..=127",
            Self::TooWide => "a channel width exceeds the supported maximum",
            Self::UnknownPreset => "unknown config name (raft-stereo-realtime, muir-fast, muir-slim)",
            Self::Version => "unsupported config_version",
            Self::MaxDisparity => "the largest disparity must be 8 ..= 1016 px",
        })
    }
}

/// Largest disparity (pixels, full resolution) that UFI's proposal search considers: each left
/// pixel's proposals are the best correlations over disparities `0 ..= min(x, max)` on the 1/8 grid,
/// `max` = this value / 8 rounded down. It is a run-time setting of every engine (and of the PyTorch
/// twin), like the disparity range of classical matchers; the refinement iterations may still move
/// a pixel beyond it. Why it exists: searching the whole row (up to 1016 px) lets a far, spurious
/// correlation peak win where the scene has near-ties, and on such pixels the fixed-point engine's
/// 8-bit features pick another peak than the float model (KITTI 000005, 1242x375: 93.0 % of pixels
/// within 1 px between the engines with the whole row, 98.5 % with 256 px; float EPE 2.12 -> 1.93 px).
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct MaxDisparity(u16);

impl MaxDisparity {
    /// The default, 256 px: every scene of `../shared/data` at its stored size (KITTI reaches
    /// ~230 px) and 1080p frames of a short-baseline module.
    pub const DEFAULT: Self = Self(256);
    /// Smallest accepted value (one 1/8-grid step).
    pub const MIN: usize = Config::FACTOR;
    /// Largest accepted value: the largest proposal the Q7.8 flow state holds
    /// ([`crate::arith::MAX_PROPOSAL_D8`] x 8 = 1016 px).
    pub const MAX: usize = crate::arith::MAX_PROPOSAL_D8 * Config::FACTOR;

    /// `px` pixels at full resolution.
    ///
    /// # Errors
    /// [`ConfigError::MaxDisparity`] outside `MIN..=MAX`.
    pub const fn new(px: usize) -> Result<Self, ConfigError> {
        if px < Self::MIN || px > Self::MAX { Err(ConfigError::MaxDisparity) } else { Ok(Self(px as u16)) }
    }

    /// The value in pixels.
    pub const fn px(self) -> usize {
        self.0 as usize
    }

    /// The largest proposal on the 1/8 grid (`px / 8`, at most [`crate::arith::MAX_PROPOSAL_D8`]).
    pub const fn grid8(self) -> usize {
        self.0 as usize / Config::FACTOR
    }
}

impl fmt::Display for MaxDisparity {
    /// The value in pixels.
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{}", self.0)
    }
}

impl Default for MaxDisparity {
    fn default() -> Self {
        Self::DEFAULT
    }
}

/// Most refinement iterations a config may ask for.
pub const MAX_ITERS: usize = 64;

/// Largest channel count of any tensor the crate accepts (bounds the engine's per-pixel scratch).
pub const MAX_WIDTH: usize = 1024;

impl Config {
    /// The public RAFT-Stereo realtime network, MUIR modules off.
    pub const RAFT_STEREO_REALTIME: Config = Config {
        name: name("raft-stereo-realtime"),
        backbone_dims: [64, 96, 128],
        hidden_dim: 128,
        context_dim: 128,
        fmap_dim: 256,
        corr_levels: 4,
        corr_radius: 4,
        motion_corr_dims: [64, 64],
        motion_flow_dims: [64, 64],
        motion_dim: 128,
        flow_head_dim: 256,
        mask_head_dim: 256,
        flow_channels: 2,
        iters: 7,
        post_pool: false,
        mud: false,
        mud_dim: 64,
        ufi: false,
        ufi_corr_dim: 64,
        ufi_flow_dim: 32,
        ufi_dim: 64,
        ufi_head_dim: 64,
        ufi_peak_separation: 2,
        mga: false,
        mga_qk_dim: 64,
        mga_rope_base: 100.0,
        eps_min: 0.25,
        eps_max: 32.0,
        checkpoint_extras: true,
        wide_trunk: false,
    };

    /// MUIR fast: realtime widths plus MUD, UFI, MGA and post-pooling lookup.
    pub const MUIR_FAST: Config = Config {
        name: name("muir-fast"),
        flow_channels: 1,
        post_pool: true,
        mud: true,
        ufi: true,
        mga: true,
        checkpoint_extras: false,
        ..Self::RAFT_STEREO_REALTIME
    };

    /// MUIR slim: half the channel widths of MUIR fast (about 1/4 of the MACs), for microcontrollers.
    pub const MUIR_SLIM: Config = Config {
        name: name("muir-slim"),
        backbone_dims: [32, 48, 64],
        hidden_dim: 64,
        context_dim: 64,
        fmap_dim: 128,
        motion_corr_dims: [32, 32],
        motion_flow_dims: [32, 32],
        motion_dim: 64,
        flow_head_dim: 128,
        mask_head_dim: 128,
        mud_dim: 32,
        ufi_corr_dim: 32,
        ufi_flow_dim: 16,
        ufi_dim: 32,
        ufi_head_dim: 32,
        mga_qk_dim: 32,
        ..Self::MUIR_FAST
    };

    /// All named presets.
    pub const PRESETS: [Config; 3] = [Self::RAFT_STEREO_REALTIME, Self::MUIR_FAST, Self::MUIR_SLIM];

    /// Looks a preset up by name.
    pub fn preset(name: &str) -> Result<Config, ConfigError> {
        Self::PRESETS.iter().find(|c| c.name.as_str() == name).copied().ok_or(ConfigError::UnknownPreset)
    }

    /// Checks the rules every part of the crate relies on.
    pub const fn validate(&self) -> Result<(), ConfigError> {
        if self.flow_channels != 1 && self.flow_channels != 2 {
            return Err(ConfigError::FlowChannels);
        }
        if self.mga && !self.mud {
            return Err(ConfigError::MgaWithoutMud);
        }
        if (self.mud || self.ufi || self.mga) && self.flow_channels != 1 {
            return Err(ConfigError::MuirFlowChannels);
        }
        if self.mga && !self.mga_qk_dim.is_multiple_of(4) {
            return Err(ConfigError::QkDim);
        }
        if !(self.eps_min > 0.0 && self.eps_min < self.eps_max && self.eps_max.is_finite()) {
            return Err(ConfigError::EpsRange);
        }
        let widths = [
            self.backbone_dims[0],
            self.backbone_dims[1],
            self.backbone_dims[2],
            self.hidden_dim,
            self.context_dim,
            self.fmap_dim,
            self.corr_levels,
            self.corr_radius,
            self.motion_corr_dims[0],
            self.motion_corr_dims[1],
            self.motion_flow_dims[0],
            self.motion_flow_dims[1],
            self.motion_dim,
            self.flow_head_dim,
            self.mask_head_dim,
            self.iters,
            self.mud_dim,
            self.ufi_corr_dim,
            self.ufi_flow_dim,
            self.ufi_dim,
            self.ufi_head_dim,
            self.mga_qk_dim,
        ];
        let mut rest: &[usize] = &widths;
        while let [w, tail @ ..] = rest {
            if *w == 0 {
                return Err(ConfigError::Zero);
            }
            if *w > MAX_WIDTH {
                return Err(ConfigError::TooWide);
            }
            rest = tail;
        }
        if self.motion_dim <= self.flow_channels || self.ufi_dim <= self.flow_channels {
            return Err(ConfigError::Zero);
        }
        if self.corr_levels > 6 || self.corr_radius > 16 {
            return Err(ConfigError::TooWide);
        }
        if self.iters > MAX_ITERS {
            return Err(ConfigError::Iterations);
        }
        if self.mga && !(self.mga_rope_base.is_finite() && self.mga_rope_base > 1.0) {
            return Err(ConfigError::RopeBase);
        }
        if self.ufi && (self.ufi_peak_separation == 0 || self.ufi_peak_separation > crate::arith::MAX_PROPOSAL_D8) {
            return Err(ConfigError::PeakSeparation);
        }
        Ok(())
    }

    /// Channels of one correlation lookup: levels x (2r+1), level-major.
    pub const fn corr_channels(&self) -> usize {
        self.corr_levels * (2 * self.corr_radius + 1)
    }

    /// Input channels of the motion encoder's first corr conv: `cat[C, C*m, m]` with MUD.
    pub const fn motion_corr_in(&self) -> usize {
        if self.mud { 2 * self.corr_channels() + 1 } else { self.corr_channels() }
    }

    /// Input channels `x` of the 1/8 ConvGRU (motion, upsampled 1/16 state, MGA output).
    pub const fn gru08_input_dim(&self) -> usize {
        self.motion_dim + self.hidden_dim + if self.mga { self.hidden_dim } else { 0 }
    }

    /// MUD input channels: `cat[H, C(D), d]`.
    pub const fn mud_in(&self) -> usize {
        self.hidden_dim + self.corr_channels() + 1
    }

    /// MGA adaptive-mask conv input channels: `cat[H, C(D), d, m]`.
    pub const fn mga_mask_in(&self) -> usize {
        self.hidden_dim + self.corr_channels() + 2
    }

    /// Image sides are padded (edge replication, right/bottom) to a multiple of this.
    pub const PAD_MULTIPLE: usize = 16;

    /// Smallest image side the network accepts after padding (two 1/16 cells).
    pub const MIN_SIDE: usize = 32;

    /// Largest image width any engine accepts (1080p; KITTI's 1242 px and 720p fit). The integer
    /// formats allow more (disparities up to 1016 px, see `arith::MAX_PROPOSAL_D8`); the limit
    /// is what the tests cover (`host-tests/fixed_vs_float.rs` runs strips up to this width) and
    /// keeps every size product of the plan far from overflow.
    pub const MAX_IMAGE_WIDTH: usize = 1920;

    /// Largest image height any engine accepts.
    pub const MAX_IMAGE_HEIGHT: usize = 1088;

    /// Upsampling factor between the 1/8 grid and the image.
    pub const FACTOR: usize = 8;
}

/// Rounds `n` up to a multiple of [`Config::PAD_MULTIPLE`].
pub const fn padded(n: usize) -> usize {
    n.div_ceil(Config::PAD_MULTIPLE) * Config::PAD_MULTIPLE
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn max_disparity_bounds() {
        assert_eq!(MaxDisparity::new(7), Err(ConfigError::MaxDisparity));
        assert_eq!(MaxDisparity::new(1017), Err(ConfigError::MaxDisparity));
        assert_eq!(MaxDisparity::new(8).map(MaxDisparity::grid8), Ok(1));
        assert_eq!(MaxDisparity::new(100).map(MaxDisparity::grid8), Ok(12));
        assert_eq!(MaxDisparity::new(1016).map(MaxDisparity::grid8), Ok(crate::arith::MAX_PROPOSAL_D8));
        assert_eq!(MaxDisparity::default().px(), 256);
    }

    #[test]
    fn presets_are_valid_and_named() {
        for c in Config::PRESETS {
            assert_eq!(c.validate(), Ok(()));
            assert_eq!(Config::preset(c.name.as_str()), Ok(c));
        }
        assert_eq!(Config::preset("nope"), Err(ConfigError::UnknownPreset));
    }

    #[test]
    fn derived_widths_match_the_realtime_checkpoint() {
        let c = Config::RAFT_STEREO_REALTIME;
        assert_eq!(c.corr_channels(), 36);
        assert_eq!(c.gru08_input_dim() + c.hidden_dim, 384);
        let f = Config::MUIR_FAST;
        assert_eq!(f.motion_corr_in(), 73);
        assert_eq!(f.gru08_input_dim() + f.hidden_dim, 512);
    }

    #[test]
    fn invalid_configs_are_rejected() {
        let mut c = Config::MUIR_FAST;
        c.mud = false;
        assert_eq!(c.validate(), Err(ConfigError::MgaWithoutMud));
        let mut c = Config::MUIR_SLIM;
        c.mga_qk_dim = 30;
        assert_eq!(c.validate(), Err(ConfigError::QkDim));
        let mut c = Config::MUIR_SLIM;
        c.eps_min = 40.0;
        assert_eq!(c.validate(), Err(ConfigError::EpsRange));
        let mut c = Config::MUIR_SLIM;
        c.hidden_dim = 0;
        assert_eq!(c.validate(), Err(ConfigError::Zero));
        // Hostile numbers that used to parse and run into garbage, or got the wrong message.
        for (f, want) in [
            ((|c: &mut Config| c.iters = 1000) as fn(&mut Config), ConfigError::Iterations),
            (|c| c.iters = MAX_ITERS + 1, ConfigError::Iterations),
            (|c| c.mga_rope_base = f32::NAN, ConfigError::RopeBase),
            (|c| c.mga_rope_base = 1.0, ConfigError::RopeBase),
            (|c| c.mga_rope_base = f32::INFINITY, ConfigError::RopeBase),
            (|c| c.ufi_peak_separation = 0, ConfigError::PeakSeparation),
            (|c| c.ufi_peak_separation = 500, ConfigError::PeakSeparation),
            (|c| c.eps_max = f32::INFINITY, ConfigError::EpsRange),
            (|c| c.eps_min = f32::NAN, ConfigError::EpsRange),
        ] {
            let mut c = Config::MUIR_SLIM;
            f(&mut c);
            assert_eq!(c.validate(), Err(want), "{c:?}");
        }
        let mut c = Config::MUIR_SLIM;
        c.iters = MAX_ITERS;
        assert_eq!(c.validate(), Ok(()));
    }

    #[test]
    fn padding() {
        assert_eq!(padded(120), 128);
        assert_eq!(padded(160), 160);
        assert_eq!(padded(1), 16);
    }
}
