//! [`super::aggregate_query`] for many queries at once on AVX-512 VNNI (host, x86-64): the
//! aggregation of one row of queries against every key, two queries at a time.
//!
//! Per call, the keys are transposed into channel pairs along keys (`kt[g][j]`: channels
//! `2g, 2g+1` of key `j`, one i32) and the values into key pairs along channels (`vt[p][ch]`:
//! channel `ch` of keys `2p, 2p+1`). Then, per block of `KEYS` (256) keys and pair of queries:
//! - logits of 16 keys by `vpdpwssd` of `kt` against the query's channel pairs, the query split
//!   as `256 qh + ql` (`qh = q >> 8`, `ql = q & 255`): every lane sums products below `2^22`, at
//!   most `2 * 128` of them (`c <=` [`MAX_C`]), so `256 h + l` is the exact logit;
//! - the weights `e = exp_q11(clamp(requantize(l - max, m), -32768, 0))` 16 at a time, as
//!   [`super::weight`] computes them (the 64-bit `requantize` path when `l - max` fits in i32 and
//!   `1 <= shift <= 62`, else [`super::weight`] itself; `exp_q11`'s knots by `vpgatherdd`);
//! - the values by `vpdpwssd` of `vt` against the weight pairs, each weight split as
//!   `256 eh + el` (`eh <= 128`, `el <= 255`): a lane sums at most `2 * KEYS / 2` products below
//!   `2^23` per block (`< 2^31`), then `256 h + l` goes into the query's i64 sums.
//!
//! So the sums are the exact `sum_j e_j v_j` and the outputs [`super::aggregate_query`]'s
//! integers (the tests compare them).
#![deny(clippy::indexing_slicing)]

use core::arch::x86_64::*;
use core::cell::RefCell;

use super::weight;
use crate::arith::Multiplier;
use crate::kernels::pool::scratch;
use crate::kernels::x86::has_avx512;

/// Keys per block (even; `KEYS / 2 <= 255` key pairs keep the value lanes exact).
const KEYS: usize = 256;
/// Most query/key channels (see the module doc).
pub const MAX_C: usize = 256;
/// Queries per pass.
const R: usize = 2;

/// Per-thread scratch.
#[derive(Default)]
struct Scratch {
    /// Weights of a block, `[query][key]`.
    e: Vec<i32>,
    /// Their high and low parts as key pairs, `[query][pair]`.
    eh: Vec<i32>,
    el: Vec<i32>,
    /// The queries' i64 sums, `[query][cv]`.
    acc: Vec<i64>,
    /// [`Prepared::stats_avx512`]'s logits of its first pass, for its second: per 16 keys and
    /// query the lanes `h` and `l` of [`logits16`].
    logits: Vec<__m512i>,
}

std::thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
}

/// A zero vector, built without AVX-512 instructions (for resizing the scratch outside the
/// `target_feature` functions).
fn zero_vector() -> __m512i {
    // SAFETY: `__m512i` is plain data; all-zero bits are a valid value.
    unsafe { core::mem::zeroed() }
}

/// `exp_q11`'s knots as `a + (b - a) << 16` for knot pairs `(a, b)` = entries `i, i + 1` of its
/// table (`i <= 1023`; the input 0 falls on knot 1023 at fraction 32: `a + (b - a) = b`). Both
/// parts fit in 16 bits (the table is in `[0, 32768]` and rises).
pub(crate) fn exp_knots() -> &'static [i32; 1024] {
    static T: std::sync::OnceLock<[i32; 1024]> = std::sync::OnceLock::new();
    T.get_or_init(|| {
        let k = |i: usize| crate::arith::lut::exp_q11(32 * i as i32 - 32768);
        core::array::from_fn(|i| k(i) + ((k(i + 1) - k(i)) << 16))
    })
}

/// [`crate::arith::lut::exp_q11`] of 16 lanes `d` in `[-32768, 0]` by the table of `exp_knots`:
/// knot `i = u >> 5` of `u = d + 32768` (at most 1023: `u = 32768` reads knot 1023 at fraction
/// 32, its end), `a + round((b - a) f / 32)`.
#[target_feature(enable = "avx512f")]
#[inline]
pub(crate) fn exp_q11x16(d: __m512i, knots: &[i32; 1024]) -> __m512i {
    let u = _mm512_add_epi32(d, _mm512_set1_epi32(32768));
    let i = _mm512_min_epi32(_mm512_srli_epi32::<5>(u), _mm512_set1_epi32(1023));
    let f = _mm512_sub_epi32(u, _mm512_slli_epi32::<5>(i));
    // SAFETY: knot `i <= 1023` of the table (`a + (b - a) << 16`, 1024 entries).
    let ab = unsafe { _mm512_i32gather_epi32::<4>(i, knots.as_ptr().cast()) };
    let (ka, kd) = (_mm512_and_si512(ab, _mm512_set1_epi32(0xFFFF)), _mm512_srli_epi32::<16>(ab));
    _mm512_add_epi32(ka, _mm512_srai_epi32::<5>(_mm512_add_epi32(_mm512_mullo_epi32(kd, f), _mm512_set1_epi32(16))))
}

/// Keys and values laid out for [`Prepared::aggregate`] (see the module doc).
pub struct Prepared {
    kt: Vec<i32>,
    vt: Vec<i32>,
    /// Keys, and keys rounded up to a whole block.
    n: usize,
    npad: usize,
    c: usize,
    cv: usize,
}

impl Default for Prepared {
    fn default() -> Self {
        Self::new()
    }
}

impl Prepared {
    /// An empty layout (fill it with [`Prepared::fill`]).
    pub const fn new() -> Self {
        Prepared { kt: Vec::new(), vt: Vec::new(), n: 0, npad: 0, c: 0, cv: 0 }
    }

    /// Lays out `keys` (`n x c`) and `values` (`n x cv`), `n` the whole keys of both, reusing the
    /// buffers; `false` where this path does not apply (no AVX-512 VNNI, `c` odd or above
    /// [`MAX_C`], `cv` not a multiple of 16, no keys).
    pub fn fill(&mut self, keys: &[i16], values: &[i16], c: usize, cv: usize) -> bool {
        if cv == 0 || !cv.is_multiple_of(16) {
            return false;
        }
        // The keys that have values: `n` of both.
        let with_values = keys.get(..values.len() / cv * c).unwrap_or(keys);
        if !self.fill_keys(with_values, c) {
            return false;
        }
        let (n, npad) = (self.n, self.npad);
        let vt = scratch(&mut self.vt, npad / 2 * cv);
        vt.fill(0);
        for (p, pair) in values.get(..n * cv).unwrap_or_default().chunks(2 * cv).enumerate() {
            let (a, b) = pair.split_at(cv.min(pair.len()));
            for (ch, d) in vt.get_mut(p * cv..(p + 1) * cv).unwrap_or_default().iter_mut().enumerate() {
                *d = pack(a.get(ch).copied().unwrap_or(0), b.get(ch).copied().unwrap_or(0));
            }
        }
        self.cv = cv;
        true
    }

    /// Lays out `keys` (`n x c`) alone, for [`Prepared::stats`]; `false` where this path does not
    /// apply (as [`Prepared::fill`]).
    pub fn fill_keys(&mut self, keys: &[i16], c: usize) -> bool {
        if !has_avx512() || c == 0 || !c.is_multiple_of(2) || c > MAX_C {
            return false;
        }
        let n = keys.len() / c;
        if n == 0 {
            return false;
        }
        let npad = n.next_multiple_of(KEYS);
        let kt = scratch(&mut self.kt, c / 2 * npad);
        kt.fill(0);
        for (j, k) in keys.chunks_exact(c).take(n).enumerate() {
            for (g, pair) in k.chunks_exact(2).enumerate() {
                if let (Some(d), &[a, b]) = (kt.get_mut(g * npad + j), pair) {
                    *d = pack(a, b);
                }
            }
        }
        (self.n, self.npad, self.c, self.cv) = (n, npad, c, 0);
        true
    }

    /// [`super::query_stats`] of the queries `qs` (`c` values each) into `out` (`max, sum` per
    /// query): the maxima of the exact logits, then the sums of the weights.
    pub fn stats(&self, qs: &[i16], m: Multiplier, out: &mut [i64]) {
        self.stats_keep(qs, m, out, &mut []);
    }

    /// Keys laid out.
    pub fn keys(&self) -> usize {
        self.n
    }

    /// Key pairs of a row of kept weights ([`Prepared::stats_keep`]).
    pub fn kept_row(&self) -> usize {
        self.npad / 2
    }

    /// [`Prepared::stats`], and where `keep` holds a row of [`Prepared::kept_row`] key pairs
    /// per query, every query's weights `e_j = weight(l_j, max, m)` there as key pairs
    /// (`e_2p | e_2p+1 << 16`; keys past the last weigh 0) for [`Prepared::aggregate_kept`].
    /// `false` where some weight lies outside `[0, 32768]` (which `exp_q11` never gives; the
    /// rows are then not to be used).
    pub fn stats_keep(&self, qs: &[i16], m: Multiplier, out: &mut [i64], keep: &mut [u32]) -> bool {
        let c = self.c;
        let nq = (qs.len() / c.max(1)).min(out.len() / 2);
        let row = self.npad / 2;
        let kept = keep.len() >= nq * row;
        let mut ok = true;
        SCRATCH.with_borrow_mut(|s| {
            // Logits of the first pass, `npad / 16` blocks of `2 R` vectors.
            if s.logits.len() < self.npad / 16 * 2 * R {
                s.logits.resize(self.npad / 16 * 2 * R, zero_vector());
            }
            let mut i = 0;
            while i < nq {
                let r = (nq - i).min(R);
                let (qh, ql) = split_queries(qs.get(i * c..(i + r) * c).unwrap_or_default(), c);
                let k = if kept { keep.get_mut(i * row..(i + r) * row).unwrap_or_default() } else { &mut [][..] };
                // SAFETY: the CPU has AVX-512 F/BW/VNNI (`fill_keys` checked); `k` is empty or
                // holds `r` rows of `npad / 2`; `s.logits` holds `npad / 16` blocks of `2 R`.
                let (st, fine) = unsafe { self.stats_avx512(&qh, &ql, r, m, k, &mut s.logits) };
                ok &= fine;
                for (o, (mx, sum)) in out.get_mut(2 * i..2 * (i + r)).unwrap_or_default().chunks_exact_mut(2).zip(st) {
                    if let [a, b] = o {
                        (*a, *b) = (mx, sum);
                    }
                }
                i += r;
            }
        });
        ok || !kept
    }

    /// `(max, sum)` of `r <= R` split queries, and where `keep` is not empty (`r` rows of
    /// `npad / 2`) their weights as key pairs; `true` when every weight is in `[0, 32768]`. The
    /// first pass (the maxima) keeps its logits in `logits` for the second (the weights).
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and VNNI; `keep` is empty or holds `r npad / 2` values;
    /// `logits` holds `npad / 16` blocks of `2 R` vectors.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn stats_avx512(&self, qh: &[[i32; R]; MAX_C / 2], ql: &[[i32; R]; MAX_C / 2], r: usize, m: Multiplier, keep: &mut [u32], logits: &mut [__m512i]) -> ([(i64, i64); R], bool) {
        let (npad, n, g_n) = (self.npad, self.n, self.c / 2);
        let (kt, qhp, qlp) = (self.kt.as_ptr(), qh.as_ptr().cast::<i32>(), ql.as_ptr().cast::<i32>());
        let lanes = _mm512_setr_epi32(0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15);
        // Keys `j .. j + 16` that exist, as 16 lanes and as two halves of 8.
        let live = |j: usize| _mm512_cmplt_epi32_mask(_mm512_add_epi32(_mm512_set1_epi32(j as i32), lanes), _mm512_set1_epi32(n as i32));
        // 1. The maxima.
        let mut mx = [_mm512_set1_epi64(i64::MIN); R];
        // 32 keys a step (`npad` is a multiple of `KEYS`): two independent sums per query and
        // part, so that the `vpdpwssd` chains do not wait on each other's latency.
        for j in (0..npad).step_by(32) {
            if live(j) == 0 {
                break;
            }
            // SAFETY: `kt` holds `c / 2` rows of `npad >= j + 32`; `qh`, `ql` `MAX_C / 2` rows.
            let both = unsafe { logits16::<2>(kt, npad, j, g_n, qhp, qlp) };
            for (v, (ah, al)) in both.into_iter().enumerate() {
                let (j, k) = (j + 16 * v, live(j + 16 * v));
                if let Some(d) = logits.get_mut(j / 16 * 2 * R..(j / 16 + 1) * 2 * R) {
                    let (dh, dl) = d.split_at_mut(R);
                    dh.copy_from_slice(&ah);
                    dl.copy_from_slice(&al);
                }
                for ((mx, ah), al) in mx.iter_mut().zip(ah).zip(al) {
                    let lo = _mm512_add_epi64(_mm512_slli_epi64::<8>(_mm512_cvtepi32_epi64(_mm512_castsi512_si256(ah))), _mm512_cvtepi32_epi64(_mm512_castsi512_si256(al)));
                    let hi = _mm512_add_epi64(
                        _mm512_slli_epi64::<8>(_mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(ah))),
                        _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(al)),
                    );
                    *mx = _mm512_mask_max_epi64(*mx, k as u8, *mx, lo);
                    *mx = _mm512_mask_max_epi64(*mx, (k >> 8) as u8, *mx, hi);
                }
            }
        }
        let mut out = [(0i64, 0i64); R];
        for (o, mx) in out.iter_mut().zip(mx) {
            o.0 = _mm512_reduce_max_epi64(mx);
        }
        // 2. The sums of the weights.
        let knots = exp_knots();
        let row = npad / 2;
        let kept = !keep.is_empty() && keep.len() >= r * row;
        let mut fine = true;
        let mut e = [0i32; 16];
        // The weights' sums, 8 + 8 i64 lanes per query.
        let mut sums = [[_mm512_setzero_si512(); 2]; R];
        for j in (0..npad).step_by(16) {
            let k = live(j);
            if k == 0 {
                break;
            }
            // The first pass's logits (computed again only where `logits` is short, which the
            // contract excludes).
            let stored = logits.get(j / 16 * 2 * R..(j / 16 + 1) * 2 * R).and_then(|b| Some((<[__m512i; R]>::try_from(b.get(..R)?).ok()?, <[__m512i; R]>::try_from(b.get(R..)?).ok()?)));
            let (ah, al) = match stored {
                Some(v) => v,
                // SAFETY: as above.
                None => {
                    let [v] = unsafe { logits16::<1>(kt, npad, j, g_n, qhp, qlp) };
                    v
                }
            };
            for (t, (((o, ah), al), sum)) in out.iter_mut().zip(ah).zip(al).zip(sums.iter_mut()).take(r).enumerate() {
                // SAFETY: `e` is 16 i32.
                unsafe { weights16(ah, al, o.0, m, knots, e.as_mut_ptr()) };
                // SAFETY: `e` is 16 i32.
                let v = _mm512_maskz_mov_epi32(k, unsafe { _mm512_loadu_si512(e.as_ptr().cast()) });
                sum[0] = _mm512_add_epi64(sum[0], _mm512_cvtepi32_epi64(_mm512_castsi512_si256(v)));
                sum[1] = _mm512_add_epi64(sum[1], _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(v)));
                if kept {
                    fine &= _mm512_cmpgt_epu32_mask(v, _mm512_set1_epi32(32768)) == 0;
                    if let Some(d) = keep.get_mut(t * row + j / 2..t * row + j / 2 + 8) {
                        // SAFETY: `d` is 8 u32: the 16 weights narrowed to u16, in key order.
                        unsafe { _mm256_storeu_si256(d.as_mut_ptr().cast(), _mm512_cvtepi32_epi16(v)) };
                    }
                }
            }
        }
        for (o, sum) in out.iter_mut().zip(sums) {
            o.1 = _mm512_reduce_add_epi64(_mm512_add_epi64(sum[0], sum[1]));
        }
        if kept {
            // Keys past the last 16 weigh nothing.
            let live_pairs = n.next_multiple_of(16) / 2;
            for t in 0..r {
                keep.get_mut(t * row + live_pairs..(t + 1) * row).unwrap_or_default().fill(0);
            }
        }
        (out, fine)
    }

    /// [`super::aggregate_query`] of the queries `qs` (`c` values each) with their statistics
    /// `stats` (`max, sum` per query) into `out` (`cv` per query).
    pub fn aggregate(&self, qs: &[i16], stats: &[i64], m: Multiplier, shift: i8, out: &mut [i16]) {
        let (c, cv) = (self.c, self.cv);
        let nq = (qs.len() / c).min(stats.len() / 2).min(out.len() / cv);
        SCRATCH.with_borrow_mut(|s| {
            let mut i = 0;
            while i < nq {
                let r = (nq - i).min(R);
                let acc = scratch(&mut s.acc, R * cv);
                acc.fill(0);
                let (e, eh, el) = (scratch(&mut s.e, R * KEYS), scratch(&mut s.eh, R * KEYS / 2), scratch(&mut s.el, R * KEYS / 2));
                let q = qs.get(i * c..(i + r) * c).unwrap_or_default();
                let st = stats.get(2 * i..2 * (i + r)).unwrap_or_default();
                // SAFETY: the CPU has AVX-512 F/BW/VNNI (`new` checked); the buffers have the
                // sizes `block` needs.
                unsafe { self.queries(q, r, st, m, e, eh, el, acc) };
                outputs(out.get_mut(i * cv..(i + r) * cv).unwrap_or_default(), acc, st, cv, shift);
                i += r;
            }
        });
    }

    /// [`Prepared::aggregate`] of queries whose weights [`Prepared::stats_keep`] kept
    /// (`weights`: their rows of [`Prepared::kept_row`] key pairs, laid out for the same keys):
    /// no logits, no weights, only the values' sums. `false` (nothing written) where the rows
    /// do not match this layout.
    pub fn aggregate_kept(&self, weights: &[u32], stats: &[i64], shift: i8, out: &mut [i16]) -> bool {
        let (cv, row) = (self.cv, self.npad / 2);
        if cv == 0 || row == 0 || !weights.len().is_multiple_of(row) {
            return false;
        }
        let nq = (weights.len() / row).min(stats.len() / 2).min(out.len() / cv);
        SCRATCH.with_borrow_mut(|s| {
            let mut i = 0;
            while i < nq {
                let r = (nq - i).min(R);
                let acc = scratch(&mut s.acc, R * cv);
                acc.fill(0);
                let rows = weights.get(i * row..(i + r) * row).unwrap_or_default();
                let mut j0 = 0;
                while j0 < self.npad {
                    let mut cb = 0;
                    while cb < cv / 16 {
                        // SAFETY: the CPU has AVX-512 F/BW/VNNI (`fill` checked); `rows` holds
                        // `r` rows of `npad / 2` key pairs; channel blocks `cb .. cb + NB <= cv / 16`.
                        unsafe {
                            if cb + 4 <= cv / 16 {
                                self.values_kept::<4>(j0, cb, rows, r, acc);
                                cb += 4;
                            } else {
                                self.values_kept::<1>(j0, cb, rows, r, acc);
                                cb += 1;
                            }
                        }
                    }
                    j0 += KEYS;
                }
                let st = stats.get(2 * i..2 * (i + r)).unwrap_or_default();
                outputs(out.get_mut(i * cv..(i + r) * cv).unwrap_or_default(), acc, st, cv, shift);
                i += r;
            }
        });
        true
    }

    /// [`values`] for the key block at `j0`, the weight pairs split from the kept rows
    /// (`rows`: `r` rows of `npad / 2` pairs `e_a | e_b << 16`, each weight in `[0, 32768]`):
    /// `eh = e >> 8`, `el = e & 255` per 16-bit half.
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and VNNI; `rows` holds `r <= R` rows of `npad / 2`;
    /// `cb + NB <= cv / 16`; `acc` holds `R cv`.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    unsafe fn values_kept<const NB: usize>(&self, j0: usize, cb: usize, rows: &[u32], r: usize, acc: &mut [i64]) {
        let (cv, row) = (self.cv, self.npad / 2);
        let z = _mm512_setzero_si512();
        let bytes = _mm512_set1_epi32(0x00FF_00FF);
        let vt = self.vt.as_ptr();
        let (mut h, mut l) = ([[z; NB]; R], [[z; NB]; R]);
        // An absent query reads the first one's row (its sums are not stored).
        let rp = [rows.as_ptr(), if r > 1 { rows.as_ptr().wrapping_add(row) } else { rows.as_ptr() }];
        for pk in j0 / 2..(j0 + KEYS) / 2 {
            // SAFETY: `vt` holds `npad / 2` key pairs of `cv` values, `pk < npad / 2`; each row
            // `npad / 2` pairs (the contract).
            unsafe {
                let vrow = vt.add(pk * cv + 16 * cb);
                let mut v = [z; NB];
                for (b, v) in v.iter_mut().enumerate() {
                    *v = _mm512_loadu_si512(vrow.add(16 * b).cast());
                }
                for ((h, l), rp) in h.iter_mut().zip(l.iter_mut()).zip(rp) {
                    let e = _mm512_set1_epi32(*rp.add(pk) as i32);
                    // (`e >> 8` per 16-bit half: each half is at most 32768, so its high byte alone.)
                    let (bh, bl) = (_mm512_srli_epi16::<8>(e), _mm512_and_si512(e, bytes));
                    for ((h, l), &v) in h.iter_mut().zip(l.iter_mut()).zip(v.iter()) {
                        *h = _mm512_dpwssd_epi32(*h, v, bh);
                        *l = _mm512_dpwssd_epi32(*l, v, bl);
                    }
                }
            }
        }
        // SAFETY: as `values`' own epilogue (`acc` holds `R cv`).
        unsafe { add_halves::<NB>(&h, &l, cv, cb, r, acc) };
    }

    /// The sums of `r <= R` queries over every key into `acc` (`R cv`).
    ///
    /// # Safety
    /// The CPU has AVX-512 F, BW and VNNI; `e` holds `R KEYS` values, `eh` and `el` `R KEYS / 2`,
    /// `acc` `R cv`.
    #[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
    #[allow(clippy::too_many_arguments)]
    unsafe fn queries(&self, q: &[i16], r: usize, stats: &[i64], m: Multiplier, e: &mut [i32], eh: &mut [i32], el: &mut [i32], acc: &mut [i64]) {
        let (c, cv, npad, n) = (self.c, self.cv, self.npad, self.n);
        let g_n = c / 2;
        // The queries' channel pairs split as `256 qh + ql`, and their maxima.
        let (qh, ql) = split_queries(q.get(..r * c).unwrap_or_default(), c);
        let mut max = [0i64; R];
        for (mx, st) in max.iter_mut().zip(stats.chunks_exact(2)).take(r) {
            *mx = st.first().copied().unwrap_or(0);
        }
        let knots = exp_knots();
        let (kt, vt) = (self.kt.as_ptr(), self.vt.as_ptr());
        let (qhp, qlp) = (qh.as_ptr().cast::<i32>(), ql.as_ptr().cast::<i32>());
        let (ep, ehp, elp) = (e.as_mut_ptr(), eh.as_mut_ptr(), el.as_mut_ptr());
        let cbs = cv / 16;
        let mut j0 = 0;
        while j0 < npad {
            // 1. Logits and weights of the block's keys, 16 at a time, both queries together.
            for jv in (0..KEYS).step_by(16) {
                let j = j0 + jv;
                // SAFETY: `kt` holds `c / 2` rows of `npad >= j + 16` keys; `qh`, `ql` hold
                // `MAX_C / 2 >= c / 2` rows of `R`.
                let [(ah, al)] = unsafe { logits16::<1>(kt, npad, j, g_n, qhp, qlp) };
                for (t, ((&ah, &al), &mxs)) in ah.iter().zip(al.iter()).zip(max.iter()).enumerate().take(r) {
                    // SAFETY: `e` holds `R KEYS` values; `t < R`, `jv + 16 <= KEYS`; the CPU has
                    // AVX-512 (this function's contract).
                    unsafe { weights16(ah, al, mxs, m, knots, ep.add(t * KEYS + jv)) };
                }
            }
            // Keys past the last weigh nothing (their values are zero too; kept for clarity of
            // the weights' own checks below).
            for t in 0..r.min(R) {
                for k in n.saturating_sub(j0).min(KEYS)..KEYS {
                    // SAFETY: `t KEYS + k < R KEYS`.
                    unsafe { ep.add(t * KEYS + k).write(0) };
                }
            }
            // 2. Weight pairs split as `256 eh + el`, `[pair][query]` (a weight outside
            // [0, 32768], which `exp_q11` never gives, is added on its own below).
            let mut odd = false;
            for t in 0..R {
                for pk in 0..KEYS / 2 {
                    // SAFETY: `e` holds `R KEYS`, `eh` and `el` `R KEYS / 2` (contract).
                    unsafe {
                        let (a, b) = if t < r { (*ep.add(t * KEYS + 2 * pk), *ep.add(t * KEYS + 2 * pk + 1)) } else { (0, 0) };
                        let ok = |v: i32| (0..=32768).contains(&v);
                        odd |= !ok(a) || !ok(b);
                        let (a, b) = (if ok(a) { a } else { 0 }, if ok(b) { b } else { 0 });
                        ehp.add(pk * R + t).write(((a >> 8) as u32 | ((b >> 8) as u32) << 16) as i32);
                        elp.add(pk * R + t).write(((a & 255) as u32 | ((b & 255) as u32) << 16) as i32);
                    }
                }
            }
            // 3. Values: four channel blocks at a time (then one), both queries' high and low sums.
            let mut cb = 0;
            while cb < cbs {
                // SAFETY: channel blocks `cb .. cb + NB <= cv / 16`; the rest as `values` says.
                unsafe {
                    if cb + 4 <= cbs {
                        values::<4>(vt, j0, cv, cb, ehp, elp, r, acc);
                        cb += 4;
                    } else {
                        values::<1>(vt, j0, cv, cb, ehp, elp, r, acc);
                        cb += 1;
                    }
                }
            }
            if odd {
                for t in 0..r.min(R) {
                    for (k, &w) in e.get(t * KEYS..(t + 1) * KEYS).unwrap_or_default().iter().enumerate() {
                        if (0..=32768).contains(&w) {
                            continue;
                        }
                        let key = j0 + k;
                        for (ch, a) in acc.get_mut(t * cv..(t + 1) * cv).unwrap_or_default().iter_mut().enumerate() {
                            let pair = self.vt.get((key / 2) * cv + ch).copied().unwrap_or(0) as u32;
                            let v = if key % 2 == 0 { pair as u16 as i16 } else { (pair >> 16) as u16 as i16 };
                            *a += w as i64 * v as i64;
                        }
                    }
                }
            }
            j0 += KEYS;
        }
    }
}

/// The queries' aggregated values into `out` (`cv` each) from their sums `acc` (`cv` each) and
/// statistics `stats` (`max, sum` each), as [`super::aggregate_query`] finishes them.
///
/// The division by a query's sum of weights estimates its quotients with the sum's f64
/// reciprocal ([`crate::arith::DivRoundSat16::apply_f64`]; a division per value took 1 % of a
/// Teddy frame).
fn outputs(out: &mut [i16], acc: &[i64], stats: &[i64], cv: usize, shift: i8) {
    for ((o, a), st) in out.chunks_exact_mut(cv.max(1)).zip(acc.chunks_exact(cv.max(1))).zip(stats.chunks_exact(2)) {
        let d = st.get(1).copied().unwrap_or(0);
        let (div, inv) = (crate::arith::DivRoundSat16::new(d), 1.0 / d as f64);
        // Eight sums a vector where the divisor is a positive i32 (the weights' sum always is) and
        // the shift moderate; a vector with a sum too large for it, and the tail, value by value.
        let mut done = 0;
        if crate::kernels::x86::has_avx512dq() && d > 0 && d <= i32::MAX as i64 && (-62..=40).contains(&shift) {
            for (o8, a8) in o.chunks_exact_mut(8).zip(a.chunks_exact(8)) {
                if let (Ok(o8), Ok(a8)) = (<&mut [i16; 8]>::try_from(o8), <&[i64; 8]>::try_from(a8)) {
                    // SAFETY: the CPU has AVX-512 F, BW and DQ (`has_avx512dq`).
                    if !unsafe { outputs8(o8, a8, d, shift) } {
                        for (o, a) in o8.iter_mut().zip(a8) {
                            *o = div.apply_f64(crate::arith::shift_round(*a, shift as i32), inv);
                        }
                    }
                }
                done += 8;
            }
        }
        for (o, a) in o.iter_mut().zip(a).skip(done) {
            *o = div.apply_f64(crate::arith::shift_round(*a, shift as i32), inv);
        }
    }
}

/// [`outputs`] of eight sums `a` by one divisor `0 < d < 2^31`, `-62 <= shift <= 40`: `sat_i16(
/// div_round(shift_round(a, shift), d))`, or `false` (nothing written) where a sum is too large
/// for the plain vector formulas (`|a| >= 2^(62 - max(shift, 0))`: the shift or its rounding
/// could saturate). Then `|a'| < 2^62` after the shift, `t = |a'| + d
/// / 2` does not overflow, a quotient reaching 32768 saturates (`t >= 32768 d`), and below that
/// bound `t < 2^46` converts to f64 exactly and `floor(t / d)` is exact: a quotient `k + r / d`
/// with `r < d` lies at least `2^-31` below `k + 1`, more than an f64 near `2^15` can round by.
///
/// # Safety
/// The CPU has AVX-512 F, BW and DQ.
#[target_feature(enable = "avx512f,avx512bw,avx512dq")]
unsafe fn outputs8(out: &mut [i16; 8], a: &[i64; 8], d: i64, shift: i8) -> bool {
    // SAFETY: 8 i64.
    let v = unsafe { _mm512_loadu_si512(a.as_ptr().cast()) };
    let lim = _mm512_set1_epi64(1i64 << (62 - shift.max(0) as u32));
    if _mm512_cmplt_epi64_mask(_mm512_abs_epi64(v), lim) != 0xFF {
        return false;
    }
    let v = if shift >= 0 {
        _mm512_sll_epi64(v, _mm_cvtsi32_si128(shift as i32))
    } else {
        let r = -(shift as i32);
        _mm512_sra_epi64(_mm512_add_epi64(v, _mm512_set1_epi64(1i64 << (r - 1))), _mm_cvtsi32_si128(r))
    };
    let t = _mm512_add_epi64(_mm512_abs_epi64(v), _mm512_set1_epi64(d / 2));
    let neg = _mm512_cmplt_epi64_mask(v, _mm512_setzero_si512());
    let sat = _mm512_cmpge_epi64_mask(t, _mm512_set1_epi64(32768 * d));
    let q = _mm512_cvttpd_epi64(_mm512_div_pd(_mm512_cvtepi64_pd(t), _mm512_set1_pd(d as f64)));
    let q = _mm512_mask_sub_epi64(q, neg, _mm512_setzero_si512(), q);
    // Saturated: `i16::MIN` for a negative sum, `i16::MAX` for a positive one.
    let q = _mm512_mask_mov_epi64(q, sat & neg, _mm512_set1_epi64(i16::MIN as i64));
    let q = _mm512_mask_mov_epi64(q, sat & !neg, _mm512_set1_epi64(i16::MAX as i64));
    // SAFETY: 8 i16.
    unsafe { _mm_storeu_si128(out.as_mut_ptr().cast(), _mm512_cvtepi64_epi16(q)) };
    true
}

/// Two i16 as the i32 lane `vpdpwssd` reads as a pair: `a` in the low half, `b` in the high.
#[inline(always)]
fn pack(a: i16, b: i16) -> i32 {
    (a as u16 as u32 | (b as u16 as u32) << 16) as i32
}

/// The channel pairs of up to `R` queries (`c` values each) split as `256 qh + ql`, as
/// `[g][query]` i32 pairs (an absent query all zero).
#[allow(clippy::type_complexity)]
fn split_queries(q: &[i16], c: usize) -> ([[i32; R]; MAX_C / 2], [[i32; R]; MAX_C / 2]) {
    let mut qh = [[0i32; R]; MAX_C / 2];
    let mut ql = [[0i32; R]; MAX_C / 2];
    for (qi, qv) in q.chunks_exact(c.max(1)).take(R).enumerate() {
        for (pair, (h, l)) in qv.chunks_exact(2).zip(qh.iter_mut().zip(ql.iter_mut())) {
            if let (&[a, b], Some(h), Some(l)) = (pair, h.get_mut(qi), l.get_mut(qi)) {
                (*h, *l) = (pack(a >> 8, b >> 8), pack(a & 255, b & 255));
            }
        }
    }
    (qh, ql)
}

/// The weights [`weight`]`(l, max, m)` of 16 keys into `out`, their logits `256 h + l` given as
/// the i32 lanes `ah` (`h`) and `al` (`l`): the 64-bit `requantize` path and one gather of the
/// packed knots where every `l - max` fits in i32 and `1 <= shift <= 62`, else [`weight`].
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; `out` points at 16 writable i32.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
unsafe fn weights16(ah: __m512i, al: __m512i, max: i64, m: Multiplier, knots: &[i32; 1024], out: *mut i32) {
    let mx = _mm512_set1_epi64(max);
    let (lo32, hi32) = (_mm512_set1_epi64(i32::MIN as i64), _mm512_set1_epi64(i32::MAX as i64));
    // Logits minus the maximum, 8 + 8 keys as i64. (Macros, not closures: a closure does not
    // inherit the target features.)
    macro_rules! diff {
        ($h:expr, $l:expr) => {
            _mm512_sub_epi64(_mm512_add_epi64(_mm512_slli_epi64::<8>(_mm512_cvtepi32_epi64($h)), _mm512_cvtepi32_epi64($l)), mx)
        };
    }
    macro_rules! inside {
        ($d:expr) => {
            _mm512_cmpge_epi64_mask($d, lo32) & _mm512_cmple_epi64_mask($d, hi32)
        };
    }
    let d0 = diff!(_mm512_castsi512_si256(ah), _mm512_castsi512_si256(al));
    let d1 = diff!(_mm512_extracti64x4_epi64::<1>(ah), _mm512_extracti64x4_epi64::<1>(al));
    if (1..=62).contains(&m.shift) && inside!(d0) == 0xFF && inside!(d1) == 0xFF {
        let (mm, half, count) = (_mm512_set1_epi64(m.m as i64), _mm512_set1_epi64(1i64 << (m.shift - 1)), _mm_cvtsi64_si128(m.shift as i64));
        macro_rules! rq {
            ($d:expr) => {
                _mm512_cvtepi64_epi32(_mm512_min_epi64(
                    _mm512_max_epi64(_mm512_sra_epi64(_mm512_add_epi64(_mm512_mul_epi32($d, mm), half), count), _mm512_set1_epi64(-32768)),
                    _mm512_setzero_si512(),
                ))
            };
        }
        let d = _mm512_inserti64x4::<1>(_mm512_castsi256_si512(rq!(d0)), rq!(d1));
        let w = exp_q11x16(d, knots);
        // SAFETY: 16 i32 at `out` (the contract).
        unsafe { _mm512_storeu_si512(out.cast(), w) };
    } else {
        let (mut l0, mut l1) = ([0i64; 8], [0i64; 8]);
        // SAFETY: 8 i64 each; 16 i32 at `out`.
        unsafe {
            _mm512_storeu_si512(l0.as_mut_ptr().cast(), _mm512_add_epi64(d0, mx));
            _mm512_storeu_si512(l1.as_mut_ptr().cast(), _mm512_add_epi64(d1, mx));
            for (k, l) in l0.iter().chain(&l1).enumerate() {
                out.add(k).write(weight(*l, max, m));
            }
        }
    }
}

/// Logits of `R` queries (channel pairs split as `256 qh + ql`, `[g][query]`) with keys
/// `j .. j + 16 V` of `kt` (`g_n` rows of `npad`), per 16 keys: per query the lanes `h` and `l`
/// of [`weights16`].
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; `kt` holds `g_n` rows of `npad >= j + 16 V`; `qh`, `ql`
/// `g_n` rows of `R`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
unsafe fn logits16<const V: usize>(kt: *const i32, npad: usize, j: usize, g_n: usize, qh: *const i32, ql: *const i32) -> [([__m512i; R], [__m512i; R]); V] {
    let z = _mm512_setzero_si512();
    let mut a = [([z; R], [z; R]); V];
    for g in 0..g_n {
        // SAFETY: the contract.
        unsafe {
            for (v, (ah, al)) in a.iter_mut().enumerate() {
                let k = _mm512_loadu_si512(kt.add(g * npad + j + 16 * v).cast());
                for (t, (ah, al)) in ah.iter_mut().zip(al.iter_mut()).enumerate() {
                    *ah = _mm512_dpwssd_epi32(*ah, k, _mm512_set1_epi32(*qh.add(g * R + t)));
                    *al = _mm512_dpwssd_epi32(*al, k, _mm512_set1_epi32(*ql.add(g * R + t)));
                }
            }
        }
    }
    a
}

/// Adds `256 h + l` of the block's key pairs into channel blocks `cb .. cb + NB` of the `r`
/// queries' sums `acc` (`R cv`): `h`, `l` the sums of the values `vt` against the weight pairs'
/// high (`eh`) and low (`el`) parts, `[pair][query]`.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; `vt` holds the key pairs `j0 / 2 .. (j0 + KEYS) / 2` of
/// `cv` values, `cb + NB <= cv / 16`; `eh` and `el` hold `KEYS / 2` rows of `R`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
#[allow(clippy::too_many_arguments)]
unsafe fn values<const NB: usize>(vt: *const i32, j0: usize, cv: usize, cb: usize, eh: *const i32, el: *const i32, r: usize, acc: &mut [i64]) {
    let z = _mm512_setzero_si512();
    let (mut h, mut l) = ([[z; NB]; R], [[z; NB]; R]);
    for pk in 0..KEYS / 2 {
        // SAFETY: the function's contract.
        unsafe {
            let row = vt.add((j0 / 2 + pk) * cv + 16 * cb);
            let mut v = [z; NB];
            for (b, v) in v.iter_mut().enumerate() {
                *v = _mm512_loadu_si512(row.add(16 * b).cast());
            }
            for (t, (h, l)) in h.iter_mut().zip(l.iter_mut()).enumerate() {
                let (bh, bl) = (_mm512_set1_epi32(*eh.add(pk * R + t)), _mm512_set1_epi32(*el.add(pk * R + t)));
                for ((h, l), &v) in h.iter_mut().zip(l.iter_mut()).zip(v.iter()) {
                    *h = _mm512_dpwssd_epi32(*h, v, bh);
                    *l = _mm512_dpwssd_epi32(*l, v, bl);
                }
            }
        }
    }
    // SAFETY: `acc` holds `R cv` (the contract).
    unsafe { add_halves::<NB>(&h, &l, cv, cb, r, acc) };
}

/// Adds `256 h + l` (i64) of the queries' channel blocks `cb .. cb + NB` into `acc` (`R cv`).
///
/// # Safety
/// The CPU has AVX-512 F.
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn add_halves<const NB: usize>(h: &[[__m512i; NB]; R], l: &[[__m512i; NB]; R], cv: usize, cb: usize, r: usize, acc: &mut [i64]) {
    for (t, (h, l)) in h.iter().zip(l.iter()).enumerate().take(r) {
        for (b, (&hv, &lv)) in h.iter().zip(l.iter()).enumerate() {
            let Some(a) = acc.get_mut(t * cv + 16 * (cb + b)..t * cv + 16 * (cb + b + 1)) else {
                continue;
            };
            // 256 h + l in i64, 8 + 8 channels.
            let lo = _mm512_add_epi64(_mm512_slli_epi64::<8>(_mm512_cvtepi32_epi64(_mm512_castsi512_si256(hv))), _mm512_cvtepi32_epi64(_mm512_castsi512_si256(lv)));
            let hi =
                _mm512_add_epi64(_mm512_slli_epi64::<8>(_mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(hv))), _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(lv)));
            // SAFETY: `a` is 16 i64.
            unsafe {
                _mm512_storeu_si512(a.as_mut_ptr().cast(), _mm512_add_epi64(_mm512_loadu_si512(a.as_ptr().cast()), lo));
                _mm512_storeu_si512(a.as_mut_ptr().add(8).cast(), _mm512_add_epi64(_mm512_loadu_si512(a.as_ptr().add(8).cast()), hi));
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::super::testutil::Rng;
    use super::*;

    /// The packed knots interpolate to `exp_q11` at every input.
    #[test]
    fn packed_knots_give_exp_q11() {
        let t = exp_knots();
        for x in -32768..=0i32 {
            let u = x + 32768;
            let i = ((u >> 5) as usize).min(1023);
            let f = u - 32 * i as i32;
            let (a, d) = (t[i] & 0xFFFF, t[i] >> 16);
            assert_eq!(a + ((d * f + 16) >> 5), crate::arith::lut::exp_q11(x), "{x}");
        }
    }

    /// `outputs`' division (an f64 estimate, corrected) gives `aggregated`'s integers: divisors
    /// across i32 and beyond, sums at the saturation bounds and the rounding halves, both signs.
    #[test]
    fn outputs_divide_as_aggregated() {
        let mut r = Rng(0xd1d0_0002);
        let mut ds = vec![1i64, 2, 3, 7, 65535, 65536, 65537, (1 << 31) - 1, 1 << 31, 0, -5, i64::MAX];
        ds.extend((0..100).map(|_| (r.next() >> (33 + r.next() % 31)) as i64 + 1));
        for &d in &ds {
            let mut ns = vec![0i64, 1, -1, i64::MAX, i64::MIN, i64::MIN + 1];
            for k in [32766i64, 32767, 32768, 32769, 1, 100] {
                if let Some(b) = d.checked_mul(k) {
                    for e in [-1i64, 0, 1, d / 2, d / 2 + 1, -(d / 2), -(d / 2) - 1] {
                        if let Some(v) = b.checked_add(e) {
                            ns.extend([Some(v), v.checked_neg()].into_iter().flatten());
                        }
                    }
                }
            }
            ns.extend((0..50).map(|_| (r.next() as i64) >> (r.next() % 63)));
            for shift in [-3i8, 0, 2] {
                let mut got = vec![0i16; ns.len()];
                outputs(&mut got, &ns, &[0, d], ns.len(), shift);
                let want: Vec<i16> = ns.iter().map(|&n| super::super::aggregated(n, shift, d)).collect();
                assert_eq!(got, want, "d {d} shift {shift}");
            }
        }
    }

    #[test]
    fn many_queries_give_aggregate_query_integers() {
        if !has_avx512() {
            eprintln!("no AVX-512 VNNI: the batched attention is not taken on this CPU");
            return;
        }
        let mut r = Rng(77);
        // `flat`: every key zero, so every weight is 32768 (the largest), and the values extreme:
        // the value sums' lanes at their largest.
        for (n, c, cv, nq, big, flat) in [
            (37, 32, 64, 5, false, false),
            (300, 32, 16, 4, true, false),
            (513, 16, 32, 3, false, false),
            (1, 2, 16, 1, true, false),
            (260, 64, 64, 2, true, false),
            (600, 32, 48, 7, true, false),
            (700, 32, 64, 6, true, true),
        ] {
            let val = |r: &mut Rng| if big { if r.next() % 2 == 0 { i16::MIN } else { i16::MAX } } else { r.i16() >> 3 };
            let keys: Vec<i16> = (0..n * c).map(|_| if flat { 0 } else { val(&mut r) }).collect();
            let values: Vec<i16> = (0..n * cv).map(|_| if flat { val(&mut r) } else { r.i16() }).collect();
            let qs: Vec<i16> = (0..nq * c).map(|_| val(&mut r)).collect();
            for m in [Multiplier { m: 1 << 30, shift: 40 }, Multiplier { m: 1_500_000_000, shift: 20 }, Multiplier { m: 1 << 30, shift: 70 }] {
                let mut stats = vec![];
                let mut want = vec![0i16; nq * cv];
                let mut acc = vec![0i64; cv];
                for (q, o) in qs.chunks_exact(c).zip(want.chunks_exact_mut(cv)) {
                    let st = super::super::query_stats(q, &keys, m);
                    stats.extend([st.0, st.1]);
                    super::super::aggregate_query(q, &keys, &values, cv, st, m, 3, &mut acc, o);
                }
                let mut prep = Prepared::new();
                assert!(prep.fill_keys(&keys, c));
                let mut got_stats = vec![0i64; 2 * nq];
                prep.stats(&qs, m, &mut got_stats);
                assert_eq!(stats, got_stats, "stats: n {n} c {c} {m:?}");
                assert!(prep.fill(&keys, &values, c, cv));
                let mut got = vec![0i16; nq * cv];
                prep.aggregate(&qs, &stats, m, 3, &mut got);
                assert_eq!(want, got, "n {n} c {c} cv {cv} {m:?}");
                assert!(want.iter().any(|v| *v != 0));
                // The same from the weights the statistics pass keeps (rows start dirty).
                let row = prep.kept_row();
                let mut keep = vec![0xDEAD_BEEFu32; nq * row];
                let mut kept_stats = vec![0i64; 2 * nq];
                assert!(prep.stats_keep(&qs, m, &mut kept_stats, &mut keep));
                assert_eq!(stats, kept_stats);
                let mut got = vec![0i16; nq * cv];
                assert!(prep.aggregate_kept(&keep, &stats, 3, &mut got));
                assert_eq!(want, got, "kept: n {n} c {c} cv {cv} {m:?}");
                assert!(!prep.aggregate_kept(&keep[..row - 1], &stats, 3, &mut got), "rows of another layout");
            }
        }
    }
}
