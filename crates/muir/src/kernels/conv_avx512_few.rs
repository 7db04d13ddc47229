//! A convolution row of i16 activations with few output channels, 1 to [`MAX_COUT`] (host,
//! x86-64, AVX-512 VNNI): the heads' last layers (the disparity update, 128 -> 1; the MGA mask,
//! 102 -> 1; the MUD outputs, 32 -> 2). [`super::direct16`] lays output channels along the vector
//! and would compute 16 lanes for one channel; [`super`]'s general path transposes the rows for
//! a handful of products. Here the vector runs along the patch instead: a kernel row of a part
//! reads `k ch` values that lie one after another in the input row (`[x][c]`: columns
//! `x - k/2 .. x + k/2`, each `ch` values), and so do its weights in the layer's `[part][ky][kx][c]`
//! patch order, so each kernel row is a dot product of 32 i16 pairs a `vpdpwssd` (the last
//! vector masked), summed over the lanes at the end, per pixel, part and output channel.
//!
//! Exactness: a part whose every output channel has `sum |w| <= 65535` has every sum of its
//! products, whatever the order or grouping, within `2^15 * 65535 < 2^31`, so the i32 lanes and
//! their sum are the part's exact sum; a layer with any other part is left to the other paths.
//! Each part's sum is then requantised, summed over the parts, rounded and activated by the
//! portable path's own functions ([`super::super::part_sum`], [`super::super::finish`]): the
//! same integers as [`super::super::conv_plain`].

use core::arch::x86_64::*;
use core::cell::RefCell;

use super::super::super::pool::scratch;
use super::super::{ConvParams, MAX_K, PartRows, finish, gather, part_sum};
use super::{Elem, OutRow, cast};
use crate::model::graph::MAX_PARTS;

/// Most output channels this path takes (from 16 on, [`super::direct16`] fills its vectors).
pub(super) const MAX_COUT: usize = 15;

/// i16 values a vector.
const LANES: usize = 32;
/// Output pixels a block computes together.
const PX: usize = 4;

std::thread_local! {
    /// The layer's weights widened to i16, each kernel row of a part padded to whole vectors
    /// ([`Weights`]), and a pixel's gathered patch where its window reaches past the row's ends.
    static BUFFERS: RefCell<(Vec<i16>, Vec<i16>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// Where the widened weights lie: channel `c`'s part `part`, kernel row `ky` starts at
/// `c * stride + at[part] + ky * len[part]` and holds `len[part]` values (`k ch` weights, then
/// zeros to a whole number of vectors).
struct Weights {
    stride: usize,
    at: [usize; MAX_PARTS],
    len: [usize; MAX_PARTS],
}

/// Whether the layer may take this path: i16 activations, 1 to [`MAX_COUT`] output channels, 1
/// to [`MAX_PARTS`] parts, an odd kernel up to [`MAX_K`], a stride, and weights as long as the
/// layer.
fn eligible<T: Elem>(p: &ConvParams<'_>) -> bool {
    cast::<T, i16>(&[]).is_some()
        && (1..=MAX_COUT).contains(&p.cout)
        && (1..=MAX_PARTS).contains(&p.parts.len())
        && p.parts.iter().all(|&ch| ch > 0)
        && p.k % 2 == 1
        && p.k <= MAX_K
        && p.stride > 0
        && p.weights.len() >= p.cout * p.patch_len()
}

/// Widens the layer's weights into `buf` as [`Weights`] says; `None` (the layer is not for this
/// path) where some channel's part has `sum |w| > 65535`.
fn widen(p: &ConvParams<'_>, buf: &mut Vec<i16>) -> Option<Weights> {
    let (k, kl) = (p.k, p.patch_len());
    let mut l = Weights { stride: 0, at: [0; MAX_PARTS], len: [0; MAX_PARTS] };
    for ((at, len), &ch) in l.at.iter_mut().zip(l.len.iter_mut()).zip(p.parts) {
        *at = l.stride;
        *len = (k * ch).next_multiple_of(LANES);
        l.stride += k * *len;
    }
    let w = scratch(buf, p.cout * l.stride);
    w.fill(0);
    for c in 0..p.cout {
        let mut off = c * kl;
        for ((&at, &len), &ch) in l.at.iter().zip(&l.len).zip(p.parts) {
            let src = p.weights.get(off..off + k * k * ch)?;
            if src.iter().map(|w| w.unsigned_abs() as u32).sum::<u32>() > 65535 {
                return None;
            }
            for (ky, row) in src.chunks_exact(k * ch).enumerate() {
                let d = w.get_mut(c * l.stride + at + ky * len..)?;
                d.iter_mut().zip(row).for_each(|(d, s)| *d = *s as i16);
            }
            off += k * k * ch;
        }
    }
    Some(l)
}

/// [`super::conv_row`] by this path, or `false` (nothing written) where the layer is not one it
/// takes.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; the layer passed [`super::conv_row`]'s checks (whole rows,
/// an output row of `out_width(w_in) cout` values).
pub(super) unsafe fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>) -> bool {
    if !eligible::<T>(p) {
        return false;
    }
    let mut rows = [[None; MAX_K]; MAX_PARTS];
    for (d, s) in rows.iter_mut().zip(inputs) {
        for (d, s) in d.iter_mut().zip(s.rows) {
            *d = s.and_then(|r| cast::<T, i16>(r));
        }
    }
    let (k, stride, pad, np, kl) = (p.k, p.stride, p.k / 2, p.parts.len(), p.patch_len());
    let w_out = p.out_width(w_in);
    BUFFERS.with_borrow_mut(|(wbuf, patch)| {
        let Some(l) = widen(p, wbuf) else { return false };
        let patch = scratch(patch, PX * kl);
        let i16_inputs: [PartRows<'_, i16>; MAX_PARTS] = core::array::from_fn(|part| PartRows { rows: rows.get(part).copied().unwrap_or([None; MAX_K]) });
        let wp = wbuf.as_ptr();
        let mut x = 0;
        while x < w_out {
            let px = (w_out - x).min(PX);
            // Each pixel's parts' kernel rows: where their `k ch` values start (in the input
            // row, or in the pixel's gathered patch, `[part][ky][kx][c]`, where its window
            // reaches past the row's ends); null for a padding row, for every pixel alike. The
            // block's unused pixels read the first one's (their sums are not stored).
            let mut src = [[[core::ptr::null::<i16>(); MAX_K]; MAX_PARTS]; PX];
            for (q, s) in src.iter_mut().enumerate().take(px) {
                let x0 = (x + q) * stride;
                let inside = x0 >= pad
                    && x0 - pad + k <= w_in
                    && rows.iter().zip(p.parts).all(|(r, &ch)| r.iter().take(k).flatten().all(|r| (x0 - pad + k) * ch <= r.len()));
                if inside {
                    for ((s, r), &ch) in s.iter_mut().zip(&rows).zip(p.parts) {
                        for (s, r) in s.iter_mut().zip(r).take(k) {
                            if let Some(r) = r {
                                *s = r.as_ptr().wrapping_add((x0 - pad) * ch);
                            }
                        }
                    }
                } else if let Some(patch) = patch.get_mut(q * kl..(q + 1) * kl) {
                    gather(p, i16_inputs.get(..np).unwrap_or_default(), w_in, x + q, patch);
                    let mut o = 0;
                    for ((s, r), &ch) in s.iter_mut().zip(&rows).zip(p.parts) {
                        for (s, r) in s.iter_mut().zip(r).take(k) {
                            if r.is_some() {
                                *s = patch.as_ptr().wrapping_add(o);
                            }
                            o += k * ch;
                        }
                    }
                }
            }
            let first = src.first().copied().unwrap_or_default();
            src.iter_mut().skip(px).for_each(|s| *s = first);
            let mut sums = [[0i64; MAX_COUT]; PX];
            for (part, &ch) in p.parts.iter().enumerate() {
                let (n, at, len) = (k * ch, l.at.get(part).copied().unwrap_or(0), l.len.get(part).copied().unwrap_or(0));
                let rows: [[*const i16; MAX_K]; PX] = core::array::from_fn(|q| src.get(q).and_then(|s| s.get(part)).copied().unwrap_or([core::ptr::null(); MAX_K]));
                // SAFETY: the caller's CPU features; each non-null `rows[q][ky]` points at `k ch`
                // values (in an input row, checked above, or in a patch of `patch_len()`), and
                // null for every pixel or none; channel `c < cout`'s weights of the part's
                // kernel row `ky` are `len >= k ch` values at `c stride + at + ky len` of the
                // `cout stride` widened ones.
                let dots = unsafe { part_dots(&rows, k, n, wp.add(at), len, l.stride, p.cout) };
                for (sums, dots) in sums.iter_mut().zip(dots) {
                    for (c, (sum, dot)) in sums.iter_mut().zip(dots).enumerate().take(p.cout) {
                        *sum = sum.saturating_add(part_sum(p, c, part, dot as i64));
                    }
                }
            }
            for (q, sums) in sums.iter().enumerate().take(px) {
                for (c, sum) in sums.iter().enumerate().take(p.cout) {
                    out.set((x + q) * p.cout + c, finish(p, c, *sum));
                }
            }
            x += px;
        }
        true
    })
}

/// A block's part: for each of its [`PX`] pixels `q` and output channel `c < cout`, the dot
/// product of the part's kernel rows (`rows[q][ky]`, `n` values each; rows null for pixel 0
/// skipped) with its weights (`w + c cs + ky len`). The pixels' sums are independent chains (one
/// chain a channel would wait on `vpdpwssd`'s latency), and each weight vector is loaded once
/// for them.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; each `rows[q][ky]` (`ky < k`) is null where `rows[0][ky]`
/// is, else points at `n` values; for `c < cout`, `ky < k`, `w + c cs + ky len` at `len >= n`
/// values, rounded up to whole vectors; `cout <= MAX_COUT`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn part_dots(rows: &[[*const i16; MAX_K]; PX], k: usize, n: usize, w: *const i16, len: usize, cs: usize, cout: usize) -> [[i32; MAX_COUT]; PX] {
    let mut dots = [[0i32; MAX_COUT]; PX];
    let mut c = 0;
    while c < cout {
        // Four channels at a time (each input vector loaded once for them), then the rest.
        // SAFETY: the contract, channels `c .. c + G <= cout`.
        unsafe {
            match cout - c {
                4.. => channels::<4>(rows, k, n, w.add(c * cs), len, cs, &mut dots, c),
                3 => channels::<3>(rows, k, n, w.add(c * cs), len, cs, &mut dots, c),
                2 => channels::<2>(rows, k, n, w.add(c * cs), len, cs, &mut dots, c),
                _ => channels::<1>(rows, k, n, w.add(c * cs), len, cs, &mut dots, c),
            }
        }
        c += 4;
    }
    dots
}

/// [`part_dots`] of `G` channels (weights at `w + g cs`) into `dots[q][c0 + g]`.
///
/// # Safety
/// As [`part_dots`] for channels `0 .. G`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn channels<const G: usize>(rows: &[[*const i16; MAX_K]; PX], k: usize, n: usize, w: *const i16, len: usize, cs: usize, dots: &mut [[i32; MAX_COUT]; PX], c0: usize) {
    let mut acc = [[_mm512_setzero_si512(); G]; PX];
    for ky in 0..k.min(MAX_K) {
        if rows.first().and_then(|r| r.get(ky)).is_none_or(|r| r.is_null()) {
            continue;
        }
        let mut i = 0;
        while i < n {
            // The rows' values `i .. min(i + 32, n)`, zeros past `n` (not read: the load is
            // masked, and masked-off lanes do not fault).
            let left = n - i;
            let mask: __mmask32 = if left >= LANES { !0 } else { (1u32 << left) - 1 };
            // SAFETY: each row holds `n` values (the contract), the mask stops at `n`; the
            // weights' kernel row holds whole vectors, `i < n <= len`.
            unsafe {
                let mut wv = [_mm512_setzero_si512(); G];
                for (g, v) in wv.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(w.add(g * cs + ky * len + i).cast());
                }
                for (acc, r) in acc.iter_mut().zip(rows) {
                    let x = _mm512_maskz_loadu_epi16(mask, r.get(ky).copied().unwrap_or(core::ptr::null()).add(i).cast());
                    for (a, &wv) in acc.iter_mut().zip(&wv) {
                        *a = _mm512_dpwssd_epi32(*a, x, wv);
                    }
                }
            }
            i += LANES;
        }
    }
    for (d, acc) in dots.iter_mut().zip(acc) {
        for (d, a) in d.iter_mut().skip(c0).zip(acc) {
            *d = _mm512_reduce_add_epi32(a);
        }
    }
}
