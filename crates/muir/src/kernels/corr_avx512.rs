//! The correlation lookup's window on AVX-512 VNNI (host, x86-64): 16 columns at a time.
//!
//! The right feature row is transposed once per row (`[group][column]`, a group four channels as
//! one i32) with every byte offset by 128 (`x + 128` as u8, the form `vpdpbusd` multiplies), and
//! [`MARGIN`] columns of offset zeros on both sides; a pixel's window is then `vpdpbusd` of 16
//! consecutive columns against each broadcast group of its own features, minus `128 sum(f1)`:
//! `sum (f2 + 128) f1 - 128 sum f1 = sum f2 f1`, exact (a lane sums `c` products below `2^15`),
//! and 0 for the margin's columns, as [`super::lookup_pixel`] has them.
#![deny(clippy::indexing_slicing)]

use core::arch::x86_64::*;

use crate::kernels::pool::scratch;
use crate::kernels::x86::has_avx512;

/// Columns of zeros on each side: more than any window reaches past the row
/// ([`super::window_len`] of the largest pyramid the configs allow).
pub const MARGIN: usize = 1024;

/// A right feature row laid out for [`Row::window`].
pub struct Row {
    t: Vec<i32>,
    /// Groups per column, and columns per group row (the row's plus both margins, rounded up).
    groups: usize,
    stride: usize,
    w: usize,
}

impl Default for Row {
    fn default() -> Self {
        Self::new()
    }
}

impl Row {
    /// An empty layout.
    pub const fn new() -> Self {
        Row { t: Vec::new(), groups: 0, stride: 0, w: 0 }
    }

    /// Lays out `f2` (`w` columns of `c` values), reusing the buffer; `false` where this path does
    /// not apply (no AVX-512 VNNI, `c` not a multiple of 4, a row shorter than `w c`).
    pub fn fill(&mut self, f2: &[i8], w: usize, c: usize) -> bool {
        if !has_avx512() || c == 0 || !c.is_multiple_of(4) || f2.len() < w * c {
            return false;
        }
        let (groups, stride) = (c / 4, (w + 2 * MARGIN + 16).next_multiple_of(16));
        // The margins hold zeros (flipped: `0x80`) from the last row of this shape: only the
        // row's own columns are written again (the margins are most of the buffer).
        let same_shape = (self.groups, self.stride, self.w) == (groups, stride, w) && self.t.len() >= groups * stride;
        let t = scratch(&mut self.t, groups * stride);
        if !same_shape {
            t.fill(0x8080_8080u32 as i32);
        }
        for (col, v) in f2.chunks_exact(c).take(w).enumerate() {
            for (g, q) in v.chunks_exact(4).enumerate() {
                if let (Some(d), &[a, b, e, f]) = (t.get_mut(g * stride + MARGIN + col), q) {
                    *d = (u32::from_le_bytes([a as u8, b as u8, e as u8, f as u8]) ^ 0x8080_8080) as i32;
                }
            }
        }
        (self.groups, self.stride, self.w) = (groups, stride, w);
        true
    }

    /// `win[i]` = the correlation of `f1` (`4 groups` values) with column `lo + i` (0 outside the
    /// row); a window reaching further than [`MARGIN`] past the row is left to the caller
    /// (`false`).
    pub fn window(&self, f1: &[i8], lo: i64, win: &mut [i32]) -> bool {
        let n = win.len() as i64;
        if f1.len() != 4 * self.groups || lo < -(MARGIN as i64) || lo + n + 16 > (self.w + MARGIN) as i64 + 16 {
            return false;
        }
        // SAFETY: the CPU has AVX-512 F/BW/VNNI (`fill` checked); columns `lo .. lo + n` rounded
        // up to 16 lie inside the margins (checked above; `stride` has 16 columns to spare).
        unsafe { self.window_avx512(f1, (lo + MARGIN as i64) as usize, win) };
        true
    }

    /// # Safety
    /// The CPU has AVX-512 F, BW and VNNI; columns `at .. at + win.len()` rounded up to 16 lie in
    /// the group rows.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn window_avx512(&self, f1: &[i8], at: usize, win: &mut [i32]) {
        let bias = 128 * f1.iter().map(|v| *v as i32).sum::<i32>();
        // Up to 8 blocks of 16 columns at a time, each its own accumulator, every group's
        // weights broadcast once for all of them: one block's products are a chain (each
        // `vpdpbusd` waits for the one before). One block at a time, the `lookup_with` bench (a
        // row of 40 pixels) took 21.9 us instead of 15.6 us.
        let mut i = 0;
        while i < win.len() {
            let blocks = (win.len() - i).div_ceil(16).min(8);
            let out = win.get_mut(i..).unwrap_or_default();
            // SAFETY: the contract, for columns `at + i ..` (blocks of 16 up to the window's end
            // rounded up to 16).
            unsafe {
                match blocks {
                    8 => self.blocks::<8>(f1, at + i, bias, out),
                    7 => self.blocks::<7>(f1, at + i, bias, out),
                    6 => self.blocks::<6>(f1, at + i, bias, out),
                    5 => self.blocks::<5>(f1, at + i, bias, out),
                    4 => self.blocks::<4>(f1, at + i, bias, out),
                    3 => self.blocks::<3>(f1, at + i, bias, out),
                    2 => self.blocks::<2>(f1, at + i, bias, out),
                    _ => self.blocks::<1>(f1, at + i, bias, out),
                }
            }
            i += 16 * blocks;
        }
    }

    /// `N` blocks of 16 columns from `at` on into `out` (as many as it holds): the correlations
    /// `sum(f1 (x + 128)) - bias` of the `x + 128` packed columns.
    ///
    /// # Safety
    /// As [`Row::window_avx512`], for columns `at .. at + 16 N`.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    #[inline]
    unsafe fn blocks<const N: usize>(&self, f1: &[i8], at: usize, bias: i32, out: &mut [i32]) {
        let t = self.t.as_ptr();
        let mut acc = [_mm512_set1_epi32(-bias); N];
        for (g, q) in f1.chunks_exact(4).enumerate() {
            if let &[a, b, c, d] = q {
                let w = _mm512_set1_epi32(i32::from_le_bytes([a as u8, b as u8, c as u8, d as u8]));
                for (k, acc) in acc.iter_mut().enumerate() {
                    // SAFETY: the function's contract (column `at + 16 k + 15` at most).
                    let x = unsafe { _mm512_loadu_si512(t.add(g * self.stride + at + 16 * k).cast()) };
                    *acc = _mm512_dpbusd_epi32(*acc, x, w);
                }
            }
        }
        for (k, acc) in acc.iter().enumerate() {
            let mut v = [0i32; 16];
            // SAFETY: 16 i32.
            unsafe { _mm512_storeu_si512(v.as_mut_ptr().cast(), *acc) };
            for (d, v) in out.get_mut(16 * k..).unwrap_or_default().iter_mut().zip(v) {
                *d = v;
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::super::testutil::Rng;
    use super::*;

    /// Windows inside, across and outside the row (and past the margin, left to the caller) give
    /// the portable correlations, on random and extreme features.
    #[test]
    fn windows_give_the_portable_correlations() {
        if !has_avx512() {
            eprintln!("no AVX-512 VNNI: the window kernel is not taken on this CPU");
            return;
        }
        let mut r = Rng(5);
        let mut row = Row::new();
        // Each shape twice in a row: the second fill keeps the first one's margins.
        for (w, c, extreme) in [(57, 128, false), (57, 128, false), (3, 4, false), (40, 64, true), (40, 64, false), (160, 32, false), (160, 32, true)] {
            let f2: Vec<i8> = (0..w * c).map(|_| if extreme { -128 } else { r.i8() }).collect();
            assert!(row.fill(&f2, w, c));
            for trial in 0..50 {
                let f1: Vec<i8> = (0..c).map(|_| if extreme && trial % 2 == 0 { -128 } else { r.i8() }).collect();
                // (Past 128 columns: the window in more than one round of 8 blocks.)
                let n = 1 + r.below(if trial % 4 == 0 { 300 } else { 120 }) as usize;
                let lo = r.below(2 * w as u64 + 240) as i64 - 120;
                let (mut want, mut got) = (vec![0i32; n], vec![7i32; n]);
                super::super::window(&f1, &f2, w, lo, &mut want);
                assert!(row.window(&f1, lo, &mut got));
                assert_eq!(want, got, "w {w} c {c} lo {lo} n {n}");
            }
            let mut far = vec![0i32; 8];
            assert!(!row.window(&vec![0i8; c], -(MARGIN as i64) - 1, &mut far));
        }
    }
}
