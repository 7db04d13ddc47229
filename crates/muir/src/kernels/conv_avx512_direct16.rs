//! A convolution row of i16 activations with the output channels along the vector (host, x86-64,
//! AVX-512 VNNI): the refinement's layers (the ConvGRUs' gates over up to six input parts, the
//! heads, the motion encoder), as [`super::direct`] does for the trunk's u8 rows. One pixel's pair
//! of input channels is broadcast against 16 output channels' weight pairs (`vpdpwssd`; the
//! weights re-laid per part, `[32 channels][tap][pair][channel]`, once per engine frame, as i8
//! and widened to i16 pairs in the loop: half the bytes, so that the three gates of a ConvGRU
//! stay in the L2 cache from one row to the next), 8 pixels x 32 channels in registers, and the
//! rows are read where they lie, in their `[x][c]` order: no transposition of the inputs or the
//! outputs ([`super`]'s layout has pixels along the vector and transposes both), and each part's
//! requantisation, the bias and the activation run on vectors of channels. A block whose columns reach past the row's ends
//! (the first and the last) reads a copy with the padding's zeros instead. A part of an odd
//! channel count reads, for its last pair, the next pixel's first value, against a zero weight.
//!
//! Exactness: a part whose every output channel has `sum |w| <= 65535` (the shipped layers:
//! [`Layer::narrow`]) has all its sums, partial ones included, within `2^15 * 65535 < 2^31`: its
//! i32 lanes hold them whole. Otherwise a lane adds at most `2 * 2^15 * 2^7 = 2^23` a pair; the
//! pairs of whole taps, at most [`super::I16_CHUNK`] of them (`255 * 2^23 < 2^31`), sum in i32
//! lanes, which are then added into i64 sums: each part's sum is the exact integer. Where it fits in i32 (every multiplier
//! short, [`super::super::short_ok`]) the contribution is `(sum m + 2^(s-1)) >> s`, the
//! portable path's integer; the contributions, the bias (`<` [`super::super::SHORT_MAX_BIAS`]) and
//! the rounding half sum far inside i64, so plain adds are its saturating ones; then `>> 8`, the
//! activation (ReLU, or the sigmoid / tanh table read as [`super::finish_channel`] reads it) and
//! the output type's saturation. A block where some part's sum does not fit in i32 is computed
//! again by the portable formula, pixel by pixel ([`scalar_block`]). Layers outside these bounds
//! take [`super`]'s path.
//!
//! A part the same all frame ([`super::with_constant_part`], the gates' context) has its exact
//! sums kept per output row for the frame, `[x][c]`, reused where its input rows equal a copy
//! kept with them.

use core::arch::x86_64::*;
use core::cell::RefCell;

use super::super::super::pool::{self, Shared, scratch};
use super::super::{ConvParams, EXTRA_BITS, MAX_K, PartRows, SHORT_MAX_BIAS, channel_at, column, gather, mult_at, short_ok};
use super::{Elem, I16_CHUNK, Memo, OutRow, PARALLEL_MACS, cast, out_ptr, out_range};
use crate::model::graph::{MAX_PARTS, PostOp};

/// Output pixels a register block holds.
const PX: usize = 8;
/// Most input channels of a part: a tap's pairs fit in one i32 chunk.
const MAX_CH: usize = 2 * I16_CHUNK;

/// A layer as [`block`] reads it ([`relay`]).
struct Layer {
    /// The layer: its weight table's address and length, output channels, kernel size, stride,
    /// parts.
    key: (usize, usize, usize, usize, usize, [usize; MAX_PARTS]),
    /// This frame's copy.
    valid: bool,
    /// Every (channel, part) multiplier short and every bias below the short bound: the layer
    /// takes this path.
    short: bool,
    /// The weights: per part, blocks of 32 output channels, each `[tap][pair][channel]`
    /// ([`weight_at`] counts slots), a slot the pair's two i8 (widened to the i16 pair
    /// `vpdpwssd` reads in the loop; a pair past the part's channels and the channels past `cout`
    /// zero).
    w: Vec<i8>,
    /// Where each part's weights start in `w`.
    at: [usize; MAX_PARTS],
    /// Per part: every output channel's `sum |w|` is at most 65535, so every sum of the part
    /// (`|x| <= 2^15`), and every partial sum, lies within `32768 * 65535 < 2^31`: the i32
    /// lanes hold it whole, with no chunks and no check.
    narrow: [bool; MAX_PARTS],
    /// The epilogue's operands, planes of `coutp`: per part its multiplier, shift and rounding
    /// half, then the bias.
    ep: Vec<i64>,
    /// Kept sums of the constant part, per output row (a narrow part's: exact in i32).
    memo: Vec<Memo<i32>>,
}

impl Layer {
    const fn new() -> Self {
        Layer { key: (0, 0, 0, 0, 0, [0; MAX_PARTS]), valid: false, short: false, w: Vec::new(), at: [0; MAX_PARTS], narrow: [false; MAX_PARTS], ep: Vec::new(), memo: Vec::new() }
    }
    fn invalidate(&mut self) {
        self.valid = false;
        self.memo.iter_mut().for_each(|m| m.valid = false);
    }
}

std::thread_local! {
    /// This thread's relaid layers (kept while a [`super::FrameScope`] lives).
    static LAYERS: RefCell<Vec<Layer>> = const { RefCell::new(Vec::new()) };
    /// A block's input columns with the padding's zeros (the row's first and last blocks).
    static EDGE: RefCell<Vec<i16>> = const { RefCell::new(Vec::new()) };
    /// A pixel's patch for [`scalar_block`].
    static PATCH: RefCell<Vec<i16>> = const { RefCell::new(Vec::new()) };
}

/// Drops this thread's relaid layers and kept sums from use (a frame starts or ends).
pub(super) fn invalidate() {
    LAYERS.with_borrow_mut(|l| l.iter_mut().for_each(Layer::invalidate));
}

/// How a part's kernel row is read: `(runs, pairs)`, `runs` runs of values a row, each `pairs`
/// i16 pairs. A part of an odd channel count up to 7 (the image's 3, a disparity's 1) reads each
/// kernel row's `k ch` values, which lie one after another in the `[x][c]` row, as one run (its
/// last pair reads the next value against a zero weight): `ceil(k ch / 2)` pairs instead of `k
/// ceil(ch / 2)`, 77 instead of 98 products a pixel for the 7x7 stem. Other parts read each tap's
/// `ch` values as a run.
fn runs(k: usize, ch: usize) -> (usize, usize) {
    if k > 1 && ch % 2 == 1 && ch <= 7 { (1, (k * ch).div_ceil(2)) } else { (k, ch.div_ceil(2)) }
}

/// A part's weight slots (one i8 pair each) for `cp` output channels.
fn part_slots(k: usize, ch: usize, cp: usize) -> usize {
    let (rpr, g_n) = runs(k, ch);
    k * rpr * g_n * cp
}

/// Output channels padded to whole vectors.
fn coutp(cout: usize) -> usize {
    cout.next_multiple_of(16)
}

/// Where a part's weight pair `i` (of `n`: tap-major, `[tap][pair]`) of output channel `c` lies
/// among its `n coutp` relaid ones: blocks of 32 channels (the last one 16 where `coutp` is odd
/// in sixteens), each `[i][channel]`, so that [`block`] reads one block's weights in order.
fn weight_at(c: usize, i: usize, n: usize, cp: usize) -> usize {
    let b = c / 32 * 32;
    b * n + i * (cp - b).min(32) + (c - b)
}

/// Whether the row may take this path (the multipliers are checked with the relaid layer): i16
/// activations, 1 to [`MAX_PARTS`] parts of 1 to [`MAX_CH`] channels, an odd kernel up to
/// [`MAX_K`], stride 1 or 2, at least 16 output channels (fewer would mostly compute padding), and
/// tables as long as the layer.
fn eligible<T: Elem>(p: &ConvParams<'_>) -> bool {
    cast::<T, i16>(&[]).is_some()
        && !p.parts.is_empty()
        && p.parts.len() <= MAX_PARTS
        && p.parts.iter().all(|&c| (1..=MAX_CH).contains(&c))
        && p.k % 2 == 1
        && p.k <= MAX_K
        && (p.stride == 1 || p.stride == 2)
        && p.cout >= 16
        && p.weights.len() >= p.cout * p.patch_len()
}

/// Layer `p` as [`block`] reads it, into `l` (see [`Layer`]).
fn relay(p: &ConvParams<'_>, l: &mut Layer) {
    let (cout, cp, k, np, kl) = (p.cout, coutp(p.cout), p.k, p.parts.len(), p.patch_len());
    let mut len = 0;
    for (at, &ch) in l.at.iter_mut().zip(p.parts) {
        *at = len;
        len += part_slots(k, ch, cp);
    }
    let w = scratch(&mut l.w, 2 * len);
    w.fill(0);
    let mut off = 0;
    for ((&at, &ch), narrow) in l.at.iter().zip(p.parts).zip(l.narrow.iter_mut()) {
        let (rpr, g_n) = runs(k, ch);
        let run_len = k * ch / rpr;
        *narrow = true;
        for c in 0..cout {
            let src = p.weights.get(c * kl + off..c * kl + off + k * k * ch).unwrap_or_default();
            *narrow &= src.iter().map(|w| w.unsigned_abs() as u64).sum::<u64>() <= 65535;
            // Run `t` (`[ky][run]` order: the blob's `[ky][kx][c]` cut into runs of `run_len`).
            for (t, run) in src.chunks_exact(run_len.max(1)).enumerate() {
                for (g, pair) in run.chunks(2).enumerate() {
                    let (a, b) = (pair.first().copied().unwrap_or(0), pair.get(1).copied().unwrap_or(0));
                    let slot = at + weight_at(c, t * g_n + g, k * rpr * g_n, cp);
                    if let Some(d) = w.get_mut(2 * slot..2 * slot + 2) {
                        d.copy_from_slice(&[a, b]);
                    }
                }
            }
        }
        off += k * k * ch;
    }
    let ep = scratch(&mut l.ep, (3 * np + 1) * cp);
    // Padding channels: a harmless multiplier (their results are never stored).
    ep.fill(0);
    let mut short = true;
    for c in 0..cp {
        for part in 0..np {
            let m = if c < cout { mult_at(p.mult.0.get(8 * (c * np + part)..).unwrap_or_default()) } else { crate::arith::Multiplier { m: 0, shift: 8 } };
            short &= short_ok(m);
            let half = 1i64.wrapping_shl(u32::from(m.shift.max(1)) - 1);
            for (j, v) in [m.m as i64, m.shift as i64, half].into_iter().enumerate() {
                if let Some(d) = ep.get_mut((3 * part + j) * cp + c) {
                    *d = v;
                }
            }
        }
        let b = if c < cout { p.bias.get(c) } else { 0 };
        short &= b.unsigned_abs() < SHORT_MAX_BIAS;
        if let Some(d) = ep.get_mut(3 * np * cp + c) {
            *d = b;
        }
    }
    l.short = short;
}

/// [`super::conv_row`] by this path, or `false` (nothing written) where the layer is not one it
/// takes or no [`super::FrameScope`] lives. `constant`: the part whose sums are kept for the
/// frame, and the output row.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; the layer passed [`super::conv_row`]'s checks.
pub(super) unsafe fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>, constant: Option<(usize, usize)>) -> bool {
    // Outside an engine frame the layer would be re-laid on every call (the portable path's
    // re-layout costs less there).
    if !eligible::<T>(p) || !super::FRAME_ON.with(|on| on.get()) {
        return false;
    }
    let mut rows = [PartRows { rows: [None; MAX_K] }; MAX_PARTS];
    for (d, s) in rows.iter_mut().zip(inputs) {
        for (d, s) in d.rows.iter_mut().zip(s.rows) {
            *d = s.and_then(|r| cast::<T, i16>(r));
        }
    }
    let rows = rows.get(..p.parts.len()).unwrap_or_default();
    let w_out = p.out_width(w_in);
    let key = (p.weights.as_ptr() as usize, p.weights.len(), p.cout, p.k, p.stride, {
        let mut parts = [0; MAX_PARTS];
        parts.iter_mut().zip(p.parts).for_each(|(d, s)| *d = *s);
        parts
    });
    LAYERS.with_borrow_mut(|layers| {
        let i = match layers.iter().position(|l| l.key == key) {
            Some(i) => i,
            None => super::free_slot(layers, |l| l.valid, Layer::new),
        };
        let Some(l) = layers.get_mut(i) else { return false };
        if !(l.valid && l.key == key) {
            l.invalidate();
            l.key = key;
            relay(p, l);
            l.valid = true;
        }
        if !l.short {
            return false;
        }
        // The constant part's kept sums for the row: this frame's where its rows are as
        // kept, else a free entry (of an earlier frame, or new) to fill.
        let cp = coutp(p.cout);
        // (A wide constant part, which no shipped layer has, is computed in every call.)
        let memo = constant.filter(|&(part, _)| l.narrow.get(part) == Some(&true)).and_then(|(part, row)| {
            let (i, hit) = Memo::entry(&mut l.memo, part, row, w_out, rows.get(part)?.rows.get(..p.k)?, w_out * cp)?;
            Some((i, hit, part))
        });
        let (w, at, ep) = (&l.w, l.at, &l.ep);
        let kept = match memo {
            Some((i, hit, part)) => l.memo.get_mut(i).map(|m| (Shared(m.sums.as_mut_ptr()), hit, part)),
            None => None,
        };
        // SAFETY: the caller's CPU features; `l` is the layer relaid, its memo entry holds
        // `w_out coutp` sums.
        unsafe { row(p, rows, w_in, w_out, w, at, l.narrow, ep, kept, out) };
        if let Some((i, false, _)) = memo
            && let Some(m) = l.memo.get_mut(i)
        {
            m.valid = true; // computed by every block of the row
        }
        true
    })
}

/// The row: blocks of [`PX`] pixels (split over the pool when the layer is large and the pool
/// free), every channel.
///
/// # Safety
/// As [`conv_row`]; `w`, `at` and `ep` are the layer relaid ([`relay`]); `memo`, where given,
/// holds `w_out coutp` sums (`hit`: this frame's of the row, else to be written).
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn row(p: &ConvParams<'_>, rows: &[PartRows<'_, i16>], w_in: usize, w_out: usize, w: &[i8], at: [usize; MAX_PARTS], narrow: [bool; MAX_PARTS], ep: &[i64], memo: Option<(Shared<i32>, bool, usize)>, out: &mut OutRow<'_>) {
    let (cout, cp, k, np) = (p.cout, coutp(p.cout), p.k, p.parts.len());
    let (lo, hi) = out_range(out);
    let signed = matches!(out, OutRow::I8(_));
    let (op, size) = out_ptr(out);
    let wlen: usize = p.parts.iter().map(|&ch| part_slots(k, ch, cp)).sum();
    if w.len() < 2 * wlen || ep.len() < (3 * np + 1) * cp {
        return;
    }
    let cx = Ctx { p, rows, w_in, w, at, ep, narrow, memo, lo, hi, op, size, signed };
    let blocks = w_out.div_ceil(PX);
    let big = w_out * cout * p.patch_len() >= PARALLEL_MACS;
    let ranges = super::block_ranges(big, blocks);
    let task = |t: usize| {
        let (b0, b1) = (t * blocks / ranges, (t + 1) * blocks / ranges);
        let (x_end, mut x) = ((b1 * PX).min(w_out), b0 * PX);
        EDGE.with_borrow_mut(|edge| {
            // Blocks of 8 pixels, then the row's tail in blocks of 4, 2 and 1 (no pixel past the
            // row computed).
            while x < x_end {
                let n = x_end - x;
                // SAFETY: pixels `x .. x + P` of the row and of the memo, this task's only; the
                // rest as `row`'s contract.
                unsafe {
                    x += match n {
                        8.. => pixel_block::<8>(&cx, x, edge),
                        4..=7 => pixel_block::<4>(&cx, x, edge),
                        2 | 3 => pixel_block::<2>(&cx, x, edge),
                        _ => pixel_block::<1>(&cx, x, edge),
                    };
                }
            }
        });
    };
    if ranges > 1 {
        pool::run(ranges, &task);
    } else {
        task(0);
    }
}

/// What every block of a row shares.
struct Ctx<'a, 'p> {
    p: &'a ConvParams<'p>,
    rows: &'a [PartRows<'a, i16>],
    w_in: usize,
    w: &'a [i8],
    at: [usize; MAX_PARTS],
    ep: &'a [i64],
    /// Per part: every sum fits in i32 ([`Layer::narrow`]).
    narrow: [bool; MAX_PARTS],
    /// The constant part's kept sums (`[x][coutp]`, i32: the part is narrow), whether they hold
    /// this row's, the part.
    memo: Option<(Shared<i32>, bool, usize)>,
    /// The output type's range, and the output row (`size` bytes a value; i8 where `signed`).
    lo: i32,
    hi: i32,
    op: Shared<u8>,
    size: usize,
    signed: bool,
}

impl Ctx<'_, '_> {
    /// Pixel `x`'s `cout` outputs, as an [`OutRow`] of the row's type.
    ///
    /// # Safety
    /// `x < w_out`; no one else touches those outputs while the result lives.
    unsafe fn pixel_out(&self, x: usize) -> OutRow<'_> {
        let n = self.p.cout;
        let d = self.op.0.wrapping_add(x * n * self.size);
        // SAFETY: `op` is the output row of `w_out cout` values of its type (`row`), aligned for
        // it; the values are the caller's (the contract).
        unsafe {
            match (self.size, self.signed) {
                (2, _) => OutRow::I16(core::slice::from_raw_parts_mut(d.cast(), n)),
                (_, true) => OutRow::I8(core::slice::from_raw_parts_mut(d.cast(), n)),
                _ => OutRow::U8(core::slice::from_raw_parts_mut(d, n)),
            }
        }
    }
}

// SAFETY: the memo and output pointers are written only at the pixels of one task (see
// [`pixel_block`]'s contract), the rest is read-only.
unsafe impl Sync for Ctx<'_, '_> {}

/// Output pixels `x0 .. x0 + P` (`P <= PX`), every channel: where each part's rows start for
/// the block (in the rows themselves, or in `edge` with the padding's zeros), then the channel
/// blocks. Returns `P`.
///
/// # Safety
/// As [`row`]; pixels `x0 .. x0 + P` of the output row and of the memo are the caller's.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn pixel_block<const P: usize>(cx: &Ctx<'_, '_>, x0: usize, edge: &mut Vec<i16>) -> usize {
    let p = cx.p;
    let (k, stride, pad) = (p.k, p.stride, p.k / 2);
    // Input columns `c_lo ..= c_hi` feed the block's `P` pixels.
    let c_lo = (stride * x0) as isize - pad as isize;
    let span = (P - 1) * stride + k;
    let c_hi = c_lo + span as isize - 1;
    // Per part and kernel row, where column `c_lo` starts (null: a padding row).
    let mut src = [[core::ptr::null::<i16>(); MAX_K]; MAX_PARTS];
    let inside = |r: &[i16], ch: usize| c_lo >= 0 && (c_hi as usize) < cx.w_in && (c_hi as usize + 1) * ch + ch % 2 <= r.len();
    let all_inside = cx.rows.iter().zip(p.parts).all(|(r, &ch)| r.rows.iter().take(k).flatten().all(|r| inside(r, ch)));
    if all_inside {
        for ((s, r), &ch) in src.iter_mut().zip(cx.rows).zip(p.parts) {
            for (s, r) in s.iter_mut().zip(r.rows).take(k) {
                if let Some(r) = r {
                    *s = r.as_ptr().wrapping_add(c_lo as usize * ch);
                }
            }
        }
    } else {
        // A copy of the columns, zeros where the portable path reads padding (`column`). Only
        // the present rows' columns are written (each once: a copy or zeros), not the whole
        // buffer zeroed first: the 1/8 ConvGRU's gates copy 23 KB a block, two blocks a row.
        let need: usize = p.parts.iter().map(|ch| k * (span * ch + 2)).sum();
        let buf = scratch(edge, need);
        let mut o = 0;
        for ((s, r), &ch) in src.iter_mut().zip(cx.rows).zip(p.parts) {
            for (s, r) in s.iter_mut().zip(r.rows).take(k) {
                let n = span * ch + 2;
                if let (Some(r), Some(dst)) = (r, buf.get_mut(o..o + n)) {
                    let (cols, tail) = dst.split_at_mut(span * ch);
                    // Columns `first .. last` of the span lie inside the row: one run, the
                    // padding's zeros on either side (not a copy call per column).
                    let first = (-c_lo).clamp(0, span as isize) as usize;
                    let last = (cx.w_in as isize - c_lo).clamp(first as isize, span as isize) as usize;
                    let start = (c_lo + first as isize) as usize * ch;
                    let (lead, rest) = cols.split_at_mut(first * ch);
                    let (mid, trail) = rest.split_at_mut((last - first) * ch);
                    match r.get(start..start + mid.len()) {
                        Some(src) => {
                            lead.fill(0);
                            mid.copy_from_slice(src);
                            trail.fill(0);
                        }
                        // A row shorter than `w_in` columns (never in the engine): column by
                        // column, as the portable path reads it.
                        None => {
                            for (j, d) in cols.chunks_exact_mut(ch).enumerate() {
                                match column(Some(r), c_lo + j as isize, cx.w_in, ch) {
                                    Some(c) => d.copy_from_slice(c),
                                    None => d.fill(0),
                                }
                            }
                        }
                    }
                    tail.fill(0);
                    *s = dst.as_ptr();
                }
                o += n;
            }
        }
    }
    let cp = coutp(p.cout);
    let mut cb = 0;
    while cb < cp {
        let nv = if cb + 32 <= cp { 2 } else { 1 };
        // SAFETY: `src` holds `span` columns of each present row (plus a value past the last);
        // the rest as this function's contract.
        let wild = unsafe { if nv == 2 { block::<2, P>(cx, &src, x0, cb) } else { block::<1, P>(cx, &src, x0, cb) } };
        if wild {
            // SAFETY: as above.
            unsafe { scalar_block(cx, x0, P, cb, cb + 16 * nv) };
        }
        cb += 16 * nv;
    }
    P
}

/// Output pixels `x0 .. x0 + P`, channels `cb .. cb + 16 NV`: each part's exact sums (or the
/// kept ones) and their requantised contributions, the bias, the activation, the output.
/// Returns whether a part's sum did not fit in i32 (nothing written then: the caller takes
/// [`scalar_block`]).
///
/// # Safety
/// As [`pixel_block`]; `src[part][ky]` points at `(P - 1) stride + k` columns of the part's
/// `ch` values (and one more value) for each present kernel row; `cb + 16 NV <= coutp`; `P <= PX`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
unsafe fn block<const NV: usize, const P: usize>(cx: &Ctx<'_, '_>, src: &[[*const i16; MAX_K]; MAX_PARTS], x0: usize, cb: usize) -> bool {
    let p = cx.p;
    let (k, stride, cp) = (p.k, p.stride, coutp(p.cout));
    // The contributions' sums, 8 i64 a vector: pixel `q`, channels `cb + 8 j ..`.
    let mut sum = [[_mm512_setzero_si512(); 4]; P];
    let mut wild = false;
    for (part, &ch) in p.parts.iter().enumerate() {
        let (rpr, g_n) = runs(k, ch);
        // Every sum of the part fits in i32 (`relay`): one chunk, no check.
        let narrow = cx.narrow.get(part).copied().unwrap_or(false);
        let kept = cx.memo.as_ref().filter(|m| m.2 == part).map(|m| (m.0.0, m.1));
        // The part's multipliers, shifts and rounding halves for channels `cb + 8 j ..`.
        let mut ops = [(_mm512_setzero_si512(), _mm512_setzero_si512(), _mm512_setzero_si512()); 4];
        for (j, op) in ops.iter_mut().enumerate().take(2 * NV) {
            let ep = cx.ep.as_ptr().wrapping_add(cb + 8 * j);
            // SAFETY: planes `3 part ..= 3 part + 2` of `coutp`, channels `cb + 8 j .. + 8 <=
            // coutp` (`row`'s check of `ep`).
            unsafe {
                let ld = |plane: usize| _mm512_loadu_si512(ep.add(plane * cp).cast());
                *op = (ld(3 * part), ld(3 * part + 1), ld(3 * part + 2));
            }
        }
        // The contribution `(e m + 2^(s-1)) >> s` of 8 exact sums `e` (in i32) of channel
        // vector `j`, into `sum[j]`. (A macro, not a closure: the intrinsics stay inline under
        // this function's target features.)
        macro_rules! contribute {
            ($sum:expr, $e:expr, $j:expr) => {{
                if let (Some(sum), Some(&(m, s, h))) = ($sum.get_mut($j), ops.get($j)) {
                    let r = _mm512_srav_epi64(_mm512_add_epi64(_mm512_mul_epi32($e, m), h), s);
                    *sum = if part == 0 { r } else { _mm512_add_epi64(*sum, r) };
                }
            }};
        }
        if let Some((m, true)) = kept {
            for (q, sum) in sum.iter_mut().enumerate() {
                for v in 0..NV {
                    // SAFETY: the memo holds `w_out coutp` sums; pixel `x0 + q < w_out`.
                    let a = unsafe { _mm512_loadu_si512(m.add((x0 + q) * cp + cb + 16 * v).cast()) };
                    contribute!(sum, _mm512_cvtepi32_epi64(_mm512_castsi512_si256(a)), 2 * v);
                    contribute!(sum, _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(a)), 2 * v + 1);
                }
            }
            continue;
        }
        let mut acc = [[_mm512_setzero_si512(); NV]; P];
        // A wide part's exact sums (chunks of whole taps), 8 i64 a vector.
        let mut e = [[_mm512_setzero_si512(); 4]; P];
        let mut used = 0;
        let mut flushed = false;
        let wp = cx.w.as_ptr().wrapping_add(2 * cx.at.get(part).copied().unwrap_or(0));
        let rows = src.get(part).copied().unwrap_or([core::ptr::null(); MAX_K]);
        for (ky, &r) in rows.iter().enumerate().take(k) {
            if r.is_null() {
                continue;
            }
            for run in 0..rpr {
                if !narrow && used + g_n > I16_CHUNK {
                    // The chunk's i32 sums into the exact ones.
                    for (e, acc) in e.iter_mut().zip(acc.iter_mut()) {
                        for (v, a) in acc.iter_mut().enumerate() {
                            widen_add(e, v, *a);
                            *a = _mm512_setzero_si512();
                        }
                    }
                    used = 0;
                    flushed = true;
                }
                // SAFETY: run `run` of pixel `q` is columns `q stride + run .. q stride + run +
                // k / rpr` (each `ch` values) of the `span` (and the value after the last pair);
                // weights of run `ky rpr + run`, pair `g < g_n`, channels `cb .. cb + 16 NV <=
                // coutp` inside the part's (`relay`).
                unsafe {
                    let xp = r.add(run * ch);
                    let wt = wp.add(2 * weight_at(cb, (ky * rpr + run) * g_n, k * rpr * g_n, cp));
                    super::tap_products::<false, NV, P>(&mut acc, xp.cast(), 2 * stride * ch, wt.cast(), (cp - cb).min(32), g_n);
                }
                used += g_n;
            }
        }
        let store = match kept {
            Some((m, false)) => m,
            _ => core::ptr::null_mut(),
        };
        for (q, ((sum, e), acc)) in sum.iter_mut().zip(e.iter_mut()).zip(acc).enumerate() {
            for (v, a) in acc.into_iter().enumerate() {
                // The lanes as i64 (added to the earlier chunks' sums, if any).
                let (mut e0, mut e1) = (_mm512_cvtepi32_epi64(_mm512_castsi512_si256(a)), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(a)));
                if flushed {
                    e0 = _mm512_add_epi64(e0, e.get(2 * v).copied().unwrap_or(_mm512_setzero_si512()));
                    e1 = _mm512_add_epi64(e1, e.get(2 * v + 1).copied().unwrap_or(_mm512_setzero_si512()));
                    for e in [e0, e1] {
                        wild |= _mm512_cmpeq_epi64_mask(e, _mm512_cvtepi32_epi64(_mm512_cvtepi64_epi32(e))) != 0xFF;
                    }
                }
                if !store.is_null() {
                    // SAFETY: as the memo's loads above (a kept part is narrow: `a` is its sums).
                    unsafe { _mm512_storeu_si512(store.add((x0 + q) * cp + cb + 16 * v).cast(), a) };
                }
                contribute!(sum, e0, 2 * v);
                contribute!(sum, e1, 2 * v + 1);
            }
        }
    }
    if wild {
        return true;
    }
    // Bias, rounding `>> EXTRA_BITS`, the activation, the output type's saturation.
    let post = p.post;
    let table = match post {
        PostOp::None | PostOp::Relu => None,
        PostOp::Sigmoid => Some(crate::arith::lut::sigmoid_table().as_ptr()),
        PostOp::Tanh => Some(crate::arith::lut::tanh_table().as_ptr()),
    };
    let lo = if post == PostOp::Relu { cx.lo.max(0) } else { cx.lo };
    let (l, h) = (_mm512_set1_epi64(lo as i64), _mm512_set1_epi64(cx.hi as i64));
    let round = _mm512_set1_epi64(1 << (EXTRA_BITS - 1));
    let nparts = p.parts.len();
    for j in 0..2 * NV {
        let c = cb + 8 * j;
        if c >= p.cout {
            break;
        }
        let lanes = (p.cout - c).min(8);
        let mask: __mmask8 = if lanes == 8 { 0xFF } else { (1u8 << lanes) - 1 };
        // SAFETY: the bias plane, channels `c .. c + 8 <= coutp`.
        let b = unsafe { _mm512_add_epi64(_mm512_loadu_si512(cx.ep.as_ptr().add(3 * nparts * cp + c).cast()), round) };
        for (q, sum) in sum.iter().enumerate() {
            let v = _mm512_srai_epi64::<{ EXTRA_BITS }>(_mm512_add_epi64(sum.get(j).copied().unwrap_or(_mm512_setzero_si512()), b));
            let r = match table {
                None => v,
                // SAFETY: a table of 1025 i16 (`super::table8`'s contract).
                Some(t) => _mm512_cvtepi32_epi64(unsafe { super::table8(t, v) }),
            };
            let r = _mm512_min_epi64(_mm512_max_epi64(r, l), h);
            // SAFETY: channels `c .. c + lanes` of pixel `x0 + q` (the contract).
            unsafe {
                let d = cx.op.0.add(((x0 + q) * p.cout + c) * cx.size);
                if cx.size == 2 {
                    _mm512_mask_cvtepi64_storeu_epi16(d.cast(), mask, r);
                } else {
                    _mm512_mask_cvtepi64_storeu_epi8(d.cast(), mask, r);
                }
            }
        }
    }
    false
}

/// Adds the 16 i32 lanes of `a` into the i64 vectors `2 v` and `2 v + 1` of `e`.
#[target_feature(enable = "avx512f")]
#[inline]
fn widen_add(e: &mut [__m512i; 4], v: usize, a: __m512i) {
    if let Some(e) = e.get_mut(2 * v) {
        *e = _mm512_add_epi64(*e, _mm512_cvtepi32_epi64(_mm512_castsi512_si256(a)));
    }
    if let Some(e) = e.get_mut(2 * v + 1) {
        *e = _mm512_add_epi64(*e, _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(a)));
    }
}

/// Pixels `x0 .. x0 + np`, channels `c0 .. c1` (those below `cout`) by the portable path's own
/// pieces (each pixel's patch gathered, each channel's value computed): the blocks where a
/// part's sum left i32.
///
/// # Safety
/// As [`block`].
unsafe fn scalar_block(cx: &Ctx<'_, '_>, x0: usize, np: usize, c0: usize, c1: usize) {
    let p = cx.p;
    PATCH.with_borrow_mut(|patch| {
        let patch = scratch(patch, p.patch_len());
        for x in x0..x0 + np {
            gather(p, cx.rows, cx.w_in, x, patch);
            // SAFETY: pixel `x`'s outputs are the caller's (the contract).
            let mut out = unsafe { cx.pixel_out(x) };
            for c in c0..c1.min(p.cout) {
                channel_at(p, patch, c, &mut out, 0);
            }
        }
    });
}
