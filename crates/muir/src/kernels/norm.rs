//! InstanceNorm (no affine parameters, eps 1e-5, biased variance) with integer statistics.
//!
//! For a channel with values `x` (fraction bits `f_in`) over `n` pixels:
//! `mean = div_round(sum x, n)`, `var = div_round(sum (x - mean)^2, n)`,
//! `eps = shift_round(EPS_Q40, 2 f_in - 40)`, `sd = isqrt((var + eps) << 30)` (= sqrt * 2^15),
//! `r = div_round(2^46, sd)`, and the output in `f_out` fraction bits is
//! `rshift_round((x - mean) * r, 31 - f_out)`.
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, isqrt_u64, rshift_round, shift_round};

/// `round(1e-5 * 2^40)`.
pub const EPS_Q40: i64 = 10_995_116;

/// Per-channel statistics of one InstanceNorm.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct ChannelNorm {
    /// Rounded mean, input units.
    pub mean: i64,
    /// Reciprocal standard deviation, `2^46 / (sqrt(var + eps) * 2^15)`.
    pub recip: i64,
}

/// Statistics of channel `ch` of an HWC tensor of `c` channels (`x.len() / c` pixels).
pub fn channel_stats(x: &[i16], c: usize, ch: usize, f_in: i8) -> ChannelNorm {
    if c == 0 {
        return from_moments(0, 0, f_in); // no channels: the statistics of no values
    }
    let n = (x.len() / c) as i64;
    let sum: i64 = x.iter().skip(ch).step_by(c).map(|v| *v as i64).sum();
    let mean = div_round(sum, n);
    let ss: i64 = x.iter().skip(ch).step_by(c).map(|v| (*v as i64 - mean) * (*v as i64 - mean)).sum();
    from_moments(mean, div_round(ss, n), f_in)
}

/// The same statistics from running sums (`sum x`, `sum x^2`) of `n` values, for streaming:
/// `sum (x - mean)^2 = sum x^2 - 2 mean sum x + n mean^2` exactly in integers.
pub fn stats_from_sums(sum: i64, sumsq: i64, n: i64, f_in: i8) -> ChannelNorm {
    let mean = div_round(sum, n);
    let ss = sumsq as i128 - 2 * mean as i128 * sum as i128 + n as i128 * mean as i128 * mean as i128;
    from_moments(mean, div_round(ss.clamp(0, i64::MAX as i128) as i64, n), f_in)
}

fn from_moments(mean: i64, var: i64, f_in: i8) -> ChannelNorm {
    let eps = shift_round(EPS_Q40, 2 * f_in as i32 - 40).max(1);
    let v = (var + eps).min((1i64 << 33) - 1) as u64;
    let sd = isqrt_u64(v << 30).max(1);
    ChannelNorm { mean, recip: div_round(1i64 << 46, sd as i64) }
}

/// Normalised value of `x` in `f_out` fraction bits (not saturated).
#[inline(always)]
pub fn normalize(x: i16, s: ChannelNorm, f_out: i8) -> i64 {
    rshift_round((x as i64 - s.mean) * s.recip, (31 - f_out as i32).clamp(0, 62) as u32)
}

/// Host forms on 512-bit vectors (x86-64, AVX-512 F, BW and DQ): the statistics' sums and the
/// normalisations of whole `[pixel][channel]` rows, 8 channels a vector, each returning `false`
/// (nothing written) where the CPU lacks the instructions or a channel's statistics lie outside
/// the bounds below; the caller then takes the scalar loops. With `|mean| <= 2^15` and
/// `0 <= recip <= 2^46` (every [`stats_from_sums`] result: the mean of i16 values, `2^46 / sd`
/// with `sd >= 1`), `|(x - mean) recip| <= 65535 * 2^46 < 2^62`, so `vpmullq` gives the exact
/// product and adding the rounding half cannot overflow: [`normalize`]'s integer.
#[cfg(all(target_arch = "x86_64", feature = "std"))]
pub mod avx512 {
    use core::arch::x86_64::*;

    /// Most channels the vector forms take.
    const MAX_C: usize = 256;

    use super::super::x86::has_avx512dq as available;

    /// The channels' means and reciprocals (`st`: `(mean, recip)` pairs), padded to whole
    /// vectors, or `None` where one lies outside the bounds or `c` is 0 or above [`MAX_C`].
    fn unpack(st: &[i64], c: usize) -> Option<([i64; MAX_C], [i64; MAX_C])> {
        if c == 0 || c > MAX_C || st.len() < 2 * c {
            return None;
        }
        let (mut mean, mut recip) = ([0i64; MAX_C], [0i64; MAX_C]);
        for ((pair, m), r) in st.chunks_exact(2).zip(mean.iter_mut()).zip(recip.iter_mut()).take(c) {
            if let &[a, b] = pair {
                if a.unsigned_abs() > 1 << 15 || !(0..=1 << 46).contains(&b) {
                    return None;
                }
                (*m, *r) = (a, b);
            }
        }
        Some((mean, recip))
    }

    /// `31 - f_out`, clamped to 0..=62, and its rounding half.
    fn shift_of(f_out: i8) -> (i32, i64) {
        let s = (31 - f_out as i32).clamp(0, 62);
        (s, if s > 0 { 1i64 << (s - 1) } else { 0 })
    }

    /// The normalisation of `[pixel][channel]` values `x` into `dst` (`c` channels, whole
    /// pixels, channels' statistics `mean`, `recip`), clamped to `0..=hi`, as u8 (`U8`) or i16.
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and DQ; `x` and `dst` hold `len` values (`dst` of the output
    /// type; they may be the same place); `len` a multiple of `c`, `0 < c <= MAX_C`.
    #[target_feature(enable = "avx512f,avx512bw,avx512dq")]
    unsafe fn normalize_clamped<const U8: bool>(x: *const i16, len: usize, c: usize, mean: &[i64; MAX_C], recip: &[i64; MAX_C], f_out: i8, dst: *mut u8) {
        let (s, half) = shift_of(f_out);
        let (s, half) = (_mm_cvtsi32_si128(s), _mm512_set1_epi64(half));
        let hi = _mm512_set1_epi64(if U8 { 255 } else { i16::MAX as i64 });
        let mut ch = 0;
        while ch < c {
            let n = (c - ch).min(8);
            let m: __mmask8 = if n >= 8 { !0 } else { (1u8 << n) - 1 };
            // SAFETY: channels `ch .. ch + 8 <= MAX_C` of the padded tables; values `at + ch ..`
            // under the mask inside the `len` of `x` and `dst` (the contract).
            unsafe {
                let (mv, rv) = (_mm512_loadu_si512(mean.as_ptr().add(ch).cast()), _mm512_loadu_si512(recip.as_ptr().add(ch).cast()));
                let mut at = 0;
                while at + c <= len {
                    let v = _mm512_cvtepi16_epi64(_mm_maskz_loadu_epi16(m, x.add(at + ch).cast()));
                    let v = _mm512_sra_epi64(_mm512_add_epi64(_mm512_mullo_epi64(_mm512_sub_epi64(v, mv), rv), half), s);
                    let v = _mm512_min_epi64(_mm512_max_epi64(v, _mm512_setzero_si512()), hi);
                    if U8 {
                        _mm_mask_storeu_epi8(dst.add(at + ch).cast(), m as u16, _mm512_cvtepi64_epi8(v));
                    } else {
                        _mm_mask_storeu_epi16(dst.cast::<i16>().add(at + ch).cast(), m, _mm512_cvtepi64_epi16(v));
                    }
                    at += c;
                }
            }
            ch += 8;
        }
    }

    /// `dst[i] = sat_u8(normalize(src[i], channel's statistics, f_out))` ([`super::normalize`])
    /// for `[pixel][channel]` values (`c` channels; `dst` as long as `src`, whole pixels).
    pub fn normalize_u8(src: &[i16], st: &[i64], c: usize, f_out: i8, dst: &mut [u8]) -> bool {
        if !available() || dst.len() != src.len() || !src.len().is_multiple_of(c.max(1)) {
            return false;
        }
        let Some((mean, recip)) = unpack(st, c) else { return false };
        // SAFETY: the CPU has AVX-512 F, BW and DQ (`available`); `src` and `dst` hold `len`
        // values, whole pixels; `0 < c <= MAX_C` (`unpack`).
        unsafe { normalize_clamped::<true>(src.as_ptr(), src.len(), c, &mean, &recip, f_out, dst.as_mut_ptr()) };
        true
    }

    /// `x[i] = sat_i16(max(normalize(x[i], channel's statistics, f_out), 0))` in place.
    pub fn normalize_relu_i16(x: &mut [i16], st: &[i64], c: usize, f_out: i8) -> bool {
        if !available() || !x.len().is_multiple_of(c.max(1)) {
            return false;
        }
        let Some((mean, recip)) = unpack(st, c) else { return false };
        let p = x.as_mut_ptr();
        // SAFETY: as `normalize_u8`, `x` read and written at the same places.
        unsafe { normalize_clamped::<false>(p, x.len(), c, &mean, &recip, f_out, p.cast()) };
        true
    }

    /// Adds each channel's sum and sum of squares of `[pixel][channel]` values `x` to `st`'s
    /// `(sum, squares)` pairs (`c` channels; squares below `2^30`, sums in i64 lanes).
    pub fn add_moments(st: &mut [i64], c: usize, x: &[i16]) -> bool {
        if !available() || c == 0 || c > MAX_C || st.len() < 2 * c || !x.len().is_multiple_of(c) {
            return false;
        }
        let (mut sum, mut sq) = ([0i64; MAX_C], [0i64; MAX_C]);
        // SAFETY: the CPU has AVX-512 F, BW and DQ; `x` whole pixels of `0 < c <= MAX_C`.
        unsafe { moments(x, c, &mut sum, &mut sq) };
        for ((pair, a), b) in st.chunks_exact_mut(2).zip(sum).zip(sq).take(c) {
            if let [s, q] = pair {
                *s += a;
                *q += b;
            }
        }
        true
    }

    /// [`add_moments`]' sums into `sum` and `sq` (channels `0 .. c`).
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and DQ; `x.len()` a multiple of `c`, `0 < c <= MAX_C`.
    #[target_feature(enable = "avx512f,avx512bw,avx512dq")]
    unsafe fn moments(x: &[i16], c: usize, sum: &mut [i64; MAX_C], sq: &mut [i64; MAX_C]) {
        let mut ch = 0;
        while ch < c {
            let n = (c - ch).min(8);
            let m: __mmask8 = if n >= 8 { !0 } else { (1u8 << n) - 1 };
            let (mut a, mut b) = (_mm512_setzero_si512(), _mm512_setzero_si512());
            let mut at = 0;
            // SAFETY: values `at + ch ..` under the mask inside `x`; channels `ch .. ch + 8 <=
            // MAX_C` of the sums.
            unsafe {
                while at + c <= x.len() {
                    let v = _mm512_cvtepi16_epi64(_mm_maskz_loadu_epi16(m, x.as_ptr().add(at + ch).cast()));
                    a = _mm512_add_epi64(a, v);
                    b = _mm512_add_epi64(b, _mm512_mul_epi32(v, v));
                    at += c;
                }
                _mm512_storeu_si512(sum.as_mut_ptr().add(ch).cast(), a);
                _mm512_storeu_si512(sq.as_mut_ptr().add(ch).cast(), b);
            }
            ch += 8;
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    /// The vector forms against the scalar formulas: random and extreme values, channel counts
    /// with and without a partial last vector, several output formats, statistics from the sums.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    #[test]
    fn avx512_forms_match_the_formulas() {
        use crate::arith::{sat_i16, sat_u8};
        let mut r = crate::kernels::testutil::Rng(0xABCD_1234);
        for (c, px, extreme) in [(64, 57, false), (3, 100, false), (70, 9, false), (1, 33, true), (64, 40, true), (13, 21, false)] {
            let x: Vec<i16> = (0..c * px).map(|i| if extreme { [i16::MIN, i16::MAX, 0, i16::MIN][i % 4] } else { (r.next() >> 48) as i16 >> (i % 5) }).collect();
            let mut st = vec![0i64; 2 * c];
            if !avx512::add_moments(&mut st, c, &x) {
                std::eprintln!("no AVX-512 DQ: the vector normalisation is not taken on this CPU");
                return;
            }
            for ch in 0..c {
                let vals = x.iter().skip(ch).step_by(c).map(|v| *v as i64);
                assert_eq!(st[2 * ch], vals.clone().sum::<i64>(), "sum c {c} ch {ch}");
                assert_eq!(st[2 * ch + 1], vals.map(|v| v * v).sum::<i64>(), "squares c {c} ch {ch}");
            }
            for f_in in [8i8, 12, 0] {
                let stats: Vec<ChannelNorm> = (0..c).map(|ch| stats_from_sums(st[2 * ch], st[2 * ch + 1], px as i64, f_in)).collect();
                let flat: Vec<i64> = stats.iter().flat_map(|s| [s.mean, s.recip]).collect();
                for f_out in [6i8, 10, 12, 31, 40, -2] {
                    let mut u = vec![0u8; x.len()];
                    assert!(avx512::normalize_u8(&x, &flat, c, f_out, &mut u));
                    let mut y = x.clone();
                    assert!(avx512::normalize_relu_i16(&mut y, &flat, c, f_out));
                    for (i, v) in x.iter().enumerate() {
                        let n = normalize(*v, stats[i % c], f_out);
                        assert_eq!(u[i], sat_u8(n), "u8 c {c} f_in {f_in} f_out {f_out} i {i}");
                        assert_eq!(y[i], sat_i16(n.max(0)), "i16 c {c} f_in {f_in} f_out {f_out} i {i}");
                    }
                }
            }
        }
    }

    #[test]
    fn normalises_to_unit_variance() {
        // values 0, 4096, 0, 4096 ... in Q12 = 0 and 1.0; mean 0.5, std 0.5 -> +-1.0
        let x: Vec<i16> = (0..64).map(|i| if i % 2 == 0 { 0 } else { 4096 }).collect();
        let s = channel_stats(&x, 1, 0, 12);
        assert_eq!(s.mean, 2048);
        assert_eq!(normalize(4096, s, 6), 64);
        assert_eq!(normalize(0, s, 6), -64);
        // a constant channel does not blow up
        let c = channel_stats(&[7i16; 16], 1, 0, 4);
        assert_eq!(normalize(7, c, 6), 0);
    }

    #[test]
    fn streaming_sums_match() {
        let x: Vec<i16> = (0..3000).map(|i| ((i * 7919) % 65536 - 32768) as i16).collect();
        for c in [1, 3] {
            for ch in 0..c {
                let vals: Vec<i64> = x.iter().skip(ch).step_by(c).map(|v| *v as i64).collect();
                let (s, ss) = (vals.iter().sum(), vals.iter().map(|v| v * v).sum());
                assert_eq!(stats_from_sums(s, ss, vals.len() as i64, 9), channel_stats(&x, c, ch, 9));
            }
        }
    }
}
