//! The refinement's census codes on AVX-512 (host, x86-64): sixteen pixels a vector.
//!
//! For each of the 48 neighbours (row-major over the 7x7 window, the centre skipped: bit `b` of
//! [`super::census_codes`]' order) the sixteen neighbour bytes are widened to i32 lanes and
//! compared with the centres (`n < c`, unsigned); the lane mask sets bit `b` of the low or high
//! 32-bit half of each pixel's code. The halves are then interleaved into the sixteen u64 codes.
//! Only columns whose whole window lies inside the row take this path (no clamping); the
//! portable loop does the others.
#![deny(clippy::indexing_slicing)]

use core::arch::x86_64::*;

use super::CENSUS_RADIUS;

/// Census codes of columns `CENSUS_RADIUS ..` in blocks of 16 while a block's window stays inside
/// the row, from the seven grey rows in `grey` (`w` each) into `out`; returns the first column
/// it did not do (`CENSUS_RADIUS` when it did none).
pub(super) fn interior(grey: &[u8], w: usize, out: &mut [u64]) -> usize {
    let r = CENSUS_RADIUS;
    let n = 2 * r + 1;
    if !super::super::x86::has_avx512() || grey.len() < n * w || out.len() < w {
        return r;
    }
    // SAFETY: the CPU has AVX-512 F and BW; `grey` holds seven rows of `w`, `out` `w` codes.
    unsafe { blocks(grey, w, out) }
}

/// [`interior`]'s blocks.
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
