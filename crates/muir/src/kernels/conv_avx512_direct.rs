//! A convolution row with the output channels along the vector (host, x86-64, AVX-512 VNNI):
//! the 3x3 layers (stride 1 or 2) of one u8 input part, the trunk's and the heads' bulk, and the
//! 1x1 ones (the trunk's strided shortcuts, the MGA keys and queries). One pixel's
//! group of 4 input channels is broadcast against 16 output channels' weights (re-laid
//! `[tap][group][cout]` once per engine frame), 8 pixels x 32 channels in registers, and the row
//! is read and written in its own `[x][c]` order: neither the input rows nor the outputs are
//! transposed ([`super`] lays pixels along the vector and transposes both), and the epilogue runs
//! on vectors of channels. `docs/experiments/host-direct-conv` measured the layout alone.
//!
//! Exactness: a lane adds at most `k^2 (c / 4)` groups of `4 * 255 * 128 < 2^17` (`c < 3640`: at
//! most [`super::U8_CHUNK`] groups, `< 2^30`), the exact i32 sum. The epilogue is the portable
//! path's formula where it is short ([`super::super::short_ok`], `|bias| <`
//! [`super::super::SHORT_MAX_BIAS`], no table): `(sum m + 2^(s-1)) >> s`, `+ bias + 2^7 >> 8`,
//! the ReLU, the output type's saturation. Layers outside these bounds take [`super`]'s path.

use core::arch::x86_64::*;
use core::cell::RefCell;

use super::super::super::pool::{self, Shared, scratch};
use super::super::{ConvParams, EXTRA_BITS, PartRows, SHORT_MAX_BIAS, short_ok};
use super::{Elem, OutRow, PARALLEL_MACS, cast, out_ptr, out_range};
use crate::model::graph::PostOp;

/// Output pixels a register block holds.
const PX: usize = 8;
/// Columns of a padded row (a zero column in front): every column a block of [`PX`] pixels
/// reads, zeros past the row's own.
fn padded_cols(w_in: usize, w_out: usize, stride: usize) -> usize {
    (w_in + 1).max(stride * (w_out + PX) + 3)
}

/// A layer as [`block`] reads it ([`relay`]).
struct Relaid {
    /// The layer: its weight table's address and length, channels in and out.
    key: (usize, usize, usize, usize),
    /// This frame's copy.
    valid: bool,
    /// The weights, `[tap][group][cout]`, 4 weights an i32.
    w: Vec<i32>,
    /// The epilogue's operands, four planes of `cout`: multiplier, shift, rounding half, bias.
    ep: Vec<i64>,
}

std::thread_local! {
    /// This thread's relaid layers (kept while a [`super::FrameScope`] lives).
    static LAYERS: RefCell<Vec<Relaid>> = const { RefCell::new(Vec::new()) };
    /// The relaid layer outside a frame, and the padded input rows.
    static SCRATCH: RefCell<(Relaid, [Vec<u8>; 3])> = const { RefCell::new((Relaid { key: (0, 0, 0, 0), valid: false, w: Vec::new(), ep: Vec::new() }, [Vec::new(), Vec::new(), Vec::new()])) };
}

/// Drops this thread's relaid layers from use (a frame starts or ends).
pub(super) fn invalidate() {
    LAYERS.with_borrow_mut(|l| l.iter_mut().for_each(|r| r.valid = false));
}

/// Whether the row takes this path: one u8 part of whole groups, 3x3 or 1x1, stride 1 or 2,
/// output channels in sixteens, no activation table, and the short epilogue for every channel.
fn eligible<T: Elem>(p: &ConvParams<'_>) -> bool {
    let Some(&ch) = p.parts.first() else { return false };
    cast::<T, u8>(&[]).is_some()
        && p.parts.len() == 1
        && (p.k == 3 || p.k == 1)
        && (p.stride == 1 || p.stride == 2)
        && ch > 0
        && ch.is_multiple_of(4)
        && p.k * p.k * ch / 4 <= super::U8_CHUNK
        && p.cout > 0
        && p.cout.is_multiple_of(16)
        && matches!(p.post, PostOp::None | PostOp::Relu)
        && p.weights.len() >= p.cout * p.k * p.k * ch
        && (0..p.cout).all(|c| short_ok(p.mult.get(c)) && p.bias.get(c).unsigned_abs() < SHORT_MAX_BIAS)
}

/// Layer `p` (`ch` channels in) as [`block`] reads it, into `l`: the blob's `[c][tap][ci]`
/// weights as `[tap][group][cout]` (`k^2 (ch / 4) cout`), and the short epilogue's operands as
/// four planes of `cout` (multiplier, shift, rounding half `2^(shift - 1)`, bias), loaded 8
/// channels at a time.
fn relay(p: &ConvParams<'_>, ch: usize, l: &mut Relaid) {
    let (cout, kk) = (p.cout, p.k * p.k);
    let w = scratch(&mut l.w, kk * (ch / 4) * cout);
    for (c, wc) in p.weights.chunks_exact(kk * ch).take(cout).enumerate() {
        for (tg, q) in wc.chunks_exact(4).enumerate() {
            if let (Some(d), &[a, b, e, f]) = (w.get_mut(tg * cout + c), q) {
                *d = i32::from_le_bytes([a as u8, b as u8, e as u8, f as u8]);
            }
        }
    }
    let ep = scratch(&mut l.ep, 4 * cout);
    for c in 0..cout {
        let m = p.mult.get(c);
        // (`eligible`: every channel's shift is in 8..=62.)
        let half = 1i64.wrapping_shl(u32::from(m.shift.max(1)) - 1);
        for (k, v) in [m.m as i64, m.shift as i64, half, p.bias.get(c)].into_iter().enumerate() {
            if let Some(d) = ep.get_mut(k * cout + c) {
                *d = v;
            }
        }
    }
}

/// [`super::conv_row`] by this path, or `false` (nothing written) where the layer is not one it
/// takes.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; the layer passed [`super::conv_row`]'s checks.
pub(super) unsafe fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>) -> bool {
    if !eligible::<T>(p) {
        return false;
    }
    let (ch, cout) = (p.parts.first().copied().unwrap_or(0), p.cout);
    let Some(rows) = inputs.first() else { return false };
    let n = p.k * p.k * (ch / 4) * cout;
    let w_out = p.out_width(w_in);
    let cols = padded_cols(w_in, w_out, p.stride);
    let framed = super::FRAME_ON.with(|on| on.get());
    SCRATCH.with_borrow_mut(|(own, pads)| {
        // The rows padded with a zero column in front and zeros behind (a missing row: none).
        let mut padded: [Option<&[u8]>; 3] = [None; 3];
        for ((dst, src), pad) in padded.iter_mut().zip(rows.rows.iter()).zip(pads.iter_mut()).take(p.k) {
            let Some(src) = src.and_then(|r| cast::<T, u8>(r)) else { continue };
            let v = scratch(pad, cols * ch);
            let (front, rest) = v.split_at_mut(ch.min(v.len()));
            front.fill(0);
            let take = (w_in * ch).min(src.len()).min(rest.len());
            if let (Some(d), Some(s)) = (rest.get_mut(..take), src.get(..take)) {
                d.copy_from_slice(s);
            }
            rest.get_mut(take..).unwrap_or_default().fill(0);
            *dst = Some(&*v);
        }
        let mut run = |l: &Relaid| {
            // SAFETY: the caller's CPU features; `l` is the layer relaid (`n` weights, `4 cout`
            // operands); the padded rows hold `padded_cols` columns.
            unsafe { row(p, ch, &padded, l.w.get(..n).unwrap_or_default(), l.ep.get(..4 * cout).unwrap_or_default(), w_out, out) }
        };
        if framed {
            LAYERS.with_borrow_mut(|layers| {
                let key = (p.weights.as_ptr() as usize, p.weights.len(), p.k * ch, cout);
                let i = match layers.iter().position(|l| l.key == key) {
                    Some(i) => i,
                    None => super::free_slot(layers, |l| l.valid, || Relaid { key, valid: false, w: Vec::new(), ep: Vec::new() }),
                };
                if let Some(l) = layers.get_mut(i) {
                    if !(l.valid && l.key == key) {
                        l.key = key;
                        relay(p, ch, l);
                        l.valid = true;
                    }
                    run(l);
                }
            });
        } else {
            relay(p, ch, own);
            run(own);
        }
    });
    true
}

/// The row: blocks of [`PX`] pixels (split over the pool when the layer is large and the pool
/// free), every channel.
///
/// # Safety
/// As [`conv_row`]; `w` and `ep` are the layer relaid ([`relay`]: `k^2 (ch / 4) cout` weights,
/// `4 cout` operands); each padded row (the first `k`) holds [`padded_cols`] columns of `ch`
/// bytes for the row's `w_out` outputs.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn row(p: &ConvParams<'_>, ch: usize, rows: &[Option<&[u8]>; 3], w: &[i32], ep: &[i64], w_out: usize, out: &mut OutRow<'_>) {
    let cout = p.cout;
    let (lo, hi) = out_range(out);
    let lo = if p.post == PostOp::Relu { lo.max(0) } else { lo };
    let (op, size) = out_ptr(out);
    let (k, stride) = (p.k, p.stride);
    if ep.len() < 4 * cout || w.len() < k * k * (ch / 4) * cout || !(k == 1 || k == 3) {
        return;
    }
    let blocks = w_out.div_ceil(PX);
    let big = w_out * cout * k * k * ch >= PARALLEL_MACS;
    let ranges = super::block_ranges(big, blocks);
    let task = |t: usize| {
        let (b0, b1) = (t * blocks / ranges, (t + 1) * blocks / ranges);
        for b in b0..b1 {
            let x0 = b * PX;
            let np = (w_out - x0).min(PX);
            let mut cb = 0;
            while cb < cout {
                // SAFETY: pixels `x0 .. x0 + np` of the row and channels `cb ..` of them, this
                // task's only; the rest as `row`'s contract.
                unsafe {
                    if cb + 32 <= cout {
                        block::<2>(rows, w, ch, cout, k, stride, x0, np, cb, ep, (lo, hi), &op, size);
                        cb += 32;
                    } else {
                        block::<1>(rows, w, ch, cout, k, stride, x0, np, cb, ep, (lo, hi), &op, size);
                        cb += 16;
                    }
                }
            }
        }
    };
    if ranges > 1 {
        pool::run(ranges, &task);
    } else {
        task(0);
    }
}

/// Output pixels `x0 .. x0 + np` (`np <= PX`), channels `cb .. cb + 16 NV`: the exact sums of
/// the present rows' taps (a `k x k` kernel, `k` 1 or 3), then the epilogue into the output row.
///
/// # Safety
/// As [`row`]; `k` is 1 or 3; `cb + 16 NV <= cout`; pixels `x0 .. x0 + np` of the output row (`size` bytes a
/// value) are the caller's to write.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn block<const NV: usize>(rows: &[Option<&[u8]>; 3], w: &[i32], ch: usize, cout: usize, k: usize, stride: usize, x0: usize, np: usize, cb: usize, ep: &[i64], (lo, hi): (i32, i32), op: &Shared<u8>, size: usize) {
    let g_n = ch / 4;
    // Output pixel `x`'s window starts at input column `stride x - k / 2`, padded column
    // `stride x + 1 - k / 2` (the padded rows have one zero column in front).
    let front = 1 - k / 2;
    let mut acc = [[_mm512_setzero_si512(); NV]; PX];
    for (ky, r) in rows.iter().enumerate().take(k) {
        let Some(r) = r else { continue };
        for kx in 0..k {
            // SAFETY: padded column `stride (x0 + p) + front + kx < stride (w_out + PX) + 3`
            // (`x0 + p < w_out + PX - 1`, `front + kx <= 2`), group `g < g_n`: inside the padded
            // row ([`padded_cols`]); weights of tap `ky k + kx`, group `g`, channels `cb .. cb +
            // 16 NV <= cout`: inside `w`.
            unsafe {
                let xp = r.as_ptr().add((stride * x0 + front + kx) * ch);
                let wt = w.as_ptr().add((ky * k + kx) * g_n * cout + cb);
                super::tap_products::<true, NV, PX>(&mut acc, xp, stride * ch, wt.cast(), cout, g_n);
            }
        }
    }
    let (l, h) = (_mm512_set1_epi64(lo as i64), _mm512_set1_epi64(hi as i64));
    let round = _mm512_set1_epi64(1 << (EXTRA_BITS - 1));
    for v in 0..NV {
        let c = cb + 16 * v;
        // The 16 channels' operands, two vectors of 8 from each plane (`ep`: four planes of
        // `cout >= c + 16`, `row`'s check).
        let [mp, sp, hp, bp] = [0, 1, 2, 3].map(|k| ep.as_ptr().wrapping_add(k * cout));
        // SAFETY: 8 i64 of each plane from `c` and from `c + 8` (above).
        let (m0, s0, h0, b0, m1, s1, h1, b1) = unsafe {
            let ld = |q: *const i64| _mm512_loadu_si512(q.cast());
            (ld(mp.add(c)), ld(sp.add(c)), ld(hp.add(c)), ld(bp.add(c)), ld(mp.add(c + 8)), ld(sp.add(c + 8)), ld(hp.add(c + 8)), ld(bp.add(c + 8)))
        };
        // requantize (short), + bias, rounded >> EXTRA_BITS, ReLU / saturation. (A macro, not a
        // closure: the intrinsics stay inline under this function's target features.)
        macro_rules! finish {
            ($a:expr, $m:expr, $s:expr, $half:expr, $b:expr) => {{
                let r = _mm512_srav_epi64(_mm512_add_epi64(_mm512_mul_epi32($a, $m), $half), $s);
                let r = _mm512_srai_epi64::<{ EXTRA_BITS }>(_mm512_add_epi64(_mm512_add_epi64(r, $b), round));
                _mm512_min_epi64(_mm512_max_epi64(r, l), h)
            }};
        }
        for (p, acc) in acc.iter().enumerate().take(np) {
            let a = acc.get(v).copied().unwrap_or(_mm512_setzero_si512());
            let (a0, a1) = (_mm512_cvtepi32_epi64(_mm512_castsi512_si256(a)), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(a)));
            let (r0, r1) = (finish!(a0, m0, s0, h0, b0), finish!(a1, m1, s1, h1, b1));
            // SAFETY: channels `c .. c + 16` of pixel `x0 + p` (the contract).
            unsafe {
                let d = op.0.add(((x0 + p) * cout + c) * size);
                if size == 2 {
                    _mm_storeu_si128(d.cast(), _mm512_cvtepi64_epi16(r0));
                    _mm_storeu_si128(d.add(16).cast(), _mm512_cvtepi64_epi16(r1));
                } else {
                    _mm_storel_epi64(d.cast(), _mm512_cvtepi64_epi8(r0));
                    _mm_storel_epi64(d.add(8).cast(), _mm512_cvtepi64_epi8(r1));
                }
            }
        }
    }
}
