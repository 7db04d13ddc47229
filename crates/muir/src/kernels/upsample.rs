//! Joint convex upsampling of disparity and uncertainty (RAFT's 8x upsampler).
//!
//! For each full-resolution pixel `(8y + dy, 8x + dx)` the 9 mask logits `l_k` (channel
//! `k*64 + dy*8 + dx`) give softmax weights `e_k = exp_q11(shift(l_k - max))`; the outputs are
//! `disparity = -div_round(sum e_k flow_k, S)` (Q8 flow at 1/8 is Q5 pixels at full resolution)
//! and `u = div_round(sum e_k u_k, S)`, with `S = sum e_k` and zero padding outside the grid.
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, lut, sat_i16};

/// Upsamples one 1/8 pixel `(y, x)` into its 8x8 block: `logits` are its 576 mask values
/// (format `mask_frac`), `flow` / `u` the whole 1/8 maps (`h x w`, one channel; `u` optional).
/// `disp_out` / `u_out` receive 8 rows of 8 values each at `out[dy * stride + dx]`.
///
/// With fewer than 576 logits nothing is written; a neighbour outside a too-short `flow` / `u`
/// counts as 0 and outputs past the end of `disp_out` / `u_out` are skipped.
#[allow(clippy::too_many_arguments)]
pub fn upsample_pixel(logits: &[i16], mask_frac: i8, flow: &[i16], u: Option<&[i16]>, h: usize, w: usize, y: usize, x: usize, disp_out: &mut [i16], u_out: Option<&mut [i16]>, stride: usize) {
    let Some(logits) = logits.get(..576) else {
        return;
    };
    let mut nb_flow = [0i32; 9];
    let mut nb_u = [0i32; 9];
    for (k, (nf, nu)) in nb_flow.iter_mut().zip(&mut nb_u).enumerate() {
        let (ny, nx) = ((y + k / 3) as isize - 1, (x + k % 3) as isize - 1);
        if ny >= 0 && nx >= 0 && (ny as usize) < h && (nx as usize) < w {
            let i = ny as usize * w + nx as usize;
            *nf = flow.get(i).map_or(0, |v| *v as i32);
            *nu = u.and_then(|u| u.get(i)).map_or(0, |v| *v as i32);
        }
    }
    // `clamp(shift_round(l - max, 11 - mask_frac), -32768, 0)` in i32: `l - max` is in
    // `-65535..=0`, so a left shift by more than 15 and a right one by more than 20 give the
    // same clamped values as 15 and 20 (every non-zero difference reaches -32768, resp. rounds
    // to 0), and neither overflows i32.
    let to_q11 = 11 - mask_frac as i32;
    let (lsh, rsh) = if to_q11 >= 0 { (to_q11.min(15) as u32, 0u32) } else { (0u32, (-to_q11).min(20) as u32) };
    let half = if rsh > 0 { 1i32 << (rsh - 1) } else { 0 };
    // Host, AVX-512: 16 sub-pixels a vector (`avx512`), where the outputs hold the whole block.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if avx512::available()
        && disp_out.len() >= 7 * stride + 8
        && u_out.as_deref().is_none_or(|o| o.len() >= 7 * stride + 8)
        && let Ok(logits) = <&[i16; 576]>::try_from(logits)
    {
        let nb_u = u.is_some().then_some(&nb_u);
        // SAFETY: the CPU has AVX-512 F, BW and DQ (`available`); the outputs hold rows
        // `dy * stride .. dy * stride + 8` for `dy < 8` (checked above).
        unsafe { avx512::block(logits, lsh, rsh, &nb_flow, nb_u, disp_out, u_out, stride) };
        return;
    }
    portable_block(logits, lsh, rsh, half, &nb_flow, &nb_u, disp_out, u_out, stride);
}

/// [`upsample_pixel`]'s block from the logits, the shifts into Q11 (`half` the rounding half of
/// `rsh`) and the 9 neighbours' values: each sub-pixel in turn.
#[allow(clippy::too_many_arguments)]
fn portable_block(logits: &[i16], lsh: u32, rsh: u32, half: i32, nb_flow: &[i32; 9], nb_u: &[i32; 9], disp_out: &mut [i16], u_out: Option<&mut [i16]>, stride: usize) {
    let mut u_out = u_out;
    for dy in 0..8 {
        for dx in 0..8 {
            let sub = dy * 8 + dx;
            // Logit `k` of sub-pixel `sub`: `logits[k * 64 + sub]` (always there: 576 of them).
            let mut l = [0i32; 9];
            for (k, lk) in l.iter_mut().enumerate() {
                *lk = logits.get(k * 64 + sub).map_or(0, |v| *v as i32);
            }
            let max = l.iter().copied().max().unwrap_or(0);
            // Weights `e_k <= 32768` (Q0.15), so `S <= 9 * 2^15` and `|e_k v_k| <= 2^30`.
            let mut e = [0i32; 9];
            let mut s = 0i32;
            for (ek, lk) in e.iter_mut().zip(&l) {
                let v = *lk - max;
                let d = if rsh == 0 { v << lsh } else { (v + half) >> rsh };
                *ek = lut::exp_q11(d.max(-32768));
                s += *ek;
            }
            // (each product below 2^30 in magnitude: the i64 products are the i32 ones, one
            // `SMLAL` each where a product widened after an i32 multiply took three)
            let fd: i64 = e.iter().zip(nb_flow).map(|(a, b)| *a as i64 * *b as i64).sum();
            if let Some(o) = disp_out.get_mut(dy * stride + dx) {
                *o = sat_i16(-div_round(fd, s as i64));
            }
            if let Some(o) = u_out.as_deref_mut().and_then(|uo| uo.get_mut(dy * stride + dx)) {
                let fu: i64 = e.iter().zip(nb_u).map(|(a, b)| *a as i64 * *b as i64).sum();
                *o = sat_i16(div_round(fu, s as i64));
            }
        }
    }
}

/// [`upsample_pixel`] on 512-bit vectors: the 64 sub-pixels as four vectors of 16, each step
/// the scalar loop's on 16 lanes. The weights by [`super::attention::avx512`]'s table of exp
/// knots (the same interpolation as [`lut::exp_q11`]); the products and sums in i64 lanes; the
/// rounded division `div_round(n, S)` as `sign(n) floor((|n| + floor(S / 2)) / S)` with the
/// floor of the f64 quotient, which is exact here: `|n| + S / 2 < 2^35` and `S < 2^19` convert
/// exactly, and a quotient `k + r / S` with `r < S` lies at least `2^-19` below `k + 1`, far
/// more than the `2^-36` an f64 near `2^16` can round by.
#[cfg(all(target_arch = "x86_64", feature = "std"))]
mod avx512 {
    use core::arch::x86_64::*;

    /// Whether the CPU has what [`block`] needs (and the 512-bit kernels are not switched off,
    /// `MUIR_X86_SIMD`).
    pub(super) use super::super::x86::has_avx512dq as available;

    /// The 8x8 block from the 576 logits, the shifts `lsh` / `rsh` (one of them 0) of `l - max`
    /// into Q11, and the 9 neighbours' disparities and uncertainties (0 outside the grid).
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and DQ; `disp_out` (and `u_out`) hold `7 stride + 8` values.
    #[target_feature(enable = "avx512f,avx512bw,avx512dq")]
    #[allow(clippy::too_many_arguments)]
    pub(super) unsafe fn block(logits: &[i16; 576], lsh: u32, rsh: u32, nb_flow: &[i32; 9], nb_u: Option<&[i32; 9]>, disp_out: &mut [i16], mut u_out: Option<&mut [i16]>, stride: usize) {
        let knots = super::super::attention::avx512::exp_knots();
        let (lsh, rsh) = (_mm_cvtsi32_si128(lsh as i32), _mm_cvtsi32_si128(rsh as i32));
        let half = if _mm_cvtsi128_si32(rsh) > 0 { 1i32 << (_mm_cvtsi128_si32(rsh) - 1) } else { 0 };
        let half = _mm512_set1_epi32(half);
        let shifted_right = _mm_cvtsi128_si32(rsh) > 0;
        let nf: [__m512i; 9] = core::array::from_fn(|k| _mm512_set1_epi64(nb_flow.get(k).copied().unwrap_or(0) as i64));
        let nu: [__m512i; 9] = core::array::from_fn(|k| _mm512_set1_epi64(nb_u.and_then(|u| u.get(k)).copied().unwrap_or(0) as i64));
        for g in 0..4 {
            // Sub-pixels `16 g ..`: rows `2 g` and `2 g + 1` of the block.
            let l: [__m512i; 9] = core::array::from_fn(|k| {
                // SAFETY: logits `64 k + 16 g .. + 16 <= 576`.
                _mm512_cvtepi16_epi32(unsafe { _mm256_loadu_si256(logits.as_ptr().add(64 * k + 16 * g).cast()) })
            });
            let max = l.iter().fold(_mm512_set1_epi32(i32::MIN), |m, v| _mm512_max_epi32(m, *v));
            let mut s = _mm512_setzero_si512();
            let (mut fd, mut fu) = ([_mm512_setzero_si512(); 2], [_mm512_setzero_si512(); 2]);
            for (k, lk) in l.iter().enumerate() {
                let v = _mm512_sub_epi32(*lk, max);
                let d = if shifted_right { _mm512_sra_epi32(_mm512_add_epi32(v, half), rsh) } else { _mm512_sll_epi32(v, lsh) };
                let d = _mm512_max_epi32(d, _mm512_set1_epi32(-32768));
                let e = super::super::attention::avx512::exp_q11x16(d, knots);
                s = _mm512_add_epi32(s, e);
                let halves = [_mm512_cvtepi32_epi64(_mm512_castsi512_si256(e)), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(e))];
                let (nfk, nuk) = (nf.get(k).copied().unwrap_or(_mm512_setzero_si512()), nu.get(k).copied().unwrap_or(_mm512_setzero_si512()));
                for (j, e) in halves.into_iter().enumerate() {
                    if let (Some(fd), Some(fu)) = (fd.get_mut(j), fu.get_mut(j)) {
                        *fd = _mm512_add_epi64(*fd, _mm512_mul_epi32(e, nfk));
                        *fu = _mm512_add_epi64(*fu, _mm512_mul_epi32(e, nuk));
                    }
                }
            }
            let s = [_mm512_cvtepi32_epi64(_mm512_castsi512_si256(s)), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(s))];
            for (j, s) in s.into_iter().enumerate() {
                let sd = _mm512_cvtepi64_pd(s);
                let half_s = _mm512_srli_epi64::<1>(s);
                // sign(n) floor((|n| + floor(S / 2)) / S)
                let div = |n: __m512i| {
                    let t = _mm512_add_epi64(_mm512_abs_epi64(n), half_s);
                    let q = _mm512_cvttpd_epi64(_mm512_div_pd(_mm512_cvtepi64_pd(t), sd));
                    _mm512_mask_sub_epi64(q, _mm512_cmplt_epi64_mask(n, _mm512_setzero_si512()), _mm512_setzero_si512(), q)
                };
                let row = (2 * g + j) * stride;
                let d = div(fd.get(j).copied().unwrap_or(_mm512_setzero_si512()));
                // SAFETY: values `row .. row + 8` of the output (`row <= 7 stride`, the contract).
                unsafe { _mm_storeu_si128(disp_out.as_mut_ptr().add(row).cast(), _mm512_cvtsepi64_epi16(_mm512_sub_epi64(_mm512_setzero_si512(), d))) };
                if let Some(uo) = u_out.as_deref_mut() {
                    let q = div(fu.get(j).copied().unwrap_or(_mm512_setzero_si512()));
                    // SAFETY: as above.
                    unsafe { _mm_storeu_si128(uo.as_mut_ptr().add(row).cast(), _mm512_cvtsepi64_epi16(q)) };
                }
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    /// The AVX-512 block against the portable one: random, narrow, flat and extreme logits, every
    /// shift into Q11 (left up to 15, right up to 20), neighbours at the i16 limits, without and
    /// with uncertainty.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    #[test]
    fn avx512_block_matches_portable() {
        if !avx512::available() {
            std::eprintln!("no AVX-512 F/BW/DQ: the vector upsampling is not taken on this CPU");
            return;
        }
        let mut r = super::super::testutil::Rng(0x51_7CC1_B727_220A);
        for case in 0..600 {
            let kind = case % 6;
            let mut logits = [0i16; 576];
            for l in logits.iter_mut() {
                let v = (r.next() >> 48) as i16;
                *l = match kind {
                    0 => v,
                    1 => if v & 1 == 0 { i16::MIN } else { i16::MAX },
                    2 => v >> 10,
                    3 => 0,
                    4 => v >> 4,
                    _ => if v & 3 == 0 { i16::MIN } else { v >> 12 },
                };
            }
            let to_q11 = (case / 6) % 37 - 21;
            let (lsh, rsh) = if to_q11 >= 0 { (to_q11.min(15) as u32, 0u32) } else { (0u32, (-to_q11).min(20) as u32) };
            let half = if rsh > 0 { 1i32 << (rsh - 1) } else { 0 };
            let (mut nf, mut nu) = ([0i32; 9], [0i32; 9]);
            for (f, u) in nf.iter_mut().zip(&mut nu) {
                let v = r.next();
                (*f, *u) = match case % 4 {
                    0 => (i16::MIN as i32, i16::MIN as i32),
                    1 => (i16::MAX as i32, i16::MAX as i32),
                    _ => ((v >> 48) as i16 as i32, (v >> 32) as i16 as i32),
                };
            }
            for with_u in [false, true] {
                let (mut d0, mut u0, mut d1, mut u1) = ([7i16; 64], [7i16; 64], [7i16; 64], [7i16; 64]);
                portable_block(&logits, lsh, rsh, half, &nf, if with_u { &nu } else { &[0; 9] }, &mut d0, Some(&mut u0), 8);
                // SAFETY: `available`; 64 outputs each at stride 8.
                unsafe { avx512::block(&logits, lsh, rsh, &nf, with_u.then_some(&nu), &mut d1, Some(&mut u1), 8) };
                assert_eq!(d0, d1, "case {case} disparity");
                assert_eq!(u0, u1, "case {case} uncertainty");
            }
        }
    }

    #[test]
    fn uniform_mask_averages_neighbours() {
        let flow = [-256i16; 9]; // 3x3 grid, disparity 8 px everywhere
        let u = [2048i16; 9];
        let logits = [0i16; 576];
        let mut d = [0i16; 64];
        let mut uo = [0i16; 64];
        upsample_pixel(&logits, 4, &flow, Some(&u), 3, 3, 1, 1, &mut d, Some(&mut uo), 8);
        assert!(d.iter().all(|v| *v == 256)); // 8 px in Q5
        assert!(uo.iter().all(|v| *v == 2048));
        // corner pixel: 4 of 9 neighbours inside
        upsample_pixel(&logits, 4, &flow, Some(&u), 3, 3, 0, 0, &mut d, Some(&mut uo), 8);
        assert_eq!(d[0], div_round(256 * 4, 9) as i16);
    }

    /// The i32 weights against the former i64 formulas (`shift_round` of `l - max` by any
    /// `11 - mask_frac`, products and sums in i64), random and extreme logits and neighbours.
    #[test]
    fn matches_i64_formulas() {
        use crate::arith::shift_round;
        let mut r = super::super::testutil::Rng(0x9E37_79B9_7F4A_7C15);
        let mut next = || r.next();
        for case in 0..400 {
            let mask_frac = (case % 80) as i8 - 40;
            let kind = case / 80;
            let mut logits = [0i16; 576];
            for l in logits.iter_mut() {
                let v = (next() >> 48) as i16;
                *l = match kind {
                    0 => v,
                    1 => if v & 1 == 0 { i16::MIN } else { i16::MAX },
                    2 => v >> 10,
                    3 => v >> 4,
                    _ => if v & 3 == 0 { i16::MIN } else { v >> 12 },
                };
            }
            let mut flow = [0i16; 9];
            let mut u = [0i16; 9];
            for (f, uu) in flow.iter_mut().zip(&mut u) {
                let v = next();
                (*f, *uu) = if kind == 1 { (if v & 1 == 0 { i16::MIN } else { i16::MAX }, i16::MAX) } else { ((v >> 48) as i16, (v >> 32) as i16) };
            }
            let (y, x) = (case % 3, (case / 3) % 3);
            let (mut d, mut uo) = ([0i16; 64], [0i16; 64]);
            upsample_pixel(&logits, mask_frac, &flow, Some(&u), 3, 3, y, x, &mut d, Some(&mut uo), 8);
            for sub in 0..64 {
                let l = |k: usize| logits[k * 64 + sub] as i64;
                let max = (0..9).map(l).max().unwrap();
                let mut e = [0i64; 9];
                for (k, ek) in e.iter_mut().enumerate() {
                    *ek = lut::exp_q11(shift_round(l(k) - max, 11 - mask_frac as i32).clamp(-32768, 0) as i32) as i64;
                }
                let s: i64 = e.iter().sum();
                let (mut fd, mut fu) = (0i64, 0i64);
                for (k, ek) in e.iter().enumerate() {
                    let (ny, nx) = ((y + k / 3) as isize - 1, (x + k % 3) as isize - 1);
                    if (0..3).contains(&ny) && (0..3).contains(&nx) {
                        let i = ny as usize * 3 + nx as usize;
                        fd += ek * flow[i] as i64;
                        fu += ek * u[i] as i64;
                    }
                }
                assert_eq!(d[sub], sat_i16(-div_round(fd, s)), "case {case} sub {sub}");
                assert_eq!(uo[sub], sat_i16(div_round(fu, s)), "case {case} sub {sub}");
            }
        }
    }
}
