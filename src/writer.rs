//! Host-side writer of `.muirq` blobs (the layout is documented in the parent module).

use muir::format::{
    CONFIG_LEN, FORMATS_AT, HEADER_LEN, LAYER_HEADER_LEN, MAGIC, MAX_LEVELS, Sections, U_TABLE_LEN, VERSION, config_record,
    crc32, layer_record_len, rope_pairs,
};
use muir::arith::{Multiplier, QFormat};
use muir::model::config::Config;
use muir::model::graph::{Act, MAX_PARTS, PostOp};
use muir::model::layers::ConvId;

/// One quantised conv, ready to serialise.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantLayer {
    /// Layer identity.
    pub id: ConvId,
    /// Kernel size.
    pub k: usize,
    /// Stride.
    pub stride: usize,
    /// Activation.
    pub post: PostOp,
    /// Channels per input part.
    pub parts: Vec<usize>,
    /// Output channels.
    pub cout: usize,
    /// `cout x patch_len` weights, `[part][ky][kx][c]` per output channel.
    pub weights: Vec<i8>,
    /// Bias per output channel (output units with `EXTRA_BITS` more fraction bits).
    pub bias: Vec<i64>,
    /// Requantisation per output channel and part (`c * parts + p`).
    pub mult: Vec<Multiplier>,
}

impl QuantLayer {
    /// Patch length.
    pub fn patch_len(&self) -> usize {
        self.k * self.k * self.parts.iter().sum::<usize>()
    }
}

/// Everything a `.muirq` blob holds.
#[derive(Clone, Debug, PartialEq)]
pub struct QuantModelData {
    /// Model config.
    pub config: Config,
    /// Format of every activation slot.
    pub formats: [QFormat; Act::COUNT],
    /// Lookup multiplier per level.
    pub corr_mults: Vec<Multiplier>,
    /// Attention logit multiplier.
    pub att_mult: Multiplier,
    /// RoPE phase step per pair.
    pub rope_phases: Vec<u32>,
    /// Uncertainty table (Q4.11 logit to Q4.11 u).
    pub u_table: Vec<i16>,
    /// Layers (any order).
    pub layers: Vec<QuantLayer>,
}

fn put_mult(out: &mut [u8], m: Multiplier) {
    out[..4].copy_from_slice(&m.m.to_le_bytes());
    out[4] = m.shift;
}

/// Serialises a model. Panics only on programming errors (inconsistent vectors).
pub fn write(d: &QuantModelData) -> Vec<u8> {
    let c = &d.config;
    let pairs = rope_pairs(c);
    assert_eq!(d.rope_phases.len(), pairs, "RoPE phases");
    assert_eq!(d.u_table.len(), U_TABLE_LEN, "uncertainty table");
    assert!(d.corr_mults.len() <= MAX_LEVELS);
    let s = Sections::new(pairs);
    let mut out = vec![0u8; s.records];
    out[..4].copy_from_slice(&MAGIC);
    out[4..6].copy_from_slice(&VERSION.to_le_bytes());
    out[HEADER_LEN..HEADER_LEN + CONFIG_LEN].copy_from_slice(&config_record(c));
    for &act in Act::ALL {
        let f = d.formats[act.index()];
        out[FORMATS_AT + 2 * act.index()] = f.bits;
        out[FORMATS_AT + 2 * act.index() + 1] = f.frac as u8;
    }
    for (l, m) in d.corr_mults.iter().enumerate() {
        put_mult(&mut out[s.corr_mults + 8 * l..], *m);
    }
    put_mult(&mut out[s.att_mult..], d.att_mult);
    out[s.rope..s.rope + 4].copy_from_slice(&(pairs as u32).to_le_bytes());
    for (i, p) in d.rope_phases.iter().enumerate() {
        out[s.rope + 4 + 4 * i..s.rope + 8 + 4 * i].copy_from_slice(&p.to_le_bytes());
    }
    for (i, v) in d.u_table.iter().enumerate() {
        out[s.u_table + 2 * i..s.u_table + 2 * i + 2].copy_from_slice(&v.to_le_bytes());
    }
    let mut layers: Vec<&QuantLayer> = d.layers.iter().collect();
    layers.sort_by_key(|l| l.id);
    for l in layers {
        let patch = l.patch_len();
        assert_eq!(l.weights.len(), l.cout * patch, "{} weights", l.id.name());
        assert!(l.bias.len() == l.cout && l.mult.len() == l.cout * l.parts.len() && l.parts.len() <= MAX_PARTS);
        let at = out.len();
        let len = layer_record_len(l.cout, patch, l.parts.len());
        out.resize(at + len, 0);
        let r = &mut out[at..at + len];
        r[0] = l.id.index() as u8;
        r[1] = l.k as u8;
        r[2] = l.stride as u8;
        r[3] = l.post as u8;
        r[4] = l.parts.len() as u8;
        r[8..12].copy_from_slice(&(l.cout as u32).to_le_bytes());
        r[12..16].copy_from_slice(&(patch as u32).to_le_bytes());
        for (i, p) in l.parts.iter().enumerate() {
            r[16 + 2 * i..18 + 2 * i].copy_from_slice(&(*p as u16).to_le_bytes());
        }
        let w0 = LAYER_HEADER_LEN;
        for (i, w) in l.weights.iter().enumerate() {
            r[w0 + i] = *w as u8;
        }
        let b0 = w0 + (l.cout * patch).div_ceil(8) * 8;
        for (i, b) in l.bias.iter().enumerate() {
            r[b0 + 8 * i..b0 + 8 * i + 8].copy_from_slice(&b.to_le_bytes());
        }
        let m0 = b0 + 8 * l.cout;
        for (i, m) in l.mult.iter().enumerate() {
            put_mult(&mut r[m0 + 8 * i..], *m);
        }
        let dir = s.directory + 8 * l.id.index();
        out[dir..dir + 4].copy_from_slice(&(at as u32).to_le_bytes());
        out[dir + 4..dir + 8].copy_from_slice(&(len as u32).to_le_bytes());
    }
    let total = out.len() as u32;
    out[8..12].copy_from_slice(&total.to_le_bytes());
    let crc = crc32(&out[HEADER_LEN..]);
    out[12..16].copy_from_slice(&crc.to_le_bytes());
    out
}
