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

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

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
