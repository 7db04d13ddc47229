//! Integer arithmetic specification, shared by every kernel, the host and the target.
//!
//! Everything the fixed-point engine computes reduces to the functions of this module; none uses
//! floating point, and all are total (no panics, saturation instead of overflow). Host and
//! Cortex-M results are therefore identical bit for bit. `docs/arithmetic.md` states the same rules
//! in prose.
//!
//! * **Rounding**: [`rshift_round`] adds half an LSB and shifts right arithmetically, i.e. rounds
//!   half toward +infinity. [`div_round`] rounds half away from zero. No other rounding exists.
//! * **Saturation**: every narrowing goes through [`sat_i8`] / [`sat_u8`] / [`sat_i16`] /
//!   [`sat_i32`].
//! * **Requantisation**: `y = sat(rshift_round(acc * m, shift))` with `m` a 31-bit multiplier in
//!   `[2^30, 2^31)` and `shift` in `[1, 126]`, computed in 128-bit ([`requantize`]). Multiplier and
//!   shift are found on the host by `Multiplier::from_f64` (host builds) and stored in the model blob.
//! * **Activation formats**: activations are `i8`, `u8` or `i16` with a power-of-two scale,
//!   `value = q * 2^-frac` ([`QFormat`]). `u8` holds the tensors that follow a ReLU (the backbone
//!   and the context): they are never negative, so the sign bit would waste half the codes. Weights are `i8`, symmetric, with a scale per output channel (in
//!   the multiplier). Accumulators are `i32` for `i8` inputs and `i64` for `i16` inputs (exact:
//!   the model blob writer checks the worst-case bound).
//! * **Nonlinearities** by table with linear interpolation ([`lut`]): sigmoid and tanh take Q3.12
//!   and return Q0.15; exp takes Q4.11 in `[-16, 0]` and returns Q0.15; sine takes a 32-bit phase.
#![deny(clippy::indexing_slicing)]

pub mod lut;
mod tables;

/// Fraction bits of gate pre-activations (inputs of sigmoid and tanh): Q3.12, range [-8, 8).
pub const GATE_FRAC: u8 = 12;
/// Fraction bits of values in [-1, 1] (hidden states, gates, masks, softmax weights): Q0.15.
pub const UNIT_FRAC: u8 = 15;
/// Fraction bits of the 1/8-grid disparity state ("flow" = -disparity/8): Q7.8, so the full
/// resolution disparity has 1/32 px steps and a range of +-1024 px.
pub const FLOW_FRAC: u8 = 8;
/// Largest UFI proposal disparity on the 1/8 grid: the largest whole disparity whose flow and its
/// negation both fit the Q7.8 flow state (127, i.e. 1016 px at full resolution). The proposal search of every engine (and
/// of the PyTorch twin) stops there, so a proposal never saturates the flow format; it only
/// matters for inputs wider than 1024 px.
pub const MAX_PROPOSAL_D8: usize = (i16::MAX as usize) >> FLOW_FRAC;
/// Fraction bits of the full-resolution disparity output (1/32 px).
pub const DISP_FRAC: u8 = 5;
/// Fraction bits of uncertainty `u = log(beta^2)` and of its logit: Q4.11, range [-16, 16).
pub const LOG_FRAC: u8 = 11;
/// `1.0` in Q0.15.
pub const ONE_Q15: i32 = 1 << 15;

/// Saturates to `i8`.
#[inline(always)]
pub const fn sat_i8(v: i64) -> i8 {
    if v > i8::MAX as i64 {
        i8::MAX
    } else if v < i8::MIN as i64 {
        i8::MIN
    } else {
        v as i8
    }
}

/// Saturates to `u8` (values below 0 become 0: a ReLU for free).
#[inline(always)]
pub const fn sat_u8(v: i64) -> u8 {
    if v > u8::MAX as i64 {
        u8::MAX
    } else if v < 0 {
        0
    } else {
        v as u8
    }
}

/// Saturates to `i16`.
#[inline(always)]
pub const fn sat_i16(v: i64) -> i16 {
    if v > i16::MAX as i64 {
        i16::MAX
    } else if v < i16::MIN as i64 {
        i16::MIN
    } else {
        v as i16
    }
}

/// Saturates to `i32`.
#[inline(always)]
pub const fn sat_i32(v: i64) -> i32 {
    if v > i32::MAX as i64 {
        i32::MAX
    } else if v < i32::MIN as i64 {
        i32::MIN
    } else {
        v as i32
    }
}

/// `round(v / 2^s)`, half toward +infinity; `s = 0` returns `v`; `s >= 63` returns the sign's
/// rounding of a vanishing value (0, or -1 never: it rounds to 0).
#[inline(always)]
pub const fn rshift_round(v: i64, s: u32) -> i64 {
    if s == 0 {
        v
    } else if s >= 63 {
        0
    } else {
        // v + 2^(s-1) cannot overflow unless v is within 2^(s-1) of i64::MAX; saturate then.
        let half = 1i64 << (s - 1);
        match v.checked_add(half) {
            Some(t) => t >> s,
            None => i64::MAX >> s,
        }
    }
}

/// `v * 2^s` for `s >= 0`, `round(v / 2^-s)` for `s < 0`, saturated to i64.
#[inline(always)]
pub const fn shift_round(v: i64, s: i32) -> i64 {
    if s >= 0 {
        if s >= 63 {
            if v > 0 {
                i64::MAX
            } else if v < 0 {
                i64::MIN
            } else {
                0
            }
        } else {
            match v.checked_mul(1i64 << s) {
                Some(p) => p,
                None => {
                    if v > 0 {
                        i64::MAX
                    } else {
                        i64::MIN
                    }
                }
            }
        }
    } else {
        rshift_round(v, (-s) as u32)
    }
}

/// Converts `v` from `from` fraction bits to `to` fraction bits (rounding as [`rshift_round`]).
#[inline(always)]
pub const fn rescale(v: i64, from: i8, to: i8) -> i64 {
    shift_round(v, to as i32 - from as i32)
}

/// `n / d` rounded half away from zero; `d == 0` gives 0 (callers never divide by zero; this
/// keeps the function total).
#[inline(always)]
pub const fn div_round(n: i64, d: i64) -> i64 {
    if d == 0 {
        return 0;
    }
    let (n_abs, d_abs) = (n.unsigned_abs(), d.unsigned_abs());
    // `n_abs <= 2^63` and `d_abs / 2 <= 2^62`: the sum fits in u64, so no 128-bit division is
    // needed; where both fit in 32 bits (most calls: pooling, resizing, attention), a 32-bit one
    // (one `UDIV` on Cortex-M, whose 64-bit division is a library call).
    let s = n_abs + d_abs / 2;
    let q = if s <= u32::MAX as u64 && d_abs <= u32::MAX as u64 { (s as u32 / d_abs as u32) as u64 } else { s / d_abs };
    if (n < 0) != (d < 0) {
        // `-q`, saturated at `i64::MIN` (`q = 2^63` is `i64::MIN` exactly).
        if q > 1 << 63 { i64::MIN } else { (q as i64).wrapping_neg() }
    } else if q > i64::MAX as u64 {
        i64::MAX
    } else {
        q as i64
    }
}

/// `sat_i16(div_round(n, d))` without a 64-bit division where `0 < d < 2^31` (the MGA's
/// aggregated values: value sums over softmax sums, 40-bit numerators, every `__aeabi_uldivmod`
/// about 80 instructions on Cortex-M): a quotient of 32768 or more saturates, found by one
/// comparison; below that the divisor, normalised to its top bit, is estimated from its top 16
/// bits by one 32-bit division, and the remainder corrects the estimate (at most a few steps).
/// Other divisors take `div_round` itself. The same value for every input.
#[inline]
pub const fn div_round_sat_i16(n: i64, d: i64) -> i16 {
    DivRoundSat16::new(d).apply(n)
}

/// [`div_round_sat_i16`] by one divisor for many numerators (a query's channels): the divisor's
/// normalisation and saturation bound computed once.
#[derive(Clone, Copy, Debug)]
pub struct DivRoundSat16 {
    d: i64,
    /// `0 < d < 2^31`: the fast path applies.
    fast: bool,
    /// `32768 d`, the shift normalising `d` to bit 31, and the normalised divisor's top 16 bits.
    bound: u64,
    z: u32,
    top: u32,
}

impl DivRoundSat16 {
    /// The constants of divisor `d`.
    #[inline]
    pub const fn new(d: i64) -> Self {
        let fast = d > 0 && d <= i32::MAX as i64;
        if !fast {
            return DivRoundSat16 { d, fast, bound: 0, z: 0, top: 1 };
        }
        let z = (d as u32).leading_zeros();
        DivRoundSat16 { d, fast, bound: 32768 * d as u64, z, top: ((d as u32) << z) >> 16 }
    }

    /// `sat_i16(div_round(n, d))`.
    #[inline]
    pub const fn apply(&self, n: i64) -> i16 {
        match self.rounded(n) {
            Err(v) => v,
            Ok(s) => {
                // `s < 2^15 d`: shifted by `z`, `s < 2^47`; the estimate from the top bits.
                let top = if self.top == 0 { 1 } else { self.top };
                self.quotient(n, s, (((s << self.z) >> 16) as u32 / top) as i64)
            }
        }
    }

    /// [`DivRoundSat16::apply`] with the quotient estimated from `inv`, `1 / d` in f64, instead of
    /// an integer division (host: the batched attention's outputs); the same integers.
    #[cfg(feature = "std")]
    #[inline]
    pub fn apply_f64(&self, n: i64, inv: f64) -> i16 {
        match self.rounded(n) {
            Err(v) => v,
            // `s < 2^15 d < 2^46`: exact in f64, the product within one of `s / d`.
            Ok(s) => self.quotient(n, s, (s as f64 * inv) as i64),
        }
    }

    /// `Ok(|n| + d / 2)` for the fast path, or `Err(result)`: the slow path's, or a quotient
    /// whose magnitude reaches 32768 saturated.
    #[inline]
    const fn rounded(&self, n: i64) -> Result<u64, i16> {
        let d = self.d;
        if !self.fast {
            return Err(sat_i16(div_round(n, d)));
        }
        // `n_abs <= 2^63`, `d / 2 < 2^30`: no overflow.
        let s = n.unsigned_abs() + d as u64 / 2;
        if s >= self.bound {
            // |quotient| >= 32768: `i16::MAX` (positive), `i16::MIN` (negative: -32768 exactly
            // or saturated).
            return Err(if n < 0 { i16::MIN } else { i16::MAX });
        }
        Ok(s)
    }

    /// `s / d` (`s < 2^15 d`) from an estimate `q` a few units off, corrected from the
    /// remainder, with `n`'s sign.
    #[inline]
    const fn quotient(&self, n: i64, s: u64, q: i64) -> i16 {
        let (d, mut q) = (self.d, q);
        let mut r = s as i64 - q * d;
        while r < 0 {
            q -= 1;
            r += d;
        }
        while r >= d {
            q += 1;
            r -= d;
        }
        (if n < 0 { -q } else { q }) as i16
    }
}

/// A real multiplier `m * 2^-shift` with `m` in `[2^30, 2^31)`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct Multiplier {
    /// Mantissa, `[2^30, 2^31)` (or 0 for a zero multiplier).
    pub m: i32,
    /// Right shift, `[1, 126]`.
    pub shift: u8,
}

impl Multiplier {
    /// The zero multiplier.
    pub const ZERO: Multiplier = Multiplier { m: 0, shift: 1 };

    /// Nearest representable multiplier to `r >= 0` (host only: float in, integers out).
    /// Returns `None` when `r` is negative, not finite, or `>= 2^30`.
    #[cfg(feature = "std")]
    pub fn from_f64(r: f64) -> Option<Multiplier> {
        if !r.is_finite() || r < 0.0 || r >= (1u64 << 30) as f64 {
            return None;
        }
        if r == 0.0 {
            return Some(Multiplier::ZERO);
        }
        // r = frac * 2^exp with frac in [0.5, 1): m = round(frac * 2^31), shift = 31 - exp.
        let mut exp = r.log2().floor() as i32 + 1;
        let mut frac = r / 2f64.powi(exp);
        if frac >= 1.0 {
            frac /= 2.0;
            exp += 1;
        }
        let mut m = (frac * (1u64 << 31) as f64).round() as i64;
        if m == 1 << 31 {
            m /= 2;
            exp += 1;
        }
        let shift = 31 - exp;
        if shift < 1 {
            return None;
        }
        if shift > 126 {
            return Some(Multiplier::ZERO);
        }
        Some(Multiplier { m: m as i32, shift: shift as u8 })
    }

    /// The real value (host-side reports).
    #[cfg(feature = "std")]
    pub fn to_f64(self) -> f64 {
        self.m as f64 / 2f64.powi(self.shift as i32)
    }
}

/// `round(acc * m / 2^shift)` (half toward +infinity) in 128-bit, saturated to i64.
///
/// Most accumulators fit in i32; then `|acc * m| < 2^62` and, for `shift <= 62`, the rounding
/// constant keeps the sum below 2^63, so 64-bit arithmetic gives exactly the 128-bit result (a
/// single `SMULL` on Cortex-M instead of a 128-bit multiply and shift).
///
/// With `33 <= shift` (every scale below 1/4: the usual case) only the product's high word
/// matters: for `p = hi 2^32 + lo`, `floor((p + 2^(s-1)) / 2^s) = floor((hi + 2^(s-33)) /
/// 2^(s-32))`, because `lo / 2^32 < 1` cannot carry the integer `hi + 2^(s-33)` past a multiple
/// of `2^(s-32)`. On Cortex-M that is `SMULL`, an add and an arithmetic shift, where the general
/// path needs a 64-bit add with carry and a 64-bit shift by a variable amount.
#[inline(always)]
pub const fn requantize(acc: i64, mult: Multiplier) -> i64 {
    if acc >= i32::MIN as i64 && acc <= i32::MAX as i64 && mult.shift <= 62 && mult.shift >= 1 {
        return requantize_i32(acc as i32, mult);
    }
    requantize_wide(acc, mult)
}

/// [`requantize`] of an `i32` accumulator for `1 <= mult.shift <= 62`: its 64-bit path without
/// the range checks, for callers that know the range (the convolution epilogue checks the
/// multiplier once per channel). Shifts are masked and adds wrap (neither can happen in the
/// range), so a shift outside it gives an unspecified value, never a panic.
#[inline(always)]
pub const fn requantize_i32(acc: i32, mult: Multiplier) -> i64 {
    let p = acc as i64 * mult.m as i64;
    let s = mult.shift as u32;
    if s >= 33 {
        // |hi| <= 2^30 (|acc|, |m| <= 2^31) and the rounding half is at most 2^29: no i32 overflow.
        let hi = (p >> 32) as i32;
        return (hi.wrapping_add(1i32 << ((s - 33) & 31)) >> ((s - 32) & 31)) as i64;
    }
    // |p| <= 2^62: adding 2^(s-1) <= 2^31 cannot overflow.
    p.wrapping_add(1i64 << (s.wrapping_sub(1) & 63)) >> (s & 63)
}

/// [`requantize_i32`] for `1 <= mult.shift <= 62`, as `floor((floor(acc m / 2^(s-1)) + 1) / 2)`:
/// the same integer `floor((acc m + 2^(s-1)) / 2^s)` (nested floors of divisions by powers of two,
/// the inner one plus an integer), with one 64-bit shift and no rounding constant. For the scalar
/// fallbacks of vector epilogues (`conv_helium`'s recomputed lanes), where the shift varies per
/// multiplier; where `requantize_i32` builds `2^(s-1)` and branches on `s >= 33`. The shift is
/// masked, so one outside the range gives an unspecified value, never a panic.
#[inline(always)]
pub const fn requantize_i32_halved(acc: i32, mult: Multiplier) -> i64 {
    let t = (mult.shift as u32).wrapping_sub(1) & 63;
    (((acc as i64 * mult.m as i64) >> t) + 1) >> 1
}

/// [`requantize`] for any operands, in 128-bit.
#[inline(never)]
pub const fn requantize_wide(acc: i64, mult: Multiplier) -> i64 {
    let p = acc as i128 * mult.m as i128;
    let s = mult.shift as u32;
    let r = (p + (1i128 << (s - 1))) >> s;
    if r > i64::MAX as i128 {
        i64::MAX
    } else if r < i64::MIN as i128 {
        i64::MIN
    } else {
        r as i64
    }
}

/// Integer square root: `floor(sqrt(v))`.
pub const fn isqrt_u64(v: u64) -> u64 {
    if v < 2 {
        return v;
    }
    // Newton iteration from an upper bound; monotone decreasing to floor(sqrt(v)).
    let mut x = 1u64 << ((64 - v.leading_zeros()).div_ceil(2));
    loop {
        // `x >= 1` throughout (it starts at a power of two and only decreases to floor(sqrt(v)) >= 1).
        let y = match v.checked_div(x) {
            Some(q) => (x + q) / 2,
            None => return 0,
        };
        if y >= x {
            return x;
        }
        x = y;
    }
}

/// Activation format: `value = q * 2^-frac`, stored as `i8` (`bits == 8`), `u8` (`bits == 8`,
/// `unsigned`) or `i16`.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct QFormat {
    /// Storage width: 8 or 16.
    pub bits: u8,
    /// Fraction bits (may exceed `bits`, or be negative for very large ranges).
    pub frac: i8,
    /// Unsigned storage (`u8`, range `[0, 255]`); only with `bits == 8`.
    pub unsigned: bool,
}

impl QFormat {
    /// An i16 format.
    pub const fn i16(frac: i8) -> Self {
        Self { bits: 16, frac, unsigned: false }
    }
    /// An i8 format.
    pub const fn i8(frac: i8) -> Self {
        Self { bits: 8, frac, unsigned: false }
    }
    /// A u8 format.
    pub const fn u8(frac: i8) -> Self {
        Self { bits: 8, frac, unsigned: true }
    }
    /// Largest stored value.
    pub const fn qmax(self) -> i64 {
        if self.unsigned {
            u8::MAX as i64
        } else if self.bits == 8 {
            i8::MAX as i64
        } else {
            i16::MAX as i64
        }
    }
    /// Smallest stored value.
    pub const fn qmin(self) -> i64 {
        if self.unsigned { 0 } else { -self.qmax() - 1 }
    }
    /// Saturates to this format's storage range.
    #[inline(always)]
    pub const fn sat(self, v: i64) -> i64 {
        if v > self.qmax() {
            self.qmax()
        } else if v < self.qmin() {
            self.qmin()
        } else {
            v
        }
    }
    /// Real value of `q` (host-side only).
    #[cfg(feature = "std")]
    pub fn to_f32(self, q: i64) -> f32 {
        (q as f64 * 2f64.powi(-(self.frac as i32))) as f32
    }
    /// Quantises a real value (host-side only).
    #[cfg(feature = "std")]
    pub fn quantize(self, v: f32) -> i64 {
        let scaled = (v as f64 * 2f64.powi(self.frac as i32)).round();
        self.sat(scaled.clamp(i64::MIN as f64, i64::MAX as f64) as i64)
    }
    /// The finest format of this storage whose range holds `max_abs` (host-side only).
    #[cfg(feature = "std")]
    pub fn for_range(self, max_abs: f32) -> Self {
        let m = (max_abs as f64).max(1e-12);
        let frac = (self.qmax() as f64 / m).log2().floor().clamp(-60.0, 60.0) as i8;
        Self { frac, ..self }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    /// `div_round_sat_i16` against `sat_i16(div_round(..))`: divisors across `1 ..= 2^31 - 1`
    /// and beyond (the fallback), numerators around the saturation bound, zero, extremes and
    /// random 40-bit values, both signs.
    #[test]
    fn div_round_sat_i16_matches() {
        let mut r = crate::kernels::testutil::Rng(0xd1d0_0001);
        let mut ds = vec![1i64, 2, 3, 7, 65535, 65536, 65537, (1 << 31) - 1, 1 << 31, 0, -5, i64::MAX];
        ds.extend((0..200).map(|_| (r.next() >> (33 + r.next() % 31)) as i64 + 1));
        for &d in &ds {
            let mut ns = vec![0i64, 1, -1, i64::MAX, i64::MIN, i64::MIN + 1];
            for k in [32766i64, 32767, 32768, 32769] {
                if let Some(b) = d.checked_mul(k) {
                    for e in [-1i64, 0, 1, d / 2, d / 2 + 1, -(d / 2), -(d / 2) - 1] {
                        ns.extend([b + e, -(b + e)]);
                    }
                }
            }
            ns.extend((0..100).map(|_| (r.next() as i64) >> (r.next() % 40)));
            for n in ns {
                assert_eq!(div_round_sat_i16(n, d), sat_i16(div_round(n, d)), "n={n} d={d}");
            }
        }
    }

    use super::*;

    /// `requantize_i32_halved` against `requantize_i32` for every shift in `1..=62`, extreme and
    /// random accumulators and multipliers (both signs, products at the rounding boundaries).
    #[test]
    fn requantize_i32_halved_matches() {
        let mut r = crate::kernels::testutil::Rng(0x4a1f_0001);
        for shift in 1u8..=62 {
            let mut accs = vec![0i32, 1, -1, 2, -2, i32::MAX, i32::MIN, i32::MIN + 1, 1 << 20, -(1 << 20)];
            accs.extend((0..200).map(|_| ((r.next() >> 32) as i32) >> (r.next() % 31)));
            let mut ms = vec![0i32, 1, -1, i32::MAX, i32::MIN, 3, -3];
            ms.extend((0..20).map(|_| ((r.next() >> 32) as i32) >> (r.next() % 31)));
            for &m in &ms {
                for &acc in &accs {
                    let mult = Multiplier { m, shift };
                    assert_eq!(requantize_i32_halved(acc, mult), requantize_i32(acc, mult), "acc={acc} m={m} shift={shift}");
                }
            }
            // Products at and next to the rounding half: `acc m = k 2^s + 2^(s-1) + e`.
            if shift <= 30 {
                for e in -2i64..=2 {
                    let target = (5i64 << shift) + (1i64 << (shift - 1)) + e;
                    for (acc, m) in [(target as i32, 1i32), (-(target as i32), 1), (1, target as i32), (-1, target as i32)] {
                        let mult = Multiplier { m, shift };
                        assert_eq!(requantize_i32_halved(acc, mult), requantize_i32(acc, mult), "acc={acc} m={m} shift={shift}");
                    }
                }
            }
        }
    }

    #[test]
    fn rounding_rules() {
        assert_eq!(rshift_round(5, 1), 3); // 2.5 -> 3
        assert_eq!(rshift_round(-5, 1), -2); // -2.5 -> -2 (half toward +inf)
        assert_eq!(rshift_round(-6, 1), -3);
        assert_eq!(rshift_round(7, 2), 2);
        assert_eq!(rshift_round(i64::MAX, 1), i64::MAX >> 1);
        assert_eq!(div_round(5, 2), 3);
        assert_eq!(div_round(-5, 2), -3); // half away from zero
        assert_eq!(div_round(7, -2), -4);
        assert_eq!(div_round(1, 0), 0);
        // Against the 128-bit formula it replaced, on edges and random operands of all sizes.
        fn wide(n: i64, d: i64) -> i64 {
            if d == 0 {
                return 0;
            }
            let (na, da) = ((n as i128).unsigned_abs(), (d as i128).unsigned_abs());
            let q = (na + da / 2) / da;
            let q = if (n < 0) != (d < 0) { -(q as i128) } else { q as i128 };
            q.clamp(i64::MIN as i128, i64::MAX as i128) as i64
        }
        let edges = [0, 1, -1, 2, -2, 3, 9, -9, i64::MAX, i64::MIN, i64::MAX - 1, i64::MIN + 1, (1 << 31) - 1, 1 << 31, (1 << 31) + 1, u32::MAX as i64, -(u32::MAX as i64), 1 << 32, (1 << 32) + 1, i32::MIN as i64, 1 << 62, -(1 << 62)];
        for &n in &edges {
            for &d in &edges {
                assert_eq!(div_round(n, d), wide(n, d), "{n} / {d}");
            }
        }
        let mut x = 0x9E37_79B9_7F4A_7C15u64;
        for i in 0..200_000u32 {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            let (bn, bd) = (i % 64, (i / 64) % 64);
            let n = (x as i64) >> bn;
            let d = ((x.rotate_left(29) as i64) >> bd) | 1;
            assert_eq!(div_round(n, d), wide(n, d), "{n} / {d}");
            assert_eq!(div_round(n, d - 1), wide(n, d - 1), "{n} / {}", d - 1);
        }
        assert_eq!(shift_round(3, 2), 12);
        assert_eq!(shift_round(i64::MAX / 2, 2), i64::MAX);
        assert_eq!(rescale(100, 4, 2), 25);
        assert_eq!(rescale(100, -1, 1), 400); // negative fraction bits (ranges above qmax)
        assert_eq!(rescale(100, 2, -2), 6);
    }

    #[test]
    fn saturation() {
        assert_eq!(sat_i8(300), 127);
        assert_eq!(sat_i8(-300), -128);
        assert_eq!(sat_i16(40000), 32767);
        assert_eq!(sat_i32(i64::MIN), i32::MIN);
        assert_eq!(QFormat::i8(3).sat(-1000), -128);
        assert_eq!(sat_u8(300), 255);
        assert_eq!(sat_u8(-3), 0);
        assert_eq!(QFormat::u8(3).sat(-1000), 0);
        assert_eq!(QFormat::u8(3).sat(1000), 255);
    }

    #[test]
    fn multipliers() {
        for r in [1e-9, 3.7e-5, 0.25, 0.3333, 1.0, 1.5, 123.456, 65535.9] {
            let m = Multiplier::from_f64(r).unwrap();
            assert!((1 << 30..1i64 << 31).contains(&(m.m as i64)), "{r}: {m:?}");
            assert!(((m.to_f64() - r) / r).abs() < 1e-9, "{r}");
        }
        assert_eq!(Multiplier::from_f64(0.0), Some(Multiplier::ZERO));
        assert_eq!(Multiplier::from_f64(-1.0), None);
        assert_eq!(Multiplier::from_f64(f64::NAN), None);
        let half = Multiplier::from_f64(0.5).unwrap();
        assert_eq!(requantize(3, half), 2); // 1.5 -> 2
        assert_eq!(requantize(-3, half), -1); // -1.5 -> -1
        let big = Multiplier::from_f64(1.0e9).unwrap();
        assert_eq!(requantize(i64::MAX, big), i64::MAX);
    }

    #[test]
    fn requantize_fast_path_is_the_wide_one() {
        let mut x = 0x243F6A8885A308D3u64;
        let mut next = move || {
            x ^= x << 13;
            x ^= x >> 7;
            x ^= x << 17;
            x
        };
        let edges = [0i64, 1, -1, i32::MAX as i64, i32::MIN as i64, i32::MAX as i64 + 1, i32::MIN as i64 - 1, i64::MAX, i64::MIN];
        for i in 0..200_000 {
            let acc = if i < 9 * 40 { edges[i % 9] } else { (next() as i64) >> (next() % 64) };
            let m = Multiplier { m: ((1u64 << 30) + next() % (1u64 << 30)) as i32, shift: 1 + (next() % 126) as u8 };
            let m = if i % 7 == 0 { Multiplier { m: i32::MAX, ..m } } else { m };
            assert_eq!(requantize(acc, m), requantize_wide(acc, m), "{acc} {m:?}");
        }
    }

    #[test]
    fn integer_sqrt() {
        for v in [0u64, 1, 2, 3, 4, 15, 16, 17, 1 << 40, u64::MAX, (1 << 62) + 12345] {
            let r = isqrt_u64(v);
            assert!(r.checked_mul(r).is_some_and(|s| s <= v), "{v}");
            assert!((r + 1).checked_mul(r + 1).is_none_or(|s| s > v), "{v}");
        }
    }

    #[test]
    fn formats() {
        let f = QFormat::i8(0).for_range(3.0);
        assert_eq!(f, QFormat::i8(5)); // 3.0 * 32 = 96 <= 127 < 3.0 * 64
        assert_eq!(f.quantize(1.0), 32);
        assert_eq!(f.quantize(100.0), 127);
        assert_eq!(QFormat::i16(0).for_range(1.0).frac, 14);
        // u8: one more bit for the same range (3.0 * 64 = 192 <= 255), no negative codes.
        let u = QFormat::u8(0).for_range(3.0);
        assert_eq!(u, QFormat::u8(6));
        assert_eq!(u.quantize(-1.0), 0);
        assert_eq!(u.quantize(100.0), 255);
    }

    /// Every format at the edges of its range (issue #19): a value just inside quantises without
    /// wrapping, one beyond saturates, and `for_range` always holds the range it was asked for,
    /// whatever the bit width and magnitude (wide frames: disparity-driven slots reach hundreds).
    #[test]
    fn formats_at_the_edges_of_their_range() {
        let fixed = [
            ("gate Q3.12", QFormat::i16(GATE_FRAC as i8), 8.0f32),
            ("unit Q0.15", QFormat::i16(UNIT_FRAC as i8), 1.0),
            ("flow Q7.8", QFormat::i16(FLOW_FRAC as i8), 128.0),
            ("disparity Q10.5", QFormat::i16(DISP_FRAC as i8), 1024.0),
            ("log Q4.11", QFormat::i16(LOG_FRAC as i8), 16.0),
        ];
        for (name, f, limit) in fixed {
            let step = 2f32.powi(-(f.frac as i32));
            assert_eq!(f.quantize(limit - step), f.qmax(), "{name}: largest code");
            assert_eq!(f.quantize(-limit), f.qmin(), "{name}: most negative code");
            assert_eq!(f.quantize(10.0 * limit), f.qmax(), "{name}: saturates above");
            assert_eq!(f.quantize(-10.0 * limit), f.qmin(), "{name}: saturates below");
            assert_eq!(f.sat(i64::MAX), f.qmax(), "{name}");
            assert_eq!(f.sat(i64::MIN), f.qmin(), "{name}");
        }
        // The largest proposal's flow fits, and so does its negation.
        assert!(((MAX_PROPOSAL_D8 as i64) << FLOW_FRAC) <= i16::MAX as i64);
        for storage in [QFormat::i8(0), QFormat::u8(0), QFormat::i16(0)] {
            for max in [1e-3f32, 0.37, 1.0, 7.9, 8.0, 39.4, 141.5, 600.0, 1.0e4] {
                let f = storage.for_range(max);
                assert!(f.to_f32(f.qmax()) >= max * 0.999, "{f:?} for {max}");
                assert!(f.to_f32(f.qmax()) < 2.0 * max + 1e-6, "{f:?} for {max}: more than one bit of headroom");
            }
        }
    }
}
