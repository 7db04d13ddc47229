//! Fixed-point kernels. Every function computes with the rules of [`crate::arith`] only.
//!
//! Tensors are HWC: element `(y, x, c)` of a `h x w x c` tensor at `(y * w + x) * c + c`, so one
//! image row (`w * c` values) is contiguous: the unit the streaming engine keeps in line buffers.
//!
//! Each family has a row (or pixel) kernel used by the streaming engine and a plain twin over whole
//! tensors used by the reference engine (`crate::reference`); their tests check identical bits.
//!
//! No input reaches a panic: slices are walked by iterators or read with `get`, and a kernel
//! given buffers shorter than its shapes say skips what does not fit (documented per kernel)
//! instead of indexing out of bounds. `clippy::indexing_slicing` is denied in each kernel file
//! that is free of it and on this file's items one by one: a module-wide deny here would also
//! reach the files that still index (attention, dsp, mve, x86).

/// Terms of an int8 x i16 dot product summed in one i32 before the sum moves to i64: every
/// product is at most `128 * 32768 = 2^22` in magnitude, and `508 * 2^22 = 2,130,706,432 <
/// 2^31`, so a chunk's sum is exact in 32 bits whatever the order (the `dsp` and `mve` kernels
/// accumulate a chunk in one 32-bit register); a multiple of 4 so that chunks of the two-pixel
/// pair layout stay in that layout. The chunk size never changes a result, only speed: 508 with
/// Helium (Cortex-M55 frame -1.1 %: fewer calls), 256 elsewhere (508 made the Cortex-M7 build's
/// frame 1.3 % longer, by code generation).
pub const I16_CHUNK: usize = if cfg!(all(target_arch = "arm", feature = "mve")) { 508 } else { 256 };
const _: () = assert!((I16_CHUNK as u64) * (1 << 22) < (1u64 << 31) && I16_CHUNK.is_multiple_of(4));

#[cfg(all(target_arch = "aarch64", feature = "std"))]
pub mod aarch64;
pub mod attention;
pub mod conv;
pub mod corr;
#[cfg(all(target_arch = "arm", feature = "dsp"))]
pub mod dsp;
pub mod eltwise;
pub mod fullres;
#[cfg(all(target_arch = "arm", feature = "mve"))]
pub mod mve;
pub mod norm;
#[cfg(feature = "std")]
pub mod pool;
pub mod resample;
pub mod upsample;
#[cfg(all(target_arch = "x86_64", feature = "std"))]
pub mod x86;

/// Activation storage type: `i8`, `u8` or `i16`.
#[deny(clippy::indexing_slicing)]
pub trait Elem: Copy + Default + PartialEq + core::fmt::Debug + Send + Sync + 'static {
    /// Storage width in bits.
    const BITS: u8;
    /// Storage format with 0 fraction bits (`QFormat::{i8, u8, i16}(0)`).
    const STORAGE: crate::arith::QFormat;
    /// Widening conversion.
    fn to_i32(self) -> i32;
    /// Saturating narrowing.
    fn from_i64_sat(v: i64) -> Self;
    /// Exact dot product with i8 weights (`w.len() == x.len()`), optimised path.
    fn dot(w: &[i8], x: &[Self]) -> i64;
    /// Two dot products over the same activations (two output channels): on Cortex-M the
    /// activations are loaded and widened once for both. Same integers as two [`Elem::dot`]s.
    #[inline]
    fn dot2(w0: &[i8], w1: &[i8], x: &[Self]) -> (i64, i64) {
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        if let Some(d) = x86::dot2(w0, w1, x) {
            return d;
        }
        (Self::dot(w0, x), Self::dot(w1, x))
    }
    /// Whether the pair layout stores groups as values 0, 2, 1, 3 ([`pair_index`]).
    const PAIR_SWAP: bool = false;
    /// Whether this type's pair layout on this target is split: patch `a`'s `n` values, then
    /// patch `b`'s (Helium, u8 and i16: both read by contiguous loads, `mve::dot2x2_split` and
    /// `mve::dot2x2_split_i16`, and gathered by whole runs of the input rows); otherwise the
    /// interleaved groups of [`pair_index`].
    const SPLIT_PAIRS: bool = false;
    /// Where value `j` of the first (`second == false`) or second of two `n`-value patches sits in
    /// this type's pair layout ([`Elem::SPLIT_PAIRS`], [`pair_index`]).
    #[inline(always)]
    fn pair_at(n: usize, j: usize, second: bool) -> usize {
        if Self::SPLIT_PAIRS {
            if second { n + j } else { j }
        } else {
            pair_index(n, j, second, Self::PAIR_SWAP)
        }
    }
    /// Two output channels at two output pixels: `[w0 . a, w1 . a, w0 . b, w1 . b]` where `a` and
    /// `b` are two patches of `n = w0.len()` values stored in the [`pair_index`] layout in `x`
    /// (`2n` values). On Cortex-M one pointer reads both patches and each weight and activation
    /// is loaded and widened once for two products. Same integers as four [`Elem::dot`]s.
    #[inline]
    fn dot2x2(w0: &[i8], w1: &[i8], x: &[Self]) -> [i64; 4] {
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        if let Some(d) = x86::dot2x2(w0, w1, x) {
            return d;
        }
        let n = w0.len().min(w1.len()).min(x.len() / 2);
        let mut acc = [0i64; 4];
        let mut mac = |u: i8, v: i8, a: Self, b: Self| {
            let (u, v, a, b) = (u as i64, v as i64, a.to_i32() as i64, b.to_i32() as i64);
            acc[0] += u * a;
            acc[1] += v * a;
            acc[2] += u * b;
            acc[3] += v * b;
        };
        // Groups of four weights against groups of eight activations (four of each patch), then
        // the `n % 4` last values: `2 (n % 4) < 8` activations, those of `a` then those of `b`.
        let (w0, w1, x) = (head(w0, n).chunks_exact(4), head(w1, n).chunks_exact(4), head(x, 2 * n).chunks_exact(8));
        let (r0, r1, rx) = (w0.remainder(), w1.remainder(), x.remainder());
        for ((g0, g1), gx) in w0.zip(w1).zip(x) {
            if let (&[u0, u1, u2, u3], &[v0, v1, v2, v3], &[a0, a1, a2, a3, b0, b1, b2, b3]) = (g0, g1, gx) {
                // With `PAIR_SWAP` each group of a patch is stored as values 0, 2, 1, 3.
                let (a1, a2, b1, b2) = if Self::PAIR_SWAP { (a2, a1, b2, b1) } else { (a1, a2, b1, b2) };
                mac(u0, v0, a0, b0);
                mac(u1, v1, a1, b1);
                mac(u2, v2, a2, b2);
                mac(u3, v3, a3, b3);
            }
        }
        let (ra, rb) = rx.split_at(rx.len() / 2);
        for (((u, v), a), b) in r0.iter().zip(r1).zip(ra).zip(rb) {
            mac(*u, *v, *a, *b);
        }
        acc
    }
    /// Groups of four of `s` into the pair layout's groups in `d` (`2 s.len()` values: group `g`
    /// of `s` to `d[8 g..8 g + 4]`, or `d[8 g + 4..8 g + 8]` for the `second` patch), each as
    /// values 0, 2, 1, 3 with [`Elem::PAIR_SWAP`]; stops at the shorter.
    #[inline(always)]
    fn put_groups(d: &mut [Self], s: &[Self], second: bool) {
        let d = d.chunks_exact_mut(8).map(|d| {
            let (a, b) = d.split_at_mut(4);
            if second { b } else { a }
        });
        if Self::PAIR_SWAP {
            d.zip(s.chunks_exact(4)).for_each(|(g, s)| {
                if let ([g0, g1, g2, g3], &[s0, s1, s2, s3]) = (g, s) {
                    (*g0, *g1, *g2, *g3) = (s0, s2, s1, s3);
                }
            });
        } else {
            d.zip(s.chunks_exact(4)).for_each(|(g, s)| g.copy_from_slice(s));
        }
    }
    /// The four channels' dot products of a Helium convolution block by one assembly call per
    /// channel pair for all parts ([`mve::PartLens::dots4`], i16 activations); `None` where this
    /// type has none (the block then takes its parts one by one).
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots4(_l: &mve::PartLens, _w: &[i8], _pair: &[Self], _d: &mut [i32; 8 * crate::model::graph::MAX_PARTS]) -> Option<bool> {
        None
    }
    /// The twelve channels' dot products of a Helium convolution block by one assembly call per
    /// three channels for all parts ([`mve::PartLens::dots12`], i16 activations); `None` where
    /// this type has none (the layer then takes blocks of four).
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12(_l: &mve::PartLens, _w: &[i8], _pair: &[Self], _s: &[i32; 2 * crate::model::graph::MAX_PARTS], _d: &mut [i32; 24 * crate::model::graph::MAX_PARTS]) -> Option<bool> {
        None
    }
    /// What [`Elem::dots12`] needs of a pair besides its values, once per pair: u8 activations
    /// `128 sum(x)` per part and patch ([`mve::pair_sums_u8`]); false where this type has no
    /// [`Elem::dots12`] or the pair does not fit it.
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12_prepare(_l: &mve::PartLens, _pair: &[Self], _s: &mut [i32; 2 * crate::model::graph::MAX_PARTS]) -> bool {
        false
    }
    /// Whether one-part Helium layers of this type take [`Elem::dots_flipped`] (u8).
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    const FLIPS: bool = false;
    /// All `cout` channels' dot products of a one-part Helium pair in one pass over the
    /// activations flipped in place to `x - 128` ([`mve::dots_flipped`], u8; `ws[c]` is `128
    /// sum(w_c)`); false, with `pair` untouched, where this type or the shapes have none.
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots_flipped(_ws: &[i32], _w: &[i8], _kl: usize, _cout: usize, _pair: &mut [Self], _d: &mut [i32; 24 * crate::model::graph::MAX_PARTS]) -> bool {
        false
    }
    /// Flips the values [`Elem::dots_flipped`] flipped back (`x ^ 0x80` on u8).
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn unflip(_pair: &mut [Self]) {}
    /// The slice as a conv output row.
    fn as_out(d: &mut [Self]) -> OutRow<'_>;
    /// A whole convolution row by a path of this type's own with the engine's byte scratch
    /// (`conv::conv_row_u8_wide` for u8 on the DSP build); false when there is none (the caller
    /// then runs `conv::conv_row`).
    #[inline(always)]
    fn conv_row_wide(_p: &conv::ConvParams<'_>, _inputs: &[conv::PartRows<'_, Self>], _w_in: usize, _out: &mut OutRow<'_>, _scratch: &mut [u8]) -> bool {
        false
    }
}

#[deny(clippy::indexing_slicing)]
impl Elem for i8 {
    const BITS: u8 = 8;
    const STORAGE: crate::arith::QFormat = crate::arith::QFormat::i8(0);
    #[inline(always)]
    fn to_i32(self) -> i32 {
        self as i32
    }
    #[inline(always)]
    fn from_i64_sat(v: i64) -> Self {
        crate::arith::sat_i8(v)
    }
    #[inline]
    fn dot(w: &[i8], x: &[i8]) -> i64 {
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        return mve::dot(w, x) as i64;
        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
        return dsp::dot(w, x) as i64;
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        if let Some(s) = x86::dot(w, x) {
            return s;
        }
        // |w*x| <= 2^14, so an i32 sum is exact for up to 2^17 terms (every layer has fewer).
        #[allow(unreachable_code)]
        let mut acc = 0i32;
        for (a, b) in w.iter().zip(x) {
            acc += *a as i32 * *b as i32;
        }
        acc as i64
    }
    fn as_out(d: &mut [i8]) -> OutRow<'_> {
        OutRow::I8(d)
    }
}

#[deny(clippy::indexing_slicing)]
impl Elem for u8 {
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline(always)]
    fn conv_row_wide(p: &conv::ConvParams<'_>, inputs: &[conv::PartRows<'_, u8>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
        conv::conv_row_u8_wide(p, inputs, w_in, out, scratch)
    }
    const BITS: u8 = 8;
    const STORAGE: crate::arith::QFormat = crate::arith::QFormat::u8(0);
    #[inline(always)]
    fn to_i32(self) -> i32 {
        self as i32
    }
    #[inline(always)]
    fn from_i64_sat(v: i64) -> Self {
        crate::arith::sat_u8(v)
    }
    #[inline]
    fn dot(w: &[i8], x: &[u8]) -> i64 {
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        return mve::dot(w, x) as i64;
        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
        return dsp::dot(w, x) as i64;
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        if let Some(s) = x86::dot(w, x) {
            return s;
        }
        // |w*x| <= 128 * 255 < 2^15, so an i32 sum is exact for up to 2^16 terms (every layer
        // has fewer).
        #[allow(unreachable_code)]
        let mut acc = 0i32;
        for (a, b) in w.iter().zip(x) {
            acc += *a as i32 * *b as i32;
        }
        acc as i64
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    const SPLIT_PAIRS: bool = true;
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline]
    fn dot2(w0: &[i8], w1: &[i8], x: &[u8]) -> (i64, i64) {
        let (a, b) = dsp::dot2(w0, w1, x);
        (a as i64, b as i64)
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline]
    fn dot2x2(w0: &[i8], w1: &[i8], x: &[u8]) -> [i64; 4] {
        dsp::dot2x2(w0, w1, x).map(|v| v as i64)
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12(l: &mve::PartLens, w: &[i8], pair: &[u8], s: &[i32; 2 * crate::model::graph::MAX_PARTS], d: &mut [i32; 24 * crate::model::graph::MAX_PARTS]) -> Option<bool> {
        Some(l.dots12_u8(w, pair, s, d))
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12_prepare(l: &mve::PartLens, pair: &[u8], s: &mut [i32; 2 * crate::model::graph::MAX_PARTS]) -> bool {
        mve::pair_sums_u8(l, pair, s)
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    const FLIPS: bool = true;
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots_flipped(ws: &[i32], w: &[i8], kl: usize, cout: usize, pair: &mut [u8], d: &mut [i32; 24 * crate::model::graph::MAX_PARTS]) -> bool {
        mve::dots_flipped(ws, w, kl, cout, pair, d)
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn unflip(pair: &mut [u8]) {
        mve::flip_u8(pair)
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline]
    fn dot2x2(w0: &[i8], w1: &[i8], x: &[u8]) -> [i64; 4] {
        // The split pair layout: patch `a`, then patch `b` (`SPLIT_PAIRS`).
        let n = w0.len().min(w1.len()).min(x.len() / 2);
        let (a, b) = x.split_at(n);
        mve::dot2x2_split(w0, w1, a, b).map(|v| v as i64)
    }
    fn as_out(d: &mut [u8]) -> OutRow<'_> {
        OutRow::U8(d)
    }
}

#[deny(clippy::indexing_slicing)]
impl Elem for i16 {
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline(always)]
    fn put_groups(d: &mut [i16], s: &[i16], second: bool) {
        dsp::put_groups_i16(d, s, second);
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline(always)]
    fn conv_row_wide(p: &conv::ConvParams<'_>, inputs: &[conv::PartRows<'_, i16>], w_in: usize, out: &mut OutRow<'_>, scratch: &mut [u8]) -> bool {
        conv::conv_row_i16_wide(p, inputs, w_in, out, scratch)
    }
    const BITS: u8 = 16;
    const PAIR_SWAP: bool = true;
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots4(l: &mve::PartLens, w: &[i8], pair: &[i16], d: &mut [i32; 8 * crate::model::graph::MAX_PARTS]) -> Option<bool> {
        Some(l.dots4(w, pair, d))
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12(l: &mve::PartLens, w: &[i8], pair: &[i16], _s: &[i32; 2 * crate::model::graph::MAX_PARTS], d: &mut [i32; 24 * crate::model::graph::MAX_PARTS]) -> Option<bool> {
        Some(l.dots12(w, pair, d))
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    #[inline(always)]
    fn dots12_prepare(_l: &mve::PartLens, _pair: &[i16], _s: &mut [i32; 2 * crate::model::graph::MAX_PARTS]) -> bool {
        true
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    const SPLIT_PAIRS: bool = true;
    const STORAGE: crate::arith::QFormat = crate::arith::QFormat::i16(0);
    #[inline(always)]
    fn to_i32(self) -> i32 {
        self as i32
    }
    #[inline(always)]
    fn from_i64_sat(v: i64) -> Self {
        crate::arith::sat_i16(v)
    }
    #[inline]
    fn dot(w: &[i8], x: &[i16]) -> i64 {
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        if let Some(s) = x86::dot(w, x) {
            return s;
        }
        // |w*x| <= 2^22: chunks of I16_CHUNK terms sum exactly in i32; chunk sums add in i64.
        // Integer addition is exact, so the result equals the plain i64 sum.
        let mut acc = 0i64;
        for (wc, xc) in w.chunks(I16_CHUNK).zip(x.chunks(I16_CHUNK)) {
            #[cfg(all(target_arch = "arm", feature = "mve"))]
            let s = mve::dot(wc, xc);
            #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
            let s = dsp::dot(wc, xc);
            #[cfg(not(all(target_arch = "arm", any(feature = "dsp", feature = "mve"))))]
            let s = {
                let mut s = 0i32;
                for (a, b) in wc.iter().zip(xc) {
                    s += *a as i32 * *b as i32;
                }
                s
            };
            acc += s as i64;
        }
        acc
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    #[inline]
    fn dot2(w0: &[i8], w1: &[i8], x: &[i16]) -> (i64, i64) {
        // Same chunks as `dot`, so every partial sum stays exact in i32.
        let (mut a, mut b) = (0i64, 0i64);
        for ((c0, c1), xc) in w0.chunks(I16_CHUNK).zip(w1.chunks(I16_CHUNK)).zip(x.chunks(I16_CHUNK)) {
            let (s0, s1) = dsp::dot2(c0, c1, xc);
            a += s0 as i64;
            b += s1 as i64;
        }
        (a, b)
    }
    #[cfg(all(target_arch = "arm", any(feature = "dsp", feature = "mve")))]
    // DSP build: inlined into the 2x2 block, so the sums go straight to its frame (no call, no
    // copy of the four i64 per part).
    #[cfg_attr(not(feature = "mve"), inline(always))]
    #[cfg_attr(feature = "mve", inline)]
    fn dot2x2(w0: &[i8], w1: &[i8], x: &[i16]) -> [i64; 4] {
        // Same chunks as `dot` (a multiple of 4: each chunk of the pair layout is itself in the
        // pair layout), so every partial sum stays exact in i32.
        #[cfg(not(feature = "mve"))]
        return dsp::dot2x2_i16(w0, w1, x);
        #[cfg(feature = "mve")]
        {
            // The split pair layout (`SPLIT_PAIRS`): patch `a`, then patch `b`.
            let n = w0.len().min(w1.len()).min(x.len() / 2);
            let (a, b) = x.split_at(n);
            mve::dot2x2_split_i16(w0, w1, a, b)
        }
    }
    fn as_out(d: &mut [i16]) -> OutRow<'_> {
        OutRow::I16(d)
    }
}

/// Where value `j` of the first (`second == false`) or second of two `n`-value patches sits in
/// their pair layout: groups of four, `a[4g..4g+4]` then `b[4g..4g+4]`, then the `n % 4` last
/// values of `a`, then those of `b`. One pointer walks both patches four values at a time. With
/// `swap` (16-bit activations) each group is stored as values 0, 2, 1, 3: the halfword pairs
/// `SMLAD` takes against `SXTB16`-widened weights, loaded as words without re-packing.
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub const fn pair_index(n: usize, j: usize, second: bool, swap: bool) -> usize {
    let q = n / 4 * 4;
    if j < q {
        let t = j % 4;
        let t = if swap && (t == 1 || t == 2) { 3 - t } else { t };
        8 * (j / 4) + t + if second { 4 } else { 0 }
    } else {
        2 * q + (j - q) + if second { n - q } else { 0 }
    }
}

/// The first `n` values of `s` (all of them when it is shorter).
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub(crate) fn head<T>(s: &[T], n: usize) -> &[T] {
    s.get(..n).unwrap_or(s)
}

/// [`head`] of a mutable slice.
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub(crate) fn head_mut<T>(s: &mut [T], n: usize) -> &mut [T] {
    let n = n.min(s.len());
    s.get_mut(..n).unwrap_or_default()
}

/// Values `i * len .. (i + 1) * len` of `t` (row `i` of rows of `len` values); empty when `t` is
/// shorter.
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub(crate) fn chunk<T>(t: &[T], i: usize, len: usize) -> &[T] {
    t.get(i * len..(i + 1) * len).unwrap_or_default()
}

/// [`chunk`] of a mutable slice.
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub(crate) fn chunk_mut<T>(t: &mut [T], i: usize, len: usize) -> &mut [T] {
    t.get_mut(i * len..(i + 1) * len).unwrap_or_default()
}

/// `s[i] = v`, skipped when `i` is past the end.
#[inline(always)]
#[deny(clippy::indexing_slicing)]
pub(crate) fn set_at<T>(s: &mut [T], i: usize, v: T) {
    if let Some(o) = s.get_mut(i) {
        *o = v;
    }
}

/// Plain exact dot product (reference twin of [`Elem::dot`]).
#[deny(clippy::indexing_slicing)]
pub fn dot_plain<T: Elem>(w: &[i8], x: &[T]) -> i64 {
    w.iter().zip(x).map(|(a, b)| *a as i64 * b.to_i32() as i64).sum()
}

/// A mutable output row of either storage type.
pub enum OutRow<'a> {
    /// i8 storage.
    I8(&'a mut [i8]),
    /// u8 storage (ReLU outputs).
    U8(&'a mut [u8]),
    /// i16 storage.
    I16(&'a mut [i16]),
}

#[deny(clippy::indexing_slicing)]
impl OutRow<'_> {
    /// Stores `v` (already saturated to the row's range by the caller's format) at `i`.
    /// An `i` past the end is skipped (the kernels' callers size their rows to fit).
    #[inline(always)]
    pub fn set(&mut self, i: usize, v: i64) {
        match self {
            OutRow::I8(r) => set_at(r, i, crate::arith::sat_i8(v)),
            OutRow::U8(r) => set_at(r, i, crate::arith::sat_u8(v)),
            OutRow::I16(r) => set_at(r, i, crate::arith::sat_i16(v)),
        }
    }
    /// Length in elements.
    pub fn len(&self) -> usize {
        match self {
            OutRow::I8(r) => r.len(),
            OutRow::U8(r) => r.len(),
            OutRow::I16(r) => r.len(),
        }
    }
    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }
    /// The first `n` elements (all of them when the row is shorter).
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    pub(crate) fn head(&mut self, n: usize) -> OutRow<'_> {
        match self {
            OutRow::I8(r) => OutRow::I8(head_mut(r, n)),
            OutRow::U8(r) => OutRow::U8(head_mut(r, n)),
            OutRow::I16(r) => OutRow::I16(head_mut(r, n)),
        }
    }
}

#[cfg(test)]
pub(crate) mod testutil {
    /// Small deterministic generator for kernel tests (xorshift64*).
    pub struct Rng(pub u64);
    impl Rng {
        pub fn next(&mut self) -> u64 {
            self.0 ^= self.0 >> 12;
            self.0 ^= self.0 << 25;
            self.0 ^= self.0 >> 27;
            self.0.wrapping_mul(0x2545F4914F6CDD1D)
        }
        pub fn i8(&mut self) -> i8 {
            (self.next() >> 56) as i8
        }
        pub fn i16(&mut self) -> i16 {
            (self.next() >> 48) as i16
        }
        pub fn below(&mut self, n: u64) -> u64 {
            self.next() % n
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::testutil::Rng;
    use super::*;

    #[test]
    fn dot_paths_agree() {
        let mut r = Rng(7);
        for n in [0, 1, 9, 255, 256, 257, 507, 508, 509, 1000, 1016, 5760] {
            let w: Vec<i8> = (0..n).map(|_| r.i8()).collect();
            let x8: Vec<i8> = (0..n).map(|_| r.i8()).collect();
            let xu: Vec<u8> = (0..n).map(|_| r.i8() as u8).collect();
            assert_eq!(u8::dot(&w, &xu), dot_plain(&w, &xu));
            assert_eq!(u8::dot(&vec![-128i8; n], &vec![255u8; n]), dot_plain(&vec![-128i8; n], &vec![255u8; n]));
            let x16: Vec<i16> = (0..n).map(|_| r.i16()).collect();
            assert_eq!(i8::dot(&w, &x8), dot_plain(&w, &x8));
            assert_eq!(i16::dot(&w, &x16), dot_plain(&w, &x16));
            // extremes
            let wm = vec![-128i8; n];
            let xm = vec![i16::MIN; n];
            assert_eq!(i16::dot(&wm, &xm), dot_plain(&wm, &xm));
        }
    }
}
