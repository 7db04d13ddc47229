//! Convolution with int8 weights over a multi-part input (the concatenation of several tensors,
//! each with its own format folded into the weights), int32/int64 accumulation and per-output-
//! channel requantisation.
//!
//! Weight order per output channel: `[part][ky][kx][c]` (a patch gathered from HWC rows). Padding
//! is `k / 2` zeros on every side.
//!
//! Each (output channel, part) has its own weight scale, so parts of very different ranges (a
//! Q0.15 hidden state beside an i8 context) keep the full int8 precision. The exact partial sum of
//! part `p` is requantised with `mult[c][p]` to the output format with [`EXTRA_BITS`] more fraction
//! bits; the parts' results and the bias (same units) are summed, then rounded:
//! `y = post(rshift_round(bias[c] + sum_p requantize(sum(w * x)_p, mult[c][p]), EXTRA_BITS))`.
//!
//! Buffers shorter than the parameters say never reach a panic: a missing input row or column
//! is padding, a missing bias is 0, a missing multiplier is [`Multiplier::ZERO`], and a missing
//! weight row, patch or output element ends that channel's (or row's) work early.
#![deny(clippy::indexing_slicing)]

use super::{Elem, OutRow, dot_plain, head_mut, pair_index, set_at};
use crate::arith::{Multiplier, lut, requantize};
#[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
use crate::arith::requantize_i32;
use crate::model::graph::PostOp;

#[cfg(all(target_arch = "x86_64", feature = "std"))]
#[path = "conv_avx512.rs"]
mod avx512;
#[cfg(all(target_arch = "x86_64", feature = "std"))]
pub use avx512::{FrameScope, with_constant_part};
#[cfg(all(target_arch = "aarch64", feature = "std"))]
#[path = "conv_neon.rs"]
mod neon;
#[cfg(all(target_arch = "arm", feature = "mve"))]
#[path = "conv_helium.rs"]
mod helium;

/// Whether `p`'s tables, its `inputs` parts and `out` (`out_len` values) are as long as its
/// parameters say for a row of `w_in` input columns, with a shape the whole-row host kernels
/// take (`conv_avx512`, `conv_neon`; each adds its own limits). Otherwise the portable path runs,
/// which defines the result of a short table.
#[cfg(all(feature = "std", any(target_arch = "x86_64", target_arch = "aarch64")))]
fn whole_row(p: &ConvParams<'_>, inputs: usize, w_in: usize, out_len: usize) -> bool {
    let (kl, np, w_out) = (p.patch_len(), p.parts.len(), p.out_width(w_in));
    kl != 0
        && p.cout != 0
        && w_out != 0
        && p.k <= MAX_K
        && p.stride != 0
        && inputs >= np
        && p.weights.len() >= p.cout * kl
        && p.mult.0.len() >= 8 * p.cout * np
        && p.bias.0.len() >= 8 * p.cout
        && out_len >= w_out * p.cout
}

/// Largest kernel size.
pub const MAX_K: usize = 7;

/// Little-endian `i64` array stored in bytes (bias in accumulator units).
#[derive(Clone, Copy, Debug)]
pub struct BiasRef<'a>(pub &'a [u8]);

impl BiasRef<'_> {
    /// Bias of channel `c` (0 past the end of the table).
    #[inline(always)]
    pub fn get(&self, c: usize) -> i64 {
        bias_at(self.0.get(8 * c..).unwrap_or_default())
    }
}

/// The bias stored at the start of `b` ([`BiasRef`] layout; 0 when `b` is shorter than 8 bytes).
#[inline(always)]
fn bias_at(b: &[u8]) -> i64 {
    b.first_chunk::<8>().map_or(0, |b| i64::from_le_bytes(*b))
}

/// Extra fraction bits of the per-part requantised sums (see the module doc).
pub const EXTRA_BITS: u32 = 8;

/// Per-(channel, part) multipliers stored as 8 bytes each: `m` (i32 LE), `shift` (u8), 3 zero
/// bytes; entry `c * parts + p`.
#[derive(Clone, Copy, Debug)]
pub struct MultRef<'a>(pub &'a [u8]);

impl MultRef<'_> {
    /// Multiplier of channel `c` ([`Multiplier::ZERO`] past the end of the table).
    #[inline(always)]
    pub fn get(&self, c: usize) -> Multiplier {
        mult_at(self.0.get(8 * c..).unwrap_or_default())
    }
}

/// The multiplier stored at the start of `b` ([`MultRef`] layout; [`Multiplier::ZERO`] when `b`
/// is shorter than 8 bytes).
#[inline(always)]
fn mult_at(b: &[u8]) -> Multiplier {
    match b.first_chunk::<8>() {
        Some(&[m0, m1, m2, m3, shift, ..]) => Multiplier { m: i32::from_le_bytes([m0, m1, m2, m3]), shift: shift.clamp(1, 126) },
        None => Multiplier::ZERO,
    }
}

/// [`mult_at`] without the clamp of the shift: for the short epilogue, whose [`short_ok`] test
/// (`8 <= shift <= 62`) implies that the clamp would change nothing; [`clamp_shift`] gives
/// [`mult_at`]'s multiplier for the other path.
#[inline(always)]
fn mult_raw(b: &[u8]) -> Multiplier {
    match b.first_chunk::<8>() {
        Some(&[m0, m1, m2, m3, shift, ..]) => Multiplier { m: i32::from_le_bytes([m0, m1, m2, m3]), shift },
        None => Multiplier::ZERO,
    }
}

/// [`mult_at`]'s multiplier from [`mult_raw`]'s.
#[inline(always)]
fn clamp_shift(m: Multiplier) -> Multiplier {
    Multiplier { m: m.m, shift: m.shift.clamp(1, 126) }
}

/// Encodes multipliers in the [`MultRef`] layout (host: blob writer and tests).
#[cfg(feature = "std")]
pub fn encode_mults(m: &[Multiplier]) -> Vec<u8> {
    m.iter().flat_map(|m| {
        let mut b = [0u8; 8];
        b[..4].copy_from_slice(&m.m.to_le_bytes());
        b[4] = m.shift;
        b
    })
    .collect()
}

/// Encodes biases in the [`BiasRef`] layout.
#[cfg(feature = "std")]
pub fn encode_bias(b: &[i64]) -> Vec<u8> {
    b.iter().flat_map(|v| v.to_le_bytes()).collect()
}

/// A quantised convolution.
#[derive(Clone, Copy, Debug)]
pub struct ConvParams<'a> {
    /// Kernel size.
    pub k: usize,
    /// Stride.
    pub stride: usize,
    /// Channels of each input part, in weight order.
    pub parts: &'a [usize],
    /// Output channels.
    pub cout: usize,
    /// `cout x (k * k * sum(parts))` int8 weights.
    pub weights: &'a [i8],
    /// Bias per output channel (accumulator units).
    pub bias: BiasRef<'a>,
    /// Requantisation per output channel and part (`c * parts + p`).
    pub mult: MultRef<'a>,
    /// Activation after requantisation.
    pub post: PostOp,
}

impl ConvParams<'_> {
    /// A convolution without inputs or outputs: every kernel does nothing with it.
    pub const EMPTY: ConvParams<'static> =
        ConvParams { k: 1, stride: 1, parts: &[], cout: 0, weights: &[], bias: BiasRef(&[]), mult: MultRef(&[]), post: PostOp::None };
    /// Patch length `k * k * sum(parts)`.
    pub fn patch_len(&self) -> usize {
        self.k * self.k * self.parts.iter().sum::<usize>()
    }
    /// Output width for an input of width `w_in`.
    pub fn out_width(&self, w_in: usize) -> usize {
        // No stride (never in a parsed model) gives no columns rather than a division by zero.
        (w_in + 2 * (self.k / 2)).saturating_sub(self.k).checked_div(self.stride).map_or(0, |q| q + 1)
    }
}

/// Contribution of part `part`'s exact partial sum to output channel `c` (output units with
/// [`EXTRA_BITS`] more fraction bits).
#[inline(always)]
pub fn part_sum(p: &ConvParams<'_>, c: usize, part: usize, acc: i64) -> i64 {
    requantize(acc, p.mult.get(c * p.parts.len() + part))
}

/// Bias, rounding and activation of output channel `c` from the sum of its parts' contributions.
#[inline(always)]
pub fn finish(p: &ConvParams<'_>, c: usize, sum: i64) -> i64 {
    finish_with(p.post, p.bias.get(c), sum)
}

/// [`finish`] with the channel's bias.
#[inline(always)]
fn finish_with(post: PostOp, bias: i64, sum: i64) -> i64 {
    activate(post, crate::arith::rshift_round(sum.saturating_add(bias), EXTRA_BITS))
}

/// The activation of [`finish_with`] on the rounded value.
#[inline(always)]
fn activate(post: PostOp, v: i64) -> i64 {
    match post {
        PostOp::None => v,
        PostOp::Relu => v.max(0),
        PostOp::Sigmoid => lut::sigmoid_q12(crate::arith::sat_i16(v)) as i64,
        PostOp::Tanh => lut::tanh_q12(crate::arith::sat_i16(v)) as i64,
    }
}

/// Bias magnitude bound of the short epilogue ([`short_ok`]).
const SHORT_MAX_BIAS: u64 = 1 << 40;

/// Whether a (channel, part) multiplier allows the short epilogue: `8 <= shift <= 62` (the
/// shipped blobs use 13 to 46). Then [`crate::arith::requantize_i32`] of an `i32` sum is [`requantize`]'s
/// integer, below `2^62 / 2^8 = 2^54` in magnitude; up to `MAX_PARTS` (6) such contributions, a
/// bias below [`SHORT_MAX_BIAS`] and the rounding half sum far inside i64, so the plain adds of
/// [`finish_short`] give [`finish_with`]'s integers. Anything else takes the saturating path.
#[inline(always)]
fn short_ok(m: Multiplier) -> bool {
    (8..=62).contains(&m.shift)
}

/// [`crate::arith::requantize_i32`] where [`short_ok`] holds: by `SMLAL` on the DSP build
/// ([`super::dsp::requantize_i32`], same integers), else the portable formula.
#[inline(always)]
fn requant_short(acc: i32, m: Multiplier) -> i64 {
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    return super::dsp::requantize_i32(acc, m);
    #[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
    requantize_i32(acc, m)
}

/// [`finish_with`] when every contribution to `sum` was short and `|bias| <` [`SHORT_MAX_BIAS`]:
/// no saturation is possible, so plain adds and one shift.
#[inline(always)]
fn finish_short(post: PostOp, bias: i64, sum: i64) -> i64 {
    activate(post, (sum + bias + (1i64 << (EXTRA_BITS - 1))) >> EXTRA_BITS)
}

/// The `k` input rows one output row reads from one part: `rows[ky]` is input row
/// `y * stride - k/2 + ky`, `None` where that row lies in the zero padding. Each row holds
/// `w_in * channels` values (HWC).
#[derive(Clone, Copy, Debug)]
pub struct PartRows<'a, T> {
    /// Row slices, `k` of them used.
    pub rows: [Option<&'a [T]>; MAX_K],
}

impl<'a, T> PartRows<'a, T> {
    /// Rows `y*stride - k/2 + ky` of a whole HWC tensor `t` (`h` rows of `row_len` values; rows
    /// past the end of a shorter `t` are padding).
    pub fn of_tensor(t: &'a [T], h: usize, row_len: usize, y: usize, k: usize, stride: usize) -> Self {
        let mut rows = [None; MAX_K];
        for (ky, r) in rows.iter_mut().enumerate().take(k) {
            let iy = (y * stride + ky) as isize - (k / 2) as isize;
            if iy >= 0 && (iy as usize) < h {
                *r = t.get(iy as usize * row_len..(iy as usize + 1) * row_len);
            }
        }
        Self { rows }
    }
    /// Row `ky`, `None` in the padding (and for `ky >= MAX_K`, which no layer has).
    #[inline(always)]
    fn row(&self, ky: usize) -> Option<&'a [T]> {
        self.rows.get(ky).copied().flatten()
    }
}

/// Values `ix * ch ..` of an input row (`ch` of them), `None` in the padding: outside the `w_in`
/// columns, or past the end of a short row.
#[inline(always)]
fn column<T>(row: Option<&[T]>, ix: isize, w_in: usize, ch: usize) -> Option<&[T]> {
    match row {
        Some(r) if ix >= 0 && (ix as usize) < w_in => r.get(ix as usize * ch..(ix as usize + 1) * ch),
        _ => None,
    }
}

/// Gathers the patch of output column `ox`: `[part][ky][kx][c]`, zeros outside the input, part by
/// part ([`gather_part`]; stops before a part a too-short `patch` cannot hold).
#[inline]
fn gather<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, ox: usize, patch: &mut [T]) {
    let mut rest = patch;
    for (part, &ch) in inputs.iter().zip(p.parts) {
        let Some((dst, tail)) = core::mem::take(&mut rest).split_at_mut_checked(p.k * p.k * ch) else {
            return;
        };
        gather_part(p.k, p.stride, part, ch, w_in, ox, dst);
        rest = tail;
    }
}

/// One part's patch of output column `ox` (`[ky][kx][c]`, zeros outside the input) into `dst`
/// (`k * k * ch` values): each kernel row is one run of the input row where the window lies
/// inside it, else value groups one by one.
#[inline]
fn gather_part<T: Elem>(k: usize, stride: usize, rows: &PartRows<'_, T>, ch: usize, w_in: usize, ox: usize, dst: &mut [T]) {
    if ch == 0 || k == 0 {
        return;
    }
    let pad = k / 2;
    let x0 = ox * stride; // the window covers input columns x0 - pad .. x0 - pad + k
    // `k ch >= 1` here; `max` keeps the chunking free of a zero-size path.
    for (d, row) in dst.chunks_exact_mut((k * ch).max(1)).zip(rows.rows.iter()) {
        match row {
            Some(r) if x0 >= pad && x0 - pad + k <= w_in => match r.get((x0 - pad) * ch..(x0 - pad + k) * ch) {
                #[cfg(all(target_arch = "arm", feature = "mve"))]
                Some(s) => super::mve::copy(d, s),
                // (`get` gave exactly `k ch` values; the guard lets the compiler drop the length check.)
                #[cfg(not(all(target_arch = "arm", feature = "mve")))]
                Some(s) if s.len() == d.len() => d.copy_from_slice(s),
                _ => d.fill(T::default()), // a row shorter than `w_in` (never in the engine)
            },
            Some(r) => {
                for (kx, dc) in d.chunks_exact_mut(ch).enumerate() {
                    match column(Some(r), (x0 + kx) as isize - pad as isize, w_in, ch) {
                        Some(s) => dc.iter_mut().zip(s).for_each(|(d, s)| *d = *s),
                        #[cfg(all(target_arch = "arm", feature = "mve"))]
                        None => super::mve::zero(dc),
                        #[cfg(not(all(target_arch = "arm", feature = "mve")))]
                        None => dc.fill(T::default()),
                    }
                }
            }
            #[cfg(all(target_arch = "arm", feature = "mve"))]
            None => super::mve::zero(d),
            #[cfg(not(all(target_arch = "arm", feature = "mve")))]
            None => d.fill(T::default()),
        }
    }
}

/// Both patches of a pair where every kernel row exists and both windows lie inside the input
/// row (the interior of the image): per kernel row one run of `k ch` values for each patch
/// ([`super::mve::copy`]), without [`gather_part`]'s general path. The same values as two
/// [`gather_part`] calls; false, with `a` and `b` partly written, where the pair is not of that
/// kind (the caller then gathers both patches with [`gather_part`], which rewrites every value).
#[cfg(all(target_arch = "arm", feature = "mve"))]
#[inline(always)]
#[allow(clippy::too_many_arguments)]
fn inside2<T: Elem>(k: usize, stride: usize, rows: &PartRows<'_, T>, ch: usize, w_in: usize, ox: usize, a: &mut [T], b: &mut [T]) -> bool {
    let run = k * ch;
    let Some(x0) = (ox * stride).checked_sub(k / 2) else {
        return false;
    };
    let x1 = x0 + stride;
    if run == 0 || x1 + k > w_in || k > MAX_K || a.len() != k * run || b.len() != k * run {
        return false;
    }
    let (s0, s1) = (x0 * ch, x1 * ch);
    for ((row, da), db) in rows.rows.iter().take(k).zip(a.chunks_exact_mut(run)).zip(b.chunks_exact_mut(run)) {
        let Some(r) = row else {
            return false;
        };
        let (Some(sa), Some(sb)) = (r.get(s0..s0 + run), r.get(s1..s1 + run)) else {
            return false;
        };
        super::mve::copy(da, sa);
        super::mve::copy(db, sb);
    }
    true
}

/// [`gather2`] for the split pair layout ([`Elem::SPLIT_PAIRS`]): per part, the patch of `ox`
/// then that of `ox + 1`, each gathered by [`gather_part`].
#[inline]
fn gather2_split<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, ox: usize, pair: &mut [T]) {
    let k = p.k;
    let mut rest = pair;
    for (part, &ch) in inputs.iter().zip(p.parts) {
        let n = ch * k * k;
        let Some((block, tail)) = core::mem::take(&mut rest).split_at_mut_checked(2 * n) else {
            return;
        };
        let Some((a, b)) = block.split_at_mut_checked(n) else {
            return;
        };
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        if inside2(k, p.stride, part, ch, w_in, ox, a, b) {
            rest = tail;
            continue;
        }
        gather_part(k, p.stride, part, ch, w_in, ox, a);
        gather_part(k, p.stride, part, ch, w_in, ox + 1, b);
        rest = tail;
    }
}

/// Gathers the patches of output columns `ox` and `ox + 1` in the pair layout
/// ([`super::pair_index`]), part by part (each part's `n` values form their own pair block of
/// `2n`), so that [`Elem::dot2x2`] reads both with one pointer.
#[inline]
fn gather2<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, ox: usize, pair: &mut [T]) {
    if T::SPLIT_PAIRS {
        gather2_split(p, inputs, w_in, ox, pair);
        return;
    }
    let k = p.k;
    let pad = (k / 2) as isize;
    let mut base = 0;
    for (part, &ch) in inputs.iter().zip(p.parts) {
        let n = ch * k * k;
        let Some(dst) = pair.get_mut(2 * base..2 * (base + n)) else {
            return;
        };
        // Armv7E-M: a part whose channels are not whole groups (the motion encoder's flow and
        // mask inputs) gathered in patch order into a small buffer first (runs and columns
        // copied whole), then its whole groups by `put_groups` and the tail value by value
        // (value by value throughout, with `pair_index` each, took some 20 instructions a
        // value).
        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
        if !ch.is_multiple_of(4) && ch + 3 <= GATHER_TMP {
            gather2_tmp(p, part, ch, w_in, ox, dst);
            base += n;
            continue;
        }
        for (second, x) in [(false, ox), (true, ox + 1)] {
            let mut j = 0;
            for ky in 0..k {
                let row = part.row(ky);
                // Whole groups and the window inside the row: its `k ch` values are one run of
                // the input row, copied group by group in one pass.
                if ch % 4 == 0
                    && let Some(r) = row
                    && let Some(x0) = (x * p.stride).checked_sub(k / 2)
                    && x0 + k <= w_in
                    && let (Some(s), Some(d)) = (r.get(x0 * ch..(x0 + k) * ch), dst.get_mut(2 * j..2 * (j + k * ch)))
                {
                    T::put_groups(d, s, second);
                    j += k * ch;
                    continue;
                }
                for kx in 0..k {
                    let ix = (x * p.stride + kx) as isize - pad;
                    let src = column(row, ix, w_in, ch);
                    if ch % 4 == 0 {
                        // Every group whole (`j` and `n` are multiples of 4): group `g` of these
                        // values goes to `2 j + 8 g` (plus 4 for the second patch).
                        let d = dst.get_mut(2 * j..2 * (j + ch)).unwrap_or_default();
                        match src {
                            Some(s) => T::put_groups(d, s, second),
                            None => d.chunks_exact_mut(8).for_each(|d| {
                                let (a, b) = d.split_at_mut(4);
                                (if second { b } else { a }).fill(T::default())
                            }),
                        }
                        j += ch;
                        continue;
                    }
                    let mut e = 0;
                    // Whole groups of four go as blocks; the rest value by value.
                    while e < ch {
                        let at = pair_index(n, j + e, second, T::PAIR_SWAP);
                        if (j + e) % 4 == 0 && e + 4 <= ch && j + e + 4 <= n / 4 * 4 {
                            if let Some(g) = dst.get_mut(at..at + 4) {
                                match src.and_then(|s| s.get(e..e + 4)) {
                                    Some(&[s0, s1, s2, s3]) if T::PAIR_SWAP => g.copy_from_slice(&[s0, s2, s1, s3]),
                                    Some(s) => g.copy_from_slice(s),
                                    None => g.fill(T::default()),
                                }
                            }
                            e += 4;
                        } else {
                            set_at(dst, at, src.and_then(|s| s.get(e)).copied().unwrap_or_default());
                            e += 1;
                        }
                    }
                    j += ch;
                }
            }
        }
        base += n;
    }
}

/// Values of [`gather2_tmp`]'s buffer: up to 3 carried over and one run of a kernel row (3
/// columns of 128 channels) or one column.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const GATHER_TMP: usize = 4 + 3 * 128;

/// [`gather2`]'s two patches of one part of `ch` channels (`n = k k ch` values, `dst` its `2 n`
/// values of the pair layout), `ch <= GATHER_TMP - 3`: each patch in patch order through a
/// word-aligned buffer, a window inside the row as one run where it fits, else column by
/// column (zeros outside the input); after each run or column the buffer's whole groups go
/// to the next groups of `dst` by [`Elem::put_groups`] and the 0 to 3 values left move to its
/// front; the last `n % 4` values by [`super::pair_index`], as [`gather2`] places them.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn gather2_tmp<T: Elem>(p: &ConvParams<'_>, part: &PartRows<'_, T>, ch: usize, w_in: usize, ox: usize, dst: &mut [T]) {
    #[repr(C, align(4))]
    struct Buf<T>([T; GATHER_TMP]);
    let k = p.k;
    let n = k * k * ch;
    let pad = (k / 2) as isize;
    let mut tmp = Buf([T::default(); GATHER_TMP]);
    let tmp = &mut tmp.0;
    for (second, x) in [(false, ox), (true, ox + 1)] {
        // Values held in `tmp` and groups written to `dst`.
        let (mut held, mut g) = (0usize, 0usize);
        let mut flush = |tmp: &mut [T; GATHER_TMP], held: &mut usize| {
            let q = *held / 4;
            T::put_groups(dst.get_mut(8 * g..8 * (g + q)).unwrap_or_default(), tmp.get(..4 * q).unwrap_or_default(), second);
            g += q;
            // The 0 to 3 values left to the front (`copy_within` called `memmove`).
            *held -= 4 * q;
            for i in 0..*held {
                if let (Some(&v), true) = (tmp.get(4 * q + i), i < 3) {
                    set_at(tmp, i, v);
                }
            }
        };
        for ky in 0..k {
            let row = part.row(ky);
            if let Some(r) = row
                && let Some(x0) = (x * p.stride).checked_sub(k / 2)
                && x0 + k <= w_in
                && let (Some(s), Some(d)) = (r.get(x0 * ch..(x0 + k) * ch), tmp.get_mut(held..held + k * ch))
            {
                d.iter_mut().zip(s).for_each(|(d, s)| *d = *s);
                held += k * ch;
                flush(tmp, &mut held);
                continue;
            }
            for kx in 0..k {
                let ix = (x * p.stride + kx) as isize - pad;
                let d = tmp.get_mut(held..held + ch).unwrap_or_default();
                match column(row, ix, w_in, ch) {
                    Some(s) => d.iter_mut().zip(s).for_each(|(d, s)| *d = *s),
                    None => d.fill(T::default()),
                }
                held += ch;
                flush(tmp, &mut held);
            }
        }
        let whole = n / 4 * 4;
        for (i, &v) in tmp.iter().take(held).enumerate() {
            set_at(dst, pair_index(n, whole + i, second, T::PAIR_SWAP), v);
        }
    }
}

/// The two halves of a two-channel block (weights, multipliers or biases of channels `c` and
/// `c + 1`).
#[inline(always)]
fn halves<T>(b: &[T]) -> (&[T], &[T]) {
    b.split_at(b.len() / 2)
}

/// Weights (`2 kl` values), multipliers (`2 parts` entries) and biases (2 entries) of output
/// channels `c + 2i` and `c + 2i + 1` (`c` even), for `c + 2i + 1 < cout`: the channel pairs walk
/// the tables in steps of two channels, with no index arithmetic or bounds check per pair (stops
/// early where a table is shorter; `kl` and the part count are not 0). The tables are sliced at
/// channel `c` once, not skipped pair by pair (a `skip` adapter costs in every step of the loop).
#[inline(always)]
fn channel_pairs<'a>(p: &ConvParams<'a>, kl: usize, c: usize) -> impl Iterator<Item = ((&'a [i8], &'a [u8]), &'a [u8])> {
    let np = p.parts.len();
    let (w, m, b) = (p.weights.get(c * kl..), p.mult.0.get(8 * c * np..), p.bias.0.get(8 * c..));
    // Chunk sizes of at least 1 (the empty shapes this rules out return before they get here):
    // no zero-size chunking path.
    let weights = w.unwrap_or_default().chunks_exact((2 * kl).max(1));
    weights
        .zip(m.unwrap_or_default().chunks_exact((16 * np).max(1)))
        .zip(b.unwrap_or_default().chunks_exact(16))
        .take(p.cout.saturating_sub(c) / 2)
}

/// Sums of the parts' contributions (before [`finish`]) of a channel pair at one pixel from its
/// gathered patch: `w` and `m` are the pair's weights and multipliers ([`channel_pairs`]).
#[inline]
fn pair_sums<T: Elem>(p: &ConvParams<'_>, patch: &[T], w: &[i8], m: &[u8]) -> (i64, i64) {
    let ((w0, w1), (m0, m1)) = (halves(w), halves(m));
    let (mut s0, mut s1) = (0i64, 0i64);
    let mut o = 0;
    for ((&ch, m0), m1) in p.parts.iter().zip(m0.chunks_exact(8)).zip(m1.chunks_exact(8)) {
        let n = ch * p.k * p.k;
        let (Some(a), Some(b), Some(x)) = (w0.get(o..o + n), w1.get(o..o + n), patch.get(o..o + n)) else {
            break;
        };
        let (d0, d1) = T::dot2(a, b, x);
        s0 = s0.saturating_add(requantize(d0, mult_at(m0)));
        s1 = s1.saturating_add(requantize(d1, mult_at(m1)));
        o += n;
    }
    (s0, s1)
}

/// Output channel `c` alone at one pixel from its gathered patch (an odd last channel).
#[inline]
fn channel_at<T: Elem>(p: &ConvParams<'_>, patch: &[T], c: usize, out: &mut OutRow<'_>, at: usize) {
    let (kl, np) = (p.patch_len(), p.parts.len());
    let (Some(w), Some(m)) = (p.weights.get(c * kl..(c + 1) * kl), p.mult.0.get(8 * c * np..8 * (c + 1) * np)) else {
        return;
    };
    let mut sum = 0i64;
    let mut o = 0;
    for (&ch, m) in p.parts.iter().zip(m.chunks_exact(8)) {
        let n = ch * p.k * p.k;
        let (Some(w), Some(x)) = (w.get(o..o + n), patch.get(o..o + n)) else {
            break;
        };
        sum = sum.saturating_add(requantize(T::dot(w, x), mult_at(m)));
        o += n;
    }
    out.set(at + c, finish(p, c, sum));
}

/// [`Elem::dot2x2`] of one part of channels `c`, `c + 1` (weight rows `w0`, `w1`) at two pixels:
/// the part's `n` values at offset `o` of the weight rows and its block of `2 n` at `2 o` of the
/// pair of patches (a one-part layer, `one_part`, passes the whole rows); `None` where a weight
/// row or the pair is shorter than that.
#[inline(always)]
fn part_dot2x2<T: Elem>(one_part: bool, w0: &[i8], w1: &[i8], pair: &[T], o: usize, n: usize) -> Option<[i64; 4]> {
    if one_part {
        return Some(T::dot2x2(w0, w1, pair));
    }
    Some(T::dot2x2(w0.get(o..o + n)?, w1.get(o..o + n)?, pair.get(2 * o..2 * (o + n))?))
}

/// Channel pairs `c ..` of output pixels `ox` and `ox + 1` (patches of `kl` values) by
/// [`block2x2`] from their pair of patches `pair` (the gathered pair, or its widened copy);
/// returns the first channel not written (an odd last one: [`odd_channel`]).
#[inline(always)]
fn pair_blocks<T: Elem>(p: &ConvParams<'_>, kl: usize, pair: &[T], out: &mut OutRow<'_>, ox: usize, mut c: usize) -> usize {
    let (at_a, at_b) = (ox * p.cout, (ox + 1) * p.cout);
    for ((w, m), b) in channel_pairs(p, kl, c) {
        block2x2(p, pair, w, m, b, out, at_a, at_b, c);
        c += 2;
    }
    c
}

/// Channel `c`, when it is the odd last one, of output pixels `ox` and `ox + 1`: each pixel one
/// at a time from its own patch, gathered again into the head of `scratch`.
#[inline]
fn odd_channel<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, ox: usize, scratch: &mut [T], out: &mut OutRow<'_>, c: usize) {
    if c >= p.cout {
        return;
    }
    for x in [ox, ox + 1] {
        let single = head_mut(scratch, p.patch_len());
        gather(p, inputs, w_in, x, single);
        channel_at(p, single, c, out, x * p.cout);
    }
}

/// Channels `c` and `c + 1` of output pixels `a` and `b` (at `at_a` and `at_b` of `out`) from
/// their gathered pair of patches: `w`, `m`, `b` are the channel pair's weights, multipliers and
/// biases ([`channel_pairs`]). Every weight and activation is loaded once for the four products
/// ([`Elem::dot2x2`]).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn block2x2<T: Elem>(p: &ConvParams<'_>, pair: &[T], w: &[i8], m: &[u8], b: &[u8], out: &mut OutRow<'_>, at_a: usize, at_b: usize, c: usize) {
    let nparts = p.parts.len();
    let (w0, w1) = halves(w);
    block2x2_by(p, m, b, out, at_a, at_b, c, |o, n, _| part_dot2x2(nparts == 1, w0, w1, pair, o, n));
}

/// [`block2x2`]'s requantisation and stores, with each part's four dot products from `dot(o,
/// n, wo)`: the part's `n` values at offset `o` of the patch, `wo` the sum of `4 (n / 4)` over
/// the parts before it (the part's offset in [`super::dsp::widen_weights`]'s words); `None`
/// ends the channel pair's parts early (a short table).
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn block2x2_by(
    p: &ConvParams<'_>,
    m: &[u8],
    b: &[u8],
    out: &mut OutRow<'_>,
    at_a: usize,
    at_b: usize,
    c: usize,
    mut dot: impl FnMut(usize, usize, usize) -> Option<[i64; 4]>,
) {
    let k = p.k;
    let (m0, m1) = halves(m);
    let mut s = [0i64; 4];
    let (b0, b1) = halves(b);
    let (b0, b1) = (bias_at(b0), bias_at(b1));
    // Whether every contribution came through `requantize_i32` and both biases are
    // small (`short_ok`): then no sum can saturate and plain adds give the same integers.
    let mut short = b0.unsigned_abs() < SHORT_MAX_BIAS && b1.unsigned_abs() < SHORT_MAX_BIAS;
    let (mut o, mut wo) = (0, 0);
    for ((&ch, m0), m1) in p.parts.iter().zip(m0.chunks_exact(8)).zip(m1.chunks_exact(8)) {
        let n = ch * k * k;
        let Some(d) = dot(o, n, wo) else {
            break;
        };
        let (m0, m1) = (mult_raw(m0), mult_raw(m1));
        match (short && short_ok(m0) && short_ok(m1), d.map(i32::try_from)) {
            (true, [Ok(a0), Ok(a1), Ok(a2), Ok(a3)]) => {
                s[0] += requant_short(a0, m0);
                s[1] += requant_short(a1, m1);
                s[2] += requant_short(a2, m0);
                s[3] += requant_short(a3, m1);
            }
            _ => {
                short = false;
                let (m0, m1) = (clamp_shift(m0), clamp_shift(m1));
                s[0] = s[0].saturating_add(requantize(d[0], m0));
                s[1] = s[1].saturating_add(requantize(d[1], m1));
                s[2] = s[2].saturating_add(requantize(d[2], m0));
                s[3] = s[3].saturating_add(requantize(d[3], m1));
            }
        }
        o += n;
        wo += n / 4 * 4;
    }
    if short {
        out.set(at_a + c, finish_short(p.post, b0, s[0]));
        out.set(at_a + c + 1, finish_short(p.post, b1, s[1]));
        out.set(at_b + c, finish_short(p.post, b0, s[2]));
        out.set(at_b + c + 1, finish_short(p.post, b1, s[3]));
    } else {
        out.set(at_a + c, finish_with(p.post, b0, s[0]));
        out.set(at_a + c + 1, finish_with(p.post, b1, s[1]));
        out.set(at_b + c, finish_with(p.post, b0, s[2]));
        out.set(at_b + c + 1, finish_with(p.post, b1, s[3]));
    }
}

/// Computes one output row (`out_width * cout` values) from the parts' input rows. `patch` is
/// scratch of at least [`ConvParams::patch_len`] elements; with room for two patches the row is
/// computed two output pixels at a time, two output channels each ([`Elem::dot2x2`]: every
/// weight and activation loaded and widened once for two products), else one pixel at a time.
/// Same integers either way. With less than one patch of scratch, or no weights per channel
/// (`patch_len() == 0`), nothing is computed.
pub fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>, patch: &mut [T]) {
    let kl = p.patch_len();
    if kl == 0 {
        return;
    }
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if avx512::conv_row(p, inputs, w_in, out) {
        return;
    }
    #[cfg(all(target_arch = "aarch64", feature = "std"))]
    if neon::conv_row(p, inputs, w_in, out) {
        return;
    }
    let w_out = p.out_width(w_in);
    let mut ox = 0;
    if let Some(pair) = patch.get_mut(..2 * kl) {
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        let mut helium = helium::Layer::of::<T>(p, out, w_out);
        while ox + 2 <= w_out {
            gather2(p, inputs, w_in, ox, pair);
            #[allow(unused_mut)]
            let mut c = 0;
            #[cfg(all(target_arch = "arm", feature = "mve"))]
            if let Some(l) = &mut helium {
                c = l.channels(p, pair, out, ox * p.cout, (ox + 1) * p.cout);
            }
            let c = pair_blocks(p, kl, pair, out, ox, c);
            odd_channel(p, inputs, w_in, ox, pair, out, c);
            ox += 2;
        }
        // The last pixel of an odd width by the same pair path, with `ox + 1` as a second pixel
        // whose outputs fall outside the row cut to `w_out` pixels (set and the vector stores
        // skip them; its patch is gathered as padding where it lies outside the input): pixel
        // `ox`'s outputs are the same integers as one pixel's alone.
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        if ox + 1 == w_out
            && let Some(l) = &mut helium
        {
            let mut row = out.head(w_out * p.cout);
            gather2(p, inputs, w_in, ox, pair);
            let c = l.channels(p, pair, &mut row, ox * p.cout, (ox + 1) * p.cout);
            let c = pair_blocks(p, kl, pair, &mut row, ox, c);
            if c < p.cout {
                let single = head_mut(pair, kl);
                gather(p, inputs, w_in, ox, single);
                channel_at(p, single, c, &mut row, ox * p.cout);
            }
            ox += 1;
        }
    }
    single_pixels(p, inputs, w_in, out, patch, ox);
}

/// Output pixels `ox ..` of the row one at a time (each from its own gathered patch).
fn single_pixels<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>, patch: &mut [T], mut ox: usize) {
    let kl = p.patch_len();
    let w_out = p.out_width(w_in);
    let Some(patch) = patch.get_mut(..kl) else {
        return;
    };
    while ox < w_out {
        gather(p, inputs, w_in, ox, patch);
        let at = ox * p.cout;
        let mut c = 0;
        for ((w, m), b) in channel_pairs(p, kl, 0) {
            let (s0, s1) = pair_sums(p, patch, w, m);
            let (b0, b1) = halves(b);
            out.set(at + c, finish_with(p.post, bias_at(b0), s0));
            out.set(at + c + 1, finish_with(p.post, bias_at(b1), s1));
            c += 2;
        }
        if c < p.cout {
            channel_at(p, patch, c, out, at);
        }
        ox += 1;
    }
}

/// [`conv_row`] for u8 activations on the Armv7E-M DSP build: each pair of patches is gathered
/// in the u8 pair layout, then widened once to the i16 pair layout (values 0, 2, 1, 3 of each
/// group: what `UXTB16` of a word and of the word rotated by 8 give), and every channel pair runs
/// the i16 loop ([`Elem::dot2x2`] for i16: 16 instructions per 16 MACs, against 20 for the u8
/// loop, which widens the same activations again for every channel pair). The same products
/// (u8 values are exact in i16) in the same chunks, so the same integers. Needs `6 patch_len()`
/// bytes of `scratch` (the engine's holds two i16 patches of its largest layer); returns false,
/// having computed nothing, when it is shorter.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn conv_row_u8_wide(p: &ConvParams<'_>, inputs: &[PartRows<'_, u8>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
    let kl = p.patch_len();
    let Some((pair, rest)) = scratch.split_at_mut_checked(2 * kl) else {
        return false;
    };
    // Word-aligned i16 pairs (the i16 loop loads them with `LDRD`).
    let skip = rest.as_ptr().align_offset(4);
    if kl == 0 {
        return false;
    }
    if conv_row_w16(p, inputs, w_in, out, pair, rest, |ox, pair, slot| {
        gather2(p, inputs, w_in, ox, pair);
        widen_pairs(p, pair, slot);
    }) {
        return true;
    }
    let Some(wide) = rest.get_mut(skip..).and_then(|r| r.get_mut(..4 * kl)) else {
        return false;
    };
    let Ok(wide) = bytemuck::try_cast_slice_mut::<u8, i16>(wide) else {
        return false;
    };
    let w_out = p.out_width(w_in);
    let mut ox = 0;
    while ox + 2 <= w_out {
        gather2(p, inputs, w_in, ox, pair);
        widen_pairs(p, pair, wide);
        let c = pair_blocks::<i16>(p, kl, wide, out, ox, 0);
        odd_channel(p, inputs, w_in, ox, pair, out, c);
        ox += 2;
    }
    single_pixels(p, inputs, w_in, out, pair, ox);
    true
}

/// Fewest pixel pairs per widening of the weights for [`conv_row_w16`]: each group of four of a
/// channel pair costs 7 instructions to widen and saves about 4 per pixel pair, so 2 pairs
/// about break even on the loop alone, yet measured 2 beats 3 (the 1/16 grid's rows of 4 and
/// 5 pixels at 64x48: -12.4 M instructions) and 1 loses (+8.1 M against 2).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const W16_MIN_PAIRS: usize = 2;
/// Most pixel pairs gathered at a time: the slots' room and the row's width bound it first
/// almost everywhere (8 left 12.9 M instructions of widening at 160x120; 1024 counts the same as 32).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const W16_MAX_PAIRS: usize = 32;

/// The DSP build's convolution row with the weights widened once per channel pair and block of
/// pixel pairs: the patches of up to [`W16_MAX_PAIRS`] pixel pairs are gathered first (`fill(ox,
/// temp, slot)` writes the pair of `ox` and `ox + 1` in the i16 pair layout into `slot`, with
/// `temp` as its scratch), then every channel pair's int8 weights are widened once
/// ([`super::dsp::widen_weights`]) and every gathered pair runs [`super::dsp::dot2x2_w16`] (12
/// instructions per 16 MACs against 16 for [`Elem::dot2x2`], which widens the weights again for
/// every pixel pair). `scratch` holds the widened weights and the gathered pairs (word-aligned);
/// where it has room for fewer than [`W16_MIN_PAIRS`] pairs (or the row has fewer), returns
/// false having computed nothing. The odd last channel and pixel as [`conv_row`] does. Same
/// products in the same chunks as [`Elem::dot2x2`], so the same integers.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn conv_row_w16<T: Elem>(
    p: &ConvParams<'_>,
    inputs: &[PartRows<'_, T>],
    w_in: usize,
    out: &mut OutRow<'_>,
    temp: &mut [T],
    scratch: &mut [u8],
    fill: impl FnMut(usize, &mut [T], &mut [i16]),
) -> bool {
    let Some(words) = aligned_words(scratch) else {
        return false;
    };
    let Some((ww, slots)) = words.split_at_mut_checked(w16_words(p)) else {
        return false;
    };
    conv_row_w16_in(p, inputs, w_in, out, temp, ww, slots, fill)
}

/// Words of one channel pair's widened weights ([`super::dsp::widen_weights`]): four per whole
/// group of every part.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn w16_words(p: &ConvParams<'_>) -> usize {
    p.parts.iter().map(|&ch| ch * p.k * p.k / 4 * 4).sum()
}

/// The whole words of `scratch` from its first word-aligned byte.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn aligned_words(scratch: &mut [u8]) -> Option<&mut [u32]> {
    let skip = scratch.as_ptr().align_offset(4);
    let words = scratch.get_mut(skip..)?;
    let len = words.len() / 4 * 4;
    bytemuck::try_cast_slice_mut::<u8, u32>(head_mut(words, len)).ok()
}

/// [`conv_row_w16`] with the widened weights in `ww` ([`w16_words`] of them) and the gathered
/// pairs in `slots` (`patch_len()` words a pair).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn conv_row_w16_in<T: Elem>(
    p: &ConvParams<'_>,
    inputs: &[PartRows<'_, T>],
    w_in: usize,
    out: &mut OutRow<'_>,
    temp: &mut [T],
    ww: &mut [u32],
    slots: &mut [u32],
    mut fill: impl FnMut(usize, &mut [T], &mut [i16]),
) -> bool {
    let (kl, w_out) = (p.patch_len(), p.out_width(w_in));
    // One pair of patches is `2 kl` i16 values, `kl` words.
    let np = (slots.len() / kl.max(1)).min(W16_MAX_PAIRS).min(w_out / 2);
    if np < W16_MIN_PAIRS || kl == 0 {
        return false;
    }
    let slots: &mut [i16] = bytemuck::cast_slice_mut(head_mut(slots, np * kl));
    // The one-part layers' i32 sums of the gathered pairs, one channel pair at a time (cleared
    // once per row: cleared per channel pair, the 512 bytes cost 4.3 M instructions at 160x120).
    let mut sums = [[0i32; 4]; W16_MAX_PAIRS];
    // The sums of a patch's or part's later chunks (`dsp::dot2x2_w16_i32_chunks`), likewise.
    let mut tmp = [[0i32; 4]; W16_MAX_PAIRS];
    // The several-part layers' sums of `w16_parts` (likewise).
    let (mut acc, mut psums) = ([[0i64; 4]; W16_PARTS_PAIRS], [[0i32; 4]; W16_PARTS_PAIRS]);
    let mut ox = 0;
    while ox + 2 <= w_out {
        let n = ((w_out - ox) / 2).min(np);
        // (`kl >= 1` here; `max` keeps the chunking free of its zero-size panic path.)
        for (i, slot) in slots.chunks_exact_mut((2 * kl).max(1)).take(n).enumerate() {
            fill(ox + 2 * i, temp, slot);
        }
        for (cp, ((w, m), b)) in channel_pairs(p, kl, 0).enumerate() {
            let (w0, w1) = halves(w);
            let (mut o, mut wo) = (0, 0);
            for &ch in p.parts {
                let n = ch * p.k * p.k;
                if let (Some(a), Some(b), Some(d)) = (w0.get(o..), w1.get(o..), ww.get_mut(wo..)) {
                    super::dsp::widen_weights(a, b, n / 4, d);
                }
                o += n;
                wo += n / 4 * 4;
            }
            let ww = &*ww;
            if let [_] = p.parts {
                w16_one_part(p, kl, ww, w0, w1, m, b, slots.get(..2 * kl * n).unwrap_or_default(), n, (&mut sums, &mut tmp), out, ox, 2 * cp);
                continue;
            }
            if w16_parts(p, kl, ww, w0, w1, m, b, slots.get(..2 * kl * n).unwrap_or_default(), n, (&mut acc, &mut psums, &mut tmp), out, ox, 2 * cp) {
                continue;
            }
            let slots = slots.chunks_exact((2 * kl).max(1)).take(n);
            for (i, slot) in slots.enumerate() {
                let x = ox + 2 * i;
                block2x2_by(p, m, b, out, x * p.cout, (x + 1) * p.cout, 2 * cp, |o, n, wo| {
                    super::dsp::dot2x2_w16(ww.get(wo..)?, w0.get(o..)?, w1.get(o..)?, slot.get(2 * o..)?, n)
                });
            }
        }
        ox += 2 * n;
    }
    // The odd last channel of every pair and the odd last pixel, each pixel from its own patch.
    let c = p.cout / 2 * 2;
    let mut x = 0;
    while x + 2 <= w_out {
        odd_channel(p, inputs, w_in, x, temp, out, c);
        x += 2;
    }
    single_pixels(p, inputs, w_in, out, temp, x);
    true
}

/// [`w16_parts`]'s arrays (lent by [`conv_row_w16_in`], cleared once per row): the pass's
/// sums, a part's i32 sums, its later chunks' sums.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
type PartsScratch<'a> = (&'a mut [[i64; 4]; W16_PARTS_PAIRS], &'a mut [[i32; 4]; W16_PARTS_PAIRS], &'a mut [[i32; 4]; W16_MAX_PAIRS]);

/// Most pixel pairs of one pass of [`w16_parts`] (its sums wait on the stack).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const W16_PARTS_PAIRS: usize = 16;

/// [`conv_row_w16_in`]'s channel pair `c`, `c + 1` for a layer of several parts whose every
/// part takes the short epilogue: part by part, the sums of all the gathered pairs (`slots`,
/// `2 kl` values each, the first at pixel `ox`), for a part of whole groups in one i32 chunk (at
/// most 508 values, a multiple of four) by one assembly call
/// ([`super::dsp::dot2x2_w16_i32_ns`]), else by [`super::dsp::dot2x2_w16`] per pair (each sum
/// must fit i32), requantised with the part's multipliers decoded once and added to each pair's
/// sums, then [`block2x2_by`]'s short-path stores. False for any other layer or where a sum
/// does not fit (the caller then computes every pair of the channel pair again).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn w16_parts(
    p: &ConvParams<'_>,
    kl: usize,
    ww: &[u32],
    w0: &[i8],
    w1: &[i8],
    m: &[u8],
    b: &[u8],
    slots: &[i16],
    n: usize,
    (acc, sums, tmp): PartsScratch<'_>,
    out: &mut OutRow<'_>,
    ox: usize,
    c: usize,
) -> bool {
    let np = p.parts.len();
    let ((m0s, m1s), (bb0, bb1)) = (halves(m), halves(b));
    let (b0, b1) = (bias_at(bb0), bias_at(bb1));
    if b0.unsigned_abs() >= SHORT_MAX_BIAS || b1.unsigned_abs() >= SHORT_MAX_BIAS || m0s.len() < 8 * np || m1s.len() < 8 * np {
        return false;
    }
    let mut reqs = [[super::dsp::NatReq::ZERO; 2]; crate::model::graph::MAX_PARTS];
    for (((r, a), b), &ch) in reqs.iter_mut().zip(m0s.chunks_exact(8)).zip(m1s.chunks_exact(8)).zip(p.parts) {
        let (a, b) = (mult_raw(a), mult_raw(b));
        if !(short_ok(a) && short_ok(b) && ch > 0) {
            return false;
        }
        *r = [super::dsp::NatReq::new(a), super::dsp::NatReq::new(b)];
    }
    let post = p.post;
    let mut first = 0;
    while first < n {
        let cnt = (n - first).min(W16_PARTS_PAIRS);
        let Some(x) = slots.get(2 * kl * first..) else {
            return false; // never: `slots` holds `n` pairs
        };
        let (mut o, mut wo) = (0, 0);
        let Some(a) = acc.get_mut(..cnt) else {
            return false; // never: `cnt <= W16_PARTS_PAIRS`
        };
        a.fill([0; 4]);
        for (&ch, req) in p.parts.iter().zip(&reqs) {
            let nv = ch * p.k * p.k;
            let (Some(s), Some(xo), Some(wq), Some(a0), Some(a1)) = (sums.get_mut(..cnt), x.get(2 * o..), ww.get(wo..), w0.get(o..), w1.get(o..)) else {
                return false;
            };
            if !(nv.is_multiple_of(4) && super::dsp::dot2x2_w16_i32_chunks(wq, xo, nv / 4, 2 * kl, s, tmp)) {
                for (d, slot) in s.iter_mut().zip(xo.chunks((2 * kl).max(1))) {
                    match super::dsp::dot2x2_w16(wq, a0, a1, slot, nv).map(|d| d.map(i32::try_from)) {
                        Some([Ok(e0), Ok(e1), Ok(e2), Ok(e3)]) => *d = [e0, e1, e2, e3],
                        _ => return false,
                    }
                }
            }
            // The part's contributions added to the pass's sums (`dsp::requant_add`).
            super::dsp::requant_add(s, req, a);
            o += nv;
            wo += nv / 4 * 4;
        }
        short_pairs(post, b0, b1, acc.get(..cnt).unwrap_or_default(), out, (ox + 2 * first) * p.cout + c, p.cout);
        first += cnt;
    }
    true
}

/// [`conv_row_w16_in`]'s channel pair `c`, `c + 1` for a one-part layer: [`block2x2_by`]'s
/// integers with the pair's multipliers, biases and short-epilogue test decoded once for all the
/// `n` gathered pairs of pixels (`slots`, `2 kl` values each, the first at pixel `ox`) instead of
/// once per pair. A patch of whole groups in one i32 chunk: the sums of all the pairs by one
/// assembly call ([`super::dsp::dot2x2_w16_i32_n`]), then, where both channels' requantisation
/// and bias fold into one multiply-add ([`super::dsp::Folded`]), an epilogue without per-value
/// dispatch ([`folded_pairs`]).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn w16_one_part(
    p: &ConvParams<'_>,
    kl: usize,
    ww: &[u32],
    w0: &[i8],
    w1: &[i8],
    m: &[u8],
    b: &[u8],
    slots: &[i16],
    n: usize,
    (sums, tmp): (&mut [[i32; 4]; W16_MAX_PAIRS], &mut [[i32; 4]; W16_MAX_PAIRS]),
    out: &mut OutRow<'_>,
    ox: usize,
    c: usize,
) {
    let ((m0, m1), (b0, b1)) = (halves(m), halves(b));
    let (m0, m1, b0, b1) = (mult_raw(m0), mult_raw(m1), bias_at(b0), bias_at(b1));
    let small = b0.unsigned_abs() < SHORT_MAX_BIAS && b1.unsigned_abs() < SHORT_MAX_BIAS;
    let short = small && short_ok(m0) && short_ok(m1);
    let post = p.post;
    // (The unfolded paths' decoded multipliers are made where they are needed: made here for
    // every channel pair they cost some 4.5 M instructions at 160x120.)
    // A patch of whole groups in one i32 chunk: the sums as i32, straight into the short path.
    let one_chunk = short && kl.is_multiple_of(4) && kl / 4 <= super::dsp::I16_ASM_GROUPS;
    if one_chunk
        && let Some(sums) = sums.get_mut(..n)
        && super::dsp::dot2x2_w16_i32_n(ww, slots, kl / 4, sums)
    {
        let sums = &*sums;
        if let (Some(f0), Some(f1)) = (super::dsp::Folded::new(m0, b0), super::dsp::Folded::new(m1, b1)) {
            folded_pairs(post, f0, f1, sums, out, ox * p.cout + c, p.cout);
            return;
        }
        let (r0, r1) = (super::dsp::Requant::new(m0), super::dsp::Requant::new(m1));
        for (i, &[a0, a1, a2, a3]) in sums.iter().enumerate() {
            let (at_a, at_b) = ((ox + 2 * i) * p.cout + c, (ox + 2 * i + 1) * p.cout + c);
            out.set(at_a, finish_short(post, b0, r0.apply(a0)));
            out.set(at_a + 1, finish_short(post, b1, r1.apply(a1)));
            out.set(at_b, finish_short(post, b0, r0.apply(a2)));
            out.set(at_b + 1, finish_short(post, b1, r1.apply(a3)));
        }
        return;
    }
    // Longer patches (several chunks, or values past the whole groups): the i64 sums of every
    // pair first; where all of them fit i32, the folded epilogue as above (else, or with a short
    // table, the per-pair path below computes the channel pair again).
    if short
        && !one_chunk
        && let (Some(f0), Some(f1)) = (super::dsp::Folded::new(m0, b0), super::dsp::Folded::new(m1, b1))
    {
        let mut fits = n <= W16_MAX_PAIRS;
        // Whole groups: each chunk of all the pairs by one call.
        let batched = kl.is_multiple_of(4) && sums.get_mut(..n).is_some_and(|s| super::dsp::dot2x2_w16_i32_chunks(ww, slots, kl / 4, 2 * kl, s, tmp));
        for (slot, s) in slots.chunks_exact((2 * kl).max(1)).take(if batched { 0 } else { n }).zip(sums.iter_mut()) {
            match super::dsp::dot2x2_w16(ww, w0, w1, slot, kl).map(|d| d.map(i32::try_from)) {
                Some([Ok(a0), Ok(a1), Ok(a2), Ok(a3)]) => *s = [a0, a1, a2, a3],
                _ => {
                    fits = false;
                    break;
                }
            }
        }
        if fits {
            folded_pairs(post, f0, f1, sums.get(..n).unwrap_or_default(), out, ox * p.cout + c, p.cout);
            return;
        }
    }
    let (c0, c1) = (clamp_shift(m0), clamp_shift(m1));
    let (r0, r1) = (super::dsp::Requant::new(m0), super::dsp::Requant::new(m1));
    for (i, slot) in slots.chunks_exact((2 * kl).max(1)).take(n).enumerate() {
        let (at_a, at_b) = ((ox + 2 * i) * p.cout + c, (ox + 2 * i + 1) * p.cout + c);
        if one_chunk && let Some([a0, a1, a2, a3]) = super::dsp::dot2x2_w16_i32(ww, slot, kl / 4) {
            out.set(at_a, finish_short(post, b0, r0.apply(a0)));
            out.set(at_a + 1, finish_short(post, b1, r1.apply(a1)));
            out.set(at_b, finish_short(post, b0, r0.apply(a2)));
            out.set(at_b + 1, finish_short(post, b1, r1.apply(a3)));
            continue;
        }
        let Some(d) = super::dsp::dot2x2_w16(ww, w0, w1, slot, kl) else {
            // A short table: `block2x2_by` stops before the part, with sums of 0.
            for (at, bias) in [(at_a, b0), (at_a + 1, b1), (at_b, b0), (at_b + 1, b1)] {
                out.set(at, if small { finish_short(post, bias, 0) } else { finish_with(post, bias, 0) });
            }
            continue;
        };
        match (short, d.map(i32::try_from)) {
            (true, [Ok(a0), Ok(a1), Ok(a2), Ok(a3)]) => {
                out.set(at_a, finish_short(post, b0, r0.apply(a0)));
                out.set(at_a + 1, finish_short(post, b1, r1.apply(a1)));
                out.set(at_b, finish_short(post, b0, r0.apply(a2)));
                out.set(at_b + 1, finish_short(post, b1, r1.apply(a3)));
            }
            _ => {
                out.set(at_a, finish_with(post, b0, 0i64.saturating_add(requantize(d[0], c0))));
                out.set(at_a + 1, finish_with(post, b1, 0i64.saturating_add(requantize(d[1], c1))));
                out.set(at_b, finish_with(post, b0, 0i64.saturating_add(requantize(d[2], c0))));
                out.set(at_b + 1, finish_with(post, b1, 0i64.saturating_add(requantize(d[3], c1))));
            }
        }
    }
}

/// The stores of [`w16_one_part`]'s folded epilogue: `sums[i]` are pair `i`'s `[w0 . a, w1 .
/// a, w0 . b, w1 . b]`, pixel a of pair `i` at `at + 2 i step` of `out`, pixel b `step` later;
/// each value `f.apply(sum)` activated and saturated as [`finish_short`] and [`OutRow::set`]
/// do, the activation and the storage type chosen once for all of them (monomorphised loops).
/// Out of line: inlined into both call sites of every `conv_row_w16_in` instance, its twelve
/// loops made each instance 40 KB instead of 17 KB, for 36 K instructions a 160x120 frame.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn folded_pairs(post: PostOp, f0: super::dsp::Folded, f1: super::dsp::Folded, sums: &[[i32; 4]], out: &mut OutRow<'_>, at: usize, step: usize) {
    use crate::arith::{sat_i8, sat_i16, sat_u8};
    match out {
        OutRow::I16(o) => folded_post(post, f0, f1, sums, o, at, step, sat_i16),
        OutRow::U8(o) => folded_post(post, f0, f1, sums, o, at, step, sat_u8),
        OutRow::I8(o) => folded_post(post, f0, f1, sums, o, at, step, sat_i8),
    }
}

/// [`folded_pairs`] for one storage type (`sat`: [`OutRow::set`]'s saturation).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn folded_post<T>(post: PostOp, f0: super::dsp::Folded, f1: super::dsp::Folded, sums: &[[i32; 4]], o: &mut [T], at: usize, step: usize, sat: fn(i64) -> T) {
    use crate::arith::sat_i16;
    match post {
        PostOp::None => folded_run(f0, f1, sums, o, at, step, |v| sat(v as i64)),
        PostOp::Relu => folded_run(f0, f1, sums, o, at, step, |v| sat(v.max(0) as i64)),
        PostOp::Sigmoid => folded_run(f0, f1, sums, o, at, step, |v| sat(lut::sigmoid_q12(sat_i16(v as i64)) as i64)),
        PostOp::Tanh => folded_run(f0, f1, sums, o, at, step, |v| sat(lut::tanh_q12(sat_i16(v as i64)) as i64)),
    }
}

/// [`folded_post`]'s loop for one activation `g`.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn folded_run<T>(f0: super::dsp::Folded, f1: super::dsp::Folded, sums: &[[i32; 4]], o: &mut [T], at: usize, step: usize, g: impl Fn(i32) -> T) {
    // Channel by channel through a raw pointer, the outputs' bounds tested once: one
    // multiplier's constants in registers (per value a `set_at` with its bounds test and the
    // other channel's constants spilled took some 15 instructions).
    let last = (2 * sums.len()).saturating_sub(1) * step + at + 1;
    if sums.is_empty() || last >= o.len() || step == 0 {
        for (i, &[a0, a1, a2, a3]) in sums.iter().enumerate() {
            let at = at + 2 * i * step;
            set_at(o, at, g(f0.apply(a0)));
            set_at(o, at + 1, g(f1.apply(a1)));
            set_at(o, at + step, g(f0.apply(a2)));
            set_at(o, at + step + 1, g(f1.apply(a3)));
        }
        return;
    }
    for (f, c) in [(f0, 0), (f1, 1)] {
        // SAFETY: pair `i`'s outputs are `at + c + 2 i step` and `step` after it, the last of
        // them `at + 1 + (2 n - 1) step < o.len()` (tested above).
        unsafe {
            let mut p = o.as_mut_ptr().add(at + c);
            if f.high_only() {
                // Shifts of 33 and more: one `SMMLA` a value (`Folded::apply_high`).
                for &[a0, a1, a2, a3] in sums {
                    let (a, b) = if c == 0 { (a0, a2) } else { (a1, a3) };
                    *p = g(f.apply_high(a));
                    *p.add(step) = g(f.apply_high(b));
                    p = p.wrapping_add(2 * step);
                }
                continue;
            }
            for &[a0, a1, a2, a3] in sums {
                let (a, b) = if c == 0 { (a0, a2) } else { (a1, a3) };
                *p = g(f.apply(a));
                *p.add(step) = g(f.apply(b));
                p = p.wrapping_add(2 * step);
            }
        }
    }
}

/// [`finish_short`]'s stores of pairs of pixels: `sums[i]` are pair `i`'s `[c0 . a, c1 . a, c0 .
/// b, c1 . b]` sums of the parts' short contributions, pixel a of pair `i` at `at + 2 i step`
/// of `out`, pixel b `step` later; `b0`, `b1` the channels' biases. The activation and the
/// storage type chosen once for all of them (monomorphised loops, as [`folded_pairs`]).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn short_pairs(post: PostOp, b0: i64, b1: i64, sums: &[[i64; 4]], out: &mut OutRow<'_>, at: usize, step: usize) {
    use crate::arith::{sat_i8, sat_i16, sat_u8};
    match out {
        OutRow::I16(o) => short_post(post, b0, b1, sums, o, at, step, sat_i16),
        OutRow::U8(o) => short_post(post, b0, b1, sums, o, at, step, sat_u8),
        OutRow::I8(o) => short_post(post, b0, b1, sums, o, at, step, sat_i8),
    }
}

/// [`short_pairs`] for one storage type (`sat`: [`OutRow::set`]'s saturation).
#[allow(clippy::too_many_arguments)]
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn short_post<T>(post: PostOp, b0: i64, b1: i64, sums: &[[i64; 4]], o: &mut [T], at: usize, step: usize, sat: fn(i64) -> T) {
    use crate::arith::sat_i16;
    match post {
        PostOp::None => short_run(b0, b1, sums, o, at, step, sat),
        PostOp::Relu => short_run(b0, b1, sums, o, at, step, |v| sat(v.max(0))),
        PostOp::Sigmoid => short_run(b0, b1, sums, o, at, step, |v| sat(lut::sigmoid_q12(sat_i16(v)) as i64)),
        PostOp::Tanh => short_run(b0, b1, sums, o, at, step, |v| sat(lut::tanh_q12(sat_i16(v)) as i64)),
    }
}

/// [`short_post`]'s loop for one activation `g`: `g((sum + bias + 2^7) >> 8)`, as
/// [`finish_short`] (no sum can overflow on the short path).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn short_run<T>(b0: i64, b1: i64, sums: &[[i64; 4]], o: &mut [T], mut at: usize, step: usize, g: impl Fn(i64) -> T) {
    let (c0, c1) = (b0 + (1 << (EXTRA_BITS - 1)), b1 + (1 << (EXTRA_BITS - 1)));
    // As `folded_run`: the outputs' bounds tested once, then stores through a raw pointer.
    let last = (2 * sums.len()).saturating_sub(1) * step + at + 1;
    if !sums.is_empty() && last < o.len() {
        // SAFETY: pair `i`'s outputs are `at + 2 i step + {0, 1}` and `step` after them, the
        // last of them `at + 1 + (2 n - 1) step < o.len()` (tested above).
        unsafe {
            let mut p = o.as_mut_ptr().add(at);
            for &[s0, s1, s2, s3] in sums {
                *p = g((s0 + c0) >> EXTRA_BITS);
                *p.add(1) = g((s1 + c1) >> EXTRA_BITS);
                *p.add(step) = g((s2 + c0) >> EXTRA_BITS);
                *p.add(step + 1) = g((s3 + c1) >> EXTRA_BITS);
                p = p.wrapping_add(2 * step);
            }
        }
        return;
    }
    for &[s0, s1, s2, s3] in sums {
        set_at(o, at, g((s0 + c0) >> EXTRA_BITS));
        set_at(o, at + 1, g((s1 + c1) >> EXTRA_BITS));
        set_at(o, at + step, g((s2 + c0) >> EXTRA_BITS));
        set_at(o, at + step + 1, g((s3 + c1) >> EXTRA_BITS));
        at += 2 * step;
    }
}

/// [`conv_row`] for i16 activations on the DSP build by [`conv_row_w16`] (the gathered pairs
/// straight into its slots), where the engine's byte `scratch` holds the widened weights, a
/// patch for the odd channel and pixel, and at least [`W16_MIN_PAIRS`] pairs of patches (the
/// layers with a patch up to a quarter of the largest); false, having computed nothing,
/// otherwise.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn conv_row_i16_w16(p: &ConvParams<'_>, inputs: &[PartRows<'_, i16>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
    let kl = p.patch_len();
    let skip = scratch.as_ptr().align_offset(2);
    let Some((single, rest)) = scratch.get_mut(skip..).and_then(|s| s.split_at_mut_checked(2 * kl)) else {
        return false;
    };
    let Ok(single) = bytemuck::try_cast_slice_mut::<u8, i16>(single) else {
        return false;
    };
    conv_row_w16(p, inputs, w_in, out, single, rest, |ox, _, slot| gather2(p, inputs, w_in, ox, slot))
}

/// Fewest pixel pairs per widening for which [`conv_row_i16_w16`] runs before
/// [`conv_row_i16_nat`] (with fewer, the in-place path first where it applies).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const W16_NAT_PAIRS: usize = 3;

/// The i16 rows' own path on the DSP build: [`conv_row_i16_w16`] where the scratch holds at
/// least [`W16_NAT_PAIRS`] pairs of patches, else [`conv_row_i16_nat`] first; false, having
/// computed nothing, where neither applies.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn conv_row_i16_wide(p: &ConvParams<'_>, inputs: &[PartRows<'_, i16>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
    let kl = p.patch_len();
    let pairs = scratch.len().saturating_sub(2 * kl + 4 * w16_words(p) + 8) / (4 * kl).max(1);
    if pairs < W16_NAT_PAIRS && conv_row_i16_nat(p, inputs, w_in, out, scratch) {
        return true;
    }
    conv_row_i16_w16(p, inputs, w_in, out, scratch) || conv_row_i16_nat(p, inputs, w_in, out, scratch)
}

/// [`conv_row_i16_w16`] with the gathered pairs of patches in `spare` (arena bytes idle while
/// the layer runs: the ConvGRU 1/16 gates, whose pairs do not fit the engine's patch scratch,
/// take the 1/8 pass's line buffers) and the patch for the odd channel and pixel and the widened
/// weights in `scratch`; false, having computed nothing, where `spare` holds fewer than
/// [`W16_MIN_PAIRS`] pairs or `scratch` is too short.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn conv_row_i16_w16_spare(p: &ConvParams<'_>, inputs: &[PartRows<'_, i16>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8], spare: &mut [u8]) -> bool {
    let kl = p.patch_len();
    let skip = scratch.as_ptr().align_offset(2);
    let Some((single, rest)) = scratch.get_mut(skip..).and_then(|s| s.split_at_mut_checked(2 * kl)) else {
        return false;
    };
    let Ok(single) = bytemuck::try_cast_slice_mut::<u8, i16>(single) else {
        return false;
    };
    let (Some(ww), Some(slots)) = (aligned_words(rest), aligned_words(spare)) else {
        return false;
    };
    let Some(ww) = ww.get_mut(..w16_words(p)) else {
        return false;
    };
    conv_row_w16_in(p, inputs, w_in, out, single, ww, slots, |ox, _, slot| gather2(p, inputs, w_in, ox, slot))
}

/// Narrowest output row for [`conv_row_i16_nat`]: widening a group of a channel pair's weights
/// costs 13 instructions per row, each block of two pixels then saves 4 or more per group
/// against the 16-instruction loop (plus the gather), and the `k / 2` pixels at each end take a
/// one-pixel block each. Measured at 64x48: from rows of 8 pixels (the 1/8 ConvGRU gates) the
/// frame takes 10.7 M fewer instructions (1.4 %); from rows of 4 (the 1/16 gates too) 1.7 M fewer.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const NAT_MIN_WIDTH: usize = 8;

/// [`conv_row`] for i16 activations on the DSP build with no gather: per channel pair, the
/// weights of every kernel row of every part are widened once for the whole row
/// (`dsp::widen_weights_nat`, natural order, into `scratch`), then every block of two pixels
/// reads its activations in place from the input rows (`dsp::nat_block` over a [`NatTable`]: 12
/// instructions per 16 MACs where both pixels' values are word-aligned, 14 otherwise, against
/// 16 plus the gather for [`Elem::dot2x2`]). For the layers whose pairs of patches fit no
/// scratch (the 1/8 ConvGRU gates): the widened weights of one channel pair need `4
/// patch_len()` bytes at most, the engine's patch scratch. Stride 1, odd `k`, an even channel
/// count, at most [`NAT_ENTRIES`] kernel rows of parts and rows of at least [`NAT_MIN_WIDTH`]
/// pixels; false, having computed nothing, otherwise. The pixels at the row's ends (and an odd
/// one left over) are blocks of one pixel taken twice. The same products, exact, so the same
/// integers.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn conv_row_i16_nat(p: &ConvParams<'_>, inputs: &[PartRows<'_, i16>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
    let (k, kl, w_out) = (p.k, p.patch_len(), p.out_width(w_in));
    if p.parts.len() > crate::model::graph::MAX_PARTS || p.stride != 1 || k.is_multiple_of(2) || !p.cout.is_multiple_of(2) || kl == 0 || w_out < NAT_MIN_WIDTH || inputs.len() < p.parts.len() {
        return false;
    }
    // Every present input row must hold the whole row (else the portable path runs), so that
    // the tables' reads stay inside the rows.
    // The tables' sizes and fields (`NatTable::build` never runs out of them then).
    if p.parts.len() * k > NAT_ENTRIES || u32::try_from(kl).is_err() {
        return false;
    }
    for (rows, &ch) in inputs.iter().zip(p.parts) {
        if k * ch / 4 > super::dsp::I16_ASM_GROUPS || u32::try_from(w_in * ch).is_err() || rows.rows.iter().take(k).flatten().any(|r| r.len() < w_in * ch) {
            return false;
        }
    }
    // Words of a channel pair's widened runs, part by part.
    let words: usize = p.parts.iter().map(|&ch| 4 * k * (k * ch / 4)).sum();
    let Some(ww) = aligned_words(scratch).and_then(|w| w.get_mut(..words)) else {
        return false;
    };
    let pad = k / 2;
    // The table's entries cleared in this frame (built by value, 2 KB of them were cleared in a
    // second copy and copied over).
    let mut entries = [super::dsp::NatEntry::EMPTY; 4 * NAT_ENTRIES];
    let mut t = NatTable { e: &mut entries, ne: 0, whole: true };
    // The inside blocks' table at the table's front, built once per row (its entries), and the
    // single pixels' tables (column and entries) after it, or at the front until the inside
    // one is built (which then overwrites them): each built once per row where they fit (one
    // that does not drops the others, then the inside one).
    let mut inside: Option<usize> = None;
    let mut keep = [[0i64; 4]; NAT_KEEP];
    let mut lone = [(0, 0, 0); 3];
    let mut nl = 0;
    for (cp, ((w, m), b)) in channel_pairs(p, kl, 0).enumerate() {
        let (w0, w1) = halves(w);
        let (mut o, mut wo) = (0, 0);
        for &ch in p.parts {
            let (run, gr) = (k * ch, k * ch / 4);
            for ky in 0..k {
                if let (Some(a), Some(b), Some(d)) = (w0.get(o + ky * run..), w1.get(o + ky * run..), ww.get_mut(wo + 4 * ky * gr..)) {
                    super::dsp::widen_weights_nat(a, b, gr, d);
                }
            }
            o += k * run;
            wo += 4 * k * gr;
        }
        let ww = &*ww;
        // The channel pair's epilogue decoded once (`block2x2_by`'s short path): the parts'
        // multipliers, the biases and whether every part and both biases allow the short path.
        let np = p.parts.len();
        let ((m0s, m1s), (bb0, bb1)) = (halves(m), halves(b));
        let (b0, b1) = (bias_at(bb0), bias_at(bb1));
        let mut reqs = [[super::dsp::NatReq::ZERO; 2]; crate::model::graph::MAX_PARTS];
        let mut short = b0.unsigned_abs() < SHORT_MAX_BIAS && b1.unsigned_abs() < SHORT_MAX_BIAS && m0s.len() >= 8 * np && m1s.len() >= 8 * np;
        for ((r, a), b) in reqs.iter_mut().zip(m0s.chunks_exact(8)).zip(m1s.chunks_exact(8)).take(np) {
            let (a, b) = (mult_raw(a), mult_raw(b));
            short &= short_ok(a) && short_ok(b);
            *r = [super::dsp::NatReq::new(a), super::dsp::NatReq::new(b)];
        }
        let reqs = reqs.get(..np).unwrap_or_default();
        // Pixels whose windows lie inside the input in pairs (one table for all of them,
        // relative to the column), the others (the `k / 2` at each end of the row, an odd one
        // left over) one at a time, as a block with both pixels the same (their own table:
        // an end pixel's runs are shorter). Tables serve every channel pair, and the channel
        // pairs walk the row in alternate directions: each starts with the last one's table.
        // The short pairs' sums kept by pair index (`(xa - pad) / 2`) and stored by one
        // `short_pairs` call after the row (a call per block took some 45 instructions around
        // its four stores); `kept` marks them (a pair on the long path is not kept).
        let mut kept = 0u32;
        for (xa, xb) in nat_blocks(pad, w_in, w_out, cp % 2 == 1) {
            let pair = xb != xa;
            let found = lone.get(..nl).unwrap_or_default().iter().find(|l| l.0 == xa).copied();
            let range = match (pair, inside, found) {
                (true, Some(n), _) => (0, n),
                (false, _, Some((_, a, e))) => (a, e),
                (true, None, _) => {
                    t.build(0, k, p.parts, inputs, w_in, words, kl, None);
                    inside = Some(t.ne);
                    // The single pixels' tables at the front are overwritten.
                    nl = 0;
                    (0, t.ne)
                }
                (false, _, None) => {
                    let base = inside.unwrap_or(0);
                    if nl >= lone.len() {
                        nl = 0;
                    }
                    let mut a = lone.get(..nl).unwrap_or_default().last().map_or(base, |l| l.2);
                    t.build(a, k, p.parts, inputs, w_in, words, kl, Some(xa));
                    if !t.whole && a > base {
                        // Out of entries: the other single pixels' tables dropped.
                        (nl, a) = (0, base);
                        t.build(a, k, p.parts, inputs, w_in, words, kl, Some(xa));
                    }
                    if !t.whole && a > 0 {
                        // Still out of entries: this one at the front, the inside one again
                        // when next needed.
                        (inside, nl, a) = (None, 0, 0);
                        t.build(0, k, p.parts, inputs, w_in, words, kl, Some(xa));
                    }
                    if let Some(l) = lone.get_mut(nl) {
                        *l = (xa, a, t.ne);
                        nl += 1;
                    }
                    (a, t.ne)
                }
            };
            if !t.whole {
                return true; // never: the checks above keep every table whole
            }
            let mut sums = [[0i64; 4]; crate::model::graph::MAX_PARTS];
            t.run(range, if pair { xa - pad } else { 0 }, kl, w, ww, &mut sums);
            // Every part's sums in i32: the short path's integers with the decoded epilogue;
            // else `block2x2_by` from the start, as before.
            if short {
                // Every part's sums requantised and added by one assembly loop (`dsp::requant_parts`).
                let mut acc = [0i64; 4];
                if super::dsp::requant_parts(&sums, reqs, &mut acc) {
                    let i = xa.wrapping_sub(pad) / 2; // (pairs: xa >= pad)
                    if pair && let Some(k) = keep.get_mut(i) {
                        *k = acc;
                        kept |= 1 << i;
                        continue;
                    }
                    // (A single pixel, `xb == xa`: its two sums twice, the same values.)
                    short_pairs(p.post, b0, b1, &[acc], out, xa * p.cout + 2 * cp, (xb - xa) * p.cout);
                    continue;
                }
            }
            let mut part = 0;
            block2x2_by(p, m, b, out, xa * p.cout, xb * p.cout, 2 * cp, |_, _, _| {
                let s = sums.get(part).copied();
                part += 1;
                s
            });
        }
        // The kept pairs: all of them by one call, else one by one.
        let np2 = (kept.count_ones() as usize).min(NAT_KEEP);
        if kept == (1u32 << np2) - 1 {
            short_pairs(p.post, b0, b1, keep.get(..np2).unwrap_or_default(), out, pad * p.cout + 2 * cp, p.cout);
        } else {
            for (i, acc) in keep.iter().enumerate().filter(|&(i, _)| kept & (1 << i) != 0) {
                short_pairs(p.post, b0, b1, core::slice::from_ref(acc), out, (pad + 2 * i) * p.cout + 2 * cp, p.cout);
            }
        }
    }
    true
}

/// Pairs of pixels per row whose short sums [`conv_row_i16_nat`] keeps for one store call (the
/// 1/8 grid's 20 columns at 160x120 are 9 pairs; further pairs are stored block by block).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const NAT_KEEP: usize = 16;

/// The blocks of [`conv_row_i16_nat`]'s row, left to right or (`reverse`) right to left: `(xa,
/// xa + 1)` for two pixels whose windows lie inside the input (pixels `pad ..` paired from the
/// left), `(x, x)` for the others.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn nat_blocks(pad: usize, w_in: usize, w_out: usize, reverse: bool) -> impl Iterator<Item = (usize, usize)> {
    // Pixels `pad .. end` see every kernel column inside the input; an odd count leaves the
    // last of them alone.
    let end = w_in.saturating_sub(pad).max(pad);
    let odd_last = (end - pad) % 2 == 1;
    let mut x = if reverse { w_out } else { 0 };
    core::iter::from_fn(move || {
        if reverse {
            let last = x.checked_sub(1)?;
            let pair = last > pad && last < end && !(odd_last && last + 1 == end);
            let xa = if pair { last - 1 } else { last };
            x = xa;
            Some((xa, last))
        } else {
            if x >= w_out {
                return None;
            }
            let xa = x;
            let xb = if xa >= pad && xa + 1 < end { xa + 1 } else { xa };
            x = xb + 1;
            Some((xa, xb))
        }
    })
}

/// Most entries of a [`NatTable`] (kernel rows times parts): 3 x 3 kernels of up to
/// [`crate::model::graph::MAX_PARTS`] parts, or fewer parts of larger kernels.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
const NAT_ENTRIES: usize = 3 * crate::model::graph::MAX_PARTS;

/// One block's work for [`conv_row_i16_nat`]: `dsp::nat_block` entries for the runs' whole
/// groups and, as plain entries, their other values (a run's last `k ch % 4`, an end pixel's
/// first and last). Room for several tables one after another (a block's needs `3
/// NAT_ENTRIES` at most): the inside blocks' and the end pixels' of a row, kept for all its
/// channel pairs (`3 NAT_ENTRIES` left the six-part gate layers rebuilding them: 28 M
/// instructions more at 160x120; `6 NAT_ENTRIES` counts as `4`).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
struct NatTable<'a> {
    e: &'a mut [super::dsp::NatEntry; 4 * NAT_ENTRIES],
    ne: usize,
    /// Whether every entry fitted (else the row stops).
    whole: bool,
}

#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
impl NatTable<'_> {
    #[inline(always)]
    fn push(&mut self, e: super::dsp::NatEntry) {
        match self.e.get_mut(self.ne) {
            Some(d) if e.part() < crate::model::graph::MAX_PARTS => {
                *d = e;
                self.ne += 1;
            }
            _ => self.whole = false,
        }
    }

    /// Values `row[at ..]` (pixel a at column 0), `n` of them (fewer than 8), against weights
    /// `w .. w + n` of the channel pair's rows (`kl` each), as a plain entry.
    #[allow(clippy::too_many_arguments)]
    #[inline(always)]
    fn plain(&mut self, row: &[i16], at: usize, step: usize, bd: usize, kl: usize, w: usize, n: usize, part: usize) {
        if n == 0 {
            return;
        }
        // The weights inside a channel's row (`nat_block` reads w1's `kl` bytes after w0's); the
        // values inside the row (the caller's bounds, as for the groups).
        match row.get(at..) {
            Some(r) if n < 8 && w + n <= kl => {
                let e = super::dsp::NatEntry::new(r.as_ptr(), w, 2 * step, n | super::dsp::NatEntry::PLAIN, 2 * bd, part);
                self.push(e);
            }
            _ => self.whole = false,
        }
    }

    /// The table of the block of pixels `col + pad`, `col + pad + 1` for every `col` whose
    /// windows lie inside the input (`lone` = None: the entries relative to the column), or of
    /// the single pixel `lone` (both pixels the same, the kernel columns inside the input only).
    /// Entries address the widened runs (`words` of them, part by part, kernel row by kernel
    /// row) and the int8 weights (`kl` per channel) by offsets, so the table serves every
    /// channel pair of the row. Written from entry `at` on (the entries before it kept).
    #[allow(clippy::too_many_arguments)]
    #[inline(never)]
    fn build(&mut self, at: usize, k: usize, parts: &[usize], inputs: &[PartRows<'_, i16>], w_in: usize, words: usize, kl: usize, lone: Option<usize>) {
        (self.ne, self.whole) = (at, true);
        let pad = k / 2;
        let (mut o, mut wo) = (0, 0);
        for (part, (rows, &ch)) in inputs.iter().zip(parts).enumerate() {
            let (run, gr) = (k * ch, k * ch / 4);
            // The run's values `s .. e` (all, or an end pixel's columns inside the input) and
            // the row index of value `s` of pixel a at column 0.
            let (s, e, base) = match lone {
                None => (0, run, 0),
                Some(x) => {
                    let (c0, c1) = (pad.saturating_sub(x), k.min((w_in + pad).saturating_sub(x)));
                    (c0 * ch, c1.max(c0) * ch, (x + c0).saturating_sub(pad) * ch)
                }
            };
            let (step, bd) = if lone.is_some() { (0, 0) } else { (ch, ch) };
            for ky in 0..k {
                let Some(row) = rows.row(ky) else {
                    continue;
                };
                let wr = o + ky * run;
                let (g0, g1) = (s.div_ceil(4), (e / 4).min(gr));
                if g0 >= g1 {
                    self.plain(row, base, step, bd, kl, wr + s, e - s, part);
                    continue;
                }
                self.plain(row, base, step, bd, kl, wr + s, 4 * g0 - s, part);
                let at = wo + 4 * ky * gr + 4 * g0;
                match row.get(base + 4 * g0 - s..) {
                    Some(first) if at + 4 * (g1 - g0) <= words => {
                        let e = super::dsp::NatEntry::new(first.as_ptr(), 4 * at, 2 * step, g1 - g0, 2 * bd, part);
                        self.push(e);
                    }
                    _ => self.whole = false,
                }
                self.plain(row, base + 4 * g1 - s, step, bd, kl, wr + 4 * g1, e - 4 * g1, part);
            }
            o += k * run;
            wo += 4 * k * gr;
        }
    }

    /// The block at column `col` (0 for a single pixel's table), entries `from .. to`, into `sums`, with the channel
    /// pair's widened weights `ww` and int8 weights `w` (`2 kl`: w0's, then w1's).
    #[inline(always)]
    fn run(&self, (from, to): (usize, usize), col: usize, kl: usize, w: &[i8], ww: &[u32], sums: &mut [[i64; 4]; crate::model::graph::MAX_PARTS]) {
        let e = self.e.get(from..to).unwrap_or_default();
        if w.len() < 2 * kl {
            return; // never: `channel_pairs` gives `2 kl` weights
        }
        // SAFETY: `build` made every entry from a row holding `w_in ch` values (checked by
        // `conv_row_i16_nat`) and values that both pixels' windows cover inside the input: for
        // the inside blocks at `col` (`col + 1 + 2 pad < w_in`) values from `col ch` on and one
        // pixel later, at most `(col + 1) ch + k ch <= w_in ch`; for a single pixel its own
        // columns inside the input. A groups entry's run lies inside the `words` widened words
        // (`ww` holds them) at a multiple of 16 bytes, `1 <= groups <= I16_ASM_GROUPS` (checked
        // by the caller, `groups <= k ch / 4`); a plain entry's weights lie inside a channel's
        // `kl` (`w` holds `2 kl`), 1 to 7 of them; every part index is below `MAX_PARTS =
        // sums.len()` (`push` keeps none else).
        unsafe { super::dsp::nat_block(e, col, sums, kl, w, ww) };
    }
}

/// The u8 pair layout of [`gather2`] (per part, groups of four values of patch `a` then `b`,
/// then the `n % 4` last values of each) in the i16 pair layout of the DSP build
/// ([`pair_index`] with the swap: each group as values 0, 2, 1, 3).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline]
fn widen_pairs(p: &ConvParams<'_>, pair: &[u8], wide: &mut [i16]) {
    let mut base = 0;
    for &ch in p.parts {
        let n = ch * p.k * p.k;
        let (Some(src), Some(dst)) = (pair.get(2 * base..2 * (base + n)), wide.get_mut(2 * base..2 * (base + n))) else {
            return;
        };
        let q = n / 4 * 4;
        let (sg, st) = src.split_at(2 * q);
        let (dg, dt) = dst.split_at_mut(2 * q);
        super::dsp::widen_u8_groups(dg, sg);
        for (d, &s) in dt.iter_mut().zip(st) {
            *d = s as i16;
        }
        base += n;
    }
}

/// Plain twin of [`conv_row`] over whole tensors: `inputs[i]` is part `i` as an HWC tensor of
/// `h_in x w_in x parts[i]`; writes the whole `h_out x w_out x cout` output.
pub fn conv_plain<T: Elem>(p: &ConvParams<'_>, inputs: &[&[T]], h_in: usize, w_in: usize, out: &mut OutRow<'_>) {
    let k = p.k as isize;
    let pad = k / 2;
    let kl = p.patch_len();
    let h_out = (h_in + 2 * (p.k / 2) - p.k) / p.stride + 1;
    let w_out = p.out_width(w_in);
    for oy in 0..h_out {
        for ox in 0..w_out {
            for c in 0..p.cout {
                let wts = p.weights.get(c * kl..(c + 1) * kl).unwrap_or_default();
                let mut sum = 0i64;
                let mut o = 0;
                for (part, (t, &ch)) in inputs.iter().zip(p.parts).enumerate() {
                    let mut acc = 0i64;
                    for ky in 0..k {
                        for kx in 0..k {
                            let iy = (oy * p.stride) as isize + ky - pad;
                            let ix = (ox * p.stride) as isize + kx - pad;
                            if iy >= 0 && ix >= 0 && (iy as usize) < h_in && (ix as usize) < w_in {
                                let base = (iy as usize * w_in + ix as usize) * ch;
                                if let (Some(w), Some(x)) = (wts.get(o..o + ch), t.get(base..base + ch)) {
                                    acc += dot_plain(w, x);
                                }
                            }
                            o += ch;
                        }
                    }
                    sum = sum.saturating_add(part_sum(p, c, part, acc));
                }
                out.set((oy * w_out + ox) * p.cout + c, finish(p, c, sum));
            }
        }
    }
}

#[cfg(all(test, feature = "std"))]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::testutil::Rng;
    use super::*;

    fn random_layer(r: &mut Rng, k: usize, stride: usize, parts: &[usize], cout: usize, post: PostOp) -> (Vec<i8>, Vec<u8>, Vec<u8>) {
        let kl = k * k * parts.iter().sum::<usize>();
        let w: Vec<i8> = (0..cout * kl).map(|_| r.i8()).collect();
        let b: Vec<i64> = (0..cout).map(|_| (r.next() as i64) >> 50).collect();
        let m: Vec<Multiplier> = (0..cout * parts.len())
            .map(|_| Multiplier { m: (1 << 30) + (r.below(1 << 30) as i32), shift: 4 + r.below(16) as u8 })
            .collect();
        let _ = (stride, post);
        (w, encode_bias(&b), encode_mults(&m))
    }

    #[derive(Clone, Copy, PartialEq)]
    enum Out {
        I8,
        U8,
        I16,
    }

    fn check<T: Elem>(make: impl Fn(&mut Rng) -> T, k: usize, stride: usize, parts: &[usize], cout: usize, post: PostOp, out: Out) {
        let mut r = Rng(0xC0FFEE + k as u64 * 31 + stride as u64);
        let (h, w) = (7, 9);
        let (wts, bias, mult) = random_layer(&mut r, k, stride, parts, cout, post);
        let p = ConvParams { k, stride, parts, cout, weights: &wts, bias: BiasRef(&bias), mult: MultRef(&mult), post };
        let tensors: Vec<Vec<T>> = parts.iter().map(|&c| (0..h * w * c).map(|_| make(&mut r)).collect()).collect();
        let refs: Vec<&[T]> = tensors.iter().map(|t| t.as_slice()).collect();
        let (ho, wo) = ((h + 2 * (k / 2) - k) / stride + 1, p.out_width(w));
        let mut a16 = vec![0i16; ho * wo * cout];
        let mut a8 = vec![0i8; ho * wo * cout];
        let mut au = vec![0u8; ho * wo * cout];
        {
            let mut o = match out {
                Out::I16 => OutRow::I16(&mut a16),
                Out::I8 => OutRow::I8(&mut a8),
                Out::U8 => OutRow::U8(&mut au),
            };
            conv_plain(&p, &refs, h, w, &mut o);
        }
        // One patch (pixel by pixel) and two (pixel pairs) must give the plain twin's integers.
        for npatch in [1, 2] {
        let mut b16 = vec![0i16; ho * wo * cout];
        let mut b8 = vec![0i8; ho * wo * cout];
        let mut bu = vec![0u8; ho * wo * cout];
        let mut patch = vec![T::default(); npatch * p.patch_len()];
        for oy in 0..ho {
            let rows: Vec<PartRows<T>> =
                tensors.iter().zip(parts).map(|(t, &c)| PartRows::of_tensor(t, h, w * c, oy, k, stride)).collect();
            let r = oy * wo * cout..(oy + 1) * wo * cout;
            let mut o = match out {
                Out::I16 => OutRow::I16(&mut b16[r]),
                Out::I8 => OutRow::I8(&mut b8[r]),
                Out::U8 => OutRow::U8(&mut bu[r]),
            };
            conv_row(&p, &rows, w, &mut o, &mut patch);
        }
        assert_eq!(a16, b16, "{npatch} patches");
        assert_eq!(a8, b8, "{npatch} patches");
        assert_eq!(au, bu, "{npatch} patches");
        }
        let nonzero = a16.iter().any(|v| *v != 0) || a8.iter().any(|v| *v != 0) || au.iter().any(|v| *v != 0);
        assert!(nonzero, "all zero: k {k} s {stride} {parts:?} {post:?}");
    }

    #[test]
    fn row_kernel_matches_plain_twin() {
        for post in [PostOp::None, PostOp::Relu, PostOp::Sigmoid, PostOp::Tanh] {
            check(|r| r.i8(), 3, 1, &[5, 3], 4, post, Out::I8);
            check(|r| r.i8(), 3, 2, &[6], 5, post, Out::I16);
            check(|r| r.i16(), 3, 1, &[4, 1, 7], 3, post, Out::I16);
            check(|r| r.i16(), 1, 1, &[9], 6, post, Out::I16);
            check(|r| r.i8(), 7, 2, &[3], 4, post, Out::I8);
            check(|r| r.i16(), 7, 1, &[1], 4, post, Out::I16);
            check(|r| r.i8(), 1, 2, &[4], 3, post, Out::I8);
            // u8 (ReLU) activations: the backbone and the context.
            check(|r| r.i8() as u8, 3, 1, &[5, 3], 4, post, Out::U8);
            check(|r| r.i8() as u8, 3, 2, &[6], 5, post, Out::I16);
            check(|r| r.i8() as u8, 1, 2, &[4], 3, post, Out::U8);
            check(|r| r.i16(), 7, 2, &[3], 4, post, Out::U8);
            // Parts of whole groups of four (and mixed), as in the shipped models.
            check(|r| r.i16(), 3, 1, &[8, 1, 16], 5, post, Out::I16);
            check(|r| r.i8() as u8, 3, 1, &[32, 12], 4, post, Out::U8);
            check(|r| r.i8(), 3, 2, &[4, 20], 3, post, Out::I8);
        }
    }
}
