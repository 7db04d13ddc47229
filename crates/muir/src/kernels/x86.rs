//! x86-64 SIMD versions of the int8 dot products ([`Elem::dot`], [`Elem::dot2`], [`Elem::dot2x2`]),
//! chosen at run time: AVX2 when the CPU has it (checked once, then one relaxed atomic load per
//! call), else the portable loops in `kernels`. Host only (feature `std`: the detection needs it);
//! the x86-64 baseline is SSE2, which the portable loops are compiled for.
//!
//! Weights (i8) and activations (u8, i8, i16) are widened to i16 and multiplied with `vpmaddwd`
//! (16 products, summed in pairs into 8 i32 lanes). `vpmaddubsw` is not used: it saturates
//! (`2 * 255 * 128 > 2^15`). Every i32 lane sums at most [`LANE_TERMS`] products before it is
//! added into an i64 (`|w x| <= 128 * 32768 = 2^22`, so `|lane| <= 2^30`): no partial sum
//! overflows, integer addition is exact, and the results are the exact sums, the same integers as
//! the portable loops (whose own bounds are documented there) for every input and length.
//!
//! The MGA attention ([`super::attention::query_stats`], [`super::attention::aggregate_query`])
//! has its own exact AVX2 forms: see [`avx2::logits`] and [`avx2::aggregate`].
//!
//! Where the CPU also has AVX-512 VNNI (with VL), [`Elem::dot2x2`] of u8 activations takes
//! `vpdpbusd` ([`vnni`]): u8 times i8 in groups of four straight into i32, no widening.
//!
//! Where it has AVX-512 F and BW as well, whole convolution rows are one matrix product on
//! 512-bit vectors (`conv::avx512`).
//!
//! `MUIR_X86_SIMD=0` in the environment (read once) keeps the portable loops, `MUIR_X86_SIMD=avx2`
//! the AVX2 ones, `MUIR_X86_SIMD=vnni` everything but the 512-bit convolution, for comparisons.
//!
//! No input reaches a panic: the slices are walked by iterators, `chunks_exact` and `get`, and the
//! SIMD loads read through pointers whose bounds the loops prove (each `// SAFETY:` says how).
#![deny(clippy::indexing_slicing)]

use core::any::TypeId;
use core::arch::x86_64::*;
use core::sync::atomic::{AtomicU8, Ordering};

use super::Elem;
use super::attention::weight;
use crate::arith::Multiplier;

const UNKNOWN: u8 = 0;
const PORTABLE: u8 = 1;
const AVX2: u8 = 2;
/// AVX2, AVX-512 VNNI and AVX-512 VL (`vpdpbusd` on 256-bit vectors).
const VNNI: u8 = 3;
/// [`VNNI`] plus AVX-512 F and BW: the 512-bit row convolution (`conv::avx512`).
const AVX512: u8 = 4;

static LEVEL: AtomicU8 = AtomicU8::new(UNKNOWN);

#[inline(always)]
fn level() -> u8 {
    match LEVEL.load(Ordering::Relaxed) {
        UNKNOWN => detect(),
        l => l,
    }
}

/// Whether the AVX2 paths are taken (detected on the first call, then cached).
#[inline(always)]
pub fn has_avx2() -> bool {
    level() >= AVX2
}

/// Whether the AVX-512 VNNI paths are taken (see [`vnni`]).
#[inline(always)]
pub fn has_vnni() -> bool {
    level() >= VNNI
}

/// Whether the 512-bit row convolution is taken (AVX-512 F, BW, VL and VNNI).
#[inline(always)]
pub fn has_avx512() -> bool {
    level() >= AVX512
}

/// Whether the 512-bit paths that also need AVX-512 DQ are taken (64-bit products and the
/// i64 <-> f64 conversions of the exact divisions: the upsampling, the attention's outputs, the
/// normalisation): [`has_avx512`] and a CPU with DQ (checked once).
pub fn has_avx512dq() -> bool {
    static DQ: std::sync::OnceLock<bool> = std::sync::OnceLock::new();
    has_avx512() && *DQ.get_or_init(|| std::is_x86_feature_detected!("avx512dq"))
}

#[cold]
#[inline(never)]
fn detect() -> u8 {
    let var = std::env::var_os("MUIR_X86_SIMD");
    let l = if var.as_ref().is_some_and(|v| v == "0") || !std::is_x86_feature_detected!("avx2") {
        PORTABLE
    } else if var.as_ref().is_some_and(|v| v == "avx2") || !(std::is_x86_feature_detected!("avx512vnni") && std::is_x86_feature_detected!("avx512vl")) {
        AVX2
    } else if var.as_ref().is_some_and(|v| v == "vnni")
        || !(std::is_x86_feature_detected!("avx512f") && std::is_x86_feature_detected!("avx512bw"))
    {
        VNNI
    } else {
        AVX512
    };
    LEVEL.store(l, Ordering::Relaxed);
    l
}

/// Most products one i32 lane sums before it is moved into an i64: `256 * 2^22 = 2^30`.
pub const LANE_TERMS: usize = 256;

/// Shorter dot products stay on the (inlined) portable loops: the call and the horizontal sums
/// would cost more than they save.
const MIN_LEN: usize = 16;

/// `x` as a slice of `U` when `T` is `U`.
#[inline(always)]
pub(super) fn cast<T: 'static, U: 'static>(x: &[T]) -> Option<&[U]> {
    if TypeId::of::<T>() == TypeId::of::<U>() {
        // SAFETY: `T` and `U` are the same type.
        Some(unsafe { core::slice::from_raw_parts(x.as_ptr().cast::<U>(), x.len()) })
    } else {
        None
    }
}

/// [`Elem::dot`] on AVX2; `None` where the portable loop should run.
#[inline(always)]
pub fn dot<T: Elem>(w: &[i8], x: &[T]) -> Option<i64> {
    if w.len().min(x.len()) < MIN_LEN || !has_avx2() {
        return None;
    }
    // SAFETY: the CPU has AVX2 (checked above).
    unsafe {
        if let Some(x) = cast::<T, u8>(x) {
            return Some(avx2::dot(w, x));
        }
        if let Some(x) = cast::<T, i16>(x) {
            return Some(avx2::dot(w, x));
        }
        if let Some(x) = cast::<T, i8>(x) {
            return Some(avx2::dot(w, x));
        }
    }
    None
}

/// [`Elem::dot2`] on AVX2; `None` where the portable loops should run.
#[inline(always)]
pub fn dot2<T: Elem>(w0: &[i8], w1: &[i8], x: &[T]) -> Option<(i64, i64)> {
    if w0.len().min(x.len()) != w1.len().min(x.len()) || w0.len().min(x.len()) < MIN_LEN || !has_avx2() {
        return None;
    }
    // SAFETY: the CPU has AVX2 (checked above).
    unsafe {
        if let Some(x) = cast::<T, u8>(x) {
            return Some(avx2::dot2(w0, w1, x));
        }
        if let Some(x) = cast::<T, i16>(x) {
            return Some(avx2::dot2(w0, w1, x));
        }
        if let Some(x) = cast::<T, i8>(x) {
            return Some(avx2::dot2(w0, w1, x));
        }
    }
    None
}

/// [`Elem::dot2x2`] on AVX2; `None` where the portable loop should run.
#[inline(always)]
pub fn dot2x2<T: Elem>(w0: &[i8], w1: &[i8], x: &[T]) -> Option<[i64; 4]> {
    if w0.len().min(w1.len()).min(x.len() / 2) < MIN_LEN || !has_avx2() {
        return None;
    }
    // SAFETY: the CPU has AVX2 (checked above), and AVX-512 VNNI and VL where `has_vnni()`.
    unsafe {
        if let Some(x) = cast::<T, u8>(x) {
            if has_vnni() {
                return Some(vnni::dot2x2_u8(w0, w1, x));
            }
            return Some(avx2::dot2x2(w0, w1, x));
        }
        if let Some(x) = cast::<T, i16>(x) {
            return Some(avx2::dot2x2(w0, w1, x));
        }
        if let Some(x) = cast::<T, i8>(x) {
            return Some(avx2::dot2x2(w0, w1, x));
        }
    }
    None
}

/// Query/key widths the AVX2 attention takes: whole 16-value vectors, at most [`avx2::MAX_QK`].
#[inline(always)]
fn attention_ok(c: usize) -> bool {
    c != 0 && c.is_multiple_of(16) && c <= avx2::MAX_QK
}

/// [`super::attention::query_stats`] on AVX2; `None` where the portable loops should run.
#[inline]
pub fn query_stats(q: &[i16], keys: &[i16], m: Multiplier) -> Option<(i64, i64)> {
    if !attention_ok(q.len()) || !has_avx2() {
        return None;
    }
    // SAFETY: the CPU has AVX2 and `q.len()` is a multiple of 16 up to `MAX_QK` (checked above).
    Some(unsafe { avx2::query_stats(q, keys, m) })
}

/// The accumulation of [`super::attention::aggregate_query`] on AVX2: adds
/// `sum_j weight(q . k_j, max, m) * v_j` into `acc` (`cv` values) and returns `true`, or returns
/// `false` (nothing done) where the portable loop should run.
#[inline]
pub fn aggregate(q: &[i16], keys: &[i16], values: &[i16], cv: usize, max: i64, m: Multiplier, acc: &mut [i64]) -> bool {
    if !attention_ok(q.len()) || cv == 0 || !has_avx2() {
        return false;
    }
    let Some(acc) = acc.get_mut(..cv) else {
        return false;
    };
    // SAFETY: the CPU has AVX2, `q.len()` is a multiple of 16 up to `MAX_QK` (checked above) and
    // `acc.len() == cv > 0`.
    unsafe { avx2::aggregate(q, keys, values, cv, max, m, acc) };
    true
}

/// The AVX2 kernels. Callers guarantee that the CPU has AVX2.
pub mod avx2 {
    use super::*;

    /// Activation types: 16 of them widened to i16.
    pub trait Act: Elem {
        /// `p[0..16]` as 16 i16 lanes.
        ///
        /// # Safety
        /// 16 values are readable from `p`, and the CPU has AVX2.
        unsafe fn load16(p: *const Self) -> __m256i;
    }

    impl Act for u8 {
        #[inline(always)]
        unsafe fn load16(p: *const u8) -> __m256i {
            // SAFETY: the caller's guarantees.
            unsafe { _mm256_cvtepu8_epi16(_mm_loadu_si128(p.cast())) }
        }
    }

    impl Act for i8 {
        #[inline(always)]
        unsafe fn load16(p: *const i8) -> __m256i {
            // SAFETY: the caller's guarantees.
            unsafe { _mm256_cvtepi8_epi16(_mm_loadu_si128(p.cast())) }
        }
    }

    impl Act for i16 {
        #[inline(always)]
        unsafe fn load16(p: *const i16) -> __m256i {
            // SAFETY: the caller's guarantees.
            unsafe { _mm256_loadu_si256(p.cast()) }
        }
    }

    /// 16 weights widened to i16.
    #[inline(always)]
    unsafe fn weights16(p: *const i8) -> __m256i {
        // SAFETY: the caller guarantees 16 readable values and AVX2.
        unsafe { _mm256_cvtepi8_epi16(_mm_loadu_si128(p.cast())) }
    }

    /// Sum of the 8 i32 lanes, in i64.
    #[inline(always)]
    unsafe fn hsum(v: __m256i) -> i64 {
        let mut l = [0i32; 8];
        // SAFETY: `l` holds 32 bytes.
        unsafe { _mm256_storeu_si256(l.as_mut_ptr().cast(), v) };
        l.iter().map(|&v| v as i64).sum()
    }

    /// Exact `sum(w[i] * x[i])` over `min(w.len(), x.len())` values.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot<T: Act>(w: &[i8], x: &[T]) -> i64 {
        // Two accumulators, each lane gets 2 products per 32 values: `BLOCK / 8` per lane.
        const BLOCK: usize = LANE_TERMS * 8;
        let n = w.len().min(x.len());
        let (wp, xp) = (w.as_ptr(), x.as_ptr());
        let mut total = 0i64;
        let mut i = 0;
        while i + 16 <= n {
            let end = (i + BLOCK).min(n);
            let (mut a0, mut a1) = (_mm256_setzero_si256(), _mm256_setzero_si256());
            // SAFETY: every load reads values `i..i + 16` or `i + 16..i + 32` below `end <= n`.
            unsafe {
                while i + 32 <= end {
                    a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(weights16(wp.add(i)), T::load16(xp.add(i))));
                    a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(weights16(wp.add(i + 16)), T::load16(xp.add(i + 16))));
                    i += 32;
                }
                if i + 16 <= end {
                    a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(weights16(wp.add(i)), T::load16(xp.add(i))));
                    i += 16;
                }
                total += hsum(_mm256_add_epi32(a0, a1));
            }
        }
        // The last `n - i` values (the zip stops at `n`).
        if i < n {
            for (&a, b) in w.get(i..).unwrap_or_default().iter().zip(x.get(i..).unwrap_or_default()) {
                total += a as i64 * b.to_i32() as i64;
            }
        }
        total
    }

    /// `(dot(w0, x), dot(w1, x))` with each activation loaded and widened once; the caller
    /// guarantees `w0.len().min(x.len()) == w1.len().min(x.len())`.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot2<T: Act>(w0: &[i8], w1: &[i8], x: &[T]) -> (i64, i64) {
        // Two accumulators per row, each lane gets 2 products per 32 values: `BLOCK / 8` per lane.
        const BLOCK: usize = LANE_TERMS * 8;
        let n = w0.len().min(w1.len()).min(x.len());
        let (p0, p1, xp) = (w0.as_ptr(), w1.as_ptr(), x.as_ptr());
        let (mut t0, mut t1) = (0i64, 0i64);
        let mut i = 0;
        while i + 16 <= n {
            let end = (i + BLOCK).min(n);
            let z = _mm256_setzero_si256();
            let (mut a0, mut a1, mut b0, mut b1) = (z, z, z, z);
            // SAFETY: every load reads values `i..i + 16` or `i + 16..i + 32` below `end <= n`.
            unsafe {
                while i + 32 <= end {
                    let (xa, xb) = (T::load16(xp.add(i)), T::load16(xp.add(i + 16)));
                    a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(weights16(p0.add(i)), xa));
                    b0 = _mm256_add_epi32(b0, _mm256_madd_epi16(weights16(p1.add(i)), xa));
                    a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(weights16(p0.add(i + 16)), xb));
                    b1 = _mm256_add_epi32(b1, _mm256_madd_epi16(weights16(p1.add(i + 16)), xb));
                    i += 32;
                }
                if i + 16 <= end {
                    let xa = T::load16(xp.add(i));
                    a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(weights16(p0.add(i)), xa));
                    b0 = _mm256_add_epi32(b0, _mm256_madd_epi16(weights16(p1.add(i)), xa));
                    i += 16;
                }
                t0 += hsum(_mm256_add_epi32(a0, a1));
                t1 += hsum(_mm256_add_epi32(b0, b1));
            }
        }
        // The last `n - i` values (the zip stops at `n`).
        if i < n {
            let (w0, w1, x) = (w0.get(i..).unwrap_or_default(), w1.get(i..).unwrap_or_default(), x.get(i..).unwrap_or_default());
            for ((&a, &b), v) in w0.iter().zip(w1).zip(x) {
                let v = v.to_i32() as i64;
                t0 += a as i64 * v;
                t1 += b as i64 * v;
            }
        }
        (t0, t1)
    }

    /// [`Elem::dot2x2`]: `[w0 . a, w1 . a, w0 . b, w1 . b]` for the two patches `a`, `b` of
    /// `n = min(w0.len(), w1.len(), x.len() / 2)` values in the pair layout of
    /// [`super::super::pair_index`] (groups stored as values 0, 2, 1, 3 when `T::PAIR_SWAP`).
    ///
    /// 16 weights at a time: `x` then holds two vectors of 16 i16 with the 128-bit halves
    /// `a[0..4] b[0..4] | a[4..8] b[4..8]` and `a[8..12] b[8..12] | a[12..16] b[12..16]`;
    /// `vpunpcklqdq` of the two gives `a[0..4] a[8..12] | a[4..8] a[12..16]`, `vpunpckhqdq` the
    /// same of `b`, and one `vpshufb` puts the weights in that order (and in the groups' stored
    /// order) before they are widened.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot2x2<T: Act>(w0: &[i8], w1: &[i8], x: &[T]) -> [i64; 4] {
        // Each lane of each accumulator gets 2 products per 16 weights: `BLOCK / 8` per lane.
        const BLOCK: usize = LANE_TERMS * 8;
        let n = w0.len().min(w1.len()).min(x.len() / 2);
        let q4 = n / 4 * 4;
        let (p0, p1, xp) = (w0.as_ptr(), w1.as_ptr(), x.as_ptr());
        // Weight bytes 0-3, 8-11 | 4-7, 12-15, each group in its stored order.
        let order = if T::PAIR_SWAP {
            _mm_setr_epi8(0, 2, 1, 3, 8, 10, 9, 11, 4, 6, 5, 7, 12, 14, 13, 15)
        } else {
            _mm_setr_epi8(0, 1, 2, 3, 8, 9, 10, 11, 4, 5, 6, 7, 12, 13, 14, 15)
        };
        let mut acc = [0i64; 4];
        let mut i = 0;
        while i + 16 <= q4 {
            let end = (i + BLOCK).min(q4);
            let z = _mm256_setzero_si256();
            let (mut a0, mut a1, mut b0, mut b1) = (z, z, z, z);
            // SAFETY: weights `i..i + 16` and activations `2i..2i + 32` lie below `q4 <= n` and
            // `2 q4 <= x.len()`.
            unsafe {
                while i + 16 <= end {
                    let (x0, x1) = (T::load16(xp.add(2 * i)), T::load16(xp.add(2 * i + 16)));
                    let (xa, xb) = (_mm256_unpacklo_epi64(x0, x1), _mm256_unpackhi_epi64(x0, x1));
                    let u = _mm256_cvtepi8_epi16(_mm_shuffle_epi8(_mm_loadu_si128(p0.add(i).cast()), order));
                    let v = _mm256_cvtepi8_epi16(_mm_shuffle_epi8(_mm_loadu_si128(p1.add(i).cast()), order));
                    a0 = _mm256_add_epi32(a0, _mm256_madd_epi16(u, xa));
                    a1 = _mm256_add_epi32(a1, _mm256_madd_epi16(v, xa));
                    b0 = _mm256_add_epi32(b0, _mm256_madd_epi16(u, xb));
                    b1 = _mm256_add_epi32(b1, _mm256_madd_epi16(v, xb));
                    i += 16;
                }
                for (s, v) in acc.iter_mut().zip([a0, a1, b0, b1]) {
                    *s += hsum(v);
                }
            }
        }
        tail2x2(w0, w1, x, n, i, &mut acc);
        acc
    }

    /// The part of [`dot2x2`] from weight `i` (a multiple of 4) on, value by value: the whole
    /// groups left, then the `n % 4` last values of each patch.
    #[inline(always)]
    pub(super) fn tail2x2<T: Elem>(w0: &[i8], w1: &[i8], x: &[T], n: usize, i: usize, acc: &mut [i64; 4]) {
        let q4 = n / 4 * 4;
        if i >= q4 && q4 == n {
            // Nothing left (the usual case: the SIMD loop took every value).
            return;
        }
        let mut mac = |u: i8, v: i8, a: T, b: T| {
            let (u, v, a, b) = (u as i64, v as i64, a.to_i32() as i64, b.to_i32() as i64);
            acc[0] += u * a;
            acc[1] += v * a;
            acc[2] += u * b;
            acc[3] += v * b;
        };
        // Whole groups `i..q4`: 4 weights of each row, then 8 activations `a[0..4] b[0..4]`, a
        // group's values stored in the order 0, 2, 1, 3 when `T::PAIR_SWAP` (the weights are put
        // in that order; the sums are exact, so the order of the additions does not matter).
        if let (Some(u), Some(v), Some(xs)) = (w0.get(i..q4), w1.get(i..q4), x.get(2 * i..2 * q4)) {
            for ((u, v), xs) in u.chunks_exact(4).zip(v.chunks_exact(4)).zip(xs.chunks_exact(8)) {
                let (Some(&u), Some(&v), Some((a, b))) = (u.first_chunk::<4>(), v.first_chunk::<4>(), xs.split_first_chunk::<4>()) else {
                    continue;
                };
                let (u, v) = if T::PAIR_SWAP { ([u[0], u[2], u[1], u[3]], [v[0], v[2], v[1], v[3]]) } else { (u, v) };
                for (((&u, &v), &a), &b) in u.iter().zip(&v).zip(a).zip(b) {
                    mac(u, v, a, b);
                }
            }
        }
        // The last `r = n % 4` values: `a[0..r]` then `b[0..r]`.
        let r = n - q4;
        if let (Some(u), Some(v), Some((a, b))) = (w0.get(q4..n), w1.get(q4..n), x.get(2 * q4..2 * n).and_then(|xs| xs.split_at_checked(r))) {
            for (((&u, &v), &a), &b) in u.iter().zip(v).zip(a).zip(b) {
                mac(u, v, a, b);
            }
        }
    }

    /// Widest query/key the attention kernels take (see [`Split`]).
    pub const MAX_QK: usize = 128;

    /// Keys per block of the attention kernels (logits and weights kept on the stack).
    const KEYS: usize = 64;

    /// A query split as `q = 256 qh + ql` (`qh = q >> 8` in `[-128, 127]`, `ql = q & 255`), 16
    /// values per vector. `vpmaddwd` of `q` itself against a key is not exact (two products of
    /// `-32768 * -32768` sum to `2^31`); of the halves it is, and the lane sums stay small: with
    /// `c <= 128` values, `|sum qh k| <= 128 * 2^22 = 2^29` and `|sum ql k| < 128 * 2^23 = 2^30`,
    /// in any grouping, so they add in i32 and the logit is `256 sum(qh k) + sum(ql k)` in i64.
    pub struct Split {
        /// `(qh, ql)` of each 16 values; the first `chunks` are the query's.
        hl: [(__m256i, __m256i); MAX_QK / 16],
        chunks: usize,
    }

    impl Split {
        /// Splits `q` (`q.len()` a multiple of 16, at most [`MAX_QK`]).
        ///
        /// # Safety
        /// The CPU has AVX2.
        #[target_feature(enable = "avx2")]
        pub unsafe fn new(q: &[i16]) -> Self {
            assert!(q.len().is_multiple_of(16) && q.len() <= MAX_QK);
            let z = _mm256_setzero_si256();
            let mut s = Split { hl: [(z, z); MAX_QK / 16], chunks: q.len() / 16 };
            for (hl, v) in s.hl.iter_mut().zip(q.chunks_exact(16)) {
                // SAFETY: the 16 values of `v`.
                let v = unsafe { _mm256_loadu_si256(v.as_ptr().cast()) };
                *hl = (_mm256_srai_epi16::<8>(v), _mm256_and_si256(v, _mm256_set1_epi16(0xFF)));
            }
            s
        }

        /// `(sum qh k, sum ql k)` as 8 i32 lanes each, for the key at `k` (`16 chunks` values).
        #[inline(always)]
        unsafe fn parts(&self, k: *const i16) -> (__m256i, __m256i) {
            // SAFETY: the caller guarantees `16 chunks` readable values and AVX2.
            unsafe {
                let (mut h, mut l) = (_mm256_setzero_si256(), _mm256_setzero_si256());
                // At most `MAX_QK / 16` chunks: over the array, the loop unrolls in full.
                for (i, &(qh, ql)) in self.hl.iter().take(self.chunks).enumerate() {
                    let kv = _mm256_loadu_si256(k.add(16 * i).cast());
                    h = _mm256_add_epi32(h, _mm256_madd_epi16(qh, kv));
                    l = _mm256_add_epi32(l, _mm256_madd_epi16(ql, kv));
                }
                (h, l)
            }
        }
    }

    /// Lane sums of four vectors: `[sum a, sum b, sum c, sum d]` (sums within the bounds of
    /// [`Split`], so the i32 additions are exact).
    #[inline(always)]
    unsafe fn hsum4(a: __m256i, b: __m256i, c: __m256i, d: __m256i) -> __m128i {
        // SAFETY: register-only AVX2 instructions; the caller guarantees AVX2.
        unsafe {
            let t = _mm256_hadd_epi32(_mm256_hadd_epi32(a, b), _mm256_hadd_epi32(c, d));
            _mm_add_epi32(_mm256_castsi256_si128(t), _mm256_extracti128_si256::<1>(t))
        }
    }

    /// Exact logits `q . k_j` (i64) of the `out.len()` keys stored from `keys` (`16 s.chunks`
    /// values each); the caller guarantees that they are readable.
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn logits(s: &Split, keys: *const i16, out: &mut [i64]) {
        let c = 16 * s.chunks;
        let mut quads = out.chunks_exact_mut(4);
        // The key of the next logit.
        let mut k = keys;
        // SAFETY: `k` points at key `j` (of `out.len()`, the caller's guarantee) for the logits
        // `j..j + 4` of `o` (or `j`); after the last, at most one past the keys.
        unsafe {
            for o in &mut quads {
                let (h0, l0) = s.parts(k);
                let (h1, l1) = s.parts(k.add(c));
                let (h2, l2) = s.parts(k.add(2 * c));
                let (h3, l3) = s.parts(k.add(3 * c));
                let h = _mm256_slli_epi64::<8>(_mm256_cvtepi32_epi64(hsum4(h0, h1, h2, h3)));
                let l = _mm256_cvtepi32_epi64(hsum4(l0, l1, l2, l3));
                _mm256_storeu_si256(o.as_mut_ptr().cast(), _mm256_add_epi64(h, l));
                k = k.add(4 * c);
            }
            for o in quads.into_remainder() {
                let (h, l) = s.parts(k);
                let z = _mm256_setzero_si256();
                let v = hsum4(h, l, z, z);
                *o = 256 * _mm_cvtsi128_si32(v) as i64 + _mm_extract_epi32::<1>(v) as i64;
                k = k.add(c);
            }
        }
    }

    /// `exp_q11` at the table's knots, as i32: entry `i` is `EXP[i]` of `arith` (the input
    /// `32 i - 32768` falls on knot `i`, where the interpolation returns the entry itself).
    pub(crate) fn exp_knots() -> &'static [i32; 1025] {
        static T: std::sync::OnceLock<[i32; 1025]> = std::sync::OnceLock::new();
        T.get_or_init(|| core::array::from_fn(|i| crate::arith::lut::exp_q11(32 * i as i32 - 32768)))
    }

    /// `e[j] = weight(l[j], max, m)` ([`weight`]: `exp_q11(clamp(requantize(l - max, m)))`), the
    /// same integers, 8 logits at a time: where all 8 differences fit in i32 (and `m.shift` is in
    /// `1..=62`), `requantize` is its 64-bit fast path (`vpmuldq`, the rounding constant, an
    /// arithmetic shift built from logical ones), and `exp_q11` reads its two knots with
    /// `vpgatherdd` (knot 1023 at fraction 32 for the input 0: `a + (b - a) = b`, knot 1024).
    /// Other groups, and the last `len % 8`, take the scalar [`weight`].
    ///
    /// # Safety
    /// The CPU has AVX2.
    #[target_feature(enable = "avx2")]
    pub unsafe fn weights(l: &[i64], max: i64, m: Multiplier, e: &mut [i32]) {
        // Logits done 8 at a time: the whole groups of 8 of `min(l.len(), e.len())`, or none.
        let mut done = 0;
        if (1..=62).contains(&m.shift) {
            done = l.len().min(e.len()) / 8 * 8;
            let t = exp_knots();
            let (mx, mm) = (_mm256_set1_epi64x(max), _mm256_set1_epi64x(m.m as i64));
            let half = _mm256_set1_epi64x(1i64 << (m.shift - 1));
            let sh = _mm_cvtsi32_si128(m.shift as i32);
            let (lo32, hi32) = (_mm256_set1_epi64x(i32::MIN as i64), _mm256_set1_epi64x(i32::MAX as i64));
            let (lo, hi) = (_mm256_set1_epi64x(-32768), _mm256_setzero_si256());
            let z = _mm256_setzero_si256();
            // Requantised and clamped differences of 4 logits, or `None` if one does not fit i32.
            let four = |p: *const i64| {
                // SAFETY: 4 logits from `p` (half of a group of 8, the loop's chunk).
                let d = _mm256_sub_epi64(unsafe { _mm256_loadu_si256(p.cast()) }, mx);
                let out = _mm256_or_si256(_mm256_cmpgt_epi64(d, hi32), _mm256_cmpgt_epi64(lo32, d));
                if _mm256_movemask_epi8(out) != 0 {
                    return None;
                }
                // |d m| < 2^62 and the constant is at most 2^61: no overflow.
                let v = _mm256_add_epi64(_mm256_mul_epi32(d, mm), half);
                let sign = _mm256_cmpgt_epi64(z, v);
                let r = _mm256_xor_si256(_mm256_srl_epi64(_mm256_xor_si256(v, sign), sh), sign);
                let r = _mm256_blendv_epi8(r, lo, _mm256_cmpgt_epi64(lo, r));
                Some(_mm256_blendv_epi8(r, hi, _mm256_cmpgt_epi64(r, hi)))
            };
            let even = _mm256_setr_epi32(0, 2, 4, 6, 0, 2, 4, 6);
            for (lc, ec) in l.chunks_exact(8).zip(e.chunks_exact_mut(8)) {
                // SAFETY: `lc` holds 8 logits.
                let (Some(a), Some(b)) = (four(lc.as_ptr()), four(unsafe { lc.as_ptr().add(4) })) else {
                    for (ek, &lk) in ec.iter_mut().zip(lc) {
                        *ek = weight(lk, max, m);
                    }
                    continue;
                };
                // The 8 values (in [-32768, 0]) as i32 lanes.
                let d = _mm256_permute2x128_si256::<0x20>(_mm256_permutevar8x32_epi32(a, even), _mm256_permutevar8x32_epi32(b, even));
                let u = _mm256_add_epi32(d, _mm256_set1_epi32(32768));
                let i = _mm256_min_epi32(_mm256_srli_epi32::<5>(u), _mm256_set1_epi32(1023));
                let f = _mm256_sub_epi32(u, _mm256_slli_epi32::<5>(i));
                // SAFETY: knots `i` and `i + 1` with `i <= 1023` lie in the 1025-entry table.
                let (ka, kb) = unsafe { (_mm256_i32gather_epi32::<4>(t.as_ptr(), i), _mm256_i32gather_epi32::<4>(t.as_ptr().add(1), i)) };
                let r = _mm256_srai_epi32::<5>(_mm256_add_epi32(_mm256_mullo_epi32(_mm256_sub_epi32(kb, ka), f), _mm256_set1_epi32(16)));
                // SAFETY: `ec` has room for 8 values.
                unsafe { _mm256_storeu_si256(ec.as_mut_ptr().cast(), _mm256_add_epi32(ka, r)) };
            }
        }
        // The rest, up to `min(l.len(), e.len())` (the zip's end).
        for (ek, &lk) in e.get_mut(done..).unwrap_or_default().iter_mut().zip(l.get(done..).unwrap_or_default()) {
            *ek = weight(lk, max, m);
        }
    }

    /// [`super::super::attention::query_stats`]: `(max_j q . k_j, sum_j weight(q . k_j, max, m))`
    /// over the keys in `keys` (`q.len()` values each), the same integers.
    ///
    /// # Safety
    /// The CPU has AVX2; `q.len()` is a multiple of 16, at most [`MAX_QK`].
    #[target_feature(enable = "avx2")]
    pub unsafe fn query_stats(q: &[i16], keys: &[i16], m: Multiplier) -> (i64, i64) {
        let c = q.len();
        let n = keys.len() / c;
        // SAFETY: the caller's guarantees.
        let s = unsafe { Split::new(q) };
        // The `n` whole keys, in blocks of `KEYS` (`nb` each, fewer in the last).
        let keys = keys.get(..n * c).unwrap_or_default();
        let (mut l, mut e) = ([0i64; KEYS], [0i32; KEYS]);
        let mut max = None;
        for kb in keys.chunks(KEYS * c) {
            let Some(l) = l.get_mut(..kb.len() / c) else {
                break;
            };
            // SAFETY: the `l.len()` keys of `kb`.
            unsafe { logits(&s, kb.as_ptr(), l) };
            let bm = l.iter().copied().max();
            max = max.max(bm);
        }
        let max = max.unwrap_or(0);
        let mut sum = 0i64;
        for kb in keys.chunks(KEYS * c) {
            let nb = kb.len() / c;
            let (Some(l), Some(e)) = (l.get_mut(..nb), e.get_mut(..nb)) else {
                break;
            };
            // SAFETY: as above.
            unsafe { logits(&s, kb.as_ptr(), l) };
            // SAFETY: the CPU has AVX2.
            unsafe { weights(l, max, m, e) };
            sum += e.iter().map(|&v| v as i64).sum::<i64>();
        }
        (max, sum)
    }

    /// The accumulation of [`super::super::attention::aggregate_query`]: adds
    /// `sum_j e_j v_j` into `acc` (`cv` values), `e_j = weight(q . k_j, max, m)`, over the keys in
    /// `keys` (`q.len()` values each) and their values in `values` (`cv` each).
    ///
    /// Keys go in blocks of `KEYS`: their logits ([`logits`]) and weights (the scalar
    /// [`weight`], so the same integers) first, then each 16 value channels over the block's keys
    /// two at a time. A weight `e` in `[0, 32768]` (all that `exp_q11` gives) is split as
    /// `256 eh + el` (`eh <= 128`, `el <= 255`); `vpmaddwd` of the interleaved values `(v_j, v_k)`
    /// against `(eh_j, eh_k)` and against `(el_j, el_k)` gives sums below `2^24` in magnitude, 32
    /// pairs of which add in i32 without overflow; each block adds `256 sum_h + sum_l` into the
    /// i64 `acc`. A weight outside that range counts 0 there and its key is added on its own;
    /// channels past the last multiple of 16 take the scalar loop.
    ///
    /// # Safety
    /// The CPU has AVX2; `q.len()` is a multiple of 16, at most [`MAX_QK`]; `acc.len() == cv > 0`.
    #[target_feature(enable = "avx2")]
    #[allow(clippy::too_many_arguments)]
    pub unsafe fn aggregate(q: &[i16], keys: &[i16], values: &[i16], cv: usize, max: i64, m: Multiplier, acc: &mut [i64]) {
        let c = q.len();
        let n = (keys.len() / c).min(values.len() / cv);
        let cv16 = cv / 16 * 16;
        // The channels taken 16 at a time, and the rest (nothing done if `acc` is short).
        let Some(acc) = acc.get_mut(..cv) else {
            return;
        };
        let Some((acc16, acc_tail)) = acc.split_at_mut_checked(cv16) else {
            return;
        };
        // SAFETY: the caller's guarantees.
        let s = unsafe { Split::new(q) };
        let in_range = |e: i32| (0..=32768).contains(&e);
        let (mut l, mut e) = ([0i64; KEYS], [0i32; KEYS]);
        // Per pair of keys: `(eh_j, eh_k)` and `(el_j, el_k)` as i16 pairs in an i32.
        let (mut wh, mut wl) = ([0i32; KEYS / 2], [0i32; KEYS / 2]);
        // The `n` whole keys and their values, in blocks of `KEYS` (`nb` each, fewer in the last).
        let (keys, values) = (keys.get(..n * c).unwrap_or_default(), values.get(..n * cv).unwrap_or_default());
        for (kb, vals) in keys.chunks(KEYS * c).zip(values.chunks(KEYS * cv)) {
            let nb = kb.len() / c;
            let (Some(l), Some(e)) = (l.get_mut(..nb), e.get_mut(..nb)) else {
                break;
            };
            // SAFETY: the `nb` keys of `kb`.
            unsafe { logits(&s, kb.as_ptr(), l) };
            // SAFETY: the CPU has AVX2.
            unsafe { weights(l, max, m, e) };
            let split = |e: i32| if in_range(e) { ((e >> 8) as u32, (e & 255) as u32) } else { (0, 0) };
            let pack = |e0: i32, e1: i32| {
                let ((h0, l0), (h1, l1)) = (split(e0), split(e1));
                ((h0 | h1 << 16) as i32, (l0 | l1 << 16) as i32)
            };
            for ((h, w), ep) in wh.iter_mut().zip(wl.iter_mut()).zip(e.chunks_exact(2)) {
                if let &[e0, e1] = ep {
                    (*h, *w) = pack(e0, e1);
                }
            }
            // An odd last key pairs with a zero weight.
            if let (&[e0], Some(h), Some(w)) = (e.chunks_exact(2).remainder(), wh.get_mut(nb / 2), wl.get_mut(nb / 2)) {
                (*h, *w) = pack(e0, 0);
            }
            if !e.iter().all(|&e| in_range(e)) {
                for (&ej, row) in e.iter().zip(vals.chunks_exact(cv)).filter(|(e, _)| !in_range(**e)) {
                    for (a, &v) in acc16.iter_mut().zip(row) {
                        *a += ej as i64 * v as i64;
                    }
                }
            }
            for (a16, c0) in acc16.chunks_exact_mut(16).zip((0..cv16).step_by(16)) {
                let z = _mm256_setzero_si256();
                // Channels 0-3 and 8-11 of the 16 (`lo`), then 4-7 and 12-15 (`hi`).
                let (mut hlo, mut hhi, mut llo, mut lhi) = (z, z, z, z);
                let mut pair = |vj: __m256i, vk: __m256i, wh: i32, wl: i32| {
                    let (h, l) = (_mm256_set1_epi32(wh), _mm256_set1_epi32(wl));
                    let (lo, hi) = (_mm256_unpacklo_epi16(vj, vk), _mm256_unpackhi_epi16(vj, vk));
                    hlo = _mm256_add_epi32(hlo, _mm256_madd_epi16(lo, h));
                    hhi = _mm256_add_epi32(hhi, _mm256_madd_epi16(hi, h));
                    llo = _mm256_add_epi32(llo, _mm256_madd_epi16(lo, l));
                    lhi = _mm256_add_epi32(lhi, _mm256_madd_epi16(hi, l));
                };
                // Two keys (`2 cv` values) at a time, then the odd last key (`cv` values, or none).
                let mut rows = vals.chunks_exact(2 * cv);
                // SAFETY: channels `c0..c0 + 16 <= cv16 <= cv` of each key of `r`.
                unsafe {
                    for (r, (&h, &l)) in (&mut rows).zip(wh.iter().zip(&wl)) {
                        let v = r.as_ptr().add(c0);
                        pair(_mm256_loadu_si256(v.cast()), _mm256_loadu_si256(v.add(cv).cast()), h, l);
                    }
                }
                if let (Some(v), Some(&h), Some(&l)) = (rows.remainder().get(c0..c0 + 16), wh.get(nb / 2), wl.get(nb / 2)) {
                    // SAFETY: the 16 values of `v`.
                    pair(unsafe { _mm256_loadu_si256(v.as_ptr().cast()) }, z, h, l);
                }
                // The 128-bit halves back in channel order: channels 0-7, then 8-15.
                let (mut th, mut tl) = ([0i32; 16], [0i32; 16]);
                // SAFETY: `th` and `tl` hold 16 i32 each: 8 from element 0, 8 from element 8.
                unsafe {
                    _mm256_storeu_si256(th.as_mut_ptr().cast(), _mm256_permute2x128_si256::<0x20>(hlo, hhi));
                    _mm256_storeu_si256(th.as_mut_ptr().add(8).cast(), _mm256_permute2x128_si256::<0x31>(hlo, hhi));
                    _mm256_storeu_si256(tl.as_mut_ptr().cast(), _mm256_permute2x128_si256::<0x20>(llo, lhi));
                    _mm256_storeu_si256(tl.as_mut_ptr().add(8).cast(), _mm256_permute2x128_si256::<0x31>(llo, lhi));
                }
                for ((a, &h), &l) in a16.iter_mut().zip(&th).zip(&tl) {
                    *a += 256 * h as i64 + l as i64;
                }
            }
            if !acc_tail.is_empty() {
                for (&ej, row) in e.iter().zip(vals.chunks_exact(cv)) {
                    for (a, &v) in acc_tail.iter_mut().zip(row.get(cv16..).unwrap_or_default()) {
                        *a += ej as i64 * v as i64;
                    }
                }
            }
        }
    }
}

/// AVX-512 VNNI kernels, with `vpdpbusd` on 256-bit vectors (EVEX; AVX-512 VL) written in `asm!`
/// (the AVX-512 intrinsics need a newer compiler than the crate's minimum). Callers guarantee that
/// the CPU has AVX2, AVX-512 VNNI and AVX-512 VL.
pub mod vnni {
    use super::*;
    use core::arch::asm;

    /// `acc += ` the sums of four products of the unsigned bytes of `x` and the signed bytes of
    /// `w`, per i32 lane (`vpdpbusd`: no saturation, exact while the lane fits). A register-only
    /// instruction; used inside `unsafe` blocks of functions whose callers guarantee the CPU has it.
    macro_rules! dpbusd {
        ($acc:ident, $x:expr, $w:expr) => {
            asm!("vpdpbusd {a}, {x}, {w}", a = inout(ymm_reg) $acc, x = in(ymm_reg) $x, w = in(ymm_reg) $w, options(pure, nomem, nostack, preserves_flags))
        };
    }

    /// [`Elem::dot2x2`] of u8 activations: the pair layout's 32 bytes `a[0..4] b[0..4] ...
    /// a[12..16] b[12..16]` are taken as they are, against each weight group of four repeated
    /// (`vpermd`: `w[0..4] w[0..4] w[4..8] w[4..8] ...`); even i32 lanes then hold products of
    /// `a`, odd ones of `b`. A product is below `2^15` in magnitude; per block of 8192 weights each
    /// of the four accumulators takes at most 257 instructions of 4 products, so the lanes (two
    /// accumulators added) stay below `2056 * 2^15 < 2^27`: exact.
    ///
    /// # Safety
    /// The CPU has AVX2, AVX-512 VNNI and AVX-512 VL.
    #[target_feature(enable = "avx2")]
    pub unsafe fn dot2x2_u8(w0: &[i8], w1: &[i8], x: &[u8]) -> [i64; 4] {
        const BLOCK: usize = 8192;
        let n = w0.len().min(w1.len()).min(x.len() / 2);
        let q4 = n / 4 * 4;
        let (p0, p1, xp) = (w0.as_ptr(), w1.as_ptr(), x.as_ptr());
        let dup = _mm256_setr_epi32(0, 0, 1, 1, 2, 2, 3, 3);
        // SAFETY (both): 16 weights from `p`, below `q4` (the loops' conditions).
        let weights = |p: *const i8| _mm256_permutevar8x32_epi32(_mm256_castsi128_si256(unsafe { _mm_loadu_si128(p.cast()) }), dup);
        let mut acc = [0i64; 4];
        let mut i = 0;
        while i + 16 <= q4 {
            let end = (i + BLOCK).min(q4);
            let z = _mm256_setzero_si256();
            // Two accumulators per weight row: `vpdpbusd` has a latency of several cycles.
            let (mut a0, mut a1, mut c0, mut c1) = (z, z, z, z);
            // SAFETY: activations `2i..2i + 64` (or `+ 32`) lie below `2 q4 <= x.len()`; the CPU
            // has `vpdpbusd` (the caller's guarantee).
            unsafe {
                while i + 32 <= end {
                    let (xa, xc) = (_mm256_loadu_si256(xp.add(2 * i).cast()), _mm256_loadu_si256(xp.add(2 * i + 32).cast()));
                    let (u, v) = (weights(p0.add(i)), weights(p1.add(i)));
                    let (u2, v2) = (weights(p0.add(i + 16)), weights(p1.add(i + 16)));
                    dpbusd!(a0, xa, u);
                    dpbusd!(a1, xa, v);
                    dpbusd!(c0, xc, u2);
                    dpbusd!(c1, xc, v2);
                    i += 32;
                }
                if i + 16 <= end {
                    let xa = _mm256_loadu_si256(xp.add(2 * i).cast());
                    let (u, v) = (weights(p0.add(i)), weights(p1.add(i)));
                    dpbusd!(a0, xa, u);
                    dpbusd!(a1, xa, v);
                    i += 16;
                }
                let (mut l0, mut l1) = ([0i32; 8], [0i32; 8]);
                _mm256_storeu_si256(l0.as_mut_ptr().cast(), _mm256_add_epi32(a0, c0));
                _mm256_storeu_si256(l1.as_mut_ptr().cast(), _mm256_add_epi32(a1, c1));
                // The sums of the even lanes (patch `a`) and of the odd ones (patch `b`).
                let lanes = |[v0, v1, v2, v3, v4, v5, v6, v7]: [i32; 8]| {
                    (v0 as i64 + v2 as i64 + v4 as i64 + v6 as i64, v1 as i64 + v3 as i64 + v5 as i64 + v7 as i64)
                };
                let ((sa0, sb0), (sa1, sb1)) = (lanes(l0), lanes(l1));
                acc[0] += sa0;
                acc[1] += sa1;
                acc[2] += sb0;
                acc[3] += sb1;
            }
        }
        avx2::tail2x2(w0, w1, x, n, i, &mut acc);
        acc
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::testutil::Rng;
    use super::super::{dot_plain, pair_index};
    use super::*;

    /// The two patches stored in the pair layout of `n` values.
    fn pair<T: Elem>(a: &[T], b: &[T]) -> Vec<T> {
        let n = a.len();
        let mut x = vec![T::default(); 2 * n];
        for j in 0..n {
            x[pair_index(n, j, false, T::PAIR_SWAP)] = a[j];
            x[pair_index(n, j, true, T::PAIR_SWAP)] = b[j];
        }
        x
    }

    /// Every path (AVX2 kernels directly, `Elem` dispatch) against the plain i64 sums.
    fn check<T: avx2::Act>(w0: &[i8], w1: &[i8], a: &[T], b: &[T], what: &str) {
        let n = w0.len();
        let want = [dot_plain(w0, a), dot_plain(w1, a), dot_plain(w0, b), dot_plain(w1, b)];
        let x = pair(a, b);
        assert_eq!(T::dot(w0, a), want[0], "dot {what} n {n}");
        assert_eq!(T::dot2(w0, w1, a), (want[0], want[1]), "dot2 {what} n {n}");
        assert_eq!(T::dot2x2(w0, w1, &x), want, "dot2x2 {what} n {n}");
        if std::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU has AVX2.
            unsafe {
                assert_eq!(avx2::dot(w0, a), want[0], "avx2 dot {what} n {n}");
                assert_eq!(avx2::dot(w1, b), want[3], "avx2 dot {what} n {n}");
                assert_eq!(avx2::dot2(w0, w1, b), (want[2], want[3]), "avx2 dot2 {what} n {n}");
                assert_eq!(avx2::dot2x2(w0, w1, &x), want, "avx2 dot2x2 {what} n {n}");
            }
        }
        if let Some(x) = cast::<T, u8>(&x) {
            if std::is_x86_feature_detected!("avx512vnni") && std::is_x86_feature_detected!("avx512vl") {
                // SAFETY: the CPU has AVX2 (implied), AVX-512 VNNI and VL.
                assert_eq!(unsafe { vnni::dot2x2_u8(w0, w1, x) }, want, "vnni dot2x2 {what} n {n}");
            }
        }
    }

    fn lengths() -> impl Iterator<Item = usize> {
        (0..=1200).chain([2047, 2048, 2049, 4096 + 17, 5760])
    }

    fn random<T: avx2::Act>(seed: u64, act: impl Fn(&mut Rng) -> T, name: &str) {
        let mut r = Rng(seed);
        for n in lengths() {
            let w0: Vec<i8> = (0..n).map(|_| r.i8()).collect();
            let w1: Vec<i8> = (0..n).map(|_| r.i8()).collect();
            let a: Vec<T> = (0..n).map(|_| act(&mut r)).collect();
            let b: Vec<T> = (0..n).map(|_| act(&mut r)).collect();
            check(&w0, &w1, &a, &b, name);
        }
    }

    #[test]
    fn random_inputs_give_the_exact_sums() {
        random(1, |r| r.i8() as u8, "u8");
        random(2, |r| r.i8(), "i8");
        random(3, |r| r.i16(), "i16");
    }

    /// Extreme values: all products at the largest magnitude, of one sign or mixed, at every
    /// length (the i32 lane bounds).
    #[test]
    fn extremes_give_the_exact_sums() {
        fn run<T: avx2::Act>(vals: &[T], name: &str) {
            let mut r = Rng(9);
            for n in lengths() {
                for &wv in &[-128i8, 127] {
                    for &xv in vals {
                        for &wu in &[-128i8, 127] {
                            let (w0, w1) = (vec![wv; n], vec![wu; n]);
                            let a = vec![xv; n];
                            // `b`: random picks among the extremes.
                            let b: Vec<T> = (0..n).map(|_| vals[r.below(vals.len() as u64) as usize]).collect();
                            check(&w0, &w1, &a, &b, name);
                        }
                    }
                }
            }
        }
        run(&[255u8, 0, 1], "u8");
        run(&[-128i8, 127], "i8");
        run(&[i16::MIN, i16::MAX], "i16");
    }

    /// A wrong pair layout (unswapped i16, or swapped u8) must be noticed: the test above would
    /// pass for a kernel that ignored the layout only if the order did not matter.
    #[test]
    fn pair_layout_matters() {
        let n = 64;
        let w0: Vec<i8> = (0..n).map(|j| j as i8).collect();
        let w1: Vec<i8> = (0..n).map(|j| (3 * j) as i8).collect();
        let a: Vec<i16> = (0..n).map(|j| (j * j) as i16).collect();
        let b: Vec<i16> = (0..n).map(|j| (1000 - 7 * j as i64) as i16).collect();
        let x = pair(&a, &b);
        let mut unswapped = vec![0i16; 2 * n];
        for j in 0..n {
            unswapped[pair_index(n, j, false, false)] = a[j];
            unswapped[pair_index(n, j, true, false)] = b[j];
        }
        assert_ne!(x, unswapped);
        let want = [dot_plain(&w0, &a), dot_plain(&w1, &a), dot_plain(&w0, &b), dot_plain(&w1, &b)];
        assert_eq!(i16::dot2x2(&w0, &w1, &x), want);
        assert_ne!(i16::dot2x2(&w0, &w1, &unswapped), want);
    }

    /// Portable attention statistics and accumulation (as in `attention`, logits in plain i64).
    fn attention_ref(q: &[i16], keys: &[i16], values: &[i16], cv: usize, m: Multiplier) -> ((i64, i64), Vec<i64>) {
        let c = q.len();
        let n = (keys.len() / c).min(values.len() / cv);
        let logit = |j: usize| q.iter().zip(&keys[j * c..(j + 1) * c]).map(|(a, b)| *a as i64 * *b as i64).sum::<i64>();
        let max = (0..keys.len() / c).map(logit).max().unwrap_or(0);
        let sum = (0..keys.len() / c).map(|j| weight(logit(j), max, m) as i64).sum();
        let mut acc = vec![0i64; cv];
        for j in 0..n {
            let e = weight(logit(j), max, m) as i64;
            for (a, v) in acc.iter_mut().zip(&values[j * cv..(j + 1) * cv]) {
                *a += e * *v as i64;
            }
        }
        ((max, sum), acc)
    }

    /// Query/key values: random, random extremes, all `-32768`, or small (spread logits).
    fn qk_values(r: &mut Rng, kind: usize, len: usize) -> Vec<i16> {
        (0..len)
            .map(|_| match kind {
                0 => r.i16(),
                1 => [i16::MIN, i16::MAX][r.below(2) as usize],
                2 => i16::MIN,
                _ => r.i16() / 256,
            })
            .collect()
    }

    /// The vector weights against the scalar `weight`: differences around every i32 and clamp
    /// boundary, positive ones, and shifts outside the fast path.
    #[test]
    fn weights_give_the_same_integers() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut r = Rng(13);
        let mut mults = vec![Multiplier { m: 1 << 30, shift: 46 }, Multiplier { m: i32::MAX, shift: 1 }, Multiplier { m: i32::MAX, shift: 62 }, Multiplier { m: 1 << 30, shift: 63 }, Multiplier::ZERO]; // shift is [1, 126] (arith::Multiplier)
        for _ in 0..40 {
            mults.push(Multiplier { m: (1 << 30) + r.below(1 << 30) as i32, shift: 1 + r.below(62) as u8 });
        }
        let edges = [0i64, -1, 1, i32::MIN as i64, i32::MIN as i64 - 1, i32::MAX as i64, i32::MAX as i64 + 1, -(1 << 40), i64::MIN / 2, 1 << 40];
        for m in mults {
            let max = r.next() as i64 >> 20;
            for len in [0, 1, 7, 8, 9, 64] {
                for kind in 0..4 {
                    let l: Vec<i64> = (0..len)
                        .map(|_| match kind {
                            0 => max - (r.below(1 << 36) as i64),
                            1 => max - (r.below(1 << 20) as i64),
                            2 => max.wrapping_add(edges[r.below(edges.len() as u64) as usize] + r.below(3) as i64 - 1),
                            _ => max - (r.below(1 << (m.shift.clamp(1, 62) as u64 + 16).min(62)) as i64),
                        })
                        .collect();
                    let want: Vec<i32> = l.iter().map(|&v| weight(v, max, m)).collect();
                    let mut got = vec![-1i32; len];
                    // SAFETY: the CPU has AVX2.
                    unsafe { avx2::weights(&l, max, m, &mut got) };
                    assert_eq!(got, want, "{m:?} max {max} kind {kind}");
                }
            }
        }
    }

    #[test]
    fn attention_gives_the_same_integers() {
        if !std::is_x86_feature_detected!("avx2") {
            return;
        }
        let mut r = Rng(11);
        // Spread weights, every weight exp(0) = 32768 (logit differences round to 0), most 0.
        let mults = [Multiplier { m: 1 << 30, shift: 46 }, Multiplier { m: 1 << 30, shift: 40 }, Multiplier { m: 1 << 30, shift: 62 }, Multiplier { m: i32::MAX, shift: 20 }];
        let mut spread = 0;
        for c in [16, 32, 48, 128] {
            for cv in [1, 15, 16, 17, 32, 64, 70] {
                for n in [0, 1, 2, 3, 4, 5, 63, 64, 65, 127, 130, 300] {
                    for kind in 0..4 {
                        let q = qk_values(&mut r, kind, c);
                        let keys = qk_values(&mut r, kind, n * c);
                        let values: Vec<i16> = (0..n * cv).map(|_| if kind == 0 { r.i16() } else { [i16::MIN, i16::MAX][r.below(2) as usize] }).collect();
                        for &m in &mults {
                            let (stats, want) = attention_ref(&q, &keys, &values, cv, m);
                            // SAFETY: the CPU has AVX2; `c` is a multiple of 16 up to `MAX_QK`.
                            let got = unsafe { avx2::query_stats(&q, &keys, m) };
                            assert_eq!(got, stats, "stats c {c} n {n} kind {kind} {m:?}");
                            let mut acc = vec![0i64; cv];
                            // SAFETY: as above; `acc.len() == cv > 0`.
                            unsafe { avx2::aggregate(&q, &keys, &values, cv, stats.0, m, &mut acc) };
                            assert_eq!(acc, want, "aggregate c {c} cv {cv} n {n} kind {kind} {m:?}");
                            // The dispatch (off under `MUIR_X86_SIMD=0`).
                            assert_eq!(query_stats(&q, &keys, m), has_avx2().then_some(stats));
                            let mut acc = vec![0i64; cv];
                            assert_eq!(aggregate(&q, &keys, &values, cv, stats.0, m, &mut acc), has_avx2());
                            assert_eq!(acc, if has_avx2() { want } else { vec![0; cv] });
                            if n > 1 && stats.1 > 32768 && stats.1 < 32768 * n as i64 {
                                spread += 1;
                            }
                        }
                    }
                }
            }
        }
        assert!(spread > 100, "weights not spread: {spread}");
        // Widths the AVX2 forms leave to the portable loops.
        assert_eq!(query_stats(&[1; 8], &[1; 80], mults[0]), None);
        assert!(!aggregate(&[1; 8], &[1; 80], &[1; 10], 1, 0, mults[0], &mut [0]));
    }

    // The whole `aggregate_query` (AVX2 accumulation, then the portable output) against the
    // plain twin: `attention::tests::streaming_matches_matrix` at the model's shape.
}
