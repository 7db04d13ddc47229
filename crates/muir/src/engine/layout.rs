//! Where every phase's buffers live: the declarations the plan sizes the arena from and the phases
//! carve their buffers and rings from, one per stage (encoder trunk and heads, UFI, MUD and MGA
//! values, ConvGRU, disparity head and output). The plan takes the largest of each zone; a phase
//! carves exactly what its declaration lists, and each ring is built from its [`RingDecl`] (depth
//! and row length written once). `const fn` throughout, so a firmware's `static` arena is sized at
//! compile time.
//!
//! This module sits below `plan`, [`super::encoder`] and [`super::refine`]: the plan uses
//! the declarations without depending on the phases that run them.
#![deny(clippy::indexing_slicing)]

use crate::model::config::Config;
use crate::model::grid::Grid;

const fn align8(n: usize) -> usize {
    (n + 7) & !7
}

/// A buffer: byte offset in the arena and byte length.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Buf {
    /// Byte offset.
    pub at: usize,
    /// Byte length.
    pub len: usize,
}

impl Buf {
    /// End offset.
    pub const fn end(&self) -> usize {
        self.at + self.len
    }
}

/// Sequential allocator used by the plan's `const fn`s.
#[derive(Clone, Copy, Debug)]
pub struct Bump {
    /// Next free offset.
    pub at: usize,
}

impl Bump {
    /// Starts at `at`.
    pub const fn new(at: usize) -> Self {
        Self { at: align8(at) }
    }
    /// Reserves `len` bytes.
    pub const fn take(&mut self, len: usize) -> Buf {
        let b = Buf { at: self.at, len };
        self.at = align8(self.at + len);
        b
    }
}

/// A ring of line buffers: its bytes in the arena, its depth (rows held) and its row length
/// (elements). Declared once in a stage's layout; the phase builds the ring from it
/// (`ring::Ring::of`), so the plan's size and the ring's shape cannot disagree.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct RingDecl {
    /// Bytes: `cap * len * element size`.
    pub buf: Buf,
    /// Rows held.
    pub cap: usize,
    /// Elements per row.
    pub len: usize,
}

impl Bump {
    /// Reserves a ring of `cap` rows of `len` i16 values.
    pub const fn ring16(&mut self, cap: usize, len: usize) -> RingDecl {
        RingDecl { buf: self.take(2 * cap * len), cap, len }
    }
}

// ------------------------------------------------------------------------------------------------
// Encoder (relative to the encoder ring region)
// ------------------------------------------------------------------------------------------------

/// Layout of the trunk's line buffers (relative to the encoder ring region).
#[derive(Clone, Copy, Debug)]
pub struct TrunkLayout {
    /// Image rows (i16).
    pub image: Buf,
    /// conv1 output.
    pub c1: Buf,
    /// Block mid and out rings, 6 blocks.
    pub blocks: [(Buf, Buf); 6],
    /// conv2 and downsample rows (i16).
    pub c2: Buf,
    /// Downsample row.
    pub ds: Buf,
    /// Total bytes.
    pub total: usize,
}

/// Out-ring capacity of each trunk block (4 in front of a stride-2 block).
pub(crate) const TRUNK_OUT_CAP: [usize; 6] = [3, 4, 3, 4, 3, 1];

impl TrunkLayout {
    /// Layout for `cfg` on grid `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let [d1, d2, d3] = cfg.backbone_dims;
        // Bytes per element of conv1, layer1 and layer2 (2 in a wide trunk).
        let e = if cfg.wide_trunk { 2 } else { 1 };
        let mut b = Bump::new(0);
        let image = b.take(7 * g.w * 3 * 2);
        let c1 = b.take(3 * g.w2 * d1 * e);
        let dims = [(g.w2, d1, e), (g.w2, d1, e), (g.w4, d2, e), (g.w4, d2, e), (g.w8, d3, 1), (g.w8, d3, 1)];
        let mut blocks = [(Buf { at: 0, len: 0 }, Buf { at: 0, len: 0 }); 6];
        // In step over the three arrays (a `const fn`: no iterators).
        let (mut dims, mut caps, mut out): (&[_], &[usize], &mut [(Buf, Buf)]) = (&dims, &TRUNK_OUT_CAP, &mut blocks);
        while let ([(w, c, e), dt @ ..], [cap, ct @ ..], [o, ot @ ..]) = (dims, caps, out) {
            let n = *w * *c * *e;
            *o = (b.take(3 * n), b.take(*cap * n));
            (dims, caps, out) = (dt, ct, ot);
        }
        let row = {
            let a = g.w2 * d1;
            let bb = g.w4 * d2;
            let c = g.w8 * d3;
            let m = if a > bb { a } else { bb };
            if m > c { m } else { c }
        };
        let c2 = b.take(2 * row);
        let ds = b.take(2 * row);
        Self { image, c1, blocks, c2, ds, total: b.at }
    }
}

/// Layout of the 1/8 and 1/16 head pipelines (relative to the encoder ring region).
#[derive(Clone, Copy, Debug)]
pub struct FeatureHeadLayout {
    /// Two blocks' mid and out rings.
    pub blocks: [(Buf, Buf); 2],
    /// conv2 / downsample rows.
    pub c2: Buf,
    /// Downsample row.
    pub ds: Buf,
    /// InstanceNorm pipeline: raw row (i16), mid ring, blk ring, y row (i16).
    pub raw: Buf,
    /// mid ring.
    pub mid: Buf,
    /// blk ring.
    pub blk: Buf,
    /// normalised row.
    pub y: Buf,
    /// Total bytes.
    pub total: usize,
}

impl FeatureHeadLayout {
    /// Layout for `cfg` on grid `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let d3 = cfg.backbone_dims[2];
        let w = g.w8; // the 1/16 pipelines are smaller
        let mut b = Bump::new(0);
        let blocks = [(b.take(3 * w * d3), b.take(4 * w * d3)), (b.take(3 * w * d3), b.take(4 * w * d3))];
        let c2 = b.take(2 * w * d3);
        let ds = b.take(2 * w * d3);
        let raw = b.take(2 * w * d3);
        let mid = b.take(3 * w * d3);
        let blk = b.take(3 * w * d3);
        let y = b.take(2 * w * d3);
        Self { blocks, c2, ds, raw, mid, blk, y, total: b.at }
    }
}

/// Bytes of `rows` i16 rows of `w x c`.
const fn ring16(w: usize, rows: usize, c: usize) -> usize {
    2 * rows * w * c
}

// ------------------------------------------------------------------------------------------------
// Refinement: the passes' line buffers (relative to the refinement ring region)
// ------------------------------------------------------------------------------------------------

/// Line buffers of the UFI passes.
#[derive(Clone, Copy, Debug)]
pub struct UfiLayout {
    /// Proposals (d1, d2 per pixel).
    pub peaks: Buf,
    /// Proposal flow, whole.
    pub flow_k: Buf,
    /// Correlation row.
    pub corr: Buf,
    /// Rings: corr features, disparity features, proposal features, candidate, context rows.
    pub c: RingDecl,
    /// Disparity features ring.
    pub f: RingDecl,
    /// Proposal features ring.
    pub feat: RingDecl,
    /// Candidate state ring.
    pub q: RingDecl,
    /// Context rows ring.
    pub inp: RingDecl,
    /// Gate row.
    pub z: Buf,
    /// Blended rows waiting for write-back.
    pub pending: RingDecl,
    /// Decoder hidden ring.
    pub h1: RingDecl,
    /// Decoder output row.
    pub h2: Buf,
    /// Total bytes.
    pub total: usize,
}

impl UfiLayout {
    /// Layout for `cfg` on `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let w = g.w8;
        let h = cfg.hidden_dim;
        let fc = cfg.flow_channels;
        let mut b = Bump::new(0);
        Self {
            peaks: b.take(2 * 2 * g.n8()),
            flow_k: b.take(2 * g.n8() * fc),
            corr: b.take(2 * w * cfg.corr_channels()),
            c: b.ring16(3, w * cfg.ufi_corr_dim),
            f: b.ring16(3, w * cfg.ufi_flow_dim),
            feat: b.ring16(3, w * (cfg.ufi_dim - fc)),
            q: b.ring16(3, w * h),
            inp: b.ring16(3, w * cfg.context_dim),
            z: b.take(2 * w * h),
            pending: b.ring16(2, w * h),
            h1: b.ring16(3, w * cfg.ufi_head_dim),
            h2: b.take(2 * w * 2),
            total: b.at,
        }
    }
}

/// Line buffers of the MUD and MGA-value passes.
#[derive(Clone, Copy, Debug)]
pub struct MudLayout {
    /// Correlation rows (3).
    pub corr: RingDecl,
    /// MUD hidden rings.
    pub mud1: RingDecl,
    /// Second MUD ring.
    pub mud2: RingDecl,
    /// MUD output row.
    pub mud3: Buf,
    /// MGA mask row.
    pub hm: Buf,
    /// MGA value row.
    pub v: Buf,
    /// Total bytes.
    pub total: usize,
}

impl MudLayout {
    /// Layout for `cfg` on `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let w = g.w8;
        let mut b = Bump::new(0);
        Self {
            corr: b.ring16(3, w * cfg.corr_channels()),
            mud1: b.ring16(3, w * cfg.mud_dim),
            mud2: b.ring16(3, w * cfg.mud_dim),
            mud3: b.take(ring16(w, 1, 2)),
            hm: b.take(ring16(w, 1, 1)),
            v: b.take(ring16(w, 1, cfg.hidden_dim)),
            total: b.at,
        }
    }
}

/// Line buffers of a ConvGRU pass (the 1/8 one with the motion encoder; the 1/16 one uses the
/// GRU rings only, with shorter rows).
#[derive(Clone, Copy, Debug)]
pub struct GruLayout {
    /// Correlation row.
    pub corr: Buf,
    /// Masked correlation row (`C * m`).
    pub corr_m: Buf,
    /// Motion rings.
    pub c1: RingDecl,
    /// ..
    pub c2: RingDecl,
    /// ..
    pub f1: RingDecl,
    /// ..
    pub f2: RingDecl,
    /// Motion features ring (4); pooled 1/8 state for the 1/16 GRU.
    pub mo: RingDecl,
    /// Upsampled 1/16 state ring (4).
    pub up: RingDecl,
    /// MGA output ring (4).
    pub glb: RingDecl,
    /// Context ring (4).
    pub inp: RingDecl,
    /// Update gate ring (2).
    pub z: RingDecl,
    /// Reset-gated state ring (3).
    pub rh: RingDecl,
    /// Gate row.
    pub gate: Buf,
    /// Candidate row.
    pub q: Buf,
    /// Total bytes.
    pub total: usize,
}

impl GruLayout {
    /// Layout for `cfg` on `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let w = g.w8;
        let h = cfg.hidden_dim;
        let fc = cfg.flow_channels;
        let mut b = Bump::new(0);
        // The buffers the 1/16 pass uses first: the rest, from `q.end()`, is idle while it runs
        // (its gates gather their pixel pairs there: `refine::gru16`).
        Self {
            mo: b.ring16(4, w * if cfg.motion_dim - fc > h { cfg.motion_dim - fc } else { h }),
            inp: b.ring16(4, w * cfg.context_dim),
            z: b.ring16(2, w * h),
            rh: b.ring16(3, w * h),
            gate: b.take(ring16(w, 1, h)),
            q: b.take(ring16(w, 1, h)),
            corr: b.take(ring16(w, 1, cfg.corr_channels())),
            corr_m: b.take(ring16(w, 1, cfg.corr_channels())),
            c1: b.ring16(3, w * cfg.motion_corr_dims[0]),
            c2: b.ring16(3, w * cfg.motion_corr_dims[1]),
            f1: b.ring16(3, w * cfg.motion_flow_dims[0]),
            f2: b.ring16(3, w * cfg.motion_flow_dims[1]),
            up: b.ring16(4, w * h),
            glb: b.ring16(4, w * h),
            total: b.at,
        }
    }
}

/// Line buffers of the disparity head and of the output (mask head, upsampling) passes.
#[derive(Clone, Copy, Debug)]
pub struct FlowHeadLayout {
    /// Head hidden ring (3).
    pub head: RingDecl,
    /// Head output row.
    pub head_out: Buf,
    /// Disparity channel 0 for the upsampler.
    pub flow0: Buf,
    /// Total bytes.
    pub total: usize,
}

impl FlowHeadLayout {
    /// Layout for `cfg` on `g`.
    pub const fn new(cfg: &Config, g: &Grid) -> Self {
        let w = g.w8;
        let mh = if cfg.flow_head_dim > cfg.mask_head_dim { cfg.flow_head_dim } else { cfg.mask_head_dim };
        let mut b = Bump::new(0);
        Self {
            head: b.ring16(3, w * mh),
            head_out: b.take(ring16(w, 1, cfg.flow_channels)),
            flow0: b.take(2 * g.n8()),
            total: b.at,
        }
    }
}

/// Bytes of the refinement line buffers: the largest pass.
pub const fn refine_rings(cfg: &Config, g: &Grid) -> usize {
    let a = UfiLayout::new(cfg, g).total;
    let b = MudLayout::new(cfg, g).total;
    let c = GruLayout::new(cfg, g).total;
    let d = FlowHeadLayout::new(cfg, g).total;
    let ab = if a > b { a } else { b };
    let cd = if c > d { c } else { d };
    if ab > cd { ab } else { cd }
}

// ------------------------------------------------------------------------------------------------
// Streaming schedules of the refinement passes
// ------------------------------------------------------------------------------------------------

/// How a refinement pass streams: it runs steps `s = 0 .. rows + depth`; its stage `d` (0: the
/// rows computed from whole tensors or the lookup; then each chained 3x3 convolution, one row
/// behind the stage whose ring it reads, the kernel's radius) produces row `s - d` at step `s`.
/// Each pass declares its stages here, next to its buffers, and its loop takes the step count and
/// every stage's row from this declaration.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Schedule {
    /// Steps beyond the tensor's rows (the deepest stage's lag, plus one where a stage writes
    /// back a row late).
    pub depth: usize,
}

impl Schedule {
    /// Steps of the pass over a tensor of `rows` rows.
    pub const fn steps(self, rows: usize) -> usize {
        rows + self.depth
    }
    /// The row stage `lag` produces at step `s`, if any.
    pub const fn row(self, s: usize, lag: usize, rows: usize) -> Option<usize> {
        match s.checked_sub(lag) {
            Some(r) if r < rows => Some(r),
            _ => None,
        }
    }
}

/// UFI, initializer and decoder: lookup and disparity/correlation features (0), proposal features
/// (1), candidate state or decoder hidden (2), gate and blend or decoder output (3; the blended
/// row is written back one step later).
pub mod ufi_stages {
    /// Lookup, correlation and disparity features.
    pub const LOOKUP: usize = 0;
    /// Proposal features.
    pub const FEATURES: usize = 1;
    /// Candidate state (initializer) / decoder hidden layer.
    pub const CANDIDATE: usize = 2;
    /// Gate and blend (initializer) / decoder output and selection.
    pub const GATE: usize = 3;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: GATE + 1 };
}

/// MUD: lookup (0), two hidden convolutions (1, 2), mask and uncertainty heads (3).
pub mod mud_stages {
    /// Correlation lookup.
    pub const LOOKUP: usize = 0;
    /// First hidden convolution.
    pub const HIDDEN1: usize = 1;
    /// Second hidden convolution.
    pub const HIDDEN2: usize = 2;
    /// Mask and uncertainty outputs.
    pub const OUT: usize = 3;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: OUT };
}

/// MGA values: lookup (0), mask and value convolutions (1).
pub mod mga_value_stages {
    /// Correlation lookup.
    pub const LOOKUP: usize = 0;
    /// Mask and value rows.
    pub const OUT: usize = 1;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: OUT };
}

/// 1/16 ConvGRU: pooled state and context rows (0), gates (1), candidate and blend (2).
pub mod gru16_stages {
    /// Pooled 1/8 state and widened context.
    pub const INPUTS: usize = 0;
    /// Update and reset gates.
    pub const GATES: usize = 1;
    /// Candidate and blend.
    pub const CANDIDATE: usize = 2;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: CANDIDATE };
}

/// 1/8 ConvGRU with the motion encoder: lookup and first motion convolutions (0), second ones (1),
/// motion features (2), gates with the 1/16 state, MGA and context rows (3), candidate and blend (4).
pub mod gru08_stages {
    /// Lookup and the first motion convolutions.
    pub const LOOKUP: usize = 0;
    /// Second motion convolutions.
    pub const MOTION2: usize = 1;
    /// Motion features.
    pub const MOTION: usize = 2;
    /// Update and reset gates (and their inputs: upsampled state, MGA output, context).
    pub const GATES: usize = 3;
    /// Candidate and blend.
    pub const CANDIDATE: usize = 4;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: CANDIDATE };
}

/// Disparity head: hidden convolution (0), update (1).
pub mod flow_head_stages {
    /// Hidden convolution.
    pub const HIDDEN: usize = 0;
    /// Disparity update.
    pub const OUT: usize = 1;
    /// The schedule.
    pub const SCHEDULE: super::Schedule = super::Schedule { depth: OUT };
}

// Every stage runs within its pass's steps, and the stages are chained one row apart (each 3x3
// convolution reads the ring of the stage before it, one row ahead).
const _: () = assert!(ufi_stages::LOOKUP + 1 == ufi_stages::FEATURES && ufi_stages::FEATURES + 1 == ufi_stages::CANDIDATE);
const _: () = assert!(ufi_stages::CANDIDATE + 1 == ufi_stages::GATE && ufi_stages::GATE < ufi_stages::SCHEDULE.depth);
const _: () = assert!(mud_stages::HIDDEN1 == 1 && mud_stages::HIDDEN2 == 2 && mud_stages::OUT <= mud_stages::SCHEDULE.depth);
const _: () = assert!(mga_value_stages::OUT == mga_value_stages::LOOKUP + 1 && mga_value_stages::OUT <= mga_value_stages::SCHEDULE.depth);
const _: () = assert!(gru16_stages::GATES == 1 && gru16_stages::CANDIDATE == 2 && gru16_stages::CANDIDATE <= gru16_stages::SCHEDULE.depth);
const _: () = assert!(gru08_stages::MOTION2 == 1 && gru08_stages::MOTION == 2 && gru08_stages::GATES == 3 && gru08_stages::CANDIDATE == 4);
const _: () = assert!(gru08_stages::CANDIDATE <= gru08_stages::SCHEDULE.depth && flow_head_stages::OUT <= flow_head_stages::SCHEDULE.depth);

#[cfg(test)]
mod tests {
    use super::*;

    /// The declarations the phases read with narrower rows (`Ring::of_len`) are wide enough for
    /// them, and every stage fits the ring region the plan sizes, for each preset at camera sizes.
    #[test]
    fn declarations_cover_their_uses() {
        for cfg in Config::PRESETS {
            for (w, h) in [(64, 48), (160, 120), (640, 480), (1242, 375)] {
                let g = Grid::new(w, h);
                let gru = GruLayout::new(&cfg, &g);
                let fc = cfg.flow_channels;
                // The 1/16 ConvGRU reuses the 1/8 rings: pooled state, context, gates.
                assert!(g.w16 * cfg.hidden_dim <= gru.mo.len && g.w16 * cfg.context_dim <= gru.inp.len);
                assert!(g.w16 * cfg.hidden_dim <= gru.z.len && g.w16 * cfg.hidden_dim <= gru.rh.len);
                assert!(g.w8 * (cfg.motion_dim - fc) <= gru.mo.len);
                let head = FlowHeadLayout::new(&cfg, &g);
                assert!(g.w8 * cfg.flow_head_dim <= head.head.len && g.w8 * cfg.mask_head_dim <= head.head.len);
                let rings = refine_rings(&cfg, &g);
                let totals = [UfiLayout::new(&cfg, &g).total, MudLayout::new(&cfg, &g).total, gru.total, head.total];
                assert!(totals.iter().all(|t| *t <= rings), "{} {w}x{h}", cfg.name.as_str());
                for d in [gru.c1, gru.c2, gru.f1, gru.f2, gru.mo, gru.up, gru.glb, gru.inp, gru.z, gru.rh, head.head] {
                    assert_eq!(d.buf.len, 2 * d.cap * d.len);
                }
            }
        }
    }
}
