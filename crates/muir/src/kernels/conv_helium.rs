//! [`super::conv_row`]'s channels on Helium (Cortex-M55, feature `mve`): the requantisation,
//! bias, rounding, activation and store of four output channels at a time on 32-bit vector lanes
//! ([`mve::requant4`]) instead of one value at a time in 64-bit scalar arithmetic.
//!
//! Per pair of output pixels and block of four output channels, the two channel pairs' dot
//! products ([`Elem::dot2x2`], as in the portable loop) are kept per part as 32-bit values, then
//! one vector epilogue per pixel writes the four outputs. The portable code defines the result,
//! and this path gives the same integers:
//! - it runs only on layers whose every shift is in `8..=62` and every bias within `2^30` (checked
//!   once per row, [`Layer::of`]), where the portable loop takes its short path (`short_ok`);
//! - a block whose dot product does not fit in `i32`, or whose parts do not fit the tables, goes
//!   through the portable block ([`super::block2x2`]) instead;
//! - the vector epilogue is exact unless one of its saturating instructions saturates, which sets
//!   `FPSCR.QC` ([`mve::take_qc`]); the block's outputs are then recomputed with the portable
//!   formula from the same dot products (layers of several parts; with one part a saturation
//!   leaves the outputs at the clamp's bound, as the exact value does: see `qc` in
//!   [`Layer::channels`]).
//!
//! `boards/qemu-mps3-m55` checks the vector epilogue against the portable formula on the target
//! (random and extreme operands, saturating cases included) and the whole frame against the host.
#![deny(clippy::indexing_slicing)]

use super::super::mve::{self, Narrow, Requant4};
use super::super::{Elem, OutRow};
use super::{ConvParams, bias_at, block2x2, mult_raw, part_dot2x2};
use crate::arith::{lut, requantize_i32_halved};
use crate::model::graph::{MAX_PARTS, PostOp};

/// Bias magnitude bound of the vector path (the bias enters a 32-bit lane).
const MAX_BIAS: u64 = 1 << 30;

/// Dot products of a block. Four channels ([`NARROW`] layout): per part, the four channels at
/// pixel `a`, then the same at pixel `b`. Twelve channels ([`WIDE`]): per part, twelve at `a`,
/// then twelve at `b`.
type Dots = [i32; MAX_PARTS * 24];

/// Values per part of a four-channel block's table.
const NARROW: usize = 8;
/// Values per part of a twelve-channel block's table.
const WIDE: usize = 24;
/// The table's length: its one part's stride in [`mve::dots_flipped`]'s layout (pixel `a`'s
/// channels at `0..FLIP_MAX`, pixel `b`'s at `FLIP_MAX..`).
const FLIP: usize = MAX_PARTS * 24;

/// A layer the vector epilogue serves, with its constants.
pub(super) struct Layer {
    k: Requant4,
    /// The lookup table of a sigmoid or tanh activation (applied to the clamped vector,
    /// [`mve::requant4_lut`]).
    lut: Option<&'static [i16; 1025]>,
    /// The parts' patch lengths for [`Elem::dots4`] (i16 activations: one assembly call per
    /// channel pair for all parts).
    lens: Option<mve::PartLens>,
    /// The block's dot products, filled by `dots12` / `dots4` / `dots` for the block's parts
    /// before every read (cleared once per row, not per pixel pair: 576 bytes).
    d: Dots,
    /// u8 layers of one part and `3..=FLIP_MAX` channels: `128 sum(w_c)` per output channel
    /// (wrapping), for [`Elem::dots_flipped`] (every channel of a pair in one call).
    ws: Option<[i32; mve::FLIP_MAX]>,
}

impl Layer {
    /// The vector epilogue's constants for `p` writing `w_out` pixels into `out`, or `None` where
    /// the portable path must run: a shift outside `8..=62`, a bias beyond [`MAX_BIAS`], tables or
    /// the output row shorter than the parameters say, or tables not 4-byte aligned.
    pub(super) fn of<T: Elem>(p: &ConvParams<'_>, out: &OutRow<'_>, w_out: usize) -> Option<Layer> {
        let np = p.parts.len();
        if np == 0 || np > MAX_PARTS || p.cout < 4 || out.len() < w_out * p.cout || p.weights.len() < p.cout * p.patch_len() {
            return None;
        }
        let (mult, bias) = (p.mult.0.get(..8 * np * p.cout)?, p.bias.0.get(..8 * p.cout)?);
        if !(mult.as_ptr() as usize).is_multiple_of(4) || !(bias.as_ptr() as usize).is_multiple_of(4) {
            return None;
        }
        if !mult.chunks_exact(8).all(|e| matches!(e.get(4), Some(8..=62))) || !bias.chunks_exact(8).all(|b| bias_at(b).unsigned_abs() < MAX_BIAS) {
            return None;
        }
        let (lo, hi) = match out {
            OutRow::U8(_) => (0, 255),
            OutRow::I8(_) => (-128, 127),
            OutRow::I16(_) => (-32768, 32767),
        };
        let (lo, hi, lut) = match p.post {
            PostOp::None => (lo, hi, None),
            PostOp::Relu => (lo.max(0), hi, None),
            PostOp::Sigmoid => (-32768, 32767, Some(lut::sigmoid_table())),
            PostOp::Tanh => (-32768, 32767, Some(lut::tanh_table())),
        };
        // After a table, the output type's range (`OutRow::set` saturates to it).
        let (out_lo, out_hi) = match out {
            OutRow::U8(_) => (0, 255),
            OutRow::I8(_) => (-128, 127),
            OutRow::I16(_) => (-32768, 32767),
        };
        let kl = p.patch_len();
        if np > 1 {
            // `channels` tests `FPSCR.QC` after the epilogues of layers of several parts only: a
            // flag left set by a one-part layer (or any kernel) must not count here.
            let _ = mve::take_qc();
        }
        let lens = mve::PartLens::new(p.parts.iter().map(|&ch| ch * p.k * p.k), kl);
        // Once per row: `cout` sums of `kl` weights, two instructions per sixteen.
        let ws = (T::FLIPS && np == 1 && (3..=mve::FLIP_MAX).contains(&p.cout) && (1..1 << 16).contains(&kl)).then(|| {
            let mut ws = [0i32; mve::FLIP_MAX];
            for (s, w) in ws.iter_mut().zip(p.weights.chunks_exact(kl.max(1))) {
                *s = mve::sum_i8(w).wrapping_mul(128);
            }
            ws
        });
        Some(Layer { k: Requant4::new(np, lo, hi).with_out(out_lo, out_hi), lut, lens, d: [0; MAX_PARTS * 24], ws })
    }

    /// Output channels `0 .. 4 (cout / 4)` of pixels `a` and `b` (at `at_a` and `at_b` of `out`)
    /// from their gathered pair of patches; returns the first channel not written. Blocks of
    /// twelve channels first ([`Elem::dots12`]: three channels per pass over the activations
    /// instead of two), then blocks of four.
    pub(super) fn channels<T: Elem>(&mut self, p: &ConvParams<'_>, pair: &mut [T], out: &mut OutRow<'_>, at_a: usize, at_b: usize) -> usize {
        let (kl, np) = (p.patch_len(), p.parts.len());
        let mut c = 0;
        // (The four-channel blocks use the first `8 MAX_PARTS` values of `d`.)
        let Layer { k, lut, lens, d, ws } = self;
        let (k, lut, lens) = (&*k, *lut, lens.as_ref());
        // u8, one part: every channel in one pass over the flipped activations, then the
        // epilogues four channels at a time (`np == 1`: multipliers 32 bytes per four channels).
        if let Some(ws) = ws
            && T::dots_flipped(ws, p.weights, kl, p.cout, pair, d)
        {
            let n4 = p.cout / 4;
            // (One part: a saturation cannot change the outputs, see `qc` below.)
            if Self::store_groups(k, lut, d, FLIP, [0, mve::FLIP_MAX], p.mult.0, p.bias.0, out, [at_a, at_b], n4).is_none() {
                for (j, (m, b)) in p.mult.0.chunks_exact(32).zip(p.bias.0.chunks_exact(32)).take(n4).enumerate() {
                    Self::store2(k, lut, d, FLIP, [4 * j, mve::FLIP_MAX + 4 * j], m, b, out, [at_a + 4 * j, at_b + 4 * j]);
                }
            }
            if 4 * n4 < p.cout {
                // The last channels read the pair again (`pair_blocks`, `odd_channel`).
                T::unflip(pair.get_mut(..2 * kl).unwrap_or_default());
            }
            return 4 * n4;
        }
        // Whether a saturation of the vector epilogue (`FPSCR.QC`) must be tested. With one part
        // it cannot change the outputs: each step saturates only where the exact value is beyond
        // i32 on the same side, and then the output is the clamp's bound on that side either way.
        // `VQRSHL` of the product's high word saturating means the requantised value `x` is at
        // least `2^31` (resp. at most `-2^31`); the saturated `2^31 - 1` plus the low word's
        // rounded part (`>= 0`), or `-2^31` plus it (`<= 2^24`, shifts `>= 8`), then plus the bias
        // (`|b| < 2^30`, `Layer::of`), is at least `2^30` (at most `-2^30 + 2^24`), so after the
        // rounding by 8 bits beyond `+-2^21`, past every clamp bound (`|lo|, |hi| <= 32768`), as
        // is the exact `(x + b) / 2^8`; the two `VQADD`s saturate only where `x`, resp. `x + b`,
        // is beyond i32 on that side, the same. With several parts, parts saturated in opposite
        // directions could cancel: the test stays (`Layer::of` clears a flag left by earlier
        // layers).
        let qc = np > 1;
        // u8: `128 sum(x)` per part and patch of this pair, for every twelve-channel block.
        let mut sums = [0i32; 2 * MAX_PARTS];
        if let Some(l) = lens
            && p.cout >= 12
            && T::dots12_prepare(l, pair, &mut sums)
        {
            let blocks = p.weights.chunks_exact((12 * kl).max(1)).zip(p.mult.0.chunks_exact((96 * np).max(1))).zip(p.bias.0.chunks_exact(96));
            for ((w, m), b) in blocks.take(p.cout / 12) {
                match T::dots12(l, w, pair, &sums, d) {
                    None => break,
                    Some(true) => {
                        // Block `j`'s four channels: pixel a's at `4 j`, b's at `12 + 4 j`; the
                        // three groups' epilogues in one call, each group's saturation reported
                        // (bit `j`: a saturation recomputes only that group's eight outputs; one
                        // test per twelve recomputed three times as many: 160x120 +8.7 M
                        // instructions in `recompute`).
                        let sat = match Self::store_groups(k, lut, d, WIDE, [0, 12], m, b, out, [at_a + c, at_b + c], 3) {
                            Some(sat) => sat,
                            None => {
                                let mut sat = 0;
                                for (j, (m, b)) in m.chunks_exact((32 * np).max(1)).zip(b.chunks_exact(32)).enumerate() {
                                    Self::store2(k, lut, d, WIDE, [4 * j, 12 + 4 * j], m, b, out, [at_a + c + 4 * j, at_b + c + 4 * j]);
                                    sat |= u32::from(mve::take_qc()) << j;
                                }
                                sat
                            }
                        };
                        if qc && sat != 0 {
                            for (j, (m, b)) in m.chunks_exact((32 * np).max(1)).zip(b.chunks_exact(32)).enumerate() {
                                if sat & (1 << j) != 0 {
                                    // A lane saturated: the portable formula from the same dot products.
                                    recompute::<WIDE>(p, d, 4 * j, m, b, out, at_a + c + 4 * j);
                                    recompute::<WIDE>(p, d, 12 + 4 * j, m, b, out, at_b + c + 4 * j);
                                }
                            }
                        }
                    }
                    Some(false) => {
                        // (Whole chunks: six channel pairs.)
                        for (i, ((w, m), b)) in w.chunks_exact((2 * kl).max(1)).zip(m.chunks_exact((16 * np).max(1))).zip(b.chunks_exact(16)).enumerate() {
                            block2x2(p, pair, w, m, b, out, at_a, at_b, c + 2 * i);
                        }
                    }
                }
                c += 12;
            }
        }
        let (Some(w), Some(m), Some(b)) = (p.weights.get(c * kl..), p.mult.0.get(8 * np * c..), p.bias.0.get(8 * c..)) else {
            return c;
        };
        let blocks = w.chunks_exact((4 * kl).max(1)).zip(m.chunks_exact((32 * np).max(1))).zip(b.chunks_exact(32));
        for ((w, m), b) in blocks.take(p.cout.saturating_sub(c) / 4) {
            let fits = match (lens, d.first_chunk_mut::<{ MAX_PARTS * 8 }>()) {
                (Some(l), Some(d4)) => T::dots4(l, w, pair, d4),
                _ => None,
            };
            let fits = match fits {
                Some(fits) => fits,
                None => dots(p, pair, w, d),
            };
            if fits {
                Self::store2(k, lut, d, NARROW, [0, 4], m, b, out, [at_a + c, at_b + c]);
                if qc && mve::take_qc() {
                    // A lane saturated: the portable formula from the same dot products.
                    recompute::<NARROW>(p, d, 0, m, b, out, at_a + c);
                    recompute::<NARROW>(p, d, 4, m, b, out, at_b + c);
                }
            } else {
                // (Whole chunks: the splits cannot fail.)
                if let (Some((w0, w1)), Some((m0, m1)), Some((b0, b1))) = (w.split_at_checked(2 * kl), m.split_at_checked(16 * np), b.split_at_checked(16)) {
                    block2x2(p, pair, w0, m0, b0, out, at_a, at_b, c);
                    block2x2(p, pair, w1, m1, b1, out, at_a, at_b, c + 2);
                }
            }
            c += 4;
        }
        c
    }

    /// The vector epilogue of two pixels' four channels (pixel `i`'s dot products at
    /// `d[off[i]..]`, per part, into `out[at[i]..at[i] + 4]`) in one call
    /// ([`mve::requant4_pair`]: each part's multipliers gathered once); where one pixel's outputs
    /// lie outside the row (the odd width's last pixel), the other's alone ([`Layer::to`]).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn store2(k: &Requant4, lut: Option<&[i16; 1025]>, d: &Dots, stride: usize, off: [usize; 2], m: &[u8], b: &[u8], out: &mut OutRow<'_>, at: [usize; 2]) {
        let np = k.mult_offsets[1] as usize / 8;
        // `off[i] <= stride - 4` ([`NARROW`]: 0 or 4, [`WIDE`]: up to 20, [`FLIP`] (one part):
        // up to `2 FLIP_MAX - 4`) and `np <= MAX_PARTS` (`np == 1` with [`FLIP`]):
        // `d[off[i] + stride (np - 1) .. + 4]` is inside `d`; `m` holds `32 np` bytes and `b`
        // 32, both 4-byte aligned (`Layer::of`, whole chunks).
        let dp = off.map(|o| d.as_ptr().wrapping_add(o));
        let wide = stride == WIDE;
        /// Both pixels through [`mve::requant4_pair`] when both ranges lie inside `r` and apart,
        /// else each one that does through [`Layer::to`].
        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn to<O: Narrow>(k: &Requant4, np: usize, dp: [*const i32; 2], wide: bool, m: &[u8], b: &[u8], lut: Option<&[i16; 1025]>, r: &mut [O], at: [usize; 2]) {
            let [a0, a1] = at;
            if a0.max(a1) + 4 <= r.len() && a0.abs_diff(a1) >= 4 {
                let o = r.as_mut_ptr();
                // SAFETY: the bounds of `store2`; both four-value ranges are inside `r` and do
                // not overlap; with a table the clamp before it is `-32768..=32767`
                // (`Layer::of`).
                unsafe { mve::requant4_pair(dp, m.as_ptr(), k, np, b.as_ptr(), lut, wide, [o.wrapping_add(a0), o.wrapping_add(a1)]) };
                return;
            }
            for (dp, at) in dp.into_iter().zip(at) {
                Layer::to(k, np, dp, wide, m, b, lut, r, at);
            }
        }
        match out {
            OutRow::U8(r) => to(k, np, dp, wide, m, b, lut, r, at),
            OutRow::I8(r) => to(k, np, dp, wide, m, b, lut, r, at),
            OutRow::I16(r) => to(k, np, dp, wide, m, b, lut, r, at),
        }
    }

    /// The vector epilogues of `groups` consecutive groups of four channels of two pixels in one
    /// call ([`mve::requant4_groups`]): group `j`'s dot products at `d[off[i] + 4 j..]` (pixel
    /// `i`, per part), multipliers and biases at `32 np j` of `m` and `32 j` of `b`, outputs at
    /// `out[at[i] + 4 j..]`. Returns the groups that saturated (bit `j`), or `None`, having
    /// written nothing, where the outputs, tables or dot products do not cover every group or
    /// the two pixels' outputs overlap (the caller then stores group by group).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn store_groups(k: &Requant4, lut: Option<&[i16; 1025]>, d: &Dots, stride: usize, off: [usize; 2], m: &[u8], b: &[u8], out: &mut OutRow<'_>, at: [usize; 2], groups: usize) -> Option<u32> {
        let np = k.mult_offsets[1] as usize / 8;
        let span = 4 * groups;
        // Every group's `d[off[i] + 4 j + stride (np - 1) .. + 4]` inside `d`, its multipliers
        // and biases inside `m` and `b` (both 4-byte aligned, `Layer::of`).
        if !(1..=32).contains(&groups) || off[0].max(off[1]) + span + stride * (np - 1) > d.len() || m.len() < 32 * np * groups || b.len() < 32 * groups {
            return None;
        }
        let dp = off.map(|o| d.as_ptr().wrapping_add(o));
        let wide = stride == WIDE;
        #[inline(always)]
        #[allow(clippy::too_many_arguments)]
        fn to<O: Narrow>(k: &Requant4, np: usize, dp: [*const i32; 2], wide: bool, m: &[u8], b: &[u8], lut: Option<&[i16; 1025]>, r: &mut [O], at: [usize; 2], groups: usize) -> Option<u32> {
            let [a0, a1] = at;
            let span = 4 * groups;
            if a0.max(a1) + span > r.len() || a0.abs_diff(a1) < span {
                return None;
            }
            let o = r.as_mut_ptr();
            // SAFETY: checked above and in `store_groups`: every group's dot products, tables
            // and outputs are inside their slices, the two pixels' outputs do not overlap, `1
            // <= groups <= 32`; with a table the clamp before it is `-32768..=32767`
            // (`Layer::of`).
            Some(unsafe { mve::requant4_groups(dp, m.as_ptr(), k, np, b.as_ptr(), lut, wide, [o.wrapping_add(a0), o.wrapping_add(a1)], groups) })
        }
        match out {
            OutRow::U8(r) => to(k, np, dp, wide, m, b, lut, r, at, groups),
            OutRow::I8(r) => to(k, np, dp, wide, m, b, lut, r, at, groups),
            OutRow::I16(r) => to(k, np, dp, wide, m, b, lut, r, at, groups),
        }
    }

    /// Stores through [`mve::requant4`] (or [`mve::requant4_lut`] with a table) into
    /// `r[at..at + 4]` (nothing when the row is short, which `Layer::of` rules out).
    #[inline(always)]
    #[allow(clippy::too_many_arguments)]
    fn to<O: Narrow>(k: &Requant4, np: usize, dp: *const i32, wide: bool, m: &[u8], b: &[u8], lut: Option<&[i16; 1025]>, r: &mut [O], at: usize) {
        if let Some(o) = r.get_mut(at..at + 4) {
            // SAFETY: the bounds of `store2`; `o` holds four values of `O`; with a table the
            // clamp before it is `-32768..=32767` (`Layer::of`).
            unsafe {
                match (lut, wide) {
                    (Some(t), false) => mve::requant4_lut(dp, m.as_ptr(), k, np, b.as_ptr(), t, o.as_mut_ptr()),
                    (None, false) => mve::requant4(dp, m.as_ptr(), k, np, b.as_ptr(), o.as_mut_ptr()),
                    (Some(t), true) => mve::requant4_lut_wide(dp, m.as_ptr(), k, np, b.as_ptr(), t, o.as_mut_ptr()),
                    (None, true) => mve::requant4_wide(dp, m.as_ptr(), k, np, b.as_ptr(), o.as_mut_ptr()),
                }
            }
        }
    }
}

/// The two channel pairs' dot products of a block (`w`: four channels' weights) into `d`; false
/// when one does not fit in `i32` or a part does not fit the tables (the portable block then
/// defines the outputs).
#[inline(always)]
fn dots<T: Elem>(p: &ConvParams<'_>, pair: &[T], w: &[i8], d: &mut Dots) -> bool {
    let kl = p.patch_len();
    let one_part = p.parts.len() == 1;
    let Some((w01, w23)) = w.split_at_checked(2 * kl) else {
        return false;
    };
    for (j, w) in [w01, w23].into_iter().enumerate() {
        let Some((w0, w1)) = w.split_at_checked(kl) else {
            return false;
        };
        let mut o = 0;
        for (&ch, dp) in p.parts.iter().zip(d.chunks_exact_mut(8)) {
            let n = ch * p.k * p.k;
            let Some(r) = part_dot2x2(one_part, w0, w1, pair, o, n) else {
                return false;
            };
            // `r` is `[w0 . a, w1 . a, w0 . b, w1 . b]`; pixel `a`'s channels first, then `b`'s.
            let [Ok(a0), Ok(a1), Ok(b0), Ok(b1)] = r.map(i32::try_from) else {
                return false;
            };
            if let Some([x0, x1]) = dp.get_mut(2 * j..2 * j + 2) {
                (*x0, *x1) = (a0, a1);
            }
            if let Some([x0, x1]) = dp.get_mut(4 + 2 * j..4 + 2 * j + 2) {
                (*x0, *x1) = (b0, b1);
            }
            o += n;
        }
    }
    true
}

/// The portable epilogue (`finish_short` of the summed `requantize_i32`s) of one pixel's four
/// channels from the block's dot products (`STRIDE` values per part, the four at `off`; a
/// constant, so that the part loop needs no division). Channel by channel over the parts, each
/// contribution by `requantize_i32_halved` (the same integer with one 64-bit shift; every shift
/// is in `8..=62`, `Layer::of`, so `mult_raw` needs no clamp). 160x120: 25.8 M instructions here
/// with the portable formula and the generic store, mostly the saturated lanes of one 64-channel
/// three-part layer; 20.5 M now.
fn recompute<const STRIDE: usize>(p: &ConvParams<'_>, d: &Dots, off: usize, m: &[u8], b: &[u8], out: &mut OutRow<'_>, at: usize) {
    let np = p.parts.len();
    let mut sums = [0i64; 4];
    for (i, (s, ml)) in sums.iter_mut().zip(m.chunks_exact((8 * np).max(1))).enumerate() {
        for (me, acc) in ml.chunks_exact(8).zip(d.iter().skip(off + i).step_by(STRIDE.max(1))) {
            *s += requantize_i32_halved(*acc, mult_raw(me));
        }
    }
    // `finish_short`'s rounding, then the value clamped to i32 (every activation and output
    // type saturates further, so the clamp changes no output), the activation and the store in
    // i32 with the output type matched once.
    let v: [i32; 4] = core::array::from_fn(|i| {
        let bias = bias_at(b.get(8 * i..).unwrap_or_default());
        let r = sums.get(i).copied().unwrap_or_default() + bias + (1 << (super::EXTRA_BITS - 1));
        (r >> super::EXTRA_BITS).clamp(i64::from(i32::MIN), i64::from(i32::MAX)) as i32
    });
    let post = p.post;
    #[inline(always)]
    fn store<O>(r: &mut [O], at: usize, v: [i32; 4], post: PostOp, sat: impl Fn(i32) -> O) {
        if let Some(o) = r.get_mut(at..).and_then(|r| r.first_chunk_mut::<4>()) {
            for (o, v) in o.iter_mut().zip(v) {
                *o = sat(activate32(post, v));
            }
        }
    }
    match out {
        OutRow::U8(r) => store(r, at, v, post, |x| x.clamp(0, 255) as u8),
        OutRow::I8(r) => store(r, at, v, post, |x| x.clamp(-128, 127) as i8),
        OutRow::I16(r) => store(r, at, v, post, |x| x.clamp(-32768, 32767) as i16),
    }
}

/// `conv::activate` on an i32 (the tables saturate to i16 first, as there).
#[inline(always)]
fn activate32(post: PostOp, v: i32) -> i32 {
    match post {
        PostOp::None => v,
        PostOp::Relu => v.max(0),
        PostOp::Sigmoid => i32::from(lut::sigmoid_q12(v.clamp(-32768, 32767) as i16)),
        PostOp::Tanh => i32::from(lut::tanh_q12(v.clamp(-32768, 32767) as i16)),
    }
}
