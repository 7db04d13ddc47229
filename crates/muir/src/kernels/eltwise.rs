//! Element-wise integer operations: residual add, GRU blend, Q0.15 products, format changes.
//!
//! Every operation walks its slices together and stops at the shortest.
#![deny(clippy::indexing_slicing)]

use crate::arith::{rescale, sat_i16};
use crate::kernels::Elem;

/// `out = relu(y + rescale(skip))`: residual-block output. `y` is the block's second conv,
/// requantised to the output format (`out_frac`) but kept in i16 so the sum saturates only once;
/// `skip` is the block input in its own format (`frac`) or the downsample conv output in
/// `out_frac`. The output is `u8` (the ReLU is the saturation) or, in a wide trunk
/// ([`crate::model::config::Config::wide_trunk`]), `i16` clamped to `[0, 32767]`.
pub fn residual_relu<X: Elem, O: Elem>(y: &[i16], skip: Skip<'_, X>, out_frac: i8, out: &mut [O]) {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    {
        let done = match skip {
            Skip::Input { x, frac } => crate::kernels::mve::residual_relu(y, x, out_frac as i32 - frac as i32, out),
            Skip::Projected(p) => crate::kernels::mve::residual_relu(y, p, 0, out),
        };
        if done {
            return;
        }
    }
    let add = |y: &i16, s: i64| O::from_i64_sat((*y as i64 + s).max(0));
    match skip {
        Skip::Input { x, frac } => {
            // The model's shifts are a few bits: then the rescaled skip and the sum fit i32 (the
            // inputs are u8 or i16, `|x| <= 2^15`: a left shift of up to 15 stays below 2^30, a
            // rounded right one below 2^15, and `y` adds at most 2^15), so one i32 formula per
            // element with the shift hoisted, the same integers as `shift_round`'s i64 one.
            let sh = out_frac as i32 - frac as i32;
            if (-30..=15).contains(&sh) {
                let (left, right) = (sh.max(0) as u32, (-sh).max(0) as u32);
                let half = if right > 0 { 1i32 << (right - 1) } else { 0 };
                for ((o, y), x) in out.iter_mut().zip(y).zip(x) {
                    let r = ((x.to_i32() << left) + half) >> right;
                    *o = O::from_i64_sat((*y as i32 + r).max(0) as i64);
                }
                return;
            }
            for ((o, y), x) in out.iter_mut().zip(y).zip(x) {
                *o = add(y, rescale(x.to_i32() as i64, frac, out_frac));
            }
        }
        Skip::Projected(p) => {
            for ((o, y), p) in out.iter_mut().zip(y).zip(p) {
                *o = add(y, *p as i64);
            }
        }
    }
}

/// Skip connection of a residual block (input elements `X`: `u8`, or `i16` in a wide trunk).
#[derive(Clone, Copy)]
pub enum Skip<'a, X> {
    /// The block input itself, with its fraction bits.
    Input {
        /// Values.
        x: &'a [X],
        /// Fraction bits of `x`.
        frac: i8,
    },
    /// A 1x1 downsample conv output already in the block's output format.
    Projected(&'a [i16]),
}

/// GRU / UFI blend in place: `h = h + z * (q - h)` (= `(1 - z) h + z q`), all Q0.15.
pub fn blend_q15(h: &mut [i16], z: &[i16], q: &[i16]) {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    return crate::kernels::mve::blend_q15(h, z, q);
    #[allow(unreachable_code)]
    for ((h, z), q) in h.iter_mut().zip(z).zip(q) {
        *h = blend1(*h, *z, *q);
    }
}

/// One value of [`blend_q15`]: `sat_i16(h + rshift_round(z (q - h), 15))` in i32 (`|z (q - h)|
/// <= 32768 * 65535`, so the product plus the rounding half `2^14` stays inside i32 and the
/// arithmetic shift is `rshift_round`'s; the i64 form's checked add took a 64-bit compare per
/// value).
#[inline(always)]
fn blend1(h: i16, z: i16, q: i16) -> i16 {
    let d = q as i32 - h as i32;
    sat_i16((h as i32 + ((z as i32 * d + (1 << 14)) >> 15)) as i64)
}

/// `sat_i16(rshift_round(x m, 15))` in i32 (`|x m| <= 2^30`).
#[inline(always)]
fn mul1(x: i16, m: i16) -> i16 {
    sat_i16(((x as i32 * m as i32 + (1 << 14)) >> 15) as i64)
}

/// `out = x * m` with `m` in Q0.15 (format of `x` kept).
pub fn mul_q15(x: &[i16], m: &[i16], out: &mut [i16]) {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    return crate::kernels::mve::mul_q15(x, m, out);
    #[allow(unreachable_code)]
    for ((o, x), m) in out.iter_mut().zip(x).zip(m) {
        *o = mul1(*x, *m);
    }
}

/// `out[p * c + i] = x[p * c + i] * m[p]`: every channel of pixel `p` times its Q0.15 scalar.
pub fn mul_plane_q15(x: &[i16], m: &[i16], c: usize, out: &mut [i16]) {
    if c == 0 {
        return; // no channels (and `chunks` takes no empty chunks)
    }
    for ((o, x), m) in out.chunks_mut(c).zip(x.chunks(c)).zip(m) {
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        {
            crate::kernels::mve::mul_q15_by(x, *m, o);
            continue;
        }
        #[allow(unreachable_code)]
        for (o, x) in o.iter_mut().zip(x) {
            *o = mul1(*x, *m);
        }
    }
}

/// [`mul_plane_q15`] of one row of `w = x.len() / c` pixels into a channel-major plane: pixel
/// `i`'s channel `ch` to `out[ch n + at + i]` (the Armv7E-M firmware's MGA values, read two keys
/// of a channel a word by `dsp::aggregate_cm`). Pixels or channels `out` does not hold are not
/// written.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn mul_plane_q15_cm(x: &[i16], m: &[i16], c: usize, out: &mut [i16], n: usize, at: usize) {
    if c == 0 {
        return;
    }
    for (i, (x, m)) in x.chunks_exact(c).zip(m).enumerate() {
        for (ch, x) in x.iter().enumerate() {
            if let Some(o) = out.get_mut(ch * n + at + i) {
                *o = mul1(*x, *m);
            }
        }
    }
}

/// Converts i16 values between fraction bits, saturating.
pub fn rescale_i16(x: &[i16], from: i8, to: i8, out: &mut [i16]) {
    for (o, x) in out.iter_mut().zip(x) {
        *o = sat_i16(crate::arith::shift_round(*x as i64, to as i32 - from as i32));
    }
}

/// Matchability mask (Q0.15) from the MUD's first output (Q4.11): `sigmoid`.
#[inline]
pub fn mud_mask(a: i16) -> i16 {
    crate::arith::lut::sigmoid_q12(sat_i16(crate::arith::shift_round(a as i64, 1)))
}

/// Q7.8 disparity state ("flow" = -disparity) of an integer 1/8-grid disparity proposal.
#[inline]
pub fn proposal_flow(d: u16) -> i16 {
    sat_i16(-((d as i64) << crate::arith::FLOW_FRAC))
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn blend_and_products() {
        let mut h = [0i16, 16384, -32768, 32767];
        blend_q15(&mut h, &[32767, 16384, 0, 32767], &[32767, -16384, 5, -32768]);
        assert_eq!(h, [32766, 0, -32768, -32766]);
        let mut o = [0i16; 2];
        mul_q15(&[1000, -1000], &[16384, 16384], &mut o);
        assert_eq!(o, [500, -500]);
        let mut o8 = [0u8; 4];
        residual_relu(&[10, -50, 120, 250], Skip::Input { x: &[8u8, 8, 40, 40], frac: 2 }, 1, &mut o8);
        assert_eq!(o8, [14, 0, 140, 255]);
        // Wide trunk: i16 in and out, the same sums clamped to [0, 32767] instead of [0, 255].
        let mut o16 = [0i16; 5];
        residual_relu(&[10, -50, 120, 250, 32000], Skip::Input { x: &[8i16, 8, 40, 40, 4000], frac: 2 }, 1, &mut o16);
        assert_eq!(o16, [14, 0, 140, 270, 32767]);
        residual_relu::<i16, i16>(&[-3, 7], Skip::Projected(&[1, 1]), 1, &mut o16[..2]);
        assert_eq!(o16[..2], [0, 8]);
    }

    /// The i32 blend and products (`blend1`, `mul1`) against the i64 formulas, every extreme
    /// and random values.
    #[test]
    fn q15_i32_matches_the_i64_formulas() {
        use crate::arith::rshift_round;
        let mut r = crate::kernels::testutil::Rng(0x5eed_0015);
        let ext = [i16::MIN, i16::MIN + 1, -16385, -16384, -1, 0, 1, 16383, 16384, i16::MAX - 1, i16::MAX];
        let mut vals: Vec<i16> = ext.to_vec();
        vals.extend((0..40).map(|_| r.i16()));
        for &a in &vals {
            for &b in &vals {
                assert_eq!(mul1(a, b), sat_i16(rshift_round(a as i64 * b as i64, 15)), "mul {a} {b}");
                for &c in &vals {
                    let want = sat_i16(a as i64 + rshift_round(b as i64 * (c as i64 - a as i64), 15));
                    assert_eq!(blend1(a, b, c), want, "blend {a} {b} {c}");
                }
            }
        }
    }

    /// The i32 path for shifts -30..=15 against `rescale`'s i64 formula, every shift from -40 to
    /// 40 (both paths), u8 and i16 skips (random and extreme), u8 and i16 outputs.
    #[test]
    #[allow(clippy::indexing_slicing)]
    fn residual_matches_the_i64_formula() {
        use crate::arith::rescale;
        let mut r = crate::kernels::testutil::Rng(0x5eed_0003);
        let y: Vec<i16> = (0..64).map(|i| if i < 4 { [i16::MIN, i16::MAX, 0, -1][i] } else { r.i16() }).collect();
        let x16: Vec<i16> = (0..64).map(|i| if i >= 60 { [i16::MIN, i16::MAX, 0, -1][i - 60] } else { r.i16() }).collect();
        let x8: Vec<u8> = (0..64).map(|i| if i >= 62 { [0, 255][i - 62] } else { r.next() as u8 }).collect();
        for sh in -40i32..=40 {
            let (frac, out_frac) = (if sh >= 0 { 0 } else { (-sh) as i8 }, if sh >= 0 { sh as i8 } else { 0 });
            let want = |x: i64, y: i16, lim: i64| (y as i64 + rescale(x, frac, out_frac)).clamp(0, lim);
            let (mut o8, mut o16) = ([0u8; 64], [0i16; 64]);
            residual_relu(&y, Skip::Input { x: &x8, frac }, out_frac, &mut o8);
            residual_relu(&y, Skip::Input { x: &x16, frac }, out_frac, &mut o16);
            for i in 0..64 {
                assert_eq!(o8[i] as i64, want(x8[i] as i64, y[i], 255), "u8 shift {sh} at {i}");
                assert_eq!(o16[i] as i64, want(x16[i] as i64, y[i], 32767), "i16 shift {sh} at {i}");
            }
        }
    }
}
