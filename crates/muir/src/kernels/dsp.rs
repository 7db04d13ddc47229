//! Dot products with int8 weights on the Armv7E-M DSP extension (Cortex-M4/M7), feature `dsp`.
//!
//! `SMLAD` multiplies two pairs of 16-bit halves and adds both products to a 32-bit accumulator:
//! two MACs per instruction. Four int8 weights are widened into two pairs with `SXTB16` (bytes 0
//! and 2, then bytes 1 and 3 after a rotation); four u8 activations likewise with `UXTB16`, four
//! i8 ones with `SXTB16`, and four i16 activations (two words) are re-paired with `PKHBT`/`PKHTB`,
//! the way CMSIS-NN does it. Two loads, four widenings or packs and two `SMLAD`s make four MACs.
//!
//! The results are the same integers as the portable loops in `kernels` (host and target stay
//! bit-exact): every product and partial sum fits in `i32` under the same bounds as there (u8 and
//! i8 inputs: `|w x| < 2^15`, fewer than 2^16 terms; i16 inputs: chunks of `kernels::I16_CHUNK`
//! terms, `|w x| <= 2^22`), so the accumulation order does not matter and `SMLAD` never overflows. The
//! QEMU firmware test checks the whole frame against the host engine.

use core::arch::asm;

/// The 4 bytes at `i` as a little-endian word; the caller guarantees `i + 4 <= b.len()`.
#[inline(always)]
fn word(b: &[u8], i: usize) -> u32 {
    debug_assert!(i + 4 <= b.len());
    // SAFETY: `i + 4 <= b.len()` (every caller loops while `i + 4 <= n`, n <= b.len()); Cortex-M4/M7
    // load unaligned words in one instruction.
    unsafe { core::ptr::read_unaligned(b.as_ptr().add(i) as *const u32) }
}

/// The 2 i16 values at `i` as one word (low half first); the caller guarantees `i + 2 <= x.len()`.
#[inline(always)]
fn pair(x: &[i16], i: usize) -> u32 {
    debug_assert!(i + 2 <= x.len());
    // SAFETY: as for `word`.
    unsafe { core::ptr::read_unaligned(x.as_ptr().add(i) as *const u32) }
}

#[inline(always)]
fn bytes_of_i8(x: &[i8]) -> &[u8] {
    // SAFETY: i8 and u8 have the same size, alignment and validity.
    unsafe { core::slice::from_raw_parts(x.as_ptr() as *const u8, x.len()) }
}

/// A register-only DSP instruction of Armv7E-M with one operand, as a function.
macro_rules! unary {
    ($(#[$doc:meta])* $name:ident = $insn:literal) => {
        $(#[$doc])*
        #[inline(always)]
        fn $name(x: u32) -> u32 {
            let r;
            // SAFETY: one register-only instruction; no memory, stack or flags touched.
            unsafe { asm!($insn, r = lateout(reg) r, x = in(reg) x, options(pure, nomem, nostack, preserves_flags)) };
            r
        }
    };
}

unary!(
    /// Bytes 0 and 2 of `x`, sign-extended into two 16-bit halves.
    sxtb16 = "sxtb16 {r}, {x}"
);
unary!(
    /// Bytes 1 and 3 of `x`, sign-extended into two 16-bit halves.
    sxtb16_ror8 = "sxtb16 {r}, {x}, ror #8"
);
unary!(
    /// Bytes 0 and 2 of `x`, zero-extended into two 16-bit halves.
    uxtb16 = "uxtb16 {r}, {x}"
);
unary!(
    /// Bytes 1 and 3 of `x`, zero-extended into two 16-bit halves.
    uxtb16_ror8 = "uxtb16 {r}, {x}, ror #8"
);

/// Low half of `lo` below the low half of `hi`: `(lo[15:0], hi[15:0])`.
#[inline(always)]
fn pkhbt(lo: u32, hi: u32) -> u32 {
    let r;
    // SAFETY: as above.
    unsafe { asm!("pkhbt {r}, {a}, {b}, lsl #16", r = lateout(reg) r, a = in(reg) lo, b = in(reg) hi, options(pure, nomem, nostack, preserves_flags)) };
    r
}

/// High half of `lo` below the high half of `hi`: `(lo[31:16], hi[31:16])`.
#[inline(always)]
fn pkhtb(lo: u32, hi: u32) -> u32 {
    let r;
    // SAFETY: as above.
    unsafe { asm!("pkhtb {r}, {a}, {b}, asr #16", r = lateout(reg) r, a = in(reg) hi, b = in(reg) lo, options(pure, nomem, nostack, preserves_flags)) };
    r
}

/// `acc + a.lo * b.lo + a.hi * b.hi` (signed 16-bit halves).
#[inline(always)]
fn smlad(a: u32, b: u32, acc: i32) -> i32 {
    let r;
    // SAFETY: register-only; SMLAD sets the Q flag on overflow, which the bounds above exclude and
    // nothing reads.
    unsafe { asm!("smlad {r}, {a}, {b}, {c}", r = lateout(reg) r, a = in(reg) a, b = in(reg) b, c = in(reg) acc, options(pure, nomem, nostack)) };
    r
}

/// `sum_i q[i] k[i]` over the shorter slice, exact in i64 (the MGA logits, `attention::logit`).
/// Where both slices are word-aligned (the engine's keys and queries rows usually are; `LDRD`
/// faults otherwise): eight products a step by two
/// `LDRD` of each and two `SMLALD` per four products (10 instructions per 8 products, where the
/// portable loop compiled into the attention's closures took about 24 with its spills); else, and
/// for the last products, the portable loop. Exact, so the same integer as the portable loop.
#[inline(always)]
pub fn dot_i16_i64(q: &[i16], k: &[i16]) -> i64 {
    let n = q.len().min(k.len());
    let steps = n / 8;
    let mut i = 0;
    let (mut lo, mut hi) = (0u32, 0u32);
    if steps > 0 && (q.as_ptr() as usize | k.as_ptr() as usize).is_multiple_of(4) {
        // SAFETY: `steps` steps read `8 steps <= n` values of each slice, word-aligned (checked:
        // `LDRD` needs it); register-only otherwise, no flags read after.
        unsafe {
            asm!(
                "2:",
                "ldrd {a0}, {a1}, [{q}], #8",
                "ldrd {b0}, {b1}, [{k}], #8",
                "smlald {lo}, {hi}, {a0}, {b0}",
                "smlald {lo}, {hi}, {a1}, {b1}",
                "ldrd {a0}, {a1}, [{q}], #8",
                "ldrd {b0}, {b1}, [{k}], #8",
                "smlald {lo}, {hi}, {a0}, {b0}",
                "smlald {lo}, {hi}, {a1}, {b1}",
                "subs {n}, #1",
                "bne 2b",
                q = inout(reg) q.as_ptr() => _,
                k = inout(reg) k.as_ptr() => _,
                n = inout(reg) steps => _,
                lo = inout(reg) lo,
                hi = inout(reg) hi,
                a0 = out(reg) _, a1 = out(reg) _, b0 = out(reg) _, b1 = out(reg) _,
                options(nostack, readonly),
            );
        }
        i = 8 * steps;
    }
    let mut s = ((hi as u64) << 32 | lo as u64) as i64;
    for (a, b) in q.iter().zip(k).take(n).skip(i) {
        s += *a as i64 * *b as i64;
    }
    s
}

/// Most keys per call of [`aggregate`]'s paired loop: the engine's blocks (the packed weights
/// wait on the stack, 256 bytes). Tied to the constant, as a larger block would silently take
/// the plain loop.
const AGG_KEYS: usize = super::attention::KEY_BLOCK;
/// Most keys of a block whose weights do not fit i16 (the query's maximum, exp(0) = 32768, and
/// its ties) that the paired loop leaves to a per-key pass.
const WIDE_KEYS: usize = 4;

/// The MGA value sums of a block of keys: `acc[ch] += sum_j e[j] v[j cv + ch]` (`v`: the keys'
/// values, HWC, `cv` a key; `acc`: `cv` sums). For a block of at most [`AGG_KEYS`] keys, two keys
/// and two channels per step: the weights packed in pairs once, each key's two values one word,
/// `PKHBT`/`PKHTB` into (key `j`, key `j + 1`) pairs per channel and one `SMLALD` per channel (5
/// instructions per product before: two `LDRSH`, the weight, `SMLAL` and the step, per channel
/// and key). A weight that does not fit i16 (32768 = exp(0) at the query's maximum, so one block
/// in a few has one) is packed as 0 and its key added by a per-key pass afterwards (at most
/// [`WIDE_KEYS`] of them, else the whole block by the plain loop); the odd last channel and key by
/// the plain loop. Exact sums, so the same integers in any order.
pub fn aggregate(e: &[i32], v: &[i16], cv: usize, acc: &mut [i64]) {
    let nb = v.len().checked_div(cv).map_or(0, |n| e.len().min(n));
    let acc = match acc.get_mut(..cv) {
        Some(a) => a,
        None => return,
    };
    let pairs = nb / 2;
    let mut done = 0;
    // The pairs' weights, and the keys whose weight is packed as 0.
    let mut ep = [0u32; AGG_KEYS / 2];
    let (mut wide, mut nw) = ([0usize; WIDE_KEYS], 0);
    if pairs > 0 && nb <= AGG_KEYS {
        for (j, &w) in e.iter().enumerate().take(2 * pairs) {
            let half = if w as i16 as i32 == w {
                w as u32 & 0xffff
            } else {
                // Past WIDE_KEYS of them, `nw` says so and the block goes to the plain loop.
                if let Some(slot) = wide.get_mut(nw) {
                    *slot = j;
                }
                nw += 1;
                0
            };
            if let Some(p) = ep.get_mut(j / 2) {
                *p |= half << (16 * (j % 2));
            }
        }
    }
    if pairs > 0 && nb <= AGG_KEYS && nw <= WIDE_KEYS {
        paired_sums(ep.get(..pairs).unwrap_or_default(), v, cv, acc);
        // The keys packed as 0, on the channels the pairs covered.
        for &j in wide.get(..nw).unwrap_or_default() {
            if let (Some(&w), Some(vk)) = (e.get(j), v.chunks_exact(cv).nth(j)) {
                for (a, x) in acc.iter_mut().zip(vk).take(cv & !1) {
                    *a += w as i64 * *x as i64;
                }
            }
        }
        if cv % 2 == 1
            && let Some(a) = acc.last_mut()
        {
            for (w, x) in e.iter().zip(v.iter().skip(cv - 1).step_by(cv)).take(2 * pairs) {
                *a += *w as i64 * *x as i64;
            }
        }
        done = 2 * pairs;
    }
    for (w, vk) in e.iter().zip(v.chunks_exact(cv.max(1))).take(nb).skip(done) {
        for (a, x) in acc.iter_mut().zip(vk) {
            *a += *w as i64 * *x as i64;
        }
    }
}

/// `dst[i] = src[i]` for `i` below both lengths, two values a word (unaligned `LDR`/`STR`, which
/// the Cortex-M4/M7 allow) by one `asm!` loop: a short copy of halfwords by `memcpy` takes the
/// library's byte loop (the path steps' windows, `fullres::path_step`).
#[inline(always)]
pub fn copy_u16(dst: &mut [u16], src: &[u16]) {
    let n = dst.len().min(src.len());
    let words = n / 2;
    if words > 0 {
        // SAFETY: `words` words read from `src` and written to `dst`, `2 words <= n` values of
        // each (an odd word first, then two a pass: 3 instructions a word against 4); no stack;
        // `lsrs`, `cmp` and `subs` set the flags (clobbered by default).
        unsafe {
            asm!(
                "lsrs {n}, {n}, #1",
                "bcc 3f",
                "ldr {t}, [{s}], #4",
                "str {t}, [{d}], #4",
                "3:",
                "cmp {n}, #0",
                "beq 4f",
                "2:",
                "ldr {t}, [{s}], #4",
                "ldr {u}, [{s}], #4",
                "str {t}, [{d}], #4",
                "str {u}, [{d}], #4",
                "subs {n}, #1",
                "bne 2b",
                "4:",
                s = inout(reg) src.as_ptr() => _,
                d = inout(reg) dst.as_mut_ptr() => _,
                n = inout(reg) words => _,
                t = out(reg) _,
                u = out(reg) _,
                options(nostack),
            );
        }
    }
    if n % 2 == 1
        && let (Some(d), Some(s)) = (dst.get_mut(n - 1), src.get(n - 1))
    {
        *d = *s;
    }
}

/// The least value of `s` (`None` when empty): two values a word, `USUB16` and `SEL` keeping the
/// lesser halfword of each lane, two words a step, then the lesser lane (the path steps of the
/// full-resolution refinement, `fullres::path_step`). The same value as `s.iter().min()`.
#[inline(always)]
pub fn min_u16(s: &[u16]) -> Option<u16> {
    let &first = s.first()?;
    let mut m = first as u32 * 0x0001_0001;
    let p = s.as_ptr();
    let mut k = 0;
    while k + 4 <= s.len() {
        // SAFETY: `k + 4 <= s.len()`: two unaligned words (Cortex-M4/M7 load them in one
        // instruction; the checked pairs took a bounds test each).
        let (a, b) = unsafe { (p.add(k).cast::<u32>().read_unaligned(), p.add(k + 2).cast::<u32>().read_unaligned()) };
        // SAFETY: register-only DSP instructions (the GE flags they set are not read after).
        unsafe {
            asm!(
                "usub16 {t}, {m}, {a}",
                "sel {m}, {a}, {m}",
                "usub16 {t}, {m}, {b}",
                "sel {m}, {b}, {m}",
                m = inout(reg) m, a = in(reg) a, b = in(reg) b, t = out(reg) _,
                options(pure, nomem, nostack),
            );
        }
        k += 4;
    }
    let mut least = (m as u16).min((m >> 16) as u16);
    for v in s.iter().skip(k) {
        least = least.min(*v);
    }
    Some(least)
}

/// The MGA logits of two consecutive keys (`k`: key `a`'s `q.len()` values, then key `b`'s):
/// `(q . a, q . b)`, exact in i64, for the query lengths the models use (32 and 64: the loop is
/// unrolled at compile time, key `b` read at a constant offset from key `a`), both slices
/// word-aligned. Per four values of the query: its two words by one `LDRD`, each key's by one,
/// four `SMLALD` (7 instructions for 8 products, where two [`dot_i16_i64`] calls take 10 and
/// their loop steps). `None` for other lengths, misaligned or short slices.
#[inline(always)]
pub fn logits2(q: &[i16], k: &[i16]) -> Option<(i64, i64)> {
    let c = q.len();
    if k.len() < 2 * c || !(q.as_ptr() as usize | k.as_ptr() as usize).is_multiple_of(4) {
        return None;
    }
    let (mut al, mut ah, mut bl, mut bh) = (0u32, 0u32, 0u32, 0u32);
    // One step of four query values, written out (not `.rept`: the compiler sizes an `asm!`
    // block by its lines, and branches and literal pools around a block larger than it thinks
    // can land out of place).
    macro_rules! step {
        () => {
            "ldrd {q0}, {q1}, [{q}], #8\nldrd {t0}, {t1}, [{k}, #{off}]\nsmlald {bl}, {bh}, {q0}, {t0}\nsmlald {bl}, {bh}, {q1}, {t1}\nldrd {t0}, {t1}, [{k}], #8\nsmlald {al}, {ah}, {q0}, {t0}\nsmlald {al}, {ah}, {q1}, {t1}\n"
        };
    }
    macro_rules! pair {
        ($c:literal, $($steps:tt)*) => {
            // SAFETY: `$c / 4` steps read `$c` values of `q` and of each key (`k.len() >= 2 c`,
            // checked), all word-aligned (checked: `LDRD` needs it; `2 c` bytes between the keys
            // is a multiple of 4); register-only otherwise, no flags.
            unsafe {
                asm!(
                    $($steps)*
                    off = const 2 * $c,
                    q = inout(reg) q.as_ptr() => _,
                    k = inout(reg) k.as_ptr() => _,
                    al = inout(reg) al, ah = inout(reg) ah, bl = inout(reg) bl, bh = inout(reg) bh,
                    q0 = out(reg) _, q1 = out(reg) _, t0 = out(reg) _, t1 = out(reg) _,
                    options(nostack, readonly, preserves_flags),
                )
            }
        };
    }
    match c {
        32 => pair!(32, step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(),),
        64 => pair!(64, step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(), step!(),),
        _ => return None,
    }
    Some((((ah as u64) << 32 | al as u64) as i64, ((bh as u64) << 32 | bl as u64) as i64))
}

/// The MGA softmax weights of a block of keys, in place (the Armv7E-M twin of
/// `mve::exp_weights`): each `e[k]`, the logit minus the query's maximum, becomes
/// `exp_q11(clamp(requantize_i32(e[k], m), -32768, 0))` for shifts `1..=62` (others: nothing
/// written, `None`); returns the largest weight and the sum. One loop per shift range with the
/// requantisation's constants hoisted (`SMULL`, then for `s >= 33` the high word's rounding
/// shift), the table read as `exp_q11`'s by one word of base and step at `u >> 5`
/// (`lut::exp_steps`) with the fraction `u & 31`. In the 160x120 profile: about 33 instructions a
/// key with two halfword loads, the index `min(u >> 5, 1023)` and the fraction `u - 32 i`; about
/// 43 for the per-key `attention::weight` (range checks, 64-bit rounding, `exp_q11`'s branch).
/// Exact: `requantize(d, m) = requantize_i32(d, m)` for an `i32` `d` and these shifts.
#[inline(never)]
pub fn exp_weights(e: &mut [i32], m: i32, shift: u8) -> Option<(i32, i64)> {
    if !(1..=62).contains(&shift) {
        return None;
    }
    let table = crate::arith::lut::exp_steps();
    let (mut most, mut sum) = (0i32, 0i64);
    // The sum in i32 per run of 2^15 keys (every weight is a table value, below 2^16: a run's sum
    // stays below 2^31), added to `sum` after.
    for e in e.chunks_mut(1 << 15) {
        let mut part = 0i32;
        let mut put = |v: &mut i32, x: i32| {
            let u = (x.clamp(-32768, 0) + 32768) as u32;
            // Base and step of interval `u >> 5` in one word (`lut::exp_steps`: `u = 32768`
            // reads the last entry with fraction 0, where `exp_q11`'s table takes entry 1023
            // with fraction 32: the same value).
            let t = table.get((u >> 5) as usize).copied().unwrap_or(0);
            // The step is at most 32768 and the fraction below 32: no overflow.
            let w = (t & 0xFFFF) as i32 + (((t >> 16) * (u & 31) + 16) >> 5) as i32;
            *v = w;
            most = most.max(w);
            part += w;
        };
        let s = shift as u32;
        if s >= 33 {
            let (half, k) = (1i32 << (s - 33), s - 32);
            for v in e.iter_mut() {
                let hi = ((*v as i64 * m as i64) >> 32) as i32;
                put(v, hi.wrapping_add(half) >> k);
            }
        } else {
            let half = 1i64 << (s - 1);
            for v in e.iter_mut() {
                let x = (*v as i64 * m as i64 + half) >> s;
                // (`x` beyond i32 is beyond the clamp on the same side.)
                put(v, x.clamp(-32768, 0) as i32);
            }
        }
        sum += part as i64;
    }
    Some((most, sum))
}

/// [`aggregate`] with the values channel-major: `acc[ch] += sum_j e[j] v[ch n + j0 + j]` for the
/// block of keys `j0 .. j0 + e.len()` of `n` (the Armv7E-M firmware's layout of the MGA values,
/// `eltwise::mul_plane_q15_cm`). Two keys of a channel are one word, so per channel pair and pair
/// of keys the weight word, one word of each channel and two `SMLALD` (5 instructions per 4
/// products, `pair_sums_cm`), where the key-major layout re-pairs two keys' words with
/// `PKHBT`/`PKHTB` (8). Weights of 32768 as in [`aggregate`] (packed as 0, their keys added by a
/// per-key pass; more than [`WIDE_KEYS`] of them, or more than [`AGG_KEYS`] keys: the plain loop);
/// the odd last channel and key by the plain loop. Exact sums, so the same integers in any order.
/// A block or `acc` the slices do not hold leaves `acc` as it is (the engine's always fit).
pub fn aggregate_cm(e: &[i32], v: &[i16], n: usize, j0: usize, cv: usize, acc: &mut [i64]) {
    let nb = e.len();
    let fits = j0.checked_add(nb).is_some_and(|end| end <= n) && n.checked_mul(cv).is_some_and(|len| len <= v.len());
    let Some(acc) = acc.get_mut(..cv).filter(|_| fits) else {
        return;
    };
    // Channel `ch`'s values of the block (every caller below passes `ch < cv`).
    let row = |ch: usize| -> &[i16] {
        debug_assert!(ch < cv);
        // SAFETY: `ch < cv` and `j0 + nb <= n`, so `ch n + j0 + nb <= cv n <= v.len()` (`fits`).
        unsafe { core::slice::from_raw_parts(v.as_ptr().add(ch * n + j0), nb) }
    };
    let pairs = nb / 2;
    let mut done = 0;
    let mut ep = [0u32; AGG_KEYS / 2];
    let (mut wide, mut nw) = ([0usize; WIDE_KEYS], 0);
    if pairs > 0 && nb <= AGG_KEYS {
        for (t, (p, w)) in ep.iter_mut().zip(e.chunks_exact(2)).enumerate().take(pairs) {
            let &[a, b] = w else {
                continue;
            };
            if (a | b) as u32 >> 15 == 0 {
                // Both in `0 ..= 32767` (every weight but exp(0)): one word.
                *p = a as u32 | (b as u32) << 16;
                continue;
            }
            for (k, w) in [a, b].into_iter().enumerate() {
                let half = if w as i16 as i32 == w {
                    w as u32 & 0xffff
                } else {
                    if let Some(slot) = wide.get_mut(nw) {
                        *slot = 2 * t + k;
                    }
                    nw += 1;
                    0
                };
                *p |= half << (16 * k);
            }
        }
    }
    if pairs > 0 && nb <= AGG_KEYS && nw <= WIDE_KEYS {
        let ep = ep.get(..pairs).unwrap_or_default();
        for (i, a) in acc.chunks_exact_mut(2).enumerate() {
            let [a0, a1] = a else {
                continue;
            };
            let (r0, r1) = (row(2 * i), row(2 * i + 1));
            // Word-aligned rows (the engine's, for an even number of keys): one row at a time by
            // `LDRD`s; else both rows by word loads.
            let (s0, s1) = match row_sums2_aligned(ep, r0, r1) {
                Some(s) => s,
                None => match (row_sums_aligned(ep, r0), row_sums_aligned(ep, r1)) {
                    (Some(s0), Some(s1)) => (s0, s1),
                    _ => pair_sums_cm(ep, r0, r1),
                },
            };
            *a0 += s0;
            *a1 += s1;
            // The keys packed as 0.
            for &j in wide.get(..nw).unwrap_or_default() {
                if let (Some(&w), Some(&x0), Some(&x1)) = (e.get(j), r0.get(j), r1.get(j)) {
                    *a0 += w as i64 * x0 as i64;
                    *a1 += w as i64 * x1 as i64;
                }
            }
        }
        if cv % 2 == 1
            && let Some(a) = acc.last_mut()
        {
            for (w, x) in e.iter().zip(row(cv - 1)).take(2 * pairs) {
                *a += *w as i64 * *x as i64;
            }
        }
        done = 2 * pairs;
    }
    if done < nb {
        for (ch, a) in acc.iter_mut().enumerate() {
            for (w, x) in e.iter().zip(row(ch)).skip(done) {
                *a += *w as i64 * *x as i64;
            }
        }
    }
}

/// `sum_t (ep[t].lo r[2t] + ep[t].hi r[2t+1])` over the pairs both slices hold, for a
/// word-aligned `ep` and `r` (`None` otherwise): four keys a step by one `LDRD` of weights, one of
/// values and two `SMLALD` (4 instructions per 4 products, against [`pair_sums_cm`]'s 5 per 4 with
/// two rows), four steps a loop, the last 0 to 7 pairs in Rust.
#[inline(always)]
fn row_sums_aligned(ep: &[u32], r: &[i16]) -> Option<i64> {
    if !(ep.as_ptr() as usize | r.as_ptr() as usize).is_multiple_of(4) {
        return None;
    }
    let pairs = ep.len().min(r.len() / 2);
    let loops = pairs / 8;
    let (mut lo, mut hi) = (0u32, 0u32);
    // Four keys' pairs: one step, written out four times a loop (not `.rept`: the compiler sizes
    // an `asm!` block by its lines).
    macro_rules! step {
        () => {
            "ldrd {e0}, {e1}, [{ep}], #8\nldrd {t0}, {t1}, [{r}], #8\nsmlald {lo}, {hi}, {e0}, {t0}\nsmlald {lo}, {hi}, {e1}, {t1}"
        };
    }
    if loops > 0 {
        // SAFETY: `loops` loops read `8 loops <= pairs` words of `ep` and `16 loops <= 2 pairs`
        // values of `r`, word-aligned (checked: `LDRD` needs it); no stack; `subs` sets the flags
        // (clobbered by default).
        unsafe {
            asm!(
                "2:",
                step!(),
                step!(),
                step!(),
                step!(),
                "subs {n}, #1",
                "bne 2b",
                ep = inout(reg) ep.as_ptr() => _,
                r = inout(reg) r.as_ptr() => _,
                n = inout(reg) loops => _,
                lo = inout(reg) lo, hi = inout(reg) hi,
                e0 = out(reg) _, e1 = out(reg) _, t0 = out(reg) _, t1 = out(reg) _,
                options(nostack, readonly),
            );
        }
    }
    let mut sum = ((hi as u64) << 32 | lo as u64) as i64;
    for t in 8 * loops..pairs {
        if let (Some(&w), Some(&[a, b])) = (ep.get(t), r.get(2 * t..2 * t + 2)) {
            sum += (w as u16 as i16 as i64) * a as i64 + ((w >> 16) as u16 as i16 as i64) * b as i64;
        }
    }
    Some(sum)
}

/// [`aggregate_cm`]'s paired loop: `(sum_t (ep[t].lo r0[2t] + ep[t].hi r0[2t+1]), the same of
/// r1)` over the pairs all three slices hold: per pair the weight word, a word of each row and
/// two `SMLALD` (unaligned word loads, which the Cortex-M4/M7 allow), four pairs a step, the last
/// 0 to 3 pairs in Rust.
#[inline(always)]
fn pair_sums_cm(ep: &[u32], r0: &[i16], r1: &[i16]) -> (i64, i64) {
    let pairs = ep.len().min(r0.len() / 2).min(r1.len() / 2);
    let quads = pairs / 4;
    let (mut l0, mut h0, mut l1, mut h1) = (0u32, 0u32, 0u32, 0u32);
    if quads > 0 {
        // SAFETY: `quads` steps read `4 quads <= pairs` words of `ep` and `8 quads <= 2 pairs`
        // values of each row, all inside the slices (`pairs` above); no stack; the flags
        // (`subs`) are clobbered, which `asm!` assumes by default.
        unsafe {
            asm!(
                "2:",
                "ldr {e}, [{ep}], #4",
                "ldr {t}, [{p0}], #4",
                "smlald {l0}, {h0}, {e}, {t}",
                "ldr {t}, [{p1}], #4",
                "smlald {l1}, {h1}, {e}, {t}",
                "ldr {e}, [{ep}], #4",
                "ldr {t}, [{p0}], #4",
                "smlald {l0}, {h0}, {e}, {t}",
                "ldr {t}, [{p1}], #4",
                "smlald {l1}, {h1}, {e}, {t}",
                "ldr {e}, [{ep}], #4",
                "ldr {t}, [{p0}], #4",
                "smlald {l0}, {h0}, {e}, {t}",
                "ldr {t}, [{p1}], #4",
                "smlald {l1}, {h1}, {e}, {t}",
                "ldr {e}, [{ep}], #4",
                "ldr {t}, [{p0}], #4",
                "smlald {l0}, {h0}, {e}, {t}",
                "ldr {t}, [{p1}], #4",
                "smlald {l1}, {h1}, {e}, {t}",
                "subs {q}, #1",
                "bne 2b",
                ep = inout(reg) ep.as_ptr() => _,
                p0 = inout(reg) r0.as_ptr() => _,
                p1 = inout(reg) r1.as_ptr() => _,
                q = inout(reg) quads => _,
                l0 = inout(reg) l0, h0 = inout(reg) h0, l1 = inout(reg) l1, h1 = inout(reg) h1,
                e = out(reg) _, t = out(reg) _,
                options(nostack, readonly),
            );
        }
    }
    let (mut s0, mut s1) = (((h0 as u64) << 32 | l0 as u64) as i64, ((h1 as u64) << 32 | l1 as u64) as i64);
    for t in 4 * quads..pairs {
        if let (Some(&w), Some(&[a0, a1]), Some(&[b0, b1])) = (ep.get(t), r0.get(2 * t..2 * t + 2), r1.get(2 * t..2 * t + 2)) {
            let (wl, wh) = (w as u16 as i16 as i64, (w >> 16) as u16 as i16 as i64);
            s0 += wl * a0 as i64 + wh * a1 as i64;
            s1 += wl * b0 as i64 + wh * b1 as i64;
        }
    }
    (s0, s1)
}

/// [`aggregate`]'s paired loop: `acc[ch] += sum_t (ep[t].lo v[2t cv + ch] + ep[t].hi
/// v[(2t+1) cv + ch])` for the even channels below `cv & !1` (`acc`: `cv` sums). By `muir_dsp_paired_sums`:
/// per channel pair and pair of keys, the weight word, the two keys' value words, `PKHBT`/`PKHTB`
/// and two `SMLALD` (8 instructions, 12 compiled from Rust), the body written once per key pair
/// of a full block and entered by a computed branch (no loop test).
#[inline(never)]
fn paired_sums(ep: &[u32], v: &[i16], cv: usize, acc: &mut [i64]) {
    if ep.is_empty() || ep.len() > AGG_KEYS / 2 || ep.len().saturating_mul(2).saturating_mul(cv) > v.len() || acc.len() > cv || acc.len() < 2 {
        return; // `aggregate` never calls it so (but for fewer than two channels: nothing to do)
    }
    // SAFETY: keys `2 t`, `2 t + 1 < 2 ep.len()` and channels `2 i`, `2 i + 1 < acc.len() <=
    // cv`: every word read lies below `2 ep.len() cv <= v.len()` (checked above; unaligned word
    // loads, which the Cortex-M4/M7 allow); `1 <= ep.len() <= AGG_KEYS / 2` words of `ep`; the
    // `acc.len() / 2 >= 1` pairs of sums read and written.
    unsafe { muir_dsp_paired_sums(ep.as_ptr(), ep.len(), v.as_ptr(), cv, acc.as_mut_ptr(), acc.len() / 2) };
}

/// [`crate::arith::requantize_i32`] for `8 <= m.shift <= 62` (the convolution's short epilogue,
/// `conv::short_ok`): the same integer, `floor((acc m + 2^(s-1)) / 2^s)`. `SMLAL` adds the
/// 64-bit product to the rounding half in one instruction (the portable formula, compiled,
/// multiplies 64 by 64 bits when the `i32` came from a range-checked `i64`), then the 64-bit
/// arithmetic shift: for `s >= 32` only the high word (shifted by `s - 32`, sign-extended), else
/// both words. A shift outside the range gives an unspecified value, never a panic.
#[inline(always)]
pub fn requantize_i32(acc: i32, m: crate::arith::Multiplier) -> i64 {
    Requant::new(m).apply(acc)
}

/// A multiplier decoded for [`requantize_i32`]: the rounding half `2^(s-1)` as (low, high)
/// words and the shift, worked out once per (channel, part) where one multiplier requantises
/// many sums (the convolutions' per-channel-pair epilogues) instead of once per sum.
#[derive(Clone, Copy, Debug)]
pub struct Requant {
    m: i32,
    lo: u32,
    hi: u32,
    s: u32,
}

impl Requant {
    /// A multiplier of 0 (requantises every sum to 0 with a shift of 8).
    pub const ZERO: Requant = Requant { m: 0, lo: 1 << 7, hi: 0, s: 8 };

    /// `m` decoded (meaningful for `8 <= m.shift <= 62`, as [`requantize_i32`]).
    #[inline(always)]
    pub fn new(m: crate::arith::Multiplier) -> Self {
        let s = m.shift as u32;
        let (lo, hi) = if s >= 33 { (0u32, 1u32 << ((s - 33) & 31)) } else { (1u32 << (s.wrapping_sub(1) & 31), 0u32) };
        Requant { m: m.m, lo, hi, s }
    }

    /// [`requantize_i32`] of `acc`: `SMLAL` onto the rounding half, then the 64-bit shift.
    #[inline(always)]
    pub fn apply(&self, acc: i32) -> i64 {
        let (mut lo, mut hi, s) = (self.lo, self.hi, self.s);
        // SAFETY: register-only; SMLAL touches no flags.
        unsafe {
            asm!("smlal {lo}, {hi}, {a}, {b}", lo = inout(reg) lo, hi = inout(reg) hi, a = in(reg) acc, b = in(reg) self.m,
                options(pure, nomem, nostack, preserves_flags))
        };
        if s >= 32 {
            ((hi as i32) >> ((s - 32) & 31)) as i64
        } else {
            // 8 <= s < 32: both words (|p + 2^(s-1)| < 2^63, so the shifted value is exact).
            let l = (lo >> (s & 31)) | (hi << ((32 - s) & 31));
            let h = (hi as i32) >> (s & 31);
            ((h as i64) << 32) | l as i64
        }
    }
}

/// A one-part convolution's short epilogue before the activation, folded: for a multiplier of
/// shift `s` and a bias `bias`, `floor((floor((acc m + 2^(s-1)) / 2^s) + bias + 2^7) / 2^8)`
/// (the short path's [`requantize_i32`], the bias and `EXTRA_BITS` = 8 bits' rounding, as
/// `conv::finish_short` computes it for one part) is `floor((acc m + C) / 2^(s+8))` with `C =
/// 2^(s-1) + (bias + 2^7) 2^s` (nested floors of divisions by powers of two, the inner one
/// plus an integer): one `SMLAL` onto `C` and one arithmetic shift of the high word by `s - 24`
/// (at most 31). Made only for `24 <= s <= 61` and `|bias + 2^7| <= 2^(61 - s)` (so `|C| <= 2^62`): then `|acc m + C| < 2^63` for
/// any i32 `acc` (`|acc m| <= 2^62`) and the result fits i32.
#[derive(Clone, Copy, Debug)]
pub struct Folded {
    m: i32,
    lo: u32,
    hi: u32,
    k: u32,
}

impl Folded {
    /// `m` and `bias` folded, or `None` outside the range above.
    #[inline(always)]
    pub fn new(m: crate::arith::Multiplier, bias: i64) -> Option<Self> {
        let s = m.shift as u32;
        if !(24..=61).contains(&s) {
            return None;
        }
        // In i64 (the i128 shifts took some 60 instructions a call): `|bias + 2^7| <= 2^(61 -
        // s)` keeps `|(bias + 2^7) 2^s| <= 2^61` and, with `2^(s-1) <= 2^61`, `|C| <= 2^62`;
        // it refuses a few constants within 2^62 that the i128 test made (a bias near 2^(62 -
        // s)), which then take the unfolded path (same integers).
        let t = bias.checked_add(128)?;
        if t.unsigned_abs() > 1u64 << (61 - s) {
            return None;
        }
        let k = (s - 24).min(31);
        if s >= 33 {
            // `C`'s low word is 0; the high word `2^(s-33) + t 2^(s-32)` in 32 bits (`|t| <=
            // 2^28`; two 64-bit shifts by a variable amount cost some 20 instructions).
            let hi = (1i32 << ((s - 33) & 31)).wrapping_add((t as i32) << ((s - 32) & 31));
            return Some(Folded { m: m.m, lo: 0, hi: hi as u32, k });
        }
        let c = (1i64 << ((s - 1) & 63)) + (t << (s & 63));
        Some(Folded { m: m.m, lo: c as u32, hi: (c >> 32) as u32, k })
    }

    /// Whether `C`'s low word is 0 (`s >= 33`): then [`Folded::apply_high`] gives
    /// [`Folded::apply`]'s value.
    #[inline(always)]
    pub fn high_only(&self) -> bool {
        self.lo == 0
    }

    /// [`Folded::apply`] where [`Folded::high_only`]: `floor((acc m + C) / 2^32)` is
    /// `floor(acc m / 2^32) + C / 2^32`, one `SMMLA` (no copy of `C`'s two words for a 64-bit
    /// accumulator), then the shift. Another value where `C`'s low word is not 0.
    #[inline(always)]
    pub fn apply_high(&self, acc: i32) -> i32 {
        let d: i32;
        // SAFETY: register-only; SMMLA touches no flags.
        unsafe {
            asm!("smmla {d}, {a}, {b}, {c}", d = lateout(reg) d, a = in(reg) acc, b = in(reg) self.m, c = in(reg) self.hi,
                options(pure, nomem, nostack, preserves_flags))
        };
        d >> self.k
    }

    /// The folded value of `acc`: `SMLAL` onto `C`, the high word shifted.
    #[inline(always)]
    pub fn apply(&self, acc: i32) -> i32 {
        let (mut lo, mut hi) = (self.lo, self.hi);
        // SAFETY: register-only; SMLAL touches no flags.
        unsafe {
            asm!("smlal {lo}, {hi}, {a}, {b}", lo = inout(reg) lo, hi = inout(reg) hi, a = in(reg) acc, b = in(reg) self.m,
                options(pure, nomem, nostack, preserves_flags))
        };
        let _ = lo;
        (hi as i32) >> self.k
    }
}

/// An activation type whose four values at `i` widen into the two 16-bit pairs `SMLAD` takes:
/// values 0 and 2, then values 1 and 3 (the order `SXTB16` gives the weights).
pub trait Quad: Copy + Into<i32> {
    /// Values `i..i + 4` as (0 and 2, 1 and 3); the caller guarantees `i + 4 <= x.len()`.
    fn quad(x: &[Self], i: usize) -> (u32, u32);
    /// The same from a group of the pair layout (`kernels::pair_index`), which stores 16-bit
    /// values already as 0, 2, 1, 3.
    #[inline(always)]
    fn quad_paired(x: &[Self], i: usize) -> (u32, u32) {
        Self::quad(x, i)
    }
    /// [`dot2x2`]'s whole groups by the hand-scheduled assembly loop, where this type has one:
    /// `q >= 1` groups of four, `w0`, `w1` at least `4 q` and `x` at least `8 q` long.
    #[inline(always)]
    fn groups_asm(_w0: &[u8], _w1: &[u8], _x: &[Self], _q: usize) -> Option<[i32; 4]> {
        None
    }
}

// The 2x2 inner loops of `dot2x2` for u8 and i16 activations, scheduled by hand. Compiled from
// Rust, the loop needs 4 accumulators, 3 pointers, a bound and 6 widened operands (14 registers)
// in the 12 that inline assembly may use on Thumb (r6 and r7 are reserved), so LLVM spilled
// accumulators on every iteration (26 instructions per 16 MACs for i16 activations, 27 for u8).
// As standalone AAPCS functions the loops have r0-r12 and lr (the callee-saved ones pushed once
// per call): no spills. Per group of four values (16 MACs): i16 2 LDRD + 2 x (LDR + 2 SXTB16) +
// 8 SMLAD = 16 instructions; u8 2 LDR + 4 UXTB16 instead of the LDRDs = 20; the loop's CMP/BNE
// once per two groups (the body is written twice; an odd count enters at the second copy).
// Arguments: r0 = x (the pair layout), r1 = w0, r2 = w1, r3 = groups (>= 1), [sp] = out (the
// four sums w0.a, w1.a, w0.b, w1.b: i32 for u8; i64, added to, for i16). x of the i16 loop must
// be word-aligned (LDRD), the other pointers need not be.
// Registers: r4..r7 accumulators (a0, a1, a2, a3), r8..r11 activations, r12 / lr weights, r3 the
// end of w0.
core::arch::global_asm!(
    ".syntax unified",
    ".thumb",
    // Module-level assembly does not see `-C target-cpu`: on Armv8-M Mainline (Cortex-M33/M55)
    // the DSP extension would be off. Every instruction below has the same Thumb-2 encoding in
    // Armv7E-M, so the loops are assembled as Armv7E-M code on both.
    ".arch armv7e-m",
    // One group of the widened-weight loops (`dot2x2_w16`, `_i32`, the batched `_n` and `_ns`):
    // four i16 activations of two pixels and four widened weights of two channels, eight `SMLAD`
    // into the four sums r2-r5.
    ".macro w16_group",
    "    ldm.w r0!, {{r6-r9}}",        // a: (a0, a2), (a1, a3); b: (b0, b2), (b1, b3)
    "    ldm.w r1!, {{r10-r12, lr}}",  // w0: (w0, w2), (w1, w3); w1: the same, widened
    "    smlad r2, r10, r6, r2",
    "    smlad r2, r11, r7, r2",
    "    smlad r3, r12, r6, r3",
    "    smlad r3, lr, r7, r3",
    "    smlad r4, r10, r8, r4",
    "    smlad r4, r11, r9, r4",
    "    smlad r5, r12, r8, r5",
    "    smlad r5, lr, r9, r5",
    ".endm",
    ".section .text.muir_dsp_dot2x2_i16,\"ax\",%progbits",
    ".global muir_dsp_dot2x2_i16",
    ".type muir_dsp_dot2x2_i16,%function",
    ".p2align 2",
    ".thumb_func",
    // i16: the whole patch in one call, `I16_ASM_GROUPS` groups at a time in i32 (exact, see
    // there), each chunk's four sums added into the i64 `out` (which the caller zeroes);
    // the groups still to do wait in the stack slot [sp].
    "muir_dsp_dot2x2_i16:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #8",
    "    str r3, [sp]",
    "2:",
    "    ldr lr, [sp]",
    "    mov r12, lr",
    "    cmp r12, #{chunk}",
    "    it hi",
    "    movhi r12, #{chunk}",
    "    sub lr, lr, r12",
    "    str lr, [sp]",
    "    add r3, r1, r12, lsl #2",
    "    movs r4, #0",
    "    movs r5, #0",
    "    movs r6, #0",
    "    movs r7, #0",
    "    tst r12, #1",               // an odd group count starts at 3
    "    bne 3f",
    "1:",
    "    ldrd r8, r9, [r0], #8",      // a: (a0, a2), (a1, a3)
    "    ldrd r10, r11, [r0], #8",    // b: (b0, b2), (b1, b3)
    "    ldr lr, [r1], #4",
    "    sxtb16 r12, lr",             // w0: (w0, w2)
    "    sxtb16 lr, lr, ror #8",      //     (w1, w3)
    "    smlad r4, r12, r8, r4",
    "    smlad r4, lr, r9, r4",
    "    smlad r6, r12, r10, r6",
    "    smlad r6, lr, r11, r6",
    "    ldr lr, [r2], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r5, r12, r8, r5",
    "    smlad r5, lr, r9, r5",
    "    smlad r7, r12, r10, r7",
    "    smlad r7, lr, r11, r7",
    "3:",
    "    ldrd r8, r9, [r0], #8",      // a: (a0, a2), (a1, a3)
    "    ldrd r10, r11, [r0], #8",    // b: (b0, b2), (b1, b3)
    "    ldr lr, [r1], #4",
    "    sxtb16 r12, lr",             // w0: (w0, w2)
    "    sxtb16 lr, lr, ror #8",      //     (w1, w3)
    "    smlad r4, r12, r8, r4",
    "    smlad r4, lr, r9, r4",
    "    smlad r6, r12, r10, r6",
    "    smlad r6, lr, r11, r6",
    "    ldr lr, [r2], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r5, r12, r8, r5",
    "    smlad r5, lr, r9, r5",
    "    smlad r7, r12, r10, r7",
    "    smlad r7, lr, r11, r7",
    "    cmp r1, r3",
    "    bne 1b",
    "    ldr r12, [sp, #44]",
    "    ldrd r8, r9, [r12]",
    "    adds r8, r8, r4",
    "    adc r9, r9, r4, asr #31",
    "    strd r8, r9, [r12]",
    "    ldrd r8, r9, [r12, #8]",
    "    adds r8, r8, r5",
    "    adc r9, r9, r5, asr #31",
    "    strd r8, r9, [r12, #8]",
    "    ldrd r8, r9, [r12, #16]",
    "    adds r8, r8, r6",
    "    adc r9, r9, r6, asr #31",
    "    strd r8, r9, [r12, #16]",
    "    ldrd r8, r9, [r12, #24]",
    "    adds r8, r8, r7",
    "    adc r9, r9, r7, asr #31",
    "    strd r8, r9, [r12, #24]",
    "    ldr lr, [sp]",
    "    cmp lr, #0",
    "    bne 2b",
    "    add sp, #8",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_dot2x2_i16, . - muir_dsp_dot2x2_i16",
    "",
    ".section .text.muir_dsp_dot2x2_u8,\"ax\",%progbits",
    ".global muir_dsp_dot2x2_u8",
    ".type muir_dsp_dot2x2_u8,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_dot2x2_u8:",
    "    push {{r4-r11, lr}}",
    "    movs r4, #0",
    "    movs r5, #0",
    "    movs r6, #0",
    "    movs r7, #0",
    "    lsls r12, r3, #31",          // Z clear when the group count is odd: start at 3
    "    add r3, r1, r3, lsl #2",
    "    bne 3f",
    "1:",
    "    ldr r10, [r0, #4]",          // b: bytes 0..3
    "    ldr r8, [r0], #8",           // a: bytes 0..3
    "    uxtb16 r9, r8, ror #8",      // (a1, a3)
    "    uxtb16 r8, r8",              // (a0, a2)
    "    uxtb16 r11, r10, ror #8",    // (b1, b3)
    "    uxtb16 r10, r10",            // (b0, b2)
    "    ldr lr, [r1], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r4, r12, r8, r4",
    "    smlad r4, lr, r9, r4",
    "    smlad r6, r12, r10, r6",
    "    smlad r6, lr, r11, r6",
    "    ldr lr, [r2], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r5, r12, r8, r5",
    "    smlad r5, lr, r9, r5",
    "    smlad r7, r12, r10, r7",
    "    smlad r7, lr, r11, r7",
    "3:",
    "    ldr r10, [r0, #4]",          // b: bytes 0..3
    "    ldr r8, [r0], #8",           // a: bytes 0..3
    "    uxtb16 r9, r8, ror #8",      // (a1, a3)
    "    uxtb16 r8, r8",              // (a0, a2)
    "    uxtb16 r11, r10, ror #8",    // (b1, b3)
    "    uxtb16 r10, r10",            // (b0, b2)
    "    ldr lr, [r1], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r4, r12, r8, r4",
    "    smlad r4, lr, r9, r4",
    "    smlad r6, r12, r10, r6",
    "    smlad r6, lr, r11, r6",
    "    ldr lr, [r2], #4",
    "    sxtb16 r12, lr",
    "    sxtb16 lr, lr, ror #8",
    "    smlad r5, r12, r8, r5",
    "    smlad r5, lr, r9, r5",
    "    smlad r7, r12, r10, r7",
    "    smlad r7, lr, r11, r7",
    "    cmp r1, r3",
    "    bne 1b",
    "    ldr r12, [sp, #36]",
    "    stm r12, {{r4-r7}}",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_dot2x2_u8, . - muir_dsp_dot2x2_u8",
    "",
    // The i16 loop against weights widened beforehand (`dot2x2_w16`), unrolled: per group one
    // LDM of the pair's four activation words (a's two, then b's), one LDM of the channel pair's
    // four widened weight words (w0's two, then w1's) and 8 SMLAD = 10 instructions per 16 MACs
    // (13 with LDRDs and the loop's CMP/BNE per two groups). The eight data registers, four
    // accumulators and two pointers take all fourteen, so there is no loop: the body is written
    // `chunk` times (40 bytes each, every instruction 32-bit) and a chunk of `n` groups enters it
    // `n` copies before its end (a computed branch). r0 = x (pair layout, word-aligned), r1 = the
    // channel pair's widened weights (per group w0's two words, then w1's; word-aligned), r2 =
    // groups (>= 1), r3 = out (four i64, added to). Chunks of `chunk` groups in i32 as in the
    // i16 loop; [sp] the groups still to do, [sp, #4] out.
    ".section .text.muir_dsp_dot2x2_w16,\"ax\",%progbits",
    ".global muir_dsp_dot2x2_w16",
    ".type muir_dsp_dot2x2_w16,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_dot2x2_w16:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #8",
    "    strd r2, r3, [sp]",
    "    b.w 8f",
    // `dot2x2_w16_i32`: one chunk (1 to `chunk` groups), its four i32 sums stored as they are
    // (no i64 sums to add to); [sp] = -1 tells the end of the body so.
    ".global muir_dsp_dot2x2_w16_i32",
    ".type muir_dsp_dot2x2_w16_i32,%function",
    ".thumb_func",
    "muir_dsp_dot2x2_w16_i32:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #8",
    "    mov r12, #-1",
    "    strd r12, r3, [sp]",
    "    mov r12, r2",
    "    movs r2, #0",
    "    movs r3, #0",
    "    movs r4, #0",
    "    movs r5, #0",
    "    b.w 7f",
    ".p2align 2",
    ".rept {chunk}",
    "    w16_group",
    ".endr",
    "9:",
    "    ldr r12, [sp]",
    "    adds r12, r12, #1",
    "    beq 5f",
    // out's four i64 (word-aligned) by two LDM/STM pairs of two sums each: r0/r1 are the
    // pointers of the next chunk, so only r6-r11 and lr are free here.
    "    ldr r12, [sp, #4]",
    "    ldm r12, {{r6-r9}}",
    "    adds r6, r6, r2",
    "    adc r7, r7, r2, asr #31",
    "    adds r8, r8, r3",
    "    adc r9, r9, r3, asr #31",
    "    stm r12!, {{r6-r9}}",
    "    ldm r12, {{r6-r9}}",
    "    adds r6, r6, r4",
    "    adc r7, r7, r4, asr #31",
    "    adds r8, r8, r5",
    "    adc r9, r9, r5, asr #31",
    "    stm r12, {{r6-r9}}",
    "8:",
    "    ldr lr, [sp]",
    "    cmp lr, #0",
    "    beq 6f",
    "    mov r12, lr",
    "    cmp r12, #{chunk}",
    "    it hi",
    "    movhi r12, #{chunk}",
    "    sub lr, lr, r12",
    "    str lr, [sp]",
    "    movs r2, #0",
    "    movs r3, #0",
    "    movs r4, #0",
    "    movs r5, #0",
    "7:",
    "    adr lr, 9b + 1",
    "    add r12, r12, r12, lsl #2",   // 40 bytes a group: the entry is 9b - 8 * (5 n)
    "    sub lr, lr, r12, lsl #3",
    "    bx lr",
    "5:",
    "    ldr r12, [sp, #4]",
    "    stm r12, {{r2-r5}}",
    "6:",
    "    add sp, #8",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_dot2x2_w16, . - muir_dsp_dot2x2_w16",
    "",
    // `dot2x2_w16_i32_n`: `dot2x2_w16_i32` for several pairs of patches one after another (the
    // gathered pairs of a one-part layer): r0 = x (the first pair; each pair is `8 groups`
    // values, so the body leaves r0 at the next one), r1 = the widened weights, r2 = groups (1
    // to `chunk`), r3 = pairs (>= 1), [sp] = out (four i32 per pair). The body is written here
    // again (its end must lie within `ADR`'s reach of the entry's computation, which follows it):
    // per pair the four zero words by one LDM, the weights and the body's entry by one LDRD,
    // the four sums by one STM (8 instructions a pair, against some 30 for a call of
    // `dot2x2_w16_i32` and its Rust set-up). Stack: [sp] four zero words, [sp, #16] ww,
    // [sp, #20] the body's entry, [sp, #24] pairs left, [sp, #28] out.
    ".section .text.muir_dsp_dot2x2_w16_n,\"ax\",%progbits",
    ".type muir_dsp_dot2x2_w16_n_body,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_dot2x2_w16_n_body:",
    ".rept {chunk}",
    "    w16_group",
    ".endr",
    "9:",
    "    ldrd r12, lr, [sp, #24]",
    "    stm lr!, {{r2-r5}}",
    "    subs r12, #1",
    "    strd r12, lr, [sp, #24]",
    "    bne 1f",
    "    add sp, #32",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_dot2x2_w16_n_body, . - muir_dsp_dot2x2_w16_n_body",
    ".global muir_dsp_dot2x2_w16_n",
    ".type muir_dsp_dot2x2_w16_n,%function",
    ".thumb_func",
    "muir_dsp_dot2x2_w16_n:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #32",
    "    ldr r12, [sp, #68]",          // out
    "    adr lr, 9b + 1",
    "    add r2, r2, r2, lsl #2",      // 40 bytes a group: the entry is 9b - 8 * (5 groups)
    "    sub lr, lr, r2, lsl #3",
    "    strd r1, lr, [sp, #16]",
    "    strd r3, r12, [sp, #24]",
    "    movs r4, #0",
    "    movs r5, #0",
    "    strd r4, r5, [sp]",
    "    strd r4, r5, [sp, #8]",
    "1:",
    "    ldm sp, {{r2-r5}}",
    "    ldrd r1, lr, [sp, #16]",
    "    bx lr",
    ".size muir_dsp_dot2x2_w16_n, . - muir_dsp_dot2x2_w16_n",
    "",
    // `dot2x2_w16_i32_ns`: `muir_dsp_dot2x2_w16_n` with the pairs `gap` bytes apart beyond
    // their `16 groups` (one part of several-part patches: the part's block at the same offset
    // of every pair's slot): r0 = x, r1 = ww, r2 = groups (1 to `chunk`), r3 = pairs (>= 1),
    // [sp] = out (four i32 per pair), [sp, #4] = gap; stack as there, [sp, #32] the gap.
    ".section .text.muir_dsp_dot2x2_w16_ns,\"ax\",%progbits",
    ".type muir_dsp_dot2x2_w16_ns_body,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_dot2x2_w16_ns_body:",
    ".rept {chunk}",
    "    w16_group",
    ".endr",
    "9:",
    "    ldrd r12, lr, [sp, #24]",
    "    stm lr!, {{r2-r5}}",
    "    ldr r6, [sp, #32]",
    "    add r0, r0, r6",
    "    subs r12, #1",
    "    strd r12, lr, [sp, #24]",
    "    bne 1f",
    "    add sp, #40",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_dot2x2_w16_ns_body, . - muir_dsp_dot2x2_w16_ns_body",
    ".global muir_dsp_dot2x2_w16_ns",
    ".type muir_dsp_dot2x2_w16_ns,%function",
    ".thumb_func",
    "muir_dsp_dot2x2_w16_ns:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #40",
    "    ldrd r12, r4, [sp, #76]",    // out, gap
    "    str r4, [sp, #32]",
    "    adr lr, 9b + 1",
    "    add r2, r2, r2, lsl #2",
    "    sub lr, lr, r2, lsl #3",
    "    strd r1, lr, [sp, #16]",
    "    strd r3, r12, [sp, #24]",
    "    movs r4, #0",
    "    movs r5, #0",
    "    strd r4, r5, [sp]",
    "    strd r4, r5, [sp, #8]",
    "1:",
    "    ldm sp, {{r2-r5}}",
    "    ldrd r1, lr, [sp, #16]",
    "    bx lr",
    ".size muir_dsp_dot2x2_w16_ns, . - muir_dsp_dot2x2_w16_ns",
    "",
    // `widen_u8_groups` on word-aligned buffers: r0 = d (i16), r1 = s (u8), r2 = groups (>= 1):
    // per two groups one LDRD, four UXTB16 and one STM (3 instructions a group, the loop's
    // SUBS/BNE once per four groups) against 7 for the compiled loop.
    ".section .text.muir_dsp_widen_u8,\"ax\",%progbits",
    ".global muir_dsp_widen_u8",
    ".type muir_dsp_widen_u8,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_widen_u8:",
    "    push {{r4-r9}}",
    "    lsrs r3, r2, #2",
    "    beq 2f",
    "1:",
    "    ldrd r4, r5, [r1], #8",
    "    uxtb16 r6, r4",
    "    uxtb16 r7, r4, ror #8",
    "    uxtb16 r8, r5",
    "    uxtb16 r9, r5, ror #8",
    "    stm r0!, {{r6-r9}}",
    "    ldrd r4, r5, [r1], #8",
    "    uxtb16 r6, r4",
    "    uxtb16 r7, r4, ror #8",
    "    uxtb16 r8, r5",
    "    uxtb16 r9, r5, ror #8",
    "    stm r0!, {{r6-r9}}",
    "    subs r3, #1",
    "    bne 1b",
    "2:",
    "    ands r2, r2, #3",
    "    beq 4f",
    "3:",
    "    ldr r4, [r1], #4",
    "    uxtb16 r6, r4",
    "    uxtb16 r7, r4, ror #8",
    "    stm r0!, {{r6-r7}}",
    "    subs r2, #1",
    "    bne 3b",
    "4:",
    "    pop {{r4-r9}}",
    "    bx lr",
    ".size muir_dsp_widen_u8, . - muir_dsp_widen_u8",
    "",
    // `put_groups_i16` on word-aligned buffers: r0 = d (the first group's four values of this
    // patch; groups 16 bytes apart), r1 = s (i16 values), r2 = groups (>= 1): per group one LDRD,
    // PKHBT, PKHTB and one STRD (4 instructions a group, the loop's SUBS/BNE once per two
    // groups) against 8 for the compiled loop.
    ".section .text.muir_dsp_put_groups_i16,\"ax\",%progbits",
    ".global muir_dsp_put_groups_i16",
    ".type muir_dsp_put_groups_i16,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_put_groups_i16:",
    "    push {{r4-r7}}",
    "    lsrs r3, r2, #1",
    "    beq 2f",
    "1:",
    "    ldrd r4, r5, [r1], #8",      // (x0, x1), (x2, x3)
    "    pkhbt r6, r4, r5, lsl #16",  // (x0, x2)
    "    pkhtb r7, r5, r4, asr #16",  // (x1, x3)
    "    strd r6, r7, [r0], #16",
    "    ldrd r4, r5, [r1], #8",
    "    pkhbt r6, r4, r5, lsl #16",
    "    pkhtb r7, r5, r4, asr #16",
    "    strd r6, r7, [r0], #16",
    "    subs r3, #1",
    "    bne 1b",
    "2:",
    "    tst r2, #1",
    "    beq 3f",
    "    ldrd r4, r5, [r1]",
    "    pkhbt r6, r4, r5, lsl #16",
    "    pkhtb r7, r5, r4, asr #16",
    "    strd r6, r7, [r0]",
    "3:",
    "    pop {{r4-r7}}",
    "    bx lr",
    ".size muir_dsp_put_groups_i16, . - muir_dsp_put_groups_i16",
    "",
    // `widen_weights`' loop: r0 = w0, r1 = w1 (int8 rows, any alignment), r2 = groups (>= 1),
    // r3 = out (word-aligned): per group LDR, LDR, 4 SXTB16, one STM. The body is written 8
    // times (28 bytes each) and entered `-groups mod 8` copies after its start (Duff's device):
    // the loop's SUBS/BNE once per 8 groups, 7 instructions a group instead of 9.
    ".section .text.muir_dsp_widen_w16,\"ax\",%progbits",
    ".global muir_dsp_widen_w16",
    ".type muir_dsp_widen_w16,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_widen_w16:",
    "    push {{r4-r7}}",
    "    rsb r12, r2, #0",
    "    and r12, r12, #7",           // copies skipped in the first pass
    "    add r2, r2, #7",
    "    lsr r2, r2, #3",             // passes
    "    rsb r12, r12, r12, lsl #3",
    "    adr r4, 4f + 1",
    "    add r4, r4, r12, lsl #2",
    "    bx r4",
    ".p2align 2",
    "4:",
    ".rept 8",
    "    ldr.w r4, [r0], #4",
    "    ldr.w r6, [r1], #4",
    "    sxtb16 r5, r4, ror #8",
    "    sxtb16 r4, r4",
    "    sxtb16 r7, r6, ror #8",
    "    sxtb16 r6, r6",
    "    stm.w r3!, {{r4-r7}}",
    ".endr",
    "    subs r2, #1",
    "    bne 4b",
    "    pop {{r4-r7}}",
    "    bx lr",
    ".size muir_dsp_widen_w16, . - muir_dsp_widen_w16",
    "",
    // `nat_block`: one block of two pixels over every kernel row of every part, from a table
    // of entries (row, w, step, groups, bstep, sums, skip: `NatEntry`), the activations read in place
    // from the input rows in natural order (so the weights are widened in natural order too,
    // `widen_weights_nat`). r0 = table, r1 = entries (>= 1), r2 = col, r3 = the parts' four i64
    // sums each (added to); [sp, #76] kl, [sp, #80] w0, [sp, #84] ww after the pushes. Per
    // entry: pixel a at row + col step, pixel b bstep bytes later, `groups` (1 to
    // `I16_ASM_GROUPS`: one i32 chunk) groups against the widened weights at ww + w, its four
    // i32 sums added into the part's i64 sums. The loops are unrolled as `dot2x2_w16`'s: each
    // body written `chunk` times, entered `groups` copies before its end by a computed branch
    // (no end pointer, no loop test): per group one LDM of the channel pair's four widened
    // weight words, then pixel a's two words, four SMLAD, pixel b's, four SMLAD: 11
    // instructions per 16 MACs where both pixels are word-aligned (LDRD), 13 otherwise (LDR
    // pairs); one pixel (bstep 0): 6 (7). Per entry around the loop: 35 instructions on the
    // aligned path (the table's cursor in r12 from one entry to the next and its end on the
    // stack, the entry's sums pointer in r3, free during the bodies, the aligned body's entry
    // from the table's `skip`, the zero words at [sp] for one LDM).
    // Stack: [sp] four zero words, [sp, #16] table cursor, [sp, #20] table end, [sp, #24] col,
    // [sp, #28] the sums.
    ".section .text.muir_dsp_nat_block,\"ax\",%progbits",
    ".global muir_dsp_nat_block",
    ".type muir_dsp_nat_block,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_nat_block:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #40",
    "    rsb r1, r1, r1, lsl #3",     // 28 bytes an entry: the table's end
    "    add r1, r0, r1, lsl #2",
    "    strd r0, r1, [sp, #16]",
    "    strd r2, r3, [sp, #24]",
    "    movs r4, #0",                // four zero words at [sp]: an entry's sums start
    "    movs r5, #0",                // from them (one LDM instead of four MOVS)
    "    strd r4, r5, [sp]",
    "    strd r4, r5, [sp, #8]",
    "    mov r12, r0",
    "5:",
    "    ldm r12!, {{r0-r5, lr}}",    // row, ww, step, groups, bstep, sums, skip
    "    str r12, [sp, #16]",
    "    ldr r12, [sp, #24]",
    "    mla r0, r12, r2, r0",        // pixel a: row + col step
    "    add r2, r0, r4",             // pixel b: bstep later
    "    ldr r12, [sp, #28]",
    "    add r5, r5, r12",            // the part's sums (to r3 once `groups` is used)
    "    cmp r3, #0",                 // a plain entry (bit 31 set): 50
    "    blt.w 50f",
    "    ldr r12, [sp, #84]",         // the widened weights: r1 is the run's byte offset
    "    add r1, r1, r12",
    "    cmp r4, #0",                 // one pixel (a block of one pixel taken twice): 40
    "    beq.w 40f",
    "    tst r0, #3",
    "    bne.w 20f",
    "    tst r2, #3",
    "    bne.w 24f",
    // Both pixels word-aligned: enter the body `groups` copies (44 bytes each) before its end,
    // `skip` bytes after its start.
    "    adr r12, 11f + 1",
    "    add r12, r12, lr",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "11:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldrd r12, lr, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    "    ldrd r12, lr, [r2], #8",
    "    smlad r6, r8, r12, r6",
    "    smlad r6, r9, lr, r6",
    "    smlad r7, r10, r12, r7",
    "    smlad r7, r11, lr, r7",
    ".endr",
    "30:",
    // the part's four i64 sums (word-aligned, at r3) by one LDM and one STM: the pointers
    // r0-r2 are reloaded by the next entry, r8-r11 held this entry's weights.
    "    ldm r3, {{r0-r2, r8-r12}}",
    "    adds r0, r0, r4",
    "    adc r1, r1, r4, asr #31",
    "    adds r2, r2, r5",
    "    adc r8, r8, r5, asr #31",
    "    adds r9, r9, r6",
    "    adc r10, r10, r6, asr #31",
    "    adds r11, r11, r7",
    "    adc r12, r12, r7, asr #31",
    "    stm r3, {{r0-r2, r8-r12}}",
    "    ldrd r12, lr, [sp, #16]",    // the cursor, the table's end
    "    cmp r12, lr",
    "    bne.w 5b",
    "    add sp, #40",
    "    pop {{r4-r11, pc}}",
    // A pixel not word-aligned (the 63-channel motion part's odd pixels): LDR pairs, 52 bytes
    // a copy.
    // Pixel a word-aligned, pixel b not (the 63-channel motion part: its pixels alternate):
    // LDRD for a, an LDR pair for b, 48 bytes a copy; then the other way round.
    "24:",
    "    adr r12, 25f + 1",
    "    rsb r8, r3, #{chunk}",
    "    lsl r9, r8, #3",
    "    add r9, r9, r8, lsl #2",
    "    add r12, r12, r9, lsl #2",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "25:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldrd r12, lr, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    "    ldr.w lr, [r2, #4]",
    "    ldr.w r12, [r2], #8",
    "    smlad r6, r8, r12, r6",
    "    smlad r6, r9, lr, r6",
    "    smlad r7, r10, r12, r7",
    "    smlad r7, r11, lr, r7",
    ".endr",
    "    b.w 30b",
    "26:",
    "    adr r12, 27f + 1",
    "    rsb r8, r3, #{chunk}",
    "    lsl r9, r8, #3",
    "    add r9, r9, r8, lsl #2",
    "    add r12, r12, r9, lsl #2",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "27:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldr.w lr, [r0, #4]",
    "    ldr.w r12, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    "    ldrd r12, lr, [r2], #8",
    "    smlad r6, r8, r12, r6",
    "    smlad r6, r9, lr, r6",
    "    smlad r7, r10, r12, r7",
    "    smlad r7, r11, lr, r7",
    ".endr",
    "    b.w 30b",
    "20:",
    "    tst r2, #3",
    "    beq.w 26b",
    "    adr r12, 21f + 1",
    "    rsb r8, r3, #{chunk}",
    "    add r9, r8, r8, lsl #2",
    "    add r9, r9, r8, lsl #3",
    "    add r12, r12, r9, lsl #2",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "21:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldr.w lr, [r0, #4]",
    "    ldr.w r12, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    "    ldr.w lr, [r2, #4]",
    "    ldr.w r12, [r2], #8",
    "    smlad r6, r8, r12, r6",
    "    smlad r6, r9, lr, r6",
    "    smlad r7, r10, r12, r7",
    "    smlad r7, r11, lr, r7",
    ".endr",
    "    b.w 30b",
    // One pixel: its two sums (24 bytes a copy, 28 unaligned), copied to pixel b's.
    "40:",
    "    tst r0, #3",
    "    bne.w 45f",
    "    adr r12, 41f + 1",
    "    rsb r8, r3, #{chunk}",
    "    add r9, r8, r8, lsl #1",
    "    add r12, r12, r9, lsl #3",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "41:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldrd r12, lr, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    ".endr",
    "48:",
    "    mov r6, r4",
    "    mov r7, r5",
    "    b.w 30b",
    "45:",
    "    adr r12, 46f + 1",
    "    rsb r8, r3, #{chunk}",
    "    rsb r9, r8, r8, lsl #3",
    "    add r12, r12, r9, lsl #2",
    "    mov r3, r5",
    "    ldm sp, {{r4-r7}}",
    "    bx r12",
    ".p2align 2",
    "46:",
    ".rept {chunk}",
    "    ldm.w r1!, {{r8-r11}}",
    "    ldr.w lr, [r0, #4]",
    "    ldr.w r12, [r0], #8",
    "    smlad r4, r8, r12, r4",
    "    smlad r4, r9, lr, r4",
    "    smlad r5, r10, r12, r5",
    "    smlad r5, r11, lr, r5",
    ".endr",
    "    b.w 48b",
    // A plain entry: `groups & !(1 << 31)` values (1 to 7) by LDRSH / LDRSB and MLA, the
    // int8 weights of w0 at w0 ([sp, #80], the sixth argument) plus r1, of w1 `kl` bytes later
    // ([sp, #76], the fifth argument).
    "50:",
    "    bic lr, r3, #0x80000000",
    "    mov r3, r5",
    "    ldr r12, [sp, #80]",         // w0's int8 weights: r1 is the byte offset
    "    add r1, r1, r12",
    "    ldm sp, {{r4-r7}}",
    "    ldr r12, [sp, #76]",
    "51:",
    "    ldrsh r8, [r0], #2",
    "    ldrsh r9, [r2], #2",
    "    ldrsb r10, [r1, r12]",
    "    ldrsb r11, [r1], #1",
    "    mla r4, r11, r8, r4",
    "    mla r5, r10, r8, r5",
    "    mla r6, r11, r9, r6",
    "    mla r7, r10, r9, r7",
    "    subs lr, #1",
    "    bne 51b",
    "    b.w 30b",
    ".size muir_dsp_nat_block, . - muir_dsp_nat_block",
    "",
    // `requant_parts`: r0 = the parts' four i64 sums each (`[i64; 4]`, 32 bytes a part), r1 =
    // their multipliers decoded (`NatReq`, two a part: channel 0 then 1, 32 bytes a part), r2 =
    // parts (>= 1), r3 = out (four i64). Per output value c (0..3: channel c & 1), over the
    // parts: the sum tested to be an i32 (else 0 is returned, nothing more written), `SMLAL`
    // onto the rounding half, the 64-bit arithmetic shift by s (t = s - 32 >= 0: the high word
    // shifted by t; else both words), added to r5:r6. 14 instructions a part and value for s >=
    // 32, 19 below (the compiled loop took about 27 with its spills).
    ".section .text.muir_dsp_requant_parts,\"ax\",%progbits",
    ".global muir_dsp_requant_parts",
    ".type muir_dsp_requant_parts,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_requant_parts:",
    "    push {{r4-r11, lr}}",
    "    movs r4, #0",                 // c
    "1:",
    "    add.w r8, r0, r4, lsl #3",    // the sums of value c
    "    and r9, r4, #1",
    "    add.w r9, r1, r9, lsl #4",    // channel c & 1's multipliers
    "    mov r10, r2",
    "    movs r5, #0",
    "    movs r6, #0",
    "2:",
    "    ldrd r11, r12, [r8], #32",    // the part's sum
    "    cmp.w r12, r11, asr #31",
    "    bne 9f",                      // not an i32
    "    ldrd lr, r7, [r9, #8]",       // the rounding half (lo, hi)
    "    ldr.w r12, [r9, #4]",         // m
    "    smlal lr, r7, r11, r12",
    "    ldr.w r12, [r9], #32",        // t = s - 32
    "    cmp.w r12, #0",
    "    blt 3f",
    "    asr.w lr, r7, r12",           // s >= 32: the high word shifted, an i32
    "    adds r5, r5, lr",
    "    adc.w r6, r6, lr, asr #31",
    "    subs r10, #1",
    "    bne 2b",
    "    b 4f",
    "3:",
    "    add.w r11, r12, #32",         // s (8 to 31)
    "    lsr.w lr, lr, r11",
    "    rsb.w r12, r12, #0",          // 32 - s
    "    lsl.w r12, r7, r12",
    "    orr.w lr, lr, r12",
    "    asr.w r7, r7, r11",
    "    adds r5, r5, lr",
    "    adc.w r6, r6, r7",
    "    subs r10, #1",
    "    bne 2b",
    "4:",
    "    add.w r11, r3, r4, lsl #3",
    "    strd r5, r6, [r11]",
    "    adds r4, #1",
    "    cmp r4, #4",
    "    bne 1b",
    "    movs r0, #1",
    "    pop {{r4-r11, pc}}",
    "9:",
    "    movs r0, #0",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_requant_parts, . - muir_dsp_requant_parts",
    "",
    // `requant_add`: r0 = the pairs' four i32 sums each (16 bytes a pair), r1 = pairs (>= 1),
    // r2 = the part's two multipliers decoded (`NatReq`, channel 0 then 1), r3 = the pairs'
    // four i64 sums (32 bytes a pair, added to). Value by value (c = 0..3, channel c & 1, its
    // multiplier in r4-r7 for all the pairs, the loop chosen by its shift): `SMLAL` onto the
    // rounding half, the 64-bit shift by s, added: 11 instructions a value for s >= 32, 14
    // below. r0 and r3 walk the pairs and are wound back to the next value.
    ".macro rq_col off",
    "    ldrd r7, r4, [r2, #\\off]",    // t = s - 32, m
    "    ldrd r5, r6, [r2, #\\off + 8]", // the rounding half (lo, hi)
    "    mov r12, r1",
    "    cmp.w r7, #0",
    "    blt 2f",
    "1:",
    "    ldr.w r8, [r0], #16",
    "    mov r10, r5",
    "    mov r11, r6",
    "    smlal r10, r11, r8, r4",
    "    asr.w r10, r11, r7",          // s >= 32: the high word shifted, an i32
    "    ldrd r8, r9, [r3]",
    "    adds r8, r8, r10",
    "    adc.w r9, r9, r10, asr #31",
    "    strd r8, r9, [r3], #32",
    "    subs r12, #1",
    "    bne 1b",
    "    b 3f",
    "2:",
    "    add.w r7, r7, #32",           // s (8 to 31)
    "    rsb.w lr, r7, #32",           // 32 - s
    "4:",
    "    ldr.w r8, [r0], #16",
    "    mov r10, r5",
    "    mov r11, r6",
    "    smlal r10, r11, r8, r4",
    "    lsr.w r10, r10, r7",
    "    lsl.w r8, r11, lr",
    "    orr.w r10, r10, r8",
    "    asr.w r11, r11, r7",
    "    ldrd r8, r9, [r3]",
    "    adds r8, r8, r10",
    "    adc.w r9, r9, r11",
    "    strd r8, r9, [r3], #32",
    "    subs r12, #1",
    "    bne 4b",
    "3:",
    "    sub.w r0, r0, r1, lsl #4",
    "    add.w r0, r0, #4",
    "    sub.w r3, r3, r1, lsl #5",
    "    add.w r3, r3, #8",
    ".endm",
    ".section .text.muir_dsp_requant_add,\"ax\",%progbits",
    ".global muir_dsp_requant_add",
    ".type muir_dsp_requant_add,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_requant_add:",
    "    push {{r4-r11, lr}}",
    "    rq_col 0",
    "    rq_col 16",
    "    rq_col 0",
    "    rq_col 16",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_requant_add, . - muir_dsp_requant_add",
    "",
    // `widen_weights_nat`'s loop: r0 = w0, r1 = w1 (int8 rows, any alignment), r2 = groups (>= 1),
    // r3 = out (word-aligned): per group LDR, LDR, 4 SXTB16 and 4 PKHBT/PKHTB into natural order
    // ((w0, w1), (w2, w3) per channel), one STM; written 8 times (44 bytes each) and entered as
    // `widen_w16`'s: 11 instructions a group instead of 13.
    ".section .text.muir_dsp_widen_nat,\"ax\",%progbits",
    ".global muir_dsp_widen_nat",
    ".type muir_dsp_widen_nat,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_widen_nat:",
    "    push {{r4-r11}}",
    "    rsb r12, r2, #0",
    "    and r12, r12, #7",           // copies skipped in the first pass
    "    add r2, r2, #7",
    "    lsr r2, r2, #3",             // passes
    "    add r5, r12, r12, lsl #1",
    "    add r5, r5, r12, lsl #3",    // 11 words a copy
    "    adr r4, 4f + 1",
    "    add r4, r4, r5, lsl #2",
    "    bx r4",
    ".p2align 2",
    "4:",
    ".rept 8",
    "    ldr.w r8, [r0], #4",
    "    ldr.w r9, [r1], #4",
    "    sxtb16 r10, r8, ror #8",     // w0: (w1, w3)
    "    sxtb16 r8, r8",              //     (w0, w2)
    "    sxtb16 r11, r9, ror #8",
    "    sxtb16 r9, r9",
    "    pkhbt r4, r8, r10, lsl #16", //     (w0, w1)
    "    pkhtb r5, r10, r8, asr #16", //     (w2, w3)
    "    pkhbt r6, r9, r11, lsl #16",
    "    pkhtb r7, r11, r9, asr #16",
    "    stm.w r3!, {{r4-r7}}",
    ".endr",
    "    subs r2, #1",
    "    bne 4b",
    "    pop {{r4-r11}}",
    "    bx lr",
    ".size muir_dsp_widen_nat, . - muir_dsp_widen_nat",
    "",
    // `paired_sums`: r0 = ep (the key pairs' packed weights), r1 = key pairs (1 to `keyp`),
    // r2 = v (keys' values, `cv` a key), r3 = cv; [sp] acc (i64 sums), [sp, #4] channel pairs
    // (>= 1). Per channel pair: its two i64 sums in r4:r5 and r6:r7, the body (one key pair: the
    // weight word, the two keys' words of the channel pair, PKHBT/PKHTB, two SMLALD; 32 bytes,
    // every instruction 32-bit) entered `pairs` copies before its end, the sums stored back.
    // r12 walks the channel pair's values a key pair (4 cv bytes, r3) at a time, lr = 2 cv bytes
    // (the second key). Stack: [sp] ep, [sp, #4] the body's entry, [sp, #8] the next channel
    // pair's values; acc at [sp, #52], channel pairs at [sp, #56] after the pushes.
    ".section .text.muir_dsp_paired_sums,\"ax\",%progbits",
    ".global muir_dsp_paired_sums",
    ".type muir_dsp_paired_sums,%function",
    ".p2align 2",
    ".thumb_func",
    "muir_dsp_paired_sums:",
    "    push {{r4-r11, lr}}",
    "    sub sp, #16",
    "    str r0, [sp]",
    "    adr r12, 1f + 1",
    "    rsb r1, r1, #{keyp}",
    "    add r12, r12, r1, lsl #5",
    "    str r12, [sp, #4]",
    "    lsl lr, r3, #1",
    "    lsl r3, r3, #2",
    "    str r2, [sp, #8]",
    "    ldr r1, [sp, #52]",
    "    ldr r2, [sp, #56]",
    "2:",
    "    ldrd r4, r5, [r1]",
    "    ldrd r6, r7, [r1, #8]",
    "    ldr r0, [sp]",
    "    ldr r12, [sp, #8]",
    "    add r9, r12, #4",
    "    str r9, [sp, #8]",
    "    ldr r9, [sp, #4]",
    "    bx r9",
    ".p2align 2",
    "1:",
    ".rept {keyp}",
    "    ldr.w r8, [r0], #4",         // (e[2t], e[2t+1])
    "    ldr.w r10, [r12, lr]",       // key 2t+1: (ch, ch+1)
    "    ldr.w r9, [r12]",            // key 2t: (ch, ch+1)
    "    add.w r12, r12, r3",
    "    pkhbt r11, r9, r10, lsl #16", // ch: (key 2t, key 2t+1)
    "    pkhtb r10, r10, r9, asr #16", // ch+1
    "    smlald r4, r5, r8, r11",
    "    smlald r6, r7, r8, r10",
    ".endr",
    "    strd r4, r5, [r1], #8",
    "    strd r6, r7, [r1], #8",
    "    subs r2, #1",
    "    bne 2b",
    "    add sp, #16",
    "    pop {{r4-r11, pc}}",
    ".size muir_dsp_paired_sums, . - muir_dsp_paired_sums",
    chunk = const I16_ASM_GROUPS,
    keyp = const AGG_KEYS / 2,
);

/// Groups of four per i32 chunk of the i16 assembly loop: `4 * 127 = 508` terms of `|w x| <=
/// 2^22` sum below `2^31` at every step (the Helium loops' `kernels::I16_CHUNK`), so each
/// chunk's sum is exact. Twice the portable chunk: half the chunk set-ups and 64-bit adds. The
/// chunking does not change the integers (the chunk sums add exactly in i64).
pub(crate) const I16_ASM_GROUPS: usize = 127;
const _: () = assert!(4 * (I16_ASM_GROUPS as u64) * (1 << 22) < (1u64 << 31));

unsafe extern "C" {
    fn muir_dsp_dot2x2_i16(x: *const i16, w0: *const u8, w1: *const u8, groups: usize, out: *mut [i64; 4]);
    fn muir_dsp_dot2x2_u8(x: *const u8, w0: *const u8, w1: *const u8, groups: usize, out: *mut [i32; 4]);
    fn muir_dsp_dot2x2_w16(x: *const i16, w: *const u32, groups: usize, out: *mut [i64; 4]);
    fn muir_dsp_dot2x2_w16_i32(x: *const i16, w: *const u32, groups: usize, out: *mut [i32; 4]);
    fn muir_dsp_dot2x2_w16_n(x: *const i16, w: *const u32, groups: usize, pairs: usize, out: *mut [i32; 4]);
    fn muir_dsp_dot2x2_w16_ns(x: *const i16, w: *const u32, groups: usize, pairs: usize, out: *mut [i32; 4], gap: usize);
    fn muir_dsp_widen_w16(w0: *const i8, w1: *const i8, groups: usize, out: *mut u32);
    fn muir_dsp_widen_u8(d: *mut i16, s: *const u8, groups: usize);
    fn muir_dsp_put_groups_i16(d: *mut i16, s: *const i16, groups: usize);
    fn muir_dsp_widen_nat(w0: *const i8, w1: *const i8, groups: usize, out: *mut u32);
    fn muir_dsp_paired_sums(ep: *const u32, pairs: usize, v: *const i16, cv: usize, acc: *mut i64, chpairs: usize);
    fn muir_dsp_nat_block(table: *const NatEntry, n: usize, col: usize, sums: *mut [i64; 4], kl: usize, w0: *const i8, ww: *const u32);
    fn muir_dsp_requant_parts(sums: *const [i64; 4], reqs: *const [NatReq; 2], parts: usize, out: *mut [i64; 4]) -> u32;
    fn muir_dsp_requant_add(sums: *const [i32; 4], pairs: usize, req: *const [NatReq; 2], acc: *mut [i64; 4]);
}

/// One (channel, part) multiplier decoded for [`requant_parts`]: `t = s - 32`, `m`, the
/// rounding half's (low, high) words as [`Requant`]'s.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct NatReq {
    t: i32,
    m: i32,
    lo: u32,
    hi: u32,
}

impl NatReq {
    /// A multiplier of 0 (as [`Requant::ZERO`]).
    pub const ZERO: NatReq = NatReq { t: 8 - 32, m: 0, lo: 1 << 7, hi: 0 };

    /// `m` decoded (meaningful for `8 <= m.shift <= 62`, as [`requantize_i32`]).
    #[inline(always)]
    pub fn new(m: crate::arith::Multiplier) -> Self {
        let r = Requant::new(m);
        NatReq { t: r.s as i32 - 32, m: r.m, lo: r.lo, hi: r.hi }
    }
}

/// The short epilogue's sum over the parts of a block of two pixels: `out[c] = sum over parts
/// p of requantize_i32(sums[p][c], reqs[p][c & 1])` ([`requantize_i32`]: `floor((acc m +
/// 2^(s-1)) / 2^s)`), true; false where a part's sum is not an i32 (`out` then unspecified).
/// Multipliers with shifts `8..=62` (the short path's); the parts are the shorter of `sums`
/// and `reqs`. By `muir_dsp_requant_parts` (14 to 19 instructions a part and value).
#[inline(always)]
pub fn requant_parts(sums: &[[i64; 4]], reqs: &[[NatReq; 2]], out: &mut [i64; 4]) -> bool {
    let n = sums.len().min(reqs.len());
    *out = [0; 4];
    if n == 0 {
        return true;
    }
    // SAFETY: `n` parts of both arrays are read, `out`'s four values written.
    unsafe { muir_dsp_requant_parts(sums.as_ptr(), reqs.as_ptr(), n, out) != 0 }
}

/// One part's short contributions added for several pairs of pixels: `acc[i][c] +=
/// requantize_i32(sums[i][c], req[c & 1])` for the shorter of `sums` and `acc` (shifts
/// `8..=62`, as [`requant_parts`]). By `muir_dsp_requant_add` (11 to 14 instructions a value).
#[inline(always)]
pub fn requant_add(sums: &[[i32; 4]], req: &[NatReq; 2], acc: &mut [[i64; 4]]) {
    let n = sums.len().min(acc.len());
    if n > 0 {
        // SAFETY: `n` pairs of `sums` read, of `acc` read and written; `req`'s two entries read.
        unsafe { muir_dsp_requant_add(sums.as_ptr(), n, req, acc.as_mut_ptr()) };
    }
}

impl Quad for u8 {
    #[inline(always)]
    fn quad(x: &[u8], i: usize) -> (u32, u32) {
        let v = word(x, i);
        (uxtb16(v), uxtb16_ror8(v))
    }
    #[inline(always)]
    fn groups_asm(w0: &[u8], w1: &[u8], x: &[u8], q: usize) -> Option<[i32; 4]> {
        if q == 0 || w0.len() < 4 * q || w1.len() < 4 * q || x.len() < 8 * q {
            return None;
        }
        let mut out = [0i32; 4];
        // SAFETY: the loop reads `4 q` bytes from each weight pointer and `8 q` from `x` (checked
        // above), with unaligned word loads only (Cortex-M4/M7 allow them), and writes `out`.
        unsafe { muir_dsp_dot2x2_u8(x.as_ptr(), w0.as_ptr(), w1.as_ptr(), q, &mut out) };
        Some(out)
    }
}

impl Quad for i8 {
    #[inline(always)]
    fn quad(x: &[i8], i: usize) -> (u32, u32) {
        let v = word(bytes_of_i8(x), i);
        (sxtb16(v), sxtb16_ror8(v))
    }
}

impl Quad for i16 {
    #[inline(always)]
    fn quad(x: &[i16], i: usize) -> (u32, u32) {
        let (x01, x23) = (pair(x, i), pair(x, i + 2));
        (pkhbt(x01, x23), pkhtb(x01, x23))
    }
    #[inline(always)]
    fn quad_paired(x: &[i16], i: usize) -> (u32, u32) {
        (pair(x, i), pair(x, i + 2))
    }
}

/// `acc` plus the four products of the int8 weights in `w` with the widened activations `x`.
#[inline(always)]
fn mac4(w: u32, x: (u32, u32), acc: i32) -> i32 {
    smlad(sxtb16_ror8(w), x.1, smlad(sxtb16(w), x.0, acc))
}

/// `sum w[i] * x[i]` (int8 weights, or i8 features against i8 features). For i16 activations at
/// most `kernels::I16_CHUNK` terms (the caller chunks, see the module doc).
#[inline]
pub fn dot<T: Quad>(w: &[i8], x: &[T]) -> i32 {
    let n = w.len().min(x.len());
    let wb = bytes_of_i8(w);
    let mut acc = 0i32;
    let mut i = 0;
    // Two quads per iteration: fewer loop instructions per MAC.
    while i + 8 <= n {
        acc = mac4(word(wb, i), T::quad(x, i), acc);
        acc = mac4(word(wb, i + 4), T::quad(x, i + 4), acc);
        i += 8;
    }
    while i + 4 <= n {
        acc = mac4(word(wb, i), T::quad(x, i), acc);
        i += 4;
    }
    // The last `n % 4` terms.
    for (w, x) in w.iter().zip(x).take(n).skip(i) {
        acc += *w as i32 * (*x).into();
    }
    acc
}

/// Two dot products sharing the activations (two output channels): each activation quad is
/// loaded and widened once. Same chunking rule as [`dot`].
#[inline]
pub fn dot2<T: Quad>(w0: &[i8], w1: &[i8], x: &[T]) -> (i32, i32) {
    let n = w0.len().min(w1.len()).min(x.len());
    let (b0, b1) = (bytes_of_i8(w0), bytes_of_i8(w1));
    let (mut a0, mut a1) = (0i32, 0i32);
    let mut i = 0;
    while i + 4 <= n {
        let q = T::quad(x, i);
        a0 = mac4(word(b0, i), q, a0);
        a1 = mac4(word(b1, i), q, a1);
        i += 4;
    }
    for ((w0, w1), x) in w0.iter().zip(w1).zip(x).take(n).skip(i) {
        let x: i32 = (*x).into();
        a0 += *w0 as i32 * x;
        a1 += *w1 as i32 * x;
    }
    (a0, a1)
}

/// Four dot products, two output channels at two output pixels: `[w0 . a, w1 . a, w0 . b,
/// w1 . b]` with the two patches in `x` in the pair layout (`kernels::pair_index`). Each weight
/// quad and each activation quad is loaded and widened once for two products (2x2 register
/// blocking, as CMSIS-NN's matrix kernels), and one pointer reads both patches, so the four
/// accumulators, three pointers and the widened operands fit the registers. Same chunking rule
/// as [`dot`].
#[inline]
pub fn dot2x2<T: Quad>(w0: &[i8], w1: &[i8], x: &[T]) -> [i32; 4] {
    let n = w0.len().min(w1.len()).min(x.len() / 2);
    let q = n / 4;
    let (b0, b1) = (bytes_of_i8(w0), bytes_of_i8(w1));
    let (mut a0, mut a1, mut a2, mut a3) = (0i32, 0i32, 0i32, 0i32);
    if let Some([s0, s1, s2, s3]) = T::groups_asm(b0, b1, x, q) {
        (a0, a1, a2, a3) = (s0, s1, s2, s3);
    } else {
        for g in 0..q {
            let (qa, qb) = (T::quad_paired(x, 8 * g), T::quad_paired(x, 8 * g + 4));
            let v0 = word(b0, 4 * g);
            let (w0l, w0h) = (sxtb16(v0), sxtb16_ror8(v0));
            a0 = smlad(w0h, qa.1, smlad(w0l, qa.0, a0));
            a2 = smlad(w0h, qb.1, smlad(w0l, qb.0, a2));
            let v1 = word(b1, 4 * g);
            let (w1l, w1h) = (sxtb16(v1), sxtb16_ror8(v1));
            a1 = smlad(w1h, qa.1, smlad(w1l, qa.0, a1));
            a3 = smlad(w1h, qb.1, smlad(w1l, qb.0, a3));
        }
    }
    // The last `r = n % 4` values of each patch: `a`'s at `2 q4`, then `b`'s (pair layout).
    let (q4, r) = (4 * q, n - 4 * q);
    let (xa, xb) = x.get(2 * q4..).unwrap_or(&[]).split_at(r.min(x.len().saturating_sub(2 * q4)));
    let ws = w0.iter().zip(w1).skip(q4);
    for (((w0, w1), xa), xb) in ws.zip(xa).zip(xb) {
        let (u, v, xa, xb) = (*w0 as i32, *w1 as i32, (*xa).into(), (*xb).into());
        a0 += u * xa;
        a1 += v * xa;
        a2 += u * xb;
        a3 += v * xb;
    }
    [a0, a1, a2, a3]
}

/// [`dot2x2`] for i16 activations over a whole patch of any length: the assembly loop takes
/// every group of four, `4 I16_ASM_GROUPS` values at a time in i32 (so each chunk's sum is exact,
/// module doc), into i64 sums; the last `n % 4` values are added here. Same integers as four
/// `dot`s.
#[inline(always)]
pub fn dot2x2_i16(w0: &[i8], w1: &[i8], x: &[i16]) -> [i64; 4] {
    let n = w0.len().min(w1.len()).min(x.len() / 2);
    let q = n / 4;
    let (b0, b1) = (bytes_of_i8(w0), bytes_of_i8(w1));
    let mut acc = [0i64; 4];
    // LDRD needs a word-aligned address: the engine's patch buffers are; a slice at an odd
    // element offset takes the Rust loop, chunk by chunk.
    if q > 0 && (x.as_ptr() as usize).is_multiple_of(4) {
        // SAFETY: the loop reads `4 q <= n` bytes from each weight slice (unaligned word loads,
        // which Cortex-M4/M7 allow) and `8 q <= 2 n <= x.len()` values from the word-aligned
        // `x`, and adds into `acc`.
        unsafe { muir_dsp_dot2x2_i16(x.as_ptr(), b0.as_ptr(), b1.as_ptr(), q, &mut acc) };
    } else {
        let (w0q, w1q, xq) = (w0.get(..4 * q).unwrap_or(&[]), w1.get(..4 * q).unwrap_or(&[]), x.get(..8 * q).unwrap_or(&[]));
        for ((c0, c1), xc) in w0q.chunks(super::I16_CHUNK).zip(w1q.chunks(super::I16_CHUNK)).zip(xq.chunks(2 * super::I16_CHUNK)) {
            for (a, s) in acc.iter_mut().zip(dot2x2(c0, c1, xc)) {
                *a += s as i64;
            }
        }
    }
    // The last `n % 4` values of each patch: `dot2x2`'s own tail, on the rest of the pair layout.
    let q4 = 4 * q;
    if q4 == n {
        return acc;
    }
    if let (Some(t0), Some(t1), Some(tx)) = (w0.get(q4..n), w1.get(q4..n), x.get(2 * q4..2 * n)) {
        for (a, s) in acc.iter_mut().zip(dot2x2(t0, t1, tx)) {
            *a += s as i64;
        }
    }
    acc
}

/// The `q` groups of four of a channel pair's int8 weight rows `w0`, `w1` widened for
/// [`dot2x2_w16`] into `out` (four words per group: `w0`'s `(w0, w2)`, `(w1, w3)` as `SXTB16`
/// gives them, then `w1`'s); stops early where a slice is shorter.
#[inline]
pub fn widen_weights(w0: &[i8], w1: &[i8], q: usize, out: &mut [u32]) {
    let q = q.min(w0.len() / 4).min(w1.len() / 4).min(out.len() / 4);
    if q > 0 {
        // SAFETY: the loop reads `4 q` bytes from each row (unaligned word loads, which
        // Cortex-M4/M7 allow) and writes `4 q` words of `out`, all within the slices (above).
        unsafe { muir_dsp_widen_w16(w0.as_ptr(), w1.as_ptr(), q, out.as_mut_ptr()) };
    }
}

/// [`dot2x2_i16`] with the weights widened beforehand ([`widen_weights`]): `[w0 . a, w1 . a,
/// w0 . b, w1 . b]` over the `q` whole groups of four of a pair of i16 patches `x` (pair layout,
/// `8 q` values) and `ww` (`4 q` words), plus the last `n % 4` values from the int8 rows `w0`,
/// `w1` (`n` values each) and `x[8 q .. 2 n]`. 12 instructions per 16 MACs in the loop instead
/// of 16: worth it where one widening serves several pixel pairs (`conv::conv_row_w16`). Same
/// integers as [`dot2x2_i16`] (the same products in the same 508-term chunks); `None` where a
/// slice is shorter than that or `x` or `ww` is not word-aligned.
#[inline(always)]
pub fn dot2x2_w16(ww: &[u32], w0: &[i8], w1: &[i8], x: &[i16], n: usize) -> Option<[i64; 4]> {
    let q = n / 4;
    let (wq, xq) = (ww.get(..4 * q)?, x.get(..2 * n)?);
    if w0.len() < n || w1.len() < n || !(xq.as_ptr() as usize).is_multiple_of(4) {
        return None;
    }
    let mut acc = [0i64; 4];
    if q > 0 {
        // SAFETY: the loop reads `4 q` words from `wq` and `8 q <= 2 n` values from the
        // word-aligned `xq` (LDRD; `wq` is a `u32` slice, so aligned too), and adds into `acc`.
        unsafe { muir_dsp_dot2x2_w16(xq.as_ptr(), wq.as_ptr(), q, &mut acc) };
    }
    let q4 = 4 * q;
    if q4 == n {
        return Some(acc);
    }
    if let (Some(t0), Some(t1), Some(tx)) = (w0.get(q4..n), w1.get(q4..n), xq.get(2 * q4..2 * n)) {
        for (a, s) in acc.iter_mut().zip(dot2x2(t0, t1, tx)) {
            *a += s as i64;
        }
    }
    Some(acc)
}

/// [`dot2x2_w16`] of a patch of `4 q` values, `1 <= q <= I16_ASM_GROUPS` (one chunk, no last
/// values): the four sums as the i32 the chunk gives (exact, module doc), with no i64 sums to
/// zero, add to and range-check afterwards (the one-part layers of up to 508 values, whose
/// sums go straight to the short epilogue). `None` where a slice is shorter, `q` is outside
/// that range or `x` is not word-aligned.
#[inline(always)]
pub fn dot2x2_w16_i32(ww: &[u32], x: &[i16], q: usize) -> Option<[i32; 4]> {
    let (wq, xq) = (ww.get(..4 * q)?, x.get(..8 * q)?);
    if q == 0 || q > I16_ASM_GROUPS || !(xq.as_ptr() as usize).is_multiple_of(4) {
        return None;
    }
    let mut out = [0i32; 4];
    // SAFETY: the loop reads `4 q` words from `wq` and `8 q` values from the word-aligned `xq`
    // (LDM; `wq` is a `u32` slice, so aligned too), `1 <= q <= I16_ASM_GROUPS` (one chunk), and
    // writes `out`.
    unsafe { muir_dsp_dot2x2_w16_i32(xq.as_ptr(), wq.as_ptr(), q, &mut out) };
    Some(out)
}

/// [`dot2x2_w16_i32`] of `out.len()` pairs of patches one after another in `x` (`8 q` values
/// each, the gathered pairs of a one-part layer), by one assembly call: `out[i]` the four sums
/// of pair `i`. False, having written nothing, where a slice is shorter, `q` is outside `1 ..=
/// I16_ASM_GROUPS`, `out` is empty or `x` is not word-aligned.
#[inline(always)]
pub fn dot2x2_w16_i32_n(ww: &[u32], x: &[i16], q: usize, out: &mut [[i32; 4]]) -> bool {
    let n = out.len();
    let (Some(wq), Some(xq)) = (ww.get(..4 * q), x.get(..8 * q * n)) else {
        return false;
    };
    if q == 0 || q > I16_ASM_GROUPS || n == 0 || !(xq.as_ptr() as usize).is_multiple_of(4) {
        return false;
    }
    // SAFETY: per pair the loop reads `4 q` words from `wq` and the pair's `8 q` values from the
    // word-aligned `xq` (`8 q n` values in all; LDM, `wq` is a `u32` slice, so aligned too),
    // `1 <= q <= I16_ASM_GROUPS` (one chunk), and writes `out[i]` for each of the `n >= 1` pairs.
    unsafe { muir_dsp_dot2x2_w16_n(xq.as_ptr(), wq.as_ptr(), q, n, out.as_mut_ptr()) };
    true
}

/// [`dot2x2_w16_i32_n`] with pair `i`'s `8 q` values at `x[i stride ..]` (`stride >= 8 q`, even:
/// one part of the gathered pairs of a several-part layer, `stride` the pair's `2 kl`). False,
/// having written nothing, where a slice is shorter, `q` is outside `1 ..= I16_ASM_GROUPS`,
/// `out` is empty, the stride is odd or short, or `x` is not word-aligned.
#[inline(always)]
pub fn dot2x2_w16_i32_ns(ww: &[u32], x: &[i16], q: usize, stride: usize, out: &mut [[i32; 4]]) -> bool {
    let n = out.len();
    if q == 0 || q > I16_ASM_GROUPS || n == 0 || stride < 8 * q || !stride.is_multiple_of(2) {
        return false;
    }
    let (Some(wq), Some(xq)) = (ww.get(..4 * q), x.get(..(n - 1) * stride + 8 * q)) else {
        return false;
    };
    if !(xq.as_ptr() as usize).is_multiple_of(4) {
        return false;
    }
    // SAFETY: per pair `i < n` the loop reads `4 q` words of `wq` and `8 q` values of the
    // word-aligned `xq` from `i stride` (inside its `(n - 1) stride + 8 q`; an even stride keeps
    // every pair word-aligned), `1 <= q <= I16_ASM_GROUPS`, and writes `out[i]`; the gap it adds
    // after each pair is `2 (stride - 8 q)` bytes.
    unsafe { muir_dsp_dot2x2_w16_ns(xq.as_ptr(), wq.as_ptr(), q, n, out.as_mut_ptr(), 2 * (stride - 8 * q)) };
    true
}

/// The i32 sums `out[i]` of `out.len()` pairs of one part of `q` whole groups (`x`: the part's
/// block of the first pair, each next pair's `stride` values later; `ww`: the part's widened
/// weights), a chunk of at most `I16_ASM_GROUPS` groups of every pair by one
/// [`dot2x2_w16_i32_ns`] call, the later chunks (in `tmp`) added with overflow
/// checks. False where a call refuses or a sum leaves i32 (then the short path does not apply:
/// the callers go the per-pair way).
#[inline(never)]
pub fn dot2x2_w16_i32_chunks(ww: &[u32], x: &[i16], q: usize, stride: usize, out: &mut [[i32; 4]], tmp: &mut [[i32; 4]]) -> bool {
    let Some(tmp) = tmp.get_mut(..out.len()) else {
        return false;
    };
    let mut g = 0;
    while g < q {
        let c = (q - g).min(I16_ASM_GROUPS);
        let (Some(wq), Some(xq)) = (ww.get(4 * g..), x.get(8 * g..)) else {
            return false;
        };
        if g == 0 {
            if !dot2x2_w16_i32_ns(wq, xq, c, stride, out) {
                return false;
            }
        } else {
            if !dot2x2_w16_i32_ns(wq, xq, c, stride, tmp) {
                return false;
            }
            for (o, t) in out.iter_mut().zip(tmp.iter()) {
                for (a, b) in o.iter_mut().zip(t) {
                    match a.checked_add(*b) {
                        Some(v) => *a = v,
                        None => return false,
                    }
                }
            }
        }
        g += c;
    }
    q > 0
}

/// `Elem::put_groups` for i16 (the pair layout's swap): each group of four as two words
/// (`(x0, x1)`, `(x2, x3)`, unaligned loads) repacked by `PKHBT`/`PKHTB` into `(x0, x2)`, `(x1,
/// x3)`: 2 loads, 2 packs and 2 stores per group instead of 4 halfword loads and 4 stores. On
/// word-aligned buffers (the engine's) by `muir_dsp_put_groups_i16`: `LDRD`, the packs, `STRD`
/// (4 instructions a group against 8 compiled).
#[inline(always)]
pub fn put_groups_i16(d: &mut [i16], s: &[i16], second: bool) {
    let off = if second { 4 } else { 0 };
    // Whole groups on word-aligned buffers (the engine's: rows and patches of channel counts
    // that are multiples of four): by `muir_dsp_put_groups_i16`.
    let q = (d.len() / 8).min(s.len() / 4);
    if q > 0
        && let Some(dd) = d.get_mut(off..8 * q)
        && (dd.as_ptr() as usize).is_multiple_of(4)
        && (s.as_ptr() as usize).is_multiple_of(4)
    {
        // SAFETY: `q` groups: the loop reads `4 q` values of `s` and writes values `16 g ..
        // 16 g + 4` bytes (`8 g + off .. 8 g + off + 4` values) of `d` for `g < q`, all inside
        // `dd` (`8 q - off` values from `off`), both word-aligned (LDRD/STRD).
        unsafe { muir_dsp_put_groups_i16(dd.as_mut_ptr(), s.as_ptr(), q) };
        return;
    }
    for (g, q) in d.chunks_exact_mut(8).zip(s.chunks_exact(4)) {
        if let Some(g) = g.get_mut(off..off + 4) {
            let (x01, x23) = (pair(q, 0), pair(q, 2));
            let (lo, hi) = (pkhbt(x01, x23), pkhtb(x01, x23));
            // SAFETY: `g` holds 4 values (8 bytes); unaligned word stores are allowed on
            // Cortex-M4/M7.
            unsafe {
                core::ptr::write_unaligned(g.as_mut_ptr() as *mut u32, lo);
                core::ptr::write_unaligned(g.as_mut_ptr().add(2) as *mut u32, hi);
            }
        }
    }
}

/// The `q` groups of four of a channel pair's int8 weight rows `w0`, `w1` widened in natural
/// order for [`nat_block`] into `out` (four words per group: `w0`'s `(w0, w1)`, `(w2, w3)`,
/// then `w1`'s); stops early where a slice is shorter.
#[inline]
pub fn widen_weights_nat(w0: &[i8], w1: &[i8], q: usize, out: &mut [u32]) {
    let q = q.min(w0.len() / 4).min(w1.len() / 4).min(out.len() / 4);
    if q > 0 {
        // SAFETY: the loop reads `4 q` bytes from each row (unaligned word loads, which
        // Cortex-M4/M7 allow) and writes `4 q` words of `out`, all within the slices (above).
        unsafe { muir_dsp_widen_nat(w0.as_ptr(), w1.as_ptr(), q, out.as_mut_ptr()) };
    }
}

/// One run of one kernel row of one part for [`nat_block`]: pixel a's values at `row + col
/// step` bytes, pixel b's `bstep` bytes later, `groups` whole groups of four against the widened
/// weights `w` bytes into `nat_block`'s `ww`, added to the part's sums. A plain entry
/// ([`NatEntry::PLAIN`] set in `groups`): the low bits count values (1 to 7), w0's int8 weights
/// `w` bytes into `nat_block`'s `w0`, w1's `kl` bytes later. (Offsets, not addresses: a table
/// serves every channel pair of a row.) Made by [`NatEntry::new`], which also works out what
/// the assembly would compute per entry: the part's sums as a byte offset and where the
/// aligned two-pixel loop is entered.
#[repr(C)]
#[derive(Clone, Copy, Debug)]
pub struct NatEntry {
    /// Pixel a's first value at column 0 (`col` adds `col step` bytes).
    pub row: *const i16,
    /// Byte offset of the run's widened weights ([`widen_weights_nat`]) or of w0's int8 weights.
    pub w: usize,
    /// Bytes per column step.
    pub step: usize,
    /// Whole groups of the run, 1 to [`I16_ASM_GROUPS`] (or values, with [`NatEntry::PLAIN`]).
    pub groups: usize,
    /// Bytes from pixel a's values to pixel b's.
    pub bstep: usize,
    /// Byte offset of the part's sums (`32 part`).
    sums: usize,
    /// Bytes of the aligned two-pixel loop's copies skipped (`44 (I16_ASM_GROUPS - groups)`;
    /// 0 for a plain entry).
    skip: usize,
}

impl NatEntry {
    /// The flag of a plain entry in `groups`.
    pub const PLAIN: usize = 1 << 31;

    /// An unused entry (all bits zero: a table of them is cleared in place).
    pub const EMPTY: NatEntry = NatEntry { row: core::ptr::null(), w: 0, step: 0, groups: 0, bstep: 0, sums: 0, skip: 0 };

    /// The entry of the run (fields as above) into the sums of part `part`.
    #[inline(always)]
    pub const fn new(row: *const i16, w: usize, step: usize, groups: usize, bstep: usize, part: usize) -> Self {
        let skip = if groups & Self::PLAIN == 0 { 44 * I16_ASM_GROUPS.saturating_sub(groups) } else { 0 };
        NatEntry { row, w, step, groups, bstep, sums: 32 * part, skip }
    }

    /// The part whose sums the entry adds to.
    #[inline(always)]
    pub fn part(&self) -> usize {
        self.sums / 32
    }
}

/// `sums[e.part()] += [w0 . a, w1 . a, w0 . b, w1 . b]` over every entry `e` of `table` (a block
/// of two pixels, or one pixel as both, at column `col`), the activations read in place: `ww`
/// the channel pair's widened weights, `w0` its int8 weights, w1's `kl` bytes later.
///
/// # Safety
///
/// For every entry: `row + col step` and `row + col step + bstep` are valid for reads of `8
/// groups` bytes (`2 n` for a plain entry of `n` values; each halfword-aligned); a groups entry:
/// `ww` is valid for reads of `4 (w / 16 + groups)` words, `w` a multiple of 16, `1 <= groups <=
/// I16_ASM_GROUPS`; a plain entry: `w0` valid for reads of `kl + w + n` bytes, `1 <= n <= 7`;
/// and `part() < sums.len()`.
#[inline(always)]
pub unsafe fn nat_block(table: &[NatEntry], col: usize, sums: &mut [[i64; 4]], kl: usize, w0: &[i8], ww: &[u32]) {
    if !table.is_empty() {
        // SAFETY: the caller's contract: the loop reads each entry's values from pixels a and b
        // and its weights, and adds into `sums[part]`.
        unsafe { muir_dsp_nat_block(table.as_ptr(), table.len(), col, sums.as_mut_ptr(), kl, w0.as_ptr(), ww.as_ptr()) };
    }
}

/// The whole groups of four u8 values of `s` widened into `d` in the i16 pair layout's order
/// (values 0, 2, 1, 3 of each group: `UXTB16` of the group's word, then of the word rotated by
/// 8): one load, two widenings and two stores per group instead of four of each (the gathered
/// u8 pairs of `conv::conv_row_u8_wide`). Stops at the shorter of `s / 4` and `d / 4` groups.
/// On word-aligned buffers (the engine's) by `muir_dsp_widen_u8` (3 instructions a group
/// against 7 compiled).
#[inline(always)]
pub fn widen_u8_groups(d: &mut [i16], s: &[u8]) {
    let q = (d.len() / 4).min(s.len() / 4);
    if q > 0 && (d.as_ptr() as usize).is_multiple_of(4) && (s.as_ptr() as usize).is_multiple_of(4) {
        // SAFETY: the loop reads `4 q` bytes of `s` and writes `4 q` values of `d` (both at
        // least that long, word-aligned: LDRD, STM).
        unsafe { muir_dsp_widen_u8(d.as_mut_ptr(), s.as_ptr(), q) };
        return;
    }
    for (g, q) in d.chunks_exact_mut(4).zip(s.chunks_exact(4)) {
        let v = word(q, 0);
        let (lo, hi) = (uxtb16(v), uxtb16_ror8(v));
        // SAFETY: `g` holds 4 values (8 bytes); unaligned word stores are allowed on
        // Cortex-M4/M7.
        unsafe {
            core::ptr::write_unaligned(g.as_mut_ptr() as *mut u32, lo);
            core::ptr::write_unaligned(g.as_mut_ptr().add(2) as *mut u32, hi);
        }
    }
}

/// The correlations of the int8 feature vector `f1` (`c` values) with four consecutive columns of
/// a feature row (`f2`: `4 c` values, column `j` at `j c`): `out[j] = sum f1[i] f2[j c + i]`.
/// Each quad of `f1` is widened once for the four columns (2 `SXTB16`), each column's quad by 2
/// more and 2 `SMLAD`: 23 instructions per 16 MACs, against 23 per 8 for four separate [`dot`]s
/// (the correlation lookup's window, `kernels::corr`). Same i32 sums as [`dot`] (`c <= 2^15`:
/// every partial sum below `2^29`).
#[inline]
pub fn dot_i8_4cols(f1: &[i8], f2: &[i8], c: usize) -> [i32; 4] {
    let (a, b) = (bytes_of_i8(f1), bytes_of_i8(f2));
    let n = c.min(a.len());
    let mut acc = [0i32; 4];
    if b.len() < 4 * c || c > 1 << 15 {
        // (a short row: the plain path decides, column by column)
        for (j, s) in acc.iter_mut().enumerate() {
            *s = dot(f1, f2.get(j * c..(j + 1) * c).unwrap_or_default());
        }
        return acc;
    }
    let mut i = 0;
    while i + 4 <= n {
        let q = word(a, i);
        let (qe, qo) = (sxtb16(q), sxtb16_ror8(q));
        for (j, s) in acc.iter_mut().enumerate() {
            let v = word(b, j * c + i);
            *s = smlad(sxtb16_ror8(v), qo, smlad(sxtb16(v), qe, *s));
        }
        i += 4;
    }
    for (k, x) in a.iter().enumerate().take(n).skip(i) {
        for (j, s) in acc.iter_mut().enumerate() {
            *s += *x as i8 as i32 * b.get(j * c + k).map_or(0, |y| *y as i8 as i32);
        }
    }
    acc
}

/// The correlation lookup's right feature row widened once per row (`kernels::corr::window_wide`):
/// each whole quad `k` of `src` (values `4k .. 4k + 4`) becomes two words, `dst[2k] =
/// SXTB16(quad)` (values 0 and 2) and `dst[2k + 1] = SXTB16(quad, ror 8)` (values 1 and 3), the
/// order [`dot_w8_4cols`] reads. Returns the quads written (the shorter of `src.len() / 4` and
/// `dst.len() / 2`).
#[inline]
pub fn widen_i8_quads(src: &[i8], dst: &mut [u32]) -> usize {
    let b = bytes_of_i8(src);
    let q = (b.len() / 4).min(dst.len() / 2);
    for (k, d) in dst.chunks_exact_mut(2).take(q).enumerate() {
        let v = word(b, 4 * k);
        if let [e, o] = d {
            (*e, *o) = (sxtb16(v), sxtb16_ror8(v));
        }
    }
    q
}

/// [`dot_i8_4cols`] on a row widened by [`widen_i8_quads`]: `cols` holds four consecutive
/// columns of `c / 2` words each (`c` a multiple of 4): `out[j] = sum f1[i] f2[j c + i]`. Each
/// quad of `f1` is widened once for the four columns, each column's quad is one `LDRD` and two
/// `SMLAD`: about 16 instructions per 16 MACs against 23 (the row's widening costs about 4 a quad,
/// once per row for all the pixels whose windows read it). `None` where `c` is not a multiple of
/// 4, over `2^15`, or either slice is short. The slim model's feature width (128) by an assembly
/// loop (columns 256 bytes apart at immediate offsets, two quads a pass: 16 instructions per 16
/// MACs; the compiled loop inlined into the lookup spilled: 26).
#[inline]
pub fn dot_w8_4cols(f1: &[i8], cols: &[u32], c: usize) -> Option<[i32; 4]> {
    let a = bytes_of_i8(f1);
    if !c.is_multiple_of(4) || c > 1 << 15 || a.len() < c || cols.len() < 2 * c {
        return None;
    }
    // SAFETY: `c` a multiple of 4, `a` at least `c` bytes, `cols` at least `4 (c / 2)` words.
    Some(unsafe {
        match c {
            128 => dot_w8_4cols_128(a.as_ptr(), cols.as_ptr()),
            _ => dot_w8_4cols_at::<0>(a.as_ptr(), cols.as_ptr(), c, c / 2),
        }
    })
}

/// [`dot_w8_4cols`]' loop: column stride `H` words when not 0, else `h`.
///
/// # Safety
/// `c` a multiple of 4, `a` valid for `c` bytes, `p` for `4 h` words (`h = H` when `H > 0`).
#[inline(always)]
unsafe fn dot_w8_4cols_at<const H: usize>(a: *const u8, p: *const u32, c: usize, h: usize) -> [i32; 4] {
    let h = if H > 0 { H } else { h };
    let (mut s0, mut s1, mut s2, mut s3) = (0i32, 0i32, 0i32, 0i32);
    let mut i = 0;
    while i + 4 <= c {
        // SAFETY: `i + 4 <= c`: bytes `i .. i + 4` of `a`, words `j h + i / 2 ..= j h + i / 2 +
        // 1` (`j < 4`) of `p`.
        unsafe {
            let q = core::ptr::read_unaligned(a.add(i) as *const u32);
            let (qe, qo) = (sxtb16(q), sxtb16_ror8(q));
            let w = p.add(i / 2);
            s0 = smlad(*w.add(1), qo, smlad(*w, qe, s0));
            s1 = smlad(*w.add(h + 1), qo, smlad(*w.add(h), qe, s1));
            s2 = smlad(*w.add(2 * h + 1), qo, smlad(*w.add(2 * h), qe, s2));
            s3 = smlad(*w.add(3 * h + 1), qo, smlad(*w.add(3 * h), qe, s3));
        }
        i += 4;
    }
    [s0, s1, s2, s3]
}

/// [`dot_w8_4cols`] for `c = 128`: per quad of `f1` one `LDR` and two `SXTB16`, per column one
/// `LDRD` (post-indexed for the first) and two `SMLAD`; two quads a pass (32 quads).
///
/// # Safety
/// `a` valid for 128 bytes, `p` for 256 words (four columns of 64).
#[inline(always)]
unsafe fn dot_w8_4cols_128(a: *const u8, p: *const u32) -> [i32; 4] {
    let (mut s0, mut s1, mut s2, mut s3) = (0i32, 0i32, 0i32, 0i32);
    // One quad of `f1` against the four columns (256 bytes apart): one step, written out twice a
    // pass (not `.rept`).
    macro_rules! step {
        () => {
            "ldr {q}, [{a}], #4\nldrd {x}, {y}, [{p}], #8\nsxtb16 {e}, {q}\nsxtb16 {q}, {q}, ror #8\nsmlad {s0}, {x}, {e}, {s0}\nsmlad {s0}, {y}, {q}, {s0}\nldrd {x}, {y}, [{p}, #248]\nsmlad {s1}, {x}, {e}, {s1}\nsmlad {s1}, {y}, {q}, {s1}\nldrd {x}, {y}, [{p}, #504]\nsmlad {s2}, {x}, {e}, {s2}\nsmlad {s2}, {y}, {q}, {s2}\nldrd {x}, {y}, [{p}, #760]\nsmlad {s3}, {x}, {e}, {s3}\nsmlad {s3}, {y}, {q}, {s3}"
        };
    }
    // SAFETY: 16 passes of two quads: bytes `a .. a + 128`, words `p + j 64 .. p + j 64 + 64`
    // (`j < 4`); SMLAD sets the Q flag only on overflow, which `c <= 2^15` excludes.
    unsafe {
        core::arch::asm!(
            "2:",
            step!(),
            step!(),
            "cmp {a}, {end}",
            "bne 2b",
            a = inout(reg) a => _,
            p = inout(reg) p => _,
            end = in(reg) a.wrapping_add(128),
            s0 = inout(reg) s0,
            s1 = inout(reg) s1,
            s2 = inout(reg) s2,
            s3 = inout(reg) s3,
            q = out(reg) _,
            e = out(reg) _,
            x = out(reg) _,
            y = out(reg) _,
            options(nostack, readonly),
        );
    }
    [s0, s1, s2, s3]
}

/// 36 halfwords on a word boundary (the path steps' predecessor window, `fullres::path_step`).
#[repr(C, align(4))]
pub struct Win36(pub [u16; 36]);

/// `w` filled with `u16::MAX` and returned as its values: nine `STRD` of one register, where
/// `[u16::MAX; N]` became a `memset` call (about 50 instructions).
#[inline(always)]
pub fn ones_u16_36(w: &mut core::mem::MaybeUninit<Win36>) -> &mut [u16; 36] {
    // SAFETY: nine STRD write the 72 bytes of `w` (word-aligned); then every value is set.
    unsafe {
        asm!(
            "strd {o}, {o}, [{p}]",
            "strd {o}, {o}, [{p}, #8]",
            "strd {o}, {o}, [{p}, #16]",
            "strd {o}, {o}, [{p}, #24]",
            "strd {o}, {o}, [{p}, #32]",
            "strd {o}, {o}, [{p}, #40]",
            "strd {o}, {o}, [{p}, #48]",
            "strd {o}, {o}, [{p}, #56]",
            "strd {o}, {o}, [{p}, #64]",
            p = in(reg) w.as_mut_ptr(),
            o = in(reg) u32::MAX,
            options(nostack, preserves_flags),
        );
        &mut w.assume_init_mut().0
    }
}

/// `x` saturated to i16 (`SSAT #16`): the same value as `arith::sat_i16(x as i64)`.
#[inline(always)]
pub fn ssat16(x: i32) -> i16 {
    let r: i32;
    // SAFETY: one register-only instruction (it may set the Q flag, which nothing reads).
    unsafe { asm!("ssat {r}, #16, {x}", r = lateout(reg) r, x = in(reg) x, options(pure, nomem, nostack)) };
    r as i16
}

/// [`row_sums_aligned`] of two channel rows with the same weights (`aggregate_cm`): per four keys
/// one `LDRD` of weights, one of each row and four `SMLALD` (7 instructions per 8 products
/// against 8 for two [`row_sums_aligned`] calls), sixteen keys a loop, the last 0 to 7 pairs in
/// Rust. `None` unless `ep`, `r0` and `r1` are word-aligned.
#[inline(always)]
fn row_sums2_aligned(ep: &[u32], r0: &[i16], r1: &[i16]) -> Option<(i64, i64)> {
    if !(ep.as_ptr() as usize | r0.as_ptr() as usize | r1.as_ptr() as usize).is_multiple_of(4) {
        return None;
    }
    let pairs = ep.len().min(r0.len() / 2).min(r1.len() / 2);
    let loops = pairs / 8;
    let (mut lo0, mut hi0, mut lo1, mut hi1) = (0u32, 0u32, 0u32, 0u32);
    // Four keys' pairs of both rows: one step, written out four times a loop (not `.rept`).
    macro_rules! step {
        () => {
            "ldrd {e0}, {e1}, [{ep}], #8\nldrd {t0}, {t1}, [{ra}], #8\nsmlald {lo0}, {hi0}, {e0}, {t0}\nsmlald {lo0}, {hi0}, {e1}, {t1}\nldrd {t0}, {t1}, [{rb}], #8\nsmlald {lo1}, {hi1}, {e0}, {t0}\nsmlald {lo1}, {hi1}, {e1}, {t1}"
        };
    }
    if loops > 0 {
        // SAFETY: `loops` loops read `8 loops <= pairs` words of `ep` and `16 loops <= 2 pairs`
        // values of each row, word-aligned (checked: `LDRD` needs it); no stack; `subs` sets the
        // flags (clobbered by default).
        unsafe {
            asm!(
                "2:",
                step!(),
                step!(),
                step!(),
                step!(),
                "subs {n}, #1",
                "bne 2b",
                ep = inout(reg) ep.as_ptr() => _,
                ra = inout(reg) r0.as_ptr() => _,
                rb = inout(reg) r1.as_ptr() => _,
                n = inout(reg) loops => _,
                lo0 = inout(reg) lo0, hi0 = inout(reg) hi0, lo1 = inout(reg) lo1, hi1 = inout(reg) hi1,
                e0 = out(reg) _, e1 = out(reg) _, t0 = out(reg) _, t1 = out(reg) _,
                options(nostack, readonly),
            );
        }
    }
    let (mut s0, mut s1) = (((hi0 as u64) << 32 | lo0 as u64) as i64, ((hi1 as u64) << 32 | lo1 as u64) as i64);
    for t in 8 * loops..pairs {
        if let (Some(&w), Some(&[a, b]), Some(&[c, d])) = (ep.get(t), r0.get(2 * t..2 * t + 2), r1.get(2 * t..2 * t + 2)) {
            let (wl, wh) = (w as u16 as i16 as i64, (w >> 16) as u16 as i16 as i64);
            s0 += wl * a as i64 + wh * b as i64;
            s1 += wl * c as i64 + wh * d as i64;
        }
    }
    Some((s0, s1))
}
