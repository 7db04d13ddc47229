//! The quantised model file (`.muirq`): a versioned, checksummed binary blob that the engine reads
//! in place from `&'static [u8]` (flash), without copying.
//!
//! Layout (little endian, every section 8-byte aligned):
//!
//! | offset | size | content |
//! |---|---|---|
//! | 0 | 4 | magic `MUIQ` |
//! | 4 | 2 | format version ([`VERSION`]; 2: backbone and context activations are u8; 3: config flag 5, a wide trunk ([`Config::wide_trunk`]); version 2 is still read) |
//! | 6 | 2 | 0 |
//! | 8 | 4 | total length in bytes |
//! | 12 | 4 | CRC-32 (IEEE) of bytes `16..total` |
//! | 16 | 128 | config record ([`config_record`]) |
//! | 144 | 2 x `Act::COUNT` | activation formats: bits (u8), fraction bits (i8); signedness is the slot's ([`Act::unsigned`]) |
//! | .. | 64 + 8 + 4 + 4 x pairs | extras: lookup multipliers per level (8 slots), attention logit multiplier, RoPE pair count and phase steps |
//! | .. | 2050 | uncertainty table (1025 x i16, Q4.11 logit to Q4.11 `u`) |
//! | .. | 8 x `ConvId::COUNT` | layer directory: offset (u32), length (u32); 0 = absent |
//! | .. | .. | layer records |
//!
//! Layer record: `id k stride post nparts 0 0 0` (8 x u8), `cout` (u32), `patch_len` (u32),
//! part channels (6 x u16), 4 zero bytes, then `cout x patch_len` i8 weights (`[part][ky][kx][c]`,
//! padded to 8), `cout` i64 biases (output units with `EXTRA_BITS` more fraction bits),
//! `cout x parts` multipliers (i32 m, u8 shift, 3 zero bytes; see `kernels::conv`).
//!
//! [`QuantModel::parse`] checks everything once (magic, version, length, checksum, config,
//! formats, every layer's shape against the config); afterwards all accessors are infallible.
//!
//! No blob reaches a panic: every read goes through `get` (a typed [`BlobError`] where `parse`
//! reads, a zero where an accessor reads a section `parse` already bounds-checked).
#![deny(clippy::indexing_slicing)]

mod crc;

use core::fmt;

pub use crc::crc32;

use crate::arith::{Multiplier, QFormat};
use crate::kernels::conv::{BiasRef, ConvParams, MultRef};
use crate::model::config::{Config, ConfigError, Name};
use crate::model::graph::{Act, MAX_PARTS, PostOp, QLayer};
use crate::model::layers::ConvId;

/// Magic bytes.
pub const MAGIC: [u8; 4] = *b"MUIQ";
/// Format version written and read by this crate.
pub const VERSION: u16 = 3;
/// Size of the fixed header.
pub const HEADER_LEN: usize = 16;
/// Size of the config record.
pub const CONFIG_LEN: usize = 128;
/// Lookup-multiplier slots (levels).
pub const MAX_LEVELS: usize = 8;
/// Entries of the uncertainty table.
pub const U_TABLE_LEN: usize = 1025;
/// Size of a layer record header.
pub const LAYER_HEADER_LEN: usize = 32;

/// Why a blob is rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum BlobError {
    /// Not a `.muirq` file.
    BadMagic,
    /// Written by an incompatible version.
    UnsupportedVersion {
        /// Version in the file.
        found: u16,
    },
    /// Shorter than its header says (or than a header).
    Truncated {
        /// Length the header declares (or the minimum).
        expected: usize,
        /// Bytes given.
        found: usize,
    },
    /// Longer than its header says.
    TrailingBytes {
        /// Length the header declares.
        expected: usize,
        /// Bytes given.
        found: usize,
    },
    /// Content does not match the checksum.
    Checksum {
        /// CRC in the header.
        expected: u32,
        /// CRC of the content.
        found: u32,
    },
    /// The config record is invalid.
    Config(ConfigError),
    /// The config name is not UTF-8 or too long.
    ConfigName,
    /// An activation format is impossible for its slot.
    Format {
        /// The slot.
        act: Act,
    },
    /// A section or record lies outside the blob.
    OutOfBounds {
        /// Which section.
        what: &'static str,
    },
    /// A layer the config computes is absent.
    MissingLayer {
        /// The layer.
        layer: ConvId,
    },
    /// A layer the config does not compute is present.
    UnexpectedLayer {
        /// The layer.
        layer: ConvId,
    },
    /// A layer's record disagrees with the config.
    LayerShape {
        /// The layer.
        layer: ConvId,
        /// Which field.
        field: &'static str,
    },
    /// Extras inconsistent with the config (RoPE pairs, multipliers).
    Extras {
        /// Which field.
        field: &'static str,
    },
}

impl fmt::Display for BlobError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::BadMagic => write!(f, "not a quantised muir model (bad magic; expected 'MUIQ')"),
            Self::UnsupportedVersion { found } => {
                write!(f, "model format version {found} is not supported (this build reads version {VERSION})")
            }
            Self::Truncated { expected, found } => {
                write!(f, "model file is truncated: {found} bytes, {expected} expected")
            }
            Self::TrailingBytes { expected, found } => {
                write!(f, "model file has {found} bytes but its header says {expected}")
            }
            Self::Checksum { expected, found } => {
                write!(f, "model file is corrupted: CRC-32 {found:#010x}, header says {expected:#010x}")
            }
            Self::Config(e) => write!(f, "model config is invalid: {e}"),
            Self::ConfigName => write!(f, "model config name is not valid UTF-8"),
            Self::Format { act } => write!(f, "activation format of '{}' is invalid", act.name()),
            Self::OutOfBounds { what } => write!(f, "model file section '{what}' lies outside the file"),
            Self::MissingLayer { layer } => write!(f, "layer '{}' is missing", layer.name()),
            Self::UnexpectedLayer { layer } => write!(f, "layer '{}' is not part of this config", layer.name()),
            Self::LayerShape { layer, field } => {
                write!(f, "layer '{}': {field} does not match the config", layer.name())
            }
            Self::Extras { field } => write!(f, "model extras: {field} does not match the config"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for BlobError {}

/// The `N` bytes at offset `o` of `b`; `None` past the end.
#[inline]
fn bytes_at<const N: usize>(b: &[u8], o: usize) -> Option<[u8; N]> {
    b.get(o..)?.first_chunk().copied()
}
// The readers below give 0 past the end: `parse` checks a section's bounds before it reads the
// section (and the accessors read only sections `parse` checked), so that never happens.
#[inline]
fn u8_at(b: &[u8], o: usize) -> u8 {
    b.get(o).copied().unwrap_or(0)
}
#[inline]
fn u16_at(b: &[u8], o: usize) -> u16 {
    bytes_at(b, o).map_or(0, u16::from_le_bytes)
}
#[inline]
fn u32_at(b: &[u8], o: usize) -> u32 {
    bytes_at(b, o).map_or(0, u32::from_le_bytes)
}
#[inline]
fn f32_at(b: &[u8], o: usize) -> f32 {
    f32::from_bits(u32_at(b, o))
}

/// Byte offset of the formats table.
pub const FORMATS_AT: usize = HEADER_LEN + CONFIG_LEN;

const fn align8(n: usize) -> usize {
    (n + 7) & !7
}

/// Offsets of the sections after the formats table (depend only on the RoPE pair count).
#[derive(Clone, Copy, Debug)]
pub struct Sections {
    /// Lookup multipliers.
    pub corr_mults: usize,
    /// Attention multiplier.
    pub att_mult: usize,
    /// RoPE pair count (u32) followed by the phase steps.
    pub rope: usize,
    /// Uncertainty table.
    pub u_table: usize,
    /// Layer directory.
    pub directory: usize,
    /// First layer record.
    pub records: usize,
}

impl Sections {
    /// Section offsets for `pairs` RoPE pairs.
    pub const fn new(pairs: usize) -> Self {
        let corr_mults = align8(FORMATS_AT + 2 * Act::COUNT);
        let att_mult = corr_mults + 8 * MAX_LEVELS;
        let rope = att_mult + 8;
        let u_table = align8(rope + 4 + 4 * pairs);
        let directory = align8(u_table + 2 * U_TABLE_LEN);
        let records = directory + 8 * ConvId::COUNT;
        Self { corr_mults, att_mult, rope, u_table, directory, records }
    }
}

/// Config record (128 bytes): name (32 bytes, zero padded), name length (u8), flags (u8: bit 0
/// post_pool, 1 mud, 2 ufi, 3 mga, 4 checkpoint_extras, 5 wide_trunk), 2 zero bytes, then u16 fields in this
/// order: backbone_dims x3, hidden, context, fmap, corr_levels, corr_radius, motion_corr_dims x2,
/// motion_flow_dims x2, motion_dim, flow_head_dim, mask_head_dim, flow_channels, iters, mud_dim,
/// ufi_corr_dim, ufi_flow_dim, ufi_dim, ufi_head_dim, ufi_peak_separation, mga_qk_dim (25 values,
/// offset 36), then f32 mga_rope_base, eps_min, eps_max (offset 88), zero padding.
pub fn config_record(c: &Config) -> [u8; CONFIG_LEN] {
    let mut r = [0u8; CONFIG_LEN];
    let (name, len) = c.name.raw();
    r[..32].copy_from_slice(name);
    r[32] = len;
    r[33] = c.post_pool as u8
        | (c.mud as u8) << 1
        | (c.ufi as u8) << 2
        | (c.mga as u8) << 3
        | (c.checkpoint_extras as u8) << 4
        | (c.wide_trunk as u8) << 5;
    let v = config_u16s(c);
    for (dst, x) in r[36..].chunks_exact_mut(2).zip(v) {
        dst.copy_from_slice(&(x as u16).to_le_bytes());
    }
    r[88..92].copy_from_slice(&c.mga_rope_base.to_bits().to_le_bytes());
    r[92..96].copy_from_slice(&c.eps_min.to_bits().to_le_bytes());
    r[96..100].copy_from_slice(&c.eps_max.to_bits().to_le_bytes());
    r
}

fn config_u16s(c: &Config) -> [usize; 25] {
    [
        c.backbone_dims[0],
        c.backbone_dims[1],
        c.backbone_dims[2],
        c.hidden_dim,
        c.context_dim,
        c.fmap_dim,
        c.corr_levels,
        c.corr_radius,
        c.motion_corr_dims[0],
        c.motion_corr_dims[1],
        c.motion_flow_dims[0],
        c.motion_flow_dims[1],
        c.motion_dim,
        c.flow_head_dim,
        c.mask_head_dim,
        c.flow_channels,
        c.iters,
        c.mud_dim,
        c.ufi_corr_dim,
        c.ufi_flow_dim,
        c.ufi_dim,
        c.ufi_head_dim,
        c.ufi_peak_separation,
        c.mga_qk_dim,
        0,
    ]
}

fn parse_config(r: &[u8; CONFIG_LEN]) -> Result<Config, BlobError> {
    let len = r[32] as usize;
    if len > Name::CAPACITY {
        return Err(BlobError::ConfigName);
    }
    let name = r.get(..len).ok_or(BlobError::ConfigName)?;
    let name = core::str::from_utf8(name).map_err(|_| BlobError::ConfigName)?;
    let name = Name::new(name).ok_or(BlobError::ConfigName)?;
    let flags = r[33];
    let v = |i: usize| u16_at(r, 36 + 2 * i) as usize;
    let c = Config {
        name,
        backbone_dims: [v(0), v(1), v(2)],
        hidden_dim: v(3),
        context_dim: v(4),
        fmap_dim: v(5),
        corr_levels: v(6),
        corr_radius: v(7),
        motion_corr_dims: [v(8), v(9)],
        motion_flow_dims: [v(10), v(11)],
        motion_dim: v(12),
        flow_head_dim: v(13),
        mask_head_dim: v(14),
        flow_channels: v(15),
        iters: v(16),
        mud_dim: v(17),
        ufi_corr_dim: v(18),
        ufi_flow_dim: v(19),
        ufi_dim: v(20),
        ufi_head_dim: v(21),
        ufi_peak_separation: v(22),
        mga_qk_dim: v(23),
        post_pool: flags & 1 != 0,
        mud: flags & 2 != 0,
        ufi: flags & 4 != 0,
        mga: flags & 8 != 0,
        checkpoint_extras: flags & 16 != 0,
        wide_trunk: flags & 32 != 0,
        mga_rope_base: f32_at(r, 88),
        eps_min: f32_at(r, 92),
        eps_max: f32_at(r, 96),
    };
    c.validate().map_err(BlobError::Config)?;
    if c.corr_levels > MAX_LEVELS {
        return Err(BlobError::Config(ConfigError::TooWide));
    }
    Ok(c)
}

/// Number of RoPE pairs of a config (0 without MGA).
pub const fn rope_pairs(c: &Config) -> usize {
    if c.mga { c.mga_qk_dim / 2 } else { 0 }
}

/// Where a layer's data lies in the blob.
#[derive(Clone, Copy, Debug, Default)]
struct LayerLoc {
    at: usize,
    cout: usize,
    patch: usize,
    parts: [usize; MAX_PARTS],
    nparts: usize,
    k: usize,
    stride: usize,
    post: u8,
}

/// Byte length of a layer record.
pub const fn layer_record_len(cout: usize, patch: usize, parts: usize) -> usize {
    LAYER_HEADER_LEN + align8(cout * patch) + 8 * cout + 8 * cout * parts
}

/// A parsed, validated quantised model borrowing the blob.
#[derive(Clone, Debug)]
pub struct QuantModel<'a> {
    blob: &'a [u8],
    config: Config,
    formats: [QFormat; Act::COUNT],
    layers: [LayerLoc; ConvId::COUNT],
    sections: Sections,
}

impl<'a> QuantModel<'a> {
    /// Validates `blob` and returns the model view.
    ///
    /// # Errors
    /// Every malformation is a [`BlobError`]; nothing panics on bad input.
    pub fn parse(blob: &'a [u8]) -> Result<Self, BlobError> {
        let magic = blob.first_chunk::<4>();
        if blob.len() < HEADER_LEN + CONFIG_LEN {
            if magic.is_some_and(|m| *m != MAGIC) {
                return Err(BlobError::BadMagic);
            }
            return Err(BlobError::Truncated { expected: HEADER_LEN + CONFIG_LEN, found: blob.len() });
        }
        if magic != Some(&MAGIC) {
            return Err(BlobError::BadMagic);
        }
        let version = u16_at(blob, 4);
        if version != VERSION && version != 2 {
            return Err(BlobError::UnsupportedVersion { found: version });
        }
        let total = u32_at(blob, 8) as usize;
        if blob.len() < total {
            return Err(BlobError::Truncated { expected: total, found: blob.len() });
        }
        if blob.len() > total {
            return Err(BlobError::TrailingBytes { expected: total, found: blob.len() });
        }
        let expected = u32_at(blob, 12);
        let found = crc32(blob.get(HEADER_LEN..).unwrap_or(&[]));
        if expected != found {
            return Err(BlobError::Checksum { expected, found });
        }
        let record = blob.get(HEADER_LEN..).and_then(|r| r.first_chunk());
        let config = parse_config(record.ok_or(BlobError::Truncated { expected: HEADER_LEN + CONFIG_LEN, found: blob.len() })?)?;
        let sections = Sections::new(rope_pairs(&config));
        if sections.records > total {
            return Err(BlobError::OutOfBounds { what: "tables" });
        }
        let mut formats = [QFormat::i8(0); Act::COUNT];
        for &act in Act::ALL {
            let o = FORMATS_AT + 2 * act.index();
            // Signedness is the slot's (the arithmetic spec's), not the blob's.
            let storage = act.storage_in(&config);
            let [bits, frac] = bytes_at(blob, o).ok_or(BlobError::OutOfBounds { what: "formats" })?;
            let f = QFormat { bits, frac: frac as i8, unsigned: storage.unsigned };
            let fixed_ok = act.fixed_format().is_none_or(|x| x == f);
            if f.bits != storage.bits || !fixed_ok || !(-24..=40).contains(&f.frac) {
                return Err(BlobError::Format { act });
            }
            // `index() < Act::COUNT`: always a slot.
            if let Some(slot) = formats.get_mut(act.index()) {
                *slot = f;
            }
        }
        for l in 0..MAX_LEVELS {
            let m = mult_at(blob, sections.corr_mults + 8 * l);
            if l < config.corr_levels && !valid_mult(m) {
                return Err(BlobError::Extras { field: "lookup multiplier" });
            }
        }
        if config.mga && !valid_mult(mult_at(blob, sections.att_mult)) {
            return Err(BlobError::Extras { field: "attention multiplier" });
        }
        if u32_at(blob, sections.rope) as usize != rope_pairs(&config) {
            return Err(BlobError::Extras { field: "RoPE pair count" });
        }
        let mut layers = [LayerLoc::default(); ConvId::COUNT];
        for &id in ConvId::ALL {
            let d = sections.directory + 8 * id.index();
            let (at, len) = (u32_at(blob, d) as usize, u32_at(blob, d + 4) as usize);
            let Some(want) = QLayer::of(id, &config) else {
                if at != 0 || len != 0 {
                    return Err(BlobError::UnexpectedLayer { layer: id });
                }
                continue;
            };
            if at == 0 {
                return Err(BlobError::MissingLayer { layer: id });
            }
            if at % 8 != 0 || at < sections.records || at.checked_add(len).is_none_or(|e| e > total) || len < LAYER_HEADER_LEN {
                return Err(BlobError::OutOfBounds { what: id.name() });
            }
            let h: &[u8; LAYER_HEADER_LEN] =
                blob.get(at..).and_then(|r| r.first_chunk()).ok_or(BlobError::OutOfBounds { what: id.name() })?;
            let shape = id.shape(&config).ok_or(BlobError::UnexpectedLayer { layer: id })?;
            let bad = |field| Err(BlobError::LayerShape { layer: id, field });
            if h[0] as usize != id.index() {
                return bad("id");
            }
            if h[1] as usize != shape.k || h[2] as usize != shape.stride {
                return bad("kernel");
            }
            if h[3] != want.post as u8 {
                return bad("activation");
            }
            let cout = u32_at(h, 8) as usize;
            let patch = u32_at(h, 12) as usize;
            if cout != shape.cout {
                return bad("output channels");
            }
            let mut loc = LayerLoc { at, cout, patch, k: shape.k, stride: shape.stride, post: h[3], ..Default::default() };
            let mut n = 0;
            for (i, part) in want.parts.iter().enumerate() {
                let ch = u16_at(h, 16 + 2 * i) as usize;
                match part {
                    Some(p) if p.channels == ch => {
                        // n < MAX_PARTS: one slot per part of `want`
                        if let Some(slot) = loc.parts.get_mut(n) {
                            *slot = ch;
                        }
                        n += 1;
                    }
                    None if ch == 0 => {}
                    _ => return bad("input parts"),
                }
            }
            loc.nparts = n;
            if h[4] as usize != n || patch != shape.k * shape.k * want.cin() {
                return bad("patch length");
            }
            if len != layer_record_len(cout, patch, n) {
                return bad("record length");
            }
            // `index() < ConvId::COUNT`: always a slot.
            if let Some(slot) = layers.get_mut(id.index()) {
                *slot = loc;
            }
        }
        Ok(Self { blob, config, formats, layers, sections })
    }

    /// The model config.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Format of an activation slot.
    pub fn format(&self, act: Act) -> QFormat {
        // `index() < Act::COUNT`: the fallback is never taken.
        self.formats.get(act.index()).copied().unwrap_or(QFormat::i8(0))
    }

    /// Conv parameters of layer `id`; `None` when the config does not compute it.
    pub fn conv(&self, id: ConvId) -> Option<ConvParams<'_>> {
        let l = self.layers.get(id.index())?;
        if l.at == 0 {
            return None;
        }
        let w0 = l.at + LAYER_HEADER_LEN;
        let b0 = w0 + align8(l.cout * l.patch);
        let m0 = b0 + 8 * l.cout;
        // `parse` checked that the record (header, weights, biases, multipliers) lies inside the blob.
        // SAFETY-free reinterpretation: i8 and u8 have the same size and alignment.
        let weights = bytes_as_i8(self.blob.get(w0..w0 + l.cout * l.patch)?);
        Some(ConvParams {
            k: l.k,
            stride: l.stride,
            parts: l.parts.get(..l.nparts)?,
            cout: l.cout,
            weights,
            bias: BiasRef(self.blob.get(b0..m0)?),
            mult: MultRef(self.blob.get(m0..m0 + 8 * l.cout * l.nparts)?),
            post: match l.post {
                1 => PostOp::Relu,
                2 => PostOp::Sigmoid,
                3 => PostOp::Tanh,
                _ => PostOp::None,
            },
        })
    }

    /// Correlation-lookup multiplier of each level.
    pub fn corr_mults(&self) -> [Multiplier; MAX_LEVELS] {
        let mut m = [Multiplier::ZERO; MAX_LEVELS];
        for (l, x) in m.iter_mut().enumerate() {
            *x = mult_at(self.blob, self.sections.corr_mults + 8 * l);
        }
        m
    }

    /// Multiplier from attention logits (`q . k`) to Q4.11 softmax arguments.
    pub fn att_mult(&self) -> Multiplier {
        mult_at(self.blob, self.sections.att_mult)
    }

    /// RoPE phase step of pair `i` (`2^32` = one turn per pixel).
    pub fn rope_phase(&self, i: usize) -> u32 {
        u32_at(self.blob, self.sections.rope + 4 + 4 * i)
    }

    /// Uncertainty table entry `i` (Q4.11).
    pub fn u_table_entry(&self, i: usize) -> i16 {
        u16_at(self.blob, self.sections.u_table + 2 * i) as i16
    }

    /// The whole uncertainty table.
    pub fn u_table(&self) -> [i16; U_TABLE_LEN] {
        let mut t = [0i16; U_TABLE_LEN];
        let src = self.blob.get(self.sections.u_table..).unwrap_or(&[]);
        for (v, b) in t.iter_mut().zip(src.chunks_exact(2)) {
            if let &[lo, hi] = b {
                *v = i16::from_le_bytes([lo, hi]);
            }
        }
        t
    }

    /// The blob.
    pub fn bytes(&self) -> &'a [u8] {
        self.blob
    }
}

fn bytes_as_i8(b: &[u8]) -> &[i8] {
    // SAFETY: u8 and i8 have identical size, alignment and validity (every bit pattern is valid);
    // the slice keeps the same length and lifetime.
    unsafe { core::slice::from_raw_parts(b.as_ptr() as *const i8, b.len()) }
}

fn mult_at(b: &[u8], o: usize) -> Multiplier {
    Multiplier { m: u32_at(b, o) as i32, shift: u8_at(b, o + 4) }
}

fn valid_mult(m: Multiplier) -> bool {
    (1..=126).contains(&m.shift) && (m.m == 0 || (1 << 30..=i32::MAX).contains(&m.m))
}
