//! MGA attention in fixed point: 2D RoPE, softmax statistics and aggregation, streaming over keys.
//!
//! Logits `l_ij = q_i . k_j` are exact i64. The query's softmax statistics, `max_j l_ij` and
//! `S_i = sum_j e_ij` with `e_ij = exp_q11(requantize(l_ij - max_i, m))`, do not change across
//! iterations (query and key come from the context), so they are computed once per frame; each
//! iteration then aggregates `glb_i = div_round(sum_j e_ij * v_j << shift, S_i)` in one pass over
//! the keys. No N x N matrix exists; the plain twin builds it and must give the same bits.
#![deny(clippy::indexing_slicing)]

use crate::arith::{Multiplier, lut, requantize, rshift_round, sat_i16, shift_round};

#[cfg(all(target_arch = "x86_64", feature = "std"))]
#[path = "attention_avx512.rs"]
pub mod avx512;

/// 2D RoPE of one pixel's query or key (`v`: channel pairs `(2i, 2i+1)`; the first half of the
/// pairs turns with the column `x`, the second with the row `y`). `phase[i]` is pair `i`'s phase
/// step per pixel (`2^32` = one turn).
pub fn rope_pixel(v: &mut [i16], x: usize, y: usize, phase: &[u32]) {
    let n = v.len() / 2 / 2;
    for (i, (pair, inc)) in v.chunks_exact_mut(2).zip(phase).enumerate() {
        let pos = if i < n { x } else { y } as u32;
        let ph = pos.wrapping_mul(*inc);
        let (c, s) = (lut::cos_phase(ph) as i64, lut::sin_phase(ph) as i64);
        if let [a, b] = pair {
            let (p, q) = (*a as i64, *b as i64);
            *a = sat_i16(rshift_round(p * c - q * s, 15));
            *b = sat_i16(rshift_round(p * s + q * c, 15));
        }
    }
}

#[inline(always)]
fn logit(q: &[i16], k: &[i16]) -> i64 {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    return super::mve::dot_i16_i64(q, k);
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    return super::dsp::dot_i16_i64(q, k);
    #[allow(unreachable_code)]
    let mut s = 0i64;
    for (a, b) in q.iter().zip(k) {
        s += *a as i64 * *b as i64;
    }
    s
}

/// Softmax weight (Q0.15) of a logit relative to its query's maximum.
#[inline(always)]
pub fn weight(l: i64, max: i64, m: Multiplier) -> i32 {
    let d = requantize(l - max, m);
    lut::exp_q11(d.clamp(-32768, 0) as i32)
}

/// Softmax statistics of query `q` over all keys (`keys`: `n x c` HWC): `(max, sum of weights)`.
pub fn query_stats(q: &[i16], keys: &[i16], m: Multiplier) -> (i64, i64) {
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if let Some(s) = super::x86::query_stats(q, keys, m) {
        return s;
    }
    let c = q.len();
    if c == 0 {
        return (0, 0); // no query channels: no logits
    }
    // Armv7E-M: the largest logit two keys a call where the query length allows (`dsp::logits2`,
    // as `block_weights`), the rest one by one.
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    let max = {
        let (mut best, mut done) = (i64::MIN, 0);
        for k in keys.chunks_exact(2 * c) {
            let Some((a, b)) = super::dsp::logits2(q, k) else {
                break;
            };
            best = best.max(a).max(b);
            done += 2;
        }
        for k in keys.chunks_exact(c).skip(done) {
            best = best.max(logit(q, k));
        }
        if keys.len() < c { 0 } else { best }
    };
    #[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
    let max = keys.chunks_exact(c).map(|k| logit(q, k)).max().unwrap_or(0);
    #[cfg(all(target_arch = "arm", any(feature = "mve", feature = "dsp")))]
    if (2..=62).contains(&m.shift) {
        // Helium: the weights of a block of keys four a vector; Armv7E-M: by one tight loop
        // (`block_weights`).
        let mut e = [0i32; KEY_BLOCK];
        let mut sum = 0i64;
        for kb in keys.chunks(c.saturating_mul(KEY_BLOCK).max(1)) {
            sum += block_weights(q, kb, max, m, &mut e).1;
        }
        return (max, sum);
    }
    #[allow(unreachable_code)]
    let sum = keys.chunks_exact(c).map(|k| weight(logit(q, k), max, m) as i64).sum();
    (max, sum)
}

/// The softmax weights of the whole keys in `kb` (`q.len()` values each, at most [`KEY_BLOCK`]
/// of them) into `e`: `(number of keys, sum of their weights, whether one is not 0)`. On
/// Cortex-M55 with Helium four keys a vector (`mve::exp_weights`) where every logit's
/// distance to the maximum fits `i32`, the same integers as [`weight`].
#[inline(always)]
fn block_weights(q: &[i16], kb: &[i16], max: i64, m: Multiplier, e: &mut [i32; KEY_BLOCK]) -> (usize, i64, bool) {
    let c = q.len().max(1);
    #[cfg(all(target_arch = "arm", any(feature = "mve", feature = "dsp")))]
    {
        // The distances to the maximum in `e`, then their weights in place.
        let (mut nb, mut fits) = (0, true);
        // Helium: 32-value queries with the query in registers for the whole block.
        #[cfg(feature = "mve")]
        if let Some(n) = super::mve::logits32(q, kb, max, e) {
            nb = n;
        }
        // Armv7E-M: two keys per call where the query length allows (`dsp::logits2`).
        #[cfg(not(feature = "mve"))]
        for (de, k) in e.chunks_exact_mut(2).zip(kb.chunks_exact(2 * c)) {
            let Some((la, lb)) = super::dsp::logits2(q, k) else {
                break;
            };
            if let [da, db] = de {
                let (la, lb) = (la - max, lb - max);
                (*da, *db) = (la as i32, lb as i32);
                fits &= *da as i64 == la && *db as i64 == lb;
            }
            nb += 2;
        }
        for (dk, k) in e.iter_mut().zip(kb.chunks_exact(c)).skip(nb) {
            let l = logit(q, k) - max;
            *dk = l as i32;
            fits &= *dk as i64 == l;
            nb += 1;
        }
        #[cfg(feature = "mve")]
        let weights = super::mve::exp_weights;
        #[cfg(not(feature = "mve"))]
        let weights = super::dsp::exp_weights;
        if fits && let Some(ek) = e.get_mut(..nb) && let Some((most, sum)) = weights(ek, m.m, m.shift) {
            return (nb, sum, most != 0);
        }
    }
    let (mut nb, mut sum, mut any) = (0, 0i64, false);
    for (w, k) in e.iter_mut().zip(kb.chunks_exact(c)) {
        *w = weight(logit(q, k), max, m);
        sum += *w as i64;
        any |= *w != 0;
        nb += 1;
    }
    (nb, sum, any)
}

/// Aggregated values for query `q` (`values`: `n x cv` HWC) into `out` (`cv`), in the values'
/// format shifted by `shift` fraction bits. `acc` is scratch of `cv` values.
#[allow(clippy::too_many_arguments)]
pub fn aggregate_query(q: &[i16], keys: &[i16], values: &[i16], cv: usize, stats: (i64, i64), m: Multiplier, shift: i8, acc: &mut [i64], out: &mut [i16]) {
    let Some(acc) = acc.get_mut(..cv) else {
        return; // scratch shorter than the values (the engine's never is)
    };
    acc.fill(0);
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    let done = super::x86::aggregate(q, keys, values, cv, stats.0, m, acc);
    #[cfg(not(all(target_arch = "x86_64", feature = "std")))]
    let done = false;
    if !done {
        aggregate_blocked(q, keys, values, cv, stats.0, m, acc);
    }
    let div = crate::arith::DivRoundSat16::new(stats.1);
    for (o, a) in out.iter_mut().zip(acc.iter()) {
        *o = div.apply(shift_round(*a, shift as i32));
    }
}

/// [`aggregate_query`] with the values channel-major (`values[ch n + j]` for the `n` keys of
/// `keys`, `n x q.len()`): the Armv7E-M firmware's layout (`refine::mga_values` writes it so),
/// whose value sums read two keys of a channel as one word ([`super::dsp::aggregate_cm`]). The
/// same weights, blocks and exact sums as [`aggregate_query`], so the same outputs.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[allow(clippy::too_many_arguments)]
pub fn aggregate_query_cm(q: &[i16], keys: &[i16], values: &[i16], n: usize, cv: usize, stats: (i64, i64), m: Multiplier, shift: i8, acc: &mut [i64], out: &mut [i16]) {
    let Some(acc) = acc.get_mut(..cv) else {
        return; // scratch shorter than the values (the engine's never is)
    };
    acc.fill(0);
    let c = q.len();
    if c > 0 && cv > 0 {
        let keys = keys.get(..n.saturating_mul(c)).unwrap_or(keys);
        let mut e = [0i32; KEY_BLOCK];
        for (b, kb) in keys.chunks(c.saturating_mul(KEY_BLOCK).max(1)).enumerate() {
            let (nb, _, any) = block_weights(q, kb, stats.0, m, &mut e);
            if any {
                super::dsp::aggregate_cm(e.get(..nb).unwrap_or_default(), values, n, b * KEY_BLOCK, cv, acc);
            }
        }
    }
    let div = crate::arith::DivRoundSat16::new(stats.1);
    for (o, a) in out.iter_mut().zip(acc.iter()) {
        *o = div.apply(shift_round(*a, shift as i32));
    }
}

/// An aggregated value from its weighted sum `acc = sum_j e_j v_j` and the query's sum of
/// weights `sum`, in the values' format shifted by `shift` fraction bits.
#[inline(always)]
pub fn aggregated(acc: i64, shift: i8, sum: i64) -> i16 {
    crate::arith::div_round_sat_i16(shift_round(acc, shift as i32), sum)
}

/// Keys per block of [`aggregate_blocked`]: their softmax weights wait on the stack (512 bytes;
/// 32 keys took 17.6 M more instructions per 160x120 frame on the Cortex-M55, per-block overhead).
pub(super) const KEY_BLOCK: usize = 128;

/// `acc[ch] += sum_j e_j * v_j[ch]` over all keys, `e_j` the softmax weight of key `j` for
/// query `q`: the portable aggregation (Cortex-M). Key by key with the `cv` sums in memory, each
/// product is a load, a 64-bit multiply-add and a store of the sum; instead the weights of a
/// block of keys are computed first, then each pair of channels runs over the block with its two
/// sums in registers (a 32 x 16 -> 64-bit `SMLAL` per product on Cortex-M). The sums are exact,
/// so the order changes nothing.
fn aggregate_blocked(q: &[i16], keys: &[i16], values: &[i16], cv: usize, max: i64, m: Multiplier, acc: &mut [i64]) {
    let c = q.len();
    if c == 0 || cv == 0 {
        return;
    }
    // Non-zero chunk sizes (no zero-size chunking path; c, cv >= 1 here).
    let (kstep, vstep) = (c.saturating_mul(KEY_BLOCK).max(1), cv.saturating_mul(KEY_BLOCK).max(1));
    let mut e = [0i32; KEY_BLOCK];
    for (kb, vb) in keys.chunks(kstep).zip(values.chunks(vstep)) {
        let (nb, _, any) = block_weights(q, kb, max, m, &mut e);
        if !any {
            continue; // far keys: every weight rounds to 0
        }
        let e = e.get(..nb).unwrap_or(&[]);
        // Every key of the block has its `cv` values (the chunks above are whole for both).
        if vb.len() < nb * cv {
            continue;
        }
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        {
            // Helium: four keys per vector, two channels per pass (`mve::aggregate`).
            super::mve::aggregate(e, vb, cv, acc);
            continue;
        }
        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
        {
            // Armv7E-M: two keys and two channels per `SMLALD` step (`dsp::aggregate`).
            super::dsp::aggregate(e, vb, cv, acc);
            continue;
        }
        #[allow(unreachable_code)]
        for (i, a) in acc.chunks_mut(2).enumerate() {
            let mut o = 2 * i;
            match a {
                [a0, a1] if o + 1 < cv => {
                    let (mut s0, mut s1) = (*a0, *a1);
                    for w in e {
                        // SAFETY: `o = j cv + 2 i` for key `j < nb` and `2 i + 1 < cv`, so
                        // `o + 1 < nb cv <= vb.len()` (checked above).
                        let (v0, v1) = unsafe { (*vb.get_unchecked(o), *vb.get_unchecked(o + 1)) };
                        s0 += *w as i64 * v0 as i64;
                        s1 += *w as i64 * v1 as i64;
                        o += cv;
                    }
                    (*a0, *a1) = (s0, s1);
                }
                [a0] if o < cv => {
                    let mut s0 = *a0;
                    for w in e {
                        // SAFETY: as above, with `2 i < cv`.
                        s0 += *w as i64 * unsafe { *vb.get_unchecked(o) } as i64;
                        o += cv;
                    }
                    *a0 = s0;
                }
                _ => {}
            }
        }
    }
}

/// Plain twin: builds the `n x n` weight matrix, then every output (host tests only).
#[cfg(feature = "std")]
#[allow(clippy::indexing_slicing)] // host-only specification, indexed as the formula reads
pub fn attention_plain(queries: &[i16], keys: &[i16], values: &[i16], c: usize, cv: usize, m: Multiplier, shift: i8) -> Vec<i16> {
    let n = queries.len() / c;
    let logits: Vec<i64> = (0..n * n).map(|ij| logit(&queries[ij / n * c..][..c], &keys[ij % n * c..][..c])).collect();
    let mut out = vec![0i16; n * cv];
    for i in 0..n {
        let row = &logits[i * n..(i + 1) * n];
        let max = *row.iter().max().unwrap_or(&0);
        let e: Vec<i64> = row.iter().map(|l| weight(*l, max, m) as i64).collect();
        let s: i64 = e.iter().sum();
        for ch in 0..cv {
            let a: i64 = (0..n).map(|j| e[j] * values[j * cv + ch] as i64).sum();
            out[i * cv + ch] = sat_i16(crate::arith::div_round(shift_round(a, shift as i32), s));
        }
    }
    out
}

#[cfg(all(test, feature = "std"))]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::testutil::Rng;
    use super::*;

    /// The streaming path (per query: statistics, then aggregation) against the attention matrix
    /// of the plain twin: a small odd shape, and the model's shape, whose channel counts take the
    /// x86 SIMD accumulation where the CPU has it.
    #[test]
    fn streaming_matches_matrix() {
        for (seed, n, c, cv) in [(3, 45, 8, 5), (5, 150, 32, 64)] {
            let mut r = Rng(seed);
            let q: Vec<i16> = (0..n * c).map(|_| r.i16() / 64).collect();
            let k: Vec<i16> = (0..n * c).map(|_| r.i16() / 64).collect();
            let v: Vec<i16> = (0..n * cv).map(|_| r.i16()).collect();
            let m = Multiplier { m: 1 << 30, shift: 26 };
            let want = attention_plain(&q, &k, &v, c, cv, m, -1);
            let mut acc = vec![0i64; cv];
            for i in 0..n {
                let st = query_stats(&q[i * c..][..c], &k, m);
                let mut out = vec![0i16; cv];
                aggregate_query(&q[i * c..][..c], &k, &v, cv, st, m, -1, &mut acc, &mut out);
                assert_eq!(out, want[i * cv..(i + 1) * cv], "{n}x{c}, query {i}");
            }
            assert!(want.iter().any(|x| *x != 0));
            // The portable path itself (Cortex-M's; the x86 one above where the CPU has it),
            // with a key count that leaves a partial block.
            for i in 0..n {
                let st = query_stats(&q[i * c..][..c], &k, m);
                let mut sums = vec![0i64; cv];
                aggregate_blocked(&q[i * c..][..c], &k, &v, cv, st.0, m, &mut sums);
                let out: Vec<i16> = sums.iter().map(|a| sat_i16(crate::arith::div_round(shift_round(*a, -1), st.1))).collect();
                assert_eq!(out, want[i * cv..(i + 1) * cv], "portable {n}x{c}, query {i}");
            }
        }
    }

    #[test]
    fn rope_rotates() {
        let mut v = [1000i16, 0, 1000, 0];
        rope_pixel(&mut v, 0, 0, &[1 << 30, 1 << 30]);
        assert_eq!(v, [1000, 0, 1000, 0]);
        rope_pixel(&mut v, 1, 2, &[1 << 30, 1 << 30]); // x: quarter turn, y: half turn
        assert_eq!(v, [0, 1000, -1000, 0]);
    }
}
