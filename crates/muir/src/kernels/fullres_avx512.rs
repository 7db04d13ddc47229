//! The refinement's kernels on AVX-512 (host, x86-64), the same integers as the portable ones.
//!
//! **Census codes**, sixteen pixels a vector: for each of the 48 neighbours (row-major over the 7x7 window, the centre skipped: bit `b` of
//! [`super::census_codes`]' order) the sixteen neighbour bytes are widened to i32 lanes and
//! compared with the centres (`n < c`, unsigned); the lane mask sets bit `b` of the low or high
//! 32-bit half of each pixel's code. The halves are then interleaved into the sixteen u64 codes.
//! Only columns whose whole window lies inside the row take this path (no clamping); the
//! portable loop does the others.
//!
//! **Costs**, eight candidates a vector (AVX-512 VPOPCNTDQ): for each of the nine window
//! positions, the left code broadcast, XOR the right codes of eight consecutive columns (one
//! load: candidates in reverse order, reversed once at the end), population counts added.
//! Candidates whose right columns would clamp at 0 take the portable cost.
//!
//! **Path sums**: the five paths' costs of a pixel's candidates added in one vector of 32 u16
//! (below `5 (432 + P2) < 2^16`, see the stage's assertion), widened to the u32 sums `decide`
//! reads.
//!
//! **Path steps**, a pixel's candidates (at most [`SLOTS`] = 30) in one vector of 32 u16: the
//! predecessor's costs laid out as a window (`u16::MAX` where no term exists, see
//! [`super::path_step_portable`]), `min(win[k + 1], min(win[k], win[k + 2]) + P1, m + P2') - m + C`
//! with saturating adds (`u16::MAX + P1` stays `u16::MAX` and never wins: every real term is below
//! `432 + P2`).
#![deny(clippy::indexing_slicing)]

use core::arch::x86_64::*;

use super::{Band, CENSUS_RADIUS, P1, SLOTS, WINDOW_ROWS};

/// Census codes of columns `CENSUS_RADIUS ..` in blocks of 16 while a block's window stays inside
/// the row, from the seven grey rows in `grey` (`w` each) into `out`; returns the first column
/// it did not do (`CENSUS_RADIUS` when it did none).
pub(super) fn census_interior(grey: &[u8], w: usize, out: &mut [u64]) -> usize {
    let r = CENSUS_RADIUS;
    let n = 2 * r + 1;
    if !super::super::x86::has_avx512() || grey.len() < n * w || out.len() < w {
        return r;
    }
    // SAFETY: the CPU has AVX-512 F and BW; `grey` holds seven rows of `w`, `out` `w` codes.
    unsafe { blocks(grey, w, out) }
}

/// [`census_interior`]'s blocks.
///
/// # Safety
/// The CPU has AVX-512 F and BW; `grey.len() >= 7 w`, `out.len() >= w`.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn blocks(grey: &[u8], w: usize, out: &mut [u64]) -> usize {
    let r = CENSUS_RADIUS;
    let mut x = r;
    // Pixels `x .. x + 16` read columns `x - 3 .. x + 19`, all inside the row.
    let lo_idx = _mm512_setr_epi32(0, 16, 1, 17, 2, 18, 3, 19, 4, 20, 5, 21, 6, 22, 7, 23);
    let hi_idx = _mm512_setr_epi32(8, 24, 9, 25, 10, 26, 11, 27, 12, 28, 13, 29, 14, 30, 15, 31);
    let (g, o) = (grey.as_ptr(), out.as_mut_ptr());
    while x + 16 + r <= w {
        // SAFETY: every load reads 16 bytes at row `dy`, columns `x + dx - 3 .. x + dx + 13` with
        // `dx <= 6`: below `x + 19 <= w` (the loop bound), inside the row; the stores write codes
        // `x .. x + 16 <= w`.
        unsafe {
            let at = |dy: usize, c: usize| _mm512_cvtepu8_epi32(_mm_loadu_si128(g.add(dy * w + c).cast()));
            let centre = at(r, x);
            let (mut lo, mut hi) = (_mm512_setzero_si512(), _mm512_setzero_si512());
            let mut bit = 0u32;
            for dy in 0..2 * r + 1 {
                for dx in 0..2 * r + 1 {
                    if dy == r && dx == r {
                        continue;
                    }
                    let k = _mm512_cmplt_epu32_mask(at(dy, x + dx - r), centre);
                    if bit < 32 {
                        lo = _mm512_mask_or_epi32(lo, k, lo, _mm512_set1_epi32((1u32 << bit) as i32));
                    } else {
                        hi = _mm512_mask_or_epi32(hi, k, hi, _mm512_set1_epi32((1u32 << (bit - 32)) as i32));
                    }
                    bit += 1;
                }
            }
            _mm512_storeu_si512(o.add(x).cast(), _mm512_permutex2var_epi32(lo, lo_idx, hi));
            _mm512_storeu_si512(o.add(x + 8).cast(), _mm512_permutex2var_epi32(lo, hi_idx, hi));
        }
        x += 16;
    }
    x
}

/// [`super::path_step`] when the CPU has AVX-512 BW, the slices hold the bands' values and the
/// sums stay inside u16 (`m + P2' + P1 <= u16::MAX`; the stage's are below 2^13); `false`
/// (nothing written) otherwise.
pub(super) fn path_step(prev: &[u16], pband: Band, cost: &[u16], band: Band, p2: u32, out: &mut [u16]) -> bool {
    let (np, n) = (pband.n(), band.n());
    if !super::super::x86::has_avx512() || np == 0 || prev.len() < np || cost.len() < n || out.len() < n || p2 > u16::MAX as u32 / 2 {
        return false;
    }
    // SAFETY: the CPU has AVX-512 F and BW; the slices hold `np` and `n` values.
    unsafe { step(prev, np, (band.first as isize) - (pband.first as isize), cost, n, p2 as u16, out) }
}

/// [`path_step`]'s vector step (`false`: the sums would leave u16, nothing written).
///
/// # Safety
/// The CPU has AVX-512 F and BW; `1 <= np <= prev.len()`, `np <= SLOTS`, `n <= cost.len()`,
/// `n <= out.len()`, `n <= SLOTS`.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn step(prev: &[u16], np: usize, shift: isize, cost: &[u16], n: usize, p2: u16, out: &mut [u16]) -> bool {
    const _: () = assert!(SLOTS + 2 <= 32);
    let pmask: __mmask32 = (1u32 << np) - 1;
    let nmask: __mmask32 = (1u32 << n) - 1;
    // SAFETY: the masked loads and stores touch the first `np` (`n`) values of the slices, the
    // window's stores 32 lanes at `at <= 64` of its 96.
    unsafe {
        let p = _mm512_mask_loadu_epi16(_mm512_set1_epi16(-1), pmask, prev.as_ptr().cast());
        // m: the least of the predecessor's values (absent lanes are u16::MAX).
        let m16 = _mm_extract_epi16::<0>(_mm512_castsi512_si128(least_u16(p))) as u32;
        if m16 + p2 as u32 + P1 > u16::MAX as u32 {
            return false;
        }
        let m = _mm512_set1_epi16(m16 as i16);
        let far = _mm512_adds_epu16(m, _mm512_set1_epi16(p2 as i16));
        // The window: `win[i] = prev[i - 1 + shift]` (offset by 32), `u16::MAX` where no term
        // exists. Lanes `k < n <= 30` read `win[32 + k ..= 34 + k]`: a predecessor stored from
        // `at` outside `0 ..= 64` has no value there.
        let mut win = [u16::MAX; 96];
        let at = 32 + 1 - shift;
        if (0..=64).contains(&at) {
            _mm512_mask_storeu_epi16(win.as_mut_ptr().add(at as usize).cast(), pmask, p);
        }
        let w = win.as_ptr().add(32);
        let (w0, w1, w2) = (_mm512_loadu_si512(w.cast()), _mm512_loadu_si512(w.add(1).cast()), _mm512_loadu_si512(w.add(2).cast()));
        let p1 = _mm512_set1_epi16(P1 as i16);
        let best = _mm512_min_epu16(_mm512_min_epu16(w1, _mm512_adds_epu16(_mm512_min_epu16(w0, w2), p1)), far);
        let c = _mm512_maskz_loadu_epi16(nmask, cost.as_ptr().cast());
        _mm512_mask_storeu_epi16(out.as_mut_ptr().cast(), nmask, _mm512_sub_epi16(_mm512_add_epi16(c, best), m));
    }
    true
}

/// The costs of the first candidates of band `b` at column `x` ([`super::pixel_costs`]'s
/// `out[k]`) in blocks of eight while no right column clamps at 0 (`first + k + 7 <= x - 1`);
/// returns how many it wrote (0 without AVX-512 BW, VL and VPOPCNTDQ).
pub(super) fn costs(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, b: Band, out: &mut [u16]) -> usize {
    let n = b.n().min(out.len());
    if x == 0 || b.first < 0 || x >= w || !super::super::x86::has_avx512() || !std::is_x86_feature_detected!("avx512vpopcntdq") || !std::is_x86_feature_detected!("avx512vl") {
        return 0;
    }
    if left.iter().chain(right.iter()).any(|r| r.len() < w) {
        return 0;
    }
    // Blocks of eight candidates `d0 .. d0 + 8` with `d0 + 7 <= x - 1` (the last one may hold
    // fewer than eight of the band's: its other lanes read columns that exist and are not stored).
    let first = b.first as usize;
    let blocks = match (x - 1).checked_sub(first + 7) {
        Some(room) => n.div_ceil(8).min(room / 8 + 1),
        None => 0,
    };
    let done = (8 * blocks).min(n);
    // SAFETY: the CPU has AVX-512 F and VPOPCNTDQ; every row holds `w` codes; columns `q - d0 -
    // 7 .. q - d0 + 1` lie in `0 ..= w - 1` for `q` in the clamped window and `d0 + 7 <= x - 1`;
    // `out` holds `done` values.
    unsafe { cost_blocks(left, right, w, x, first, blocks, done, out) };
    done
}

/// [`costs`]' blocks.
///
/// # Safety
/// As [`costs`] says.
#[target_feature(enable = "avx512f,avx512bw,avx512vl,avx512vpopcntdq")]
#[allow(clippy::too_many_arguments)]
unsafe fn cost_blocks(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, first: usize, blocks: usize, done: usize, out: &mut [u16]) {
    let cols = [x - 1, x, (x + 1).min(w - 1)];
    let reverse = _mm512_setr_epi64(7, 6, 5, 4, 3, 2, 1, 0);
    for k in 0..blocks {
        let d0 = first + 8 * k;
        let mut acc = _mm512_setzero_si512();
        for (l, r) in left.iter().zip(right.iter()) {
            for q in cols {
                // SAFETY: the contract: `q < w`, `q - d0 - 7 >= 0`.
                unsafe {
                    let a = _mm512_set1_epi64(*l.as_ptr().add(q) as i64);
                    let v = _mm512_loadu_si512(r.as_ptr().add(q - d0 - 7).cast());
                    acc = _mm512_add_epi64(acc, _mm512_popcnt_epi64(_mm512_xor_si512(a, v)));
                }
            }
        }
        let keep = ((1u32 << (done - 8 * k).min(8)) - 1) as __mmask8;
        // SAFETY: the mask keeps the store inside `out[.. done]`.
        unsafe { _mm_mask_storeu_epi16(out.as_mut_ptr().add(8 * k).cast(), keep, _mm512_cvtepi64_epi16(_mm512_permutexvar_epi64(reverse, acc))) };
    }
}

/// `sum[k] = a[k] + b[k] + c[k] + d[k] + e[k]` for `k < n` of the five paths' costs `p` (as the
/// portable loop sums them) and the index of the first least sum; `None` (nothing written) for
/// `n = 0`, without AVX-512 BW or where a slice is shorter than `n`.
pub(super) fn path_sums(p: [&[u16]; 5], n: usize, sum: &mut [u32; SLOTS]) -> Option<usize> {
    if n == 0 || n > SLOTS || p.iter().any(|p| p.len() < n) || !super::super::x86::has_avx512() {
        return None;
    }
    // SAFETY: the CPU has AVX-512 F and BW; every slice holds `1 <= n <= SLOTS` values.
    Some(unsafe { sums(p, n, sum) })
}

/// [`path_sums`]' vector.
///
/// # Safety
/// The CPU has AVX-512 F and BW; every slice of `p` holds `1 <= n <= SLOTS` values.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn sums(p: [&[u16]; 5], n: usize, sum: &mut [u32; SLOTS]) -> usize {
    let mask: __mmask32 = (1u32 << n) - 1;
    // SAFETY: the loads are masked to `n` values; `sum` holds 30 u32: the second half's store is
    // masked to its first 14.
    unsafe {
        let mut t = _mm512_setzero_si512();
        for p in p {
            t = _mm512_add_epi16(t, _mm512_maskz_loadu_epi16(mask, p.as_ptr().cast()));
        }
        _mm512_storeu_si512(sum.as_mut_ptr().cast(), _mm512_cvtepu16_epi32(_mm512_castsi512_si256(t)));
        _mm512_mask_storeu_epi32(sum.as_mut_ptr().add(16).cast(), (1u16 << (SLOTS - 16)) - 1, _mm512_cvtepu16_epi32(_mm512_extracti64x4_epi64::<1>(t)));
        // The first least of the `n` sums (the others as u16::MAX).
        let v = _mm512_mask_mov_epi16(_mm512_set1_epi16(-1), mask, t);
        let least = _mm512_cmpeq_epi16_mask(v, least_u16(v)) & mask;
        least.trailing_zeros() as usize
    }
}

/// The least of the 32 u16 lanes of `v`, in every lane.
#[target_feature(enable = "avx512f,avx512bw")]
#[inline]
fn least_u16(v: __m512i) -> __m512i {
    let mut m = _mm512_min_epu16(v, _mm512_shuffle_i64x2::<0b01_00_11_10>(v, v));
    m = _mm512_min_epu16(m, _mm512_shuffle_i64x2::<0b10_11_00_01>(m, m));
    m = _mm512_min_epu16(m, _mm512_bsrli_epi128::<8>(m));
    m = _mm512_min_epu16(m, _mm512_bsrli_epi128::<4>(m));
    m = _mm512_min_epu16(m, _mm512_bsrli_epi128::<2>(m));
    _mm512_broadcastw_epi16(_mm512_castsi512_si128(m))
}
