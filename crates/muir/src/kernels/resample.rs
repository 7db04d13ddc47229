//! Pooling and resizing between the 1/8 and 1/16 grids.
//!
//! Reads past the end of a too-short `src` count as 0 and writes past the end of `out` are
//! skipped (the engine's buffers always fit).
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, sat_i16};

/// One row of `avg_pool2d(x, 3, stride=2, padding=1)` (padding counted, so the sum is divided by
/// 9) of an HWC i16 tensor `src` (`h x w x c`). Output row `y` has `ceil(w/2) * c` values.
pub fn pool2x_row(src: &[i16], h: usize, w: usize, c: usize, y: usize, out: &mut [i16]) {
    // Channels a pass (the sums wait on the stack: 9 i16 fit in i32).
    const CH: usize = 64;
    let wo = w.div_ceil(2);
    let rows = [(2 * y).checked_sub(1), Some(2 * y), Some(2 * y + 1)];
    // Host, AVX-512: 16 channels a vector where every window pixel's values are in `src` and the
    // row's in `out`.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if super::x86::has_avx512() && src.len() >= h * w * c && out.len() >= wo * c {
        // SAFETY: the CPU has AVX-512 F and BW; `src` holds `h w c` values, `out` `wo c`.
        unsafe { avx512::pool2x_row(src, h, w, c, rows, out) };
        return;
    }
    for ox in 0..wo {
        let mut c0 = 0;
        while c0 < c {
            let n = (c - c0).min(CH);
            let mut s = [0i32; CH];
            for iy in rows.iter().flatten().filter(|&&iy| iy < h) {
                for ix in [(2 * ox).checked_sub(1), Some(2 * ox), Some(2 * ox + 1)].into_iter().flatten().filter(|&ix| ix < w) {
                    let at = (iy * w + ix) * c + c0;
                    for (s, v) in s.iter_mut().zip(src.get(at..at + n).unwrap_or_default()) {
                        *s += *v as i32;
                    }
                }
            }
            for (o, s) in out.get_mut(ox * c + c0..ox * c + c0 + n).unwrap_or_default().iter_mut().zip(s) {
                *o = sat_i16(div_round(s as i64, 9));
            }
            c0 += n;
        }
    }
}

/// Source index and remainder of output `i` of an align_corners resize from `n_in` to `n_out`:
/// position `i * (n_in - 1) / (n_out - 1)` as integer part and numerator over `n_out - 1`.
#[inline]
fn align_corners(i: usize, n_in: usize, n_out: usize) -> (usize, i64, i64) {
    if n_out <= 1 || n_in <= 1 {
        return (0, 0, 1);
    }
    let num = (i * (n_in - 1)) as i64;
    let den = (n_out - 1) as i64;
    ((num / den) as usize, num % den, den)
}

/// One row of `F.interpolate(src, (h_out, w_out), mode="bilinear", align_corners=True)` for an HWC
/// i16 tensor `src` (`h x w x c`), with exact rational weights and one rounding.
#[allow(clippy::too_many_arguments)]
pub fn interp_row(src: &[i16], h: usize, w: usize, c: usize, h_out: usize, w_out: usize, y: usize, out: &mut [i16]) {
    interp_cols(src, h, w, c, h_out, w_out, y, 0..w_out, out);
}

/// Columns `xs` of [`interp_row`]'s row `y` into `out` (`xs.len() c` values, column `xs.start`
/// first).
#[allow(clippy::too_many_arguments)]
pub fn interp_cols(src: &[i16], h: usize, w: usize, c: usize, h_out: usize, w_out: usize, y: usize, xs: core::ops::Range<usize>, out: &mut [i16]) {
    let x_first = xs.start;
    let (y0, ry, dy) = align_corners(y, h, h_out);
    let y1 = (y0 + 1).min(h.saturating_sub(1));
    // A source pixel's `c` values (empty past the end of `src`: zeros).
    let px = |yy: usize, xx: usize| src.get((yy * w + xx) * c..(yy * w + xx + 1) * c).unwrap_or_default();
    let at = |p: &[i16], ch: usize| p.get(ch).map_or(0, |v| *v as i64);
    for x in xs.start..xs.end.min(w_out) {
        let (x0, rx, dx) = align_corners(x, w, w_out);
        let x1 = (x0 + 1).min(w.saturating_sub(1));
        let (a, b, e, f) = (px(y0, x0), px(y0, x1), px(y1, x0), px(y1, x1));
        let at_out = (x - x_first) * c;
        if dx * dy <= 1 << 15 {
            // The four corner weights once per pixel: `(dy - ry) ((dx - rx) a + rx b) + ry ((dx -
            // rx) e + rx f)` is the same integer as their weighted sum, below `dx dy 2^15 <= 2^30`
            // in magnitude, so i32 products and the 32-bit rounded division (`div_round`'s).
            let (wa, wb, we, wf) = ((dy - ry) * (dx - rx), (dy - ry) * rx, ry * (dx - rx), ry * rx);
            let (wa, wb, we, wf, d) = (wa as i32, wb as i32, we as i32, wf as i32, ((dx * dy) as u32).max(1));
            // Host, AVX-512: 16 channels a vector where the four pixels' values are all there.
            #[cfg(all(target_arch = "x86_64", feature = "std"))]
            if super::x86::has_avx512()
                && [a, b, e, f].iter().all(|p| p.len() == c)
                && let Some(o) = out.get_mut(at_out..at_out + c)
            {
                // SAFETY: the CPU has AVX-512 F and BW; `a`, `b`, `e`, `f` and `o` hold `c`
                // values.
                unsafe { avx512::blend4([a, b, e, f], [wa, wb, we, wf], d, o) };
                continue;
            }
            let at32 = |p: &[i16], ch: usize| p.get(ch).map_or(0, |v| *v as i32);
            for (ch, o) in out.get_mut(at_out..at_out + c).unwrap_or_default().iter_mut().enumerate() {
                let num = wa * at32(a, ch) + wb * at32(b, ch) + we * at32(e, ch) + wf * at32(f, ch);
                let q = ((num.unsigned_abs() + d / 2) / d) as i64;
                *o = sat_i16(if num < 0 { -q } else { q });
            }
            continue;
        }
        for (ch, o) in out.get_mut(at_out..at_out + c).unwrap_or_default().iter_mut().enumerate() {
            let top = (dx - rx) * at(a, ch) + rx * at(b, ch);
            let bot = (dx - rx) * at(e, ch) + rx * at(f, ch);
            *o = sat_i16(div_round((dy - ry) * top + ry * bot, dy * dx));
        }
    }
}

/// The pooling and the interpolation on 512-bit vectors, 16 channels a vector (the last one
/// masked): the scalar loops' sums in i32 lanes, and their rounded divisions
/// `sign(n) floor((|n| + floor(d / 2)) / d)` as the floor of an f64 quotient, which is exact
/// here: `|n| + d / 2 < 2^31` and `d <= 2^15` convert exactly, and a quotient `k + r / d` with
/// `r < d` lies at least `2^-15` below `k + 1`, more than an f64 near `2^16` can round by.
#[cfg(all(target_arch = "x86_64", feature = "std"))]
mod avx512 {
    use core::arch::x86_64::*;

    /// `sat_i16(sign(n) floor((|n| + d / 2) / d))` of 16 i32 lanes (`|n| + d / 2 < 2^31`, `0 < d
    /// <= 2^15`).
    #[target_feature(enable = "avx512f,avx512bw")]
    #[inline]
    fn div_round16(n: __m512i, d: u32) -> __m256i {
        let t = _mm512_add_epi32(_mm512_abs_epi32(n), _mm512_set1_epi32((d / 2) as i32));
        let dd = _mm512_set1_pd(d as f64);
        let lo = _mm512_cvttpd_epi32(_mm512_div_pd(_mm512_cvtepi32_pd(_mm512_castsi512_si256(t)), dd));
        let hi = _mm512_cvttpd_epi32(_mm512_div_pd(_mm512_cvtepi32_pd(_mm512_extracti64x4_epi64::<1>(t)), dd));
        let q = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(lo), hi);
        let q = _mm512_mask_sub_epi32(q, _mm512_cmplt_epi32_mask(n, _mm512_setzero_si512()), _mm512_setzero_si512(), q);
        _mm512_cvtsepi32_epi16(q)
    }

    /// `o[ch] = sat_i16(div_round(wa a + wb b + we e + wf f, d))` per channel, the weighted sum
    /// below `2^30` in magnitude (`interp_cols`' i32 case).
    ///
    /// # Safety
    /// The CPU has AVX-512 F and BW; the four pixels and `o` have the same length.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub(super) unsafe fn blend4(px: [&[i16]; 4], wt: [i32; 4], d: u32, o: &mut [i16]) {
        let n = o.len();
        let [w0, w1, w2, w3] = wt;
        let wv = [_mm512_set1_epi32(w0), _mm512_set1_epi32(w1), _mm512_set1_epi32(w2), _mm512_set1_epi32(w3)];
        let mut i = 0;
        while i < n {
            let m: __mmask16 = if n - i >= 16 { !0 } else { (1u16 << (n - i)) - 1 };
            let mut num = _mm512_setzero_si512();
            for (p, w) in px.iter().zip(wv) {
                // SAFETY: values `i ..` of the pixel under the mask (`n` of them, the contract).
                let v = _mm512_cvtepi16_epi32(unsafe { _mm256_maskz_loadu_epi16(m, p.as_ptr().add(i).cast()) });
                num = _mm512_add_epi32(num, _mm512_mullo_epi32(v, w));
            }
            // SAFETY: as the loads.
            unsafe { _mm256_mask_storeu_epi16(o.as_mut_ptr().add(i).cast(), m, div_round16(num, d)) };
            i += 16;
        }
    }

    /// [`super::pool2x_row`]: each output pixel's window sums, divided by 9.
    ///
    /// # Safety
    /// The CPU has AVX-512 F and BW; `src` holds `h w c` values and `out` `ceil(w / 2) c`.
    #[target_feature(enable = "avx512f,avx512bw")]
    pub(super) unsafe fn pool2x_row(src: &[i16], h: usize, w: usize, c: usize, rows: [Option<usize>; 3], out: &mut [i16]) {
        for ox in 0..w.div_ceil(2) {
            let cols = [(2 * ox).checked_sub(1), Some(2 * ox), Some(2 * ox + 1)];
            let mut c0 = 0;
            while c0 < c {
                let m: __mmask16 = if c - c0 >= 16 { !0 } else { (1u16 << (c - c0)) - 1 };
                let mut s = _mm512_setzero_si512();
                for iy in rows.iter().flatten().filter(|&&iy| iy < h) {
                    for ix in cols.iter().flatten().filter(|&&ix| ix < w) {
                        // SAFETY: values `(iy w + ix) c + c0 ..` under the mask, inside `src`.
                        let v = unsafe { _mm256_maskz_loadu_epi16(m, src.as_ptr().add((iy * w + ix) * c + c0).cast()) };
                        s = _mm512_add_epi32(s, _mm512_cvtepi16_epi32(v));
                    }
                }
                // SAFETY: values `ox c + c0 ..` under the mask, inside `out`.
                unsafe { _mm256_mask_storeu_epi16(out.as_mut_ptr().add(ox * c + c0).cast(), m, div_round16(s, 9)) };
                c0 += 16;
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn pool_and_interp() {
        // 3x3 of ones: the centre output (0,0) sees 4 inside pixels of 9.
        let src = [900i16; 9];
        let mut o = [0i16; 2];
        pool2x_row(&src, 3, 3, 1, 0, &mut o);
        assert_eq!(o, [400, 400]);
        let small = [0i16, 100, 200, 300]; // 2x2
        let mut r = [0i16; 3];
        interp_row(&small, 2, 2, 1, 3, 3, 1, &mut r);
        assert_eq!(r, [100, 150, 200]);
        interp_row(&small, 2, 2, 1, 3, 3, 2, &mut r);
        assert_eq!(r, [200, 250, 300]);
    }

    /// Both against their definitions, pixel by pixel, on random tensors of odd sizes and more
    /// channels than one pass of the pooling holds.
    #[test]
    fn pool_and_interp_match_their_formulas() {
        let mut x = 12345u64;
        let mut rnd = || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x as i16
        };
        // (The last two: extreme values, whose weighted sums reach the i32 path's bound; and
        // an output whose `dx dy` exceeds 2^15, the i64 path.)
        for (h, w, c, extreme) in [(5, 7, 3, false), (4, 6, 70, false), (1, 1, 2, false), (9, 5, 128, false), (6, 9, 3, true), (60, 150, 2, false)] {
            let src: Vec<i16> = (0..h * w * c).map(|i| if extreme { [i16::MIN, i16::MAX, i16::MIN, i16::MIN][i % 4] } else { rnd() }).collect();
            let at = |y: isize, x: isize, ch: usize| if y < 0 || x < 0 || y >= h as isize || x >= w as isize { 0 } else { src[(y as usize * w + x as usize) * c + ch] as i64 };
            let wo = w.div_ceil(2);
            for y in 0..h.div_ceil(2) {
                let mut o = vec![0i16; wo * c];
                pool2x_row(&src, h, w, c, y, &mut o);
                for ox in 0..wo {
                    for ch in 0..c {
                        let s: i64 = (0..9).map(|i| at(2 * y as isize - 1 + i / 3, 2 * ox as isize - 1 + i % 3, ch)).sum();
                        assert_eq!(o[ox * c + ch], sat_i16(div_round(s, 9)), "pool {h}x{w}x{c} y {y} x {ox} ch {ch}");
                    }
                }
            }
            let (ho, wo) = (2 * h + 1, 2 * w + 3);
            for y in 0..ho {
                let mut o = vec![0i16; wo * c];
                interp_row(&src, h, w, c, ho, wo, y, &mut o);
                // A range of columns alone gives the same values.
                let (a, b) = (wo / 3, wo - 1);
                let mut part = vec![0i16; (b - a) * c];
                interp_cols(&src, h, w, c, ho, wo, y, a..b, &mut part);
                assert_eq!(part, o[a * c..b * c], "columns {a}..{b} of row {y}");
                let (y0, ry, dy) = align_corners(y, h, ho);
                let y1 = (y0 + 1).min(h - 1);
                for xo in 0..wo {
                    let (x0, rx, dx) = align_corners(xo, w, wo);
                    let x1 = (x0 + 1).min(w - 1);
                    for ch in 0..c {
                        let v = |yy: usize, xx: usize| at(yy as isize, xx as isize, ch);
                        let num = (dy - ry) * ((dx - rx) * v(y0, x0) + rx * v(y0, x1)) + ry * ((dx - rx) * v(y1, x0) + rx * v(y1, x1));
                        assert_eq!(o[xo * c + ch], sat_i16(div_round(num, dy * dx)), "interp y {y} x {xo} ch {ch}");
                    }
                }
            }
        }
    }
}
