//! Correlation lookup and UFI proposals from int8 feature rows; no correlation volume.
//!
//! `C(x1, x2) = <f1(x1), f2(x2)>` is an exact i32 dot product (features i8); columns outside the
//! row are 0. A lookup for one left pixel needs only the columns its samples touch: the tiled
//! kernel computes them once into a window of at most [`window_len`] columns and reads box sums
//! from its prefix sums, so its memory depends on neither the image width nor the disparity range.
//!
//! Sample numerators (exact integers), with `centre = (x << 8) + flow` (Q8, `flow` = -disparity):
//! * post-pooling, level `l`, offset `j`: first sub-sample `p0 = centre + (j << (8+l)) - ((2^l - 1) << 7)`,
//!   `m = p0 >> 8`, `a = p0 & 255`: `(256 - a) * S(m, m + 2^l) + a * S(m + 1, m + 1 + 2^l)` with
//!   `S(u, v) = sum_{u <= t < v} C(t)`; units: C / (256 * 2^l).
//! * RAFT pyramid, level `l`: `q = centre + (j << (8+l))`, `i = q >> (8+l)`, `a = q & (2^(8+l) - 1)`:
//!   `(2^(8+l) - a) * B(i) + a * B(i + 1)` with `B(k)` the sum of block `k` of `2^l` columns
//!   (0 unless `k < floor(w / 2^l)`); units: C / 2^(8+2l).
//!
//! Each numerator is requantised with the level's multiplier (blob) into the `Corr` format.
//!
//! Columns of a too-short feature row count as 0 (uncorrelated); scratch or output shorter than
//! the parameters need gets only what fits.
#![deny(clippy::indexing_slicing)]

use crate::arith::{MAX_PROPOSAL_D8, Multiplier, requantize, requantize_i32, sat_i16};

#[cfg(all(target_arch = "x86_64", feature = "std"))]
#[path = "corr_avx512.rs"]
pub mod avx512;

/// Parameters of a lookup.
#[derive(Clone, Copy, Debug)]
pub struct LookupParams<'a> {
    /// Levels.
    pub levels: usize,
    /// Radius (2r+1 samples per level).
    pub radius: usize,
    /// Post-pooling (MUIR) or RAFT pyramid.
    pub post_pool: bool,
    /// Multiplier per level: numerator units to the output format.
    pub mults: &'a [Multiplier],
}

/// Columns one lookup can touch (window length of the tiled kernel).
pub const fn window_len(levels: usize, radius: usize) -> usize {
    let s = 1usize << (levels - 1);
    // post-pooling spans 2 (r s + (s-1)/2) + 3 columns, the pyramid s (2r + 3) + 1.
    s * (2 * radius + 3) + 4
}

#[inline(always)]
fn dot_i8(a: &[i8], b: &[i8]) -> i32 {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    return super::mve::dot(a, b);
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    return super::dsp::dot(a, b);
    #[allow(unreachable_code)]
    let mut s = 0i32;
    for (x, y) in a.iter().zip(b) {
        s += *x as i32 * *y as i32;
    }
    s
}

/// Column range `[lo, hi)` (possibly outside the row) the samples of a pixel touch.
fn span(p: &LookupParams<'_>, centre: i64) -> (i64, i64) {
    let l = p.levels as u32 - 1;
    let s = 1i64 << l;
    let r = p.radius as i64;
    if p.post_pool {
        let reach = (r << (8 + l)) + ((s - 1) << 7);
        ((centre - reach) >> 8, ((centre + reach) >> 8) + 2)
    } else {
        let q = centre >> (8 + l);
        ((q - r) * s, (q + r + 2) * s)
    }
}

/// Scratch of the tiled lookup.
pub struct LookupScratch<'a> {
    /// Correlations of the window's columns.
    pub window: &'a mut [i32],
    /// Prefix sums of `window` (one longer).
    pub prefix: &'a mut [i64],
}

/// Correlation of `f1` with column `col` of the feature row `f2` (`c` values per column): 0
/// outside the row's `w` columns (and past the end of a too-short `f2`).
#[inline(always)]
fn corr_at(f1: &[i8], f2: &[i8], c: usize, w: usize, col: i64) -> i32 {
    if col < 0 || col as usize >= w {
        return 0;
    }
    let col = col as usize;
    f2.get(col * c..(col + 1) * c).map_or(0, |f| dot_i8(f1, f))
}

/// Tiled lookup for left pixel `x` of a row: `f1` is the pixel's feature vector, `f2` the right
/// feature row (`w * c`, HWC), `flow` the pixel's Q8 flow. Writes `levels * (2r+1)` values
/// (none when the scratch is shorter than [`window_len`]; levels without a multiplier or
/// without room in `out` are skipped).
#[allow(clippy::too_many_arguments)]
pub fn lookup_pixel(p: &LookupParams<'_>, f1: &[i8], f2: &[i8], w: usize, x: usize, flow: i16, s: &mut LookupScratch<'_>, out: &mut [i16]) {
    lookup_with(p, w, x, flow, s, out, |lo, win| window(f1, f2, w, lo, win));
}

/// `win[i]` = the correlation of `f1` with column `lo + i` of the feature row `f2` (`w` columns
/// of `f1.len()` values; 0 outside them).
pub fn window(f1: &[i8], f2: &[i8], w: usize, lo: i64, win: &mut [i32]) {
    let c = f1.len();
    // Helium: the in-row columns `s..e` by one assembly loop, zeros around them.
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    {
        let n = win.len() as i64;
        let (s, e) = (lo.clamp(0, w as i64), (lo + n).clamp(0, w as i64).max(lo.clamp(0, w as i64)));
        let (i, j) = ((s - lo).clamp(0, n) as usize, (e - lo).clamp(0, n) as usize);
        if let (Some(f2), Some(mid)) = (f2.get(s as usize * c..e as usize * c), win.get_mut(i..j))
            && super::mve::corr_window(f1, f2, mid)
        {
            win.get_mut(..i).unwrap_or_default().fill(0);
            win.get_mut(j..).unwrap_or_default().fill(0);
            return;
        }
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    {
        // Armv7E-M: four columns of the row at a time (`f1`'s quads widened once for the four).
        let mut i = 0;
        while i < win.len() {
            let col = lo + i as i64;
            let four = (col >= 0 && col as usize + 4 <= w).then(|| f2.get(col as usize * c..(col as usize + 4) * c)).flatten();
            match (four, win.get_mut(i..i + 4)) {
                (Some(cols), Some(dst)) => {
                    dst.copy_from_slice(&super::dsp::dot_i8_4cols(f1, cols, c));
                    i += 4;
                }
                _ => {
                    if let Some(v) = win.get_mut(i) {
                        *v = corr_at(f1, f2, c, w, col);
                    }
                    i += 1;
                }
            }
        }
        return;
    }
    #[allow(unreachable_code)]
    for (i, v) in win.iter_mut().enumerate() {
        *v = corr_at(f1, f2, c, w, lo + i as i64);
    }
}

/// [`window`] with the row `f2` also widened by `dsp::widen_i8_quads` into `wide` (`w c / 2`
/// words; the engine widens each right feature row once for its pixels): four in-row columns at
/// a time by `dsp::dot_w8_4cols` (16 instructions per 16 MACs against 23 for
/// `dsp::dot_i8_4cols`), the rest one by one; the same integers. Only the columns inside the row
/// are written (the others, 0 by [`window`]'s contract, are left as they are: [`lookup_with`]
/// on this build reads none of them).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn window_wide(f1: &[i8], f2: &[i8], wide: &[u32], w: usize, lo: i64, win: &mut [i32]) {
    let c = f1.len();
    let h = c / 2;
    let n = win.len() as i64;
    // (`min` then `max`, not `clamp`: `clamp` checks its bounds' order by a panic)
    let i = (-lo).clamp(0, n);
    let j = (w as i64 - lo).min(n).max(i);
    let (mut t, j) = (i as usize, j as usize);
    while t < j {
        // `lo + t` is in `0..w` here.
        let col = (lo + t as i64) as usize;
        let four = if t + 4 <= j { wide.get(col * h..(col + 4) * h).and_then(|cols| super::dsp::dot_w8_4cols(f1, cols, c)) } else { None };
        match (four, win.get_mut(t..t + 4)) {
            (Some(v), Some(dst)) => {
                dst.copy_from_slice(&v);
                t += 4;
            }
            _ => {
                if let Some(v) = win.get_mut(t) {
                    *v = corr_at(f1, f2, c, w, col as i64);
                }
                t += 1;
            }
        }
    }
}

/// [`lookup_pixel`] with the window's correlations from `window(lo, win)`: `win[i]` must be the
/// correlation with column `lo + i` (0 outside the row's `w` columns).
#[allow(clippy::too_many_arguments)]
#[inline]
pub fn lookup_with(p: &LookupParams<'_>, w: usize, x: usize, flow: i16, s: &mut LookupScratch<'_>, out: &mut [i16], window: impl FnOnce(i64, &mut [i32])) {
    let centre = ((x as i64) << 8) + flow as i64;
    let (lo, hi) = span(p, centre);
    let n = (hi - lo) as usize;
    let (Some(win), Some(pre)) = (s.window.get_mut(..n), s.prefix.get_mut(..n + 1)) else {
        return;
    };
    window(lo, win);
    // pre[i] = sum of win[..i].
    let mut acc = 0i64;
    // The OR of the correlations' magnitudes: below `2^k` when every one is.
    let mut mag = 0u32;
    if let Some((first, rest)) = pre.split_first_mut() {
        *first = 0;
        // Helium: the largest magnitude by a vector loop (below `2^k` exactly when the OR is).
        #[cfg(all(target_arch = "arm", feature = "mve"))]
        {
            mag = crate::kernels::mve::max_abs_i32(win);
            for (q, v) in rest.iter_mut().zip(win.iter()) {
                acc += *v as i64;
                *q = acc;
            }
        }
        // Armv7E-M: only the window's columns inside the row are summed (the others are 0 by
        // the window's contract: the sums before them 0, after them the row's total; at 160x120
        // most of a window's columns lie outside the 1/8 row). `window_wide` writes only those.
        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
        {
            let i = (-lo).clamp(0, n as i64) as usize;
            // (`min` then `max`, not `clamp`: `clamp` checks its bounds' order by a panic)
            let j = (w as i64 - lo).min(n as i64).max(i as i64) as usize;
            let (before, rest) = rest.split_at_mut(i.min(rest.len()));
            before.iter_mut().for_each(|q| *q = 0);
            let (inside, after) = rest.split_at_mut((j - i).min(rest.len()));
            for (q, v) in inside.iter_mut().zip(win.iter().skip(i)) {
                acc += *v as i64;
                mag |= v.unsigned_abs();
                *q = acc;
            }
            after.iter_mut().for_each(|q| *q = acc);
        }
        #[cfg(not(all(target_arch = "arm", any(feature = "mve", feature = "dsp"))))]
        for (q, v) in rest.iter_mut().zip(win.iter()) {
            acc += *v as i64;
            mag |= v.unsigned_abs();
            *q = acc;
        }
    }
    let pre = &*pre;
    // S(u, v) over columns, clipped to the window (columns outside it hold no samples' data and
    // those outside the row are 0 by construction); `pre` has `n + 1` values.
    let box_sum = |u: i64, v: i64| {
        let a = (u - lo).clamp(0, n as i64) as usize;
        let b = (v - lo).clamp(0, n as i64) as usize;
        match (pre.get(a), pre.get(b)) {
            (Some(a), Some(b)) => b - a,
            _ => 0,
        }
    };
    let k = 2 * p.radius + 1;
    let r = p.radius as i64;
    for ((lvl, &mult), out) in p.mults.iter().enumerate().take(p.levels).zip(out.chunks_exact_mut(k)) {
        let s_l = 1i64 << lvl;
        if p.post_pool {
            // The level's samples `j = -r..=r` share the sub-pixel phase `a` (their offsets `j
            // 2^(8 + lvl)` are whole multiples of `s_l` columns) and their first columns `m` step
            // by `s_l`: sample `t = j + r` reads `pre` at `i0 + t s_l + {0, s_l, 1, 1 + s_l}`.
            // Where all of these lie inside `pre` (always: the window spans the widest level)
            // no clamp applies and `box_sum` is a difference of two of them, walked by strides.
            let p0 = centre - (r << (8 + lvl)) - ((s_l - 1) << 7);
            let (i0, a) = ((p0 >> 8) - lo, p0 & 255);
            // (`max`: a stride the compiler sees is not 0, no panic path in `step_by`.)
            let (sl, last) = ((s_l as usize).max(1), i0 + 2 * r * s_l + 1 + s_l);
            if i0 >= 0
                && last <= n as i64
                && let Some(pre) = pre.get(i0 as usize..=last as usize)
            {
                let i32_ok = lvl <= 20 && mag < (1 << 21) >> lvl && (1..=62).contains(&mult.shift);
                // Helium: the same i32 arithmetic four samples a vector.
                #[cfg(all(target_arch = "arm", feature = "mve"))]
                if i32_ok && crate::kernels::mve::lookup_samples(pre, sl, a as i32, mult, out) {
                    continue;
                }
                #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
                if i32_ok && samples_i32(pre, sl, a as i32, mult, out) {
                    continue;
                }
                let (x0, x1) = (pre.iter().step_by(sl), pre.get(sl..).unwrap_or_default().iter().step_by(sl));
                let (y0, y1) = (pre.get(1..).unwrap_or_default().iter().step_by(sl), pre.get(1 + sl..).unwrap_or_default().iter().step_by(sl));
                let samples = out.iter_mut().zip(x0).zip(x1).zip(y0).zip(y1);
                if i32_ok {
                    // Every box of `s_l` correlations is below `2^21` in magnitude, so `num`
                    // is below `256 * 2^21 = 2^29`: i32 arithmetic (the low words of the prefix
                    // sums differ by the box exactly) and `requantize`'s own i32 path.
                    let a = a as i32;
                    for ((((o, x0), x1), y0), y1) in samples {
                        let (b0, b1) = ((*x1 as i32).wrapping_sub(*x0 as i32), (*y1 as i32).wrapping_sub(*y0 as i32));
                        *o = sat_i16(requantize_i32((256 - a).wrapping_mul(b0).wrapping_add(a.wrapping_mul(b1)), mult));
                    }
                } else {
                    for ((((o, x0), x1), y0), y1) in samples {
                        *o = sat_i16(requantize((256 - a) * (x1 - x0) + a * (y1 - y0), mult));
                    }
                }
                continue;
            }
        }
        for (j, o) in (-r..=r).zip(out) {
            let num = if p.post_pool {
                let p0 = centre + (j << (8 + lvl)) - ((s_l - 1) << 7);
                let (m, a) = (p0 >> 8, p0 & 255);
                (256 - a) * box_sum(m, m + s_l) + a * box_sum(m + 1, m + 1 + s_l)
            } else {
                let q = centre + (j << (8 + lvl));
                let (i, a) = (q >> (8 + lvl), q & ((1i64 << (8 + lvl)) - 1));
                let blocks = (w >> lvl) as i64;
                let block = |b: i64| if b >= 0 && b < blocks { box_sum(b * s_l, (b + 1) * s_l) } else { 0 };
                ((1i64 << (8 + lvl)) - a) * block(i) + a * block(i + 1)
            };
            *o = sat_i16(requantize(num, mult));
        }
    }
}

/// The post-pooling samples of one level where their numerators fit i32 (`lookup_with`'s
/// `i32_ok` case): sample `t` reads the prefix sums' low words at `t sl`, `t sl + 1`, `(t + 1) sl`
/// and `(t + 1) sl + 1` (`pre`: at least `out.len() sl + 2` values), each shared with the next
/// sample, out of line (inlined into the lookup the loop spilled its pointers: about 80
/// instructions a sample, against about 14). The same integers as the compiled loop:
/// `requantize_i32` and `sat_i16` (by `SSAT`). `false` (nothing written) for a stride of 0 or a
/// short `pre`.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn samples_i32(pre: &[i64], sl: usize, a: i32, mult: Multiplier, out: &mut [i16]) -> bool {
    let k = out.len();
    if sl == 0 || pre.len() < k * sl + 2 {
        return false;
    }
    // The low word of `pre[i]` (little-endian), unchecked: every `i` below is at most `k sl + 1`.
    let base = pre.as_ptr().cast::<i32>();
    // SAFETY: `i <= k sl + 1 < pre.len()` (checked above).
    let lo = |i: usize| unsafe { *base.add(2 * i) };
    let (mut x0, mut y0) = (lo(0), lo(1));
    let s = mult.shift as u32;
    let b = 256 - a;
    if (33..=62).contains(&s) {
        let (half, sh) = (1i32 << (s - 33), s - 32);
        for (t, o) in out.iter_mut().enumerate() {
            let i = (t + 1) * sl;
            let (x1, y1) = (lo(i), lo(i + 1));
            let num = b.wrapping_mul(x1.wrapping_sub(x0)).wrapping_add(a.wrapping_mul(y1.wrapping_sub(y0)));
            let hi = ((num as i64 * mult.m as i64) >> 32) as i32;
            *o = super::dsp::ssat16(hi.wrapping_add(half) >> sh);
            (x0, y0) = (x1, y1);
        }
    } else {
        for (t, o) in out.iter_mut().enumerate() {
            let i = (t + 1) * sl;
            let (x1, y1) = (lo(i), lo(i + 1));
            let num = b.wrapping_mul(x1.wrapping_sub(x0)).wrapping_add(a.wrapping_mul(y1.wrapping_sub(y0)));
            *o = sat_i16(requantize_i32(num, mult));
            (x0, y0) = (x1, y1);
        }
    }
    true
}

/// Plain twin of [`lookup_pixel`]: every sub-sample interpolated on its own, every correlation
/// recomputed from the features.
pub fn lookup_pixel_plain(p: &LookupParams<'_>, f1: &[i8], f2: &[i8], w: usize, x: usize, flow: i16, out: &mut [i16]) {
    let c = f1.len();
    let corr = |col: i64| -> i64 { corr_at(f1, f2, c, w, col) as i64 };
    let centre = ((x as i64) << 8) + flow as i64;
    let k = 2 * p.radius + 1;
    let r = p.radius as i64;
    for ((lvl, &mult), out) in p.mults.iter().enumerate().take(p.levels).zip(out.chunks_exact_mut(k)) {
        let s_l = 1i64 << lvl;
        for (j, o) in (-r..=r).zip(out) {
            let mut num = 0i64;
            if p.post_pool {
                for i in 0..s_l {
                    let pos = centre + (j << (8 + lvl)) + ((2 * i - s_l + 1) << 7);
                    let (m, a) = (pos >> 8, pos & 255);
                    num += (256 - a) * corr(m) + a * corr(m + 1);
                }
            } else {
                let q = centre + (j << (8 + lvl));
                let (i, a) = (q >> (8 + lvl), q & ((1i64 << (8 + lvl)) - 1));
                let blocks = (w >> lvl) as i64;
                let block = |b: i64| -> i64 {
                    if b < 0 || b >= blocks {
                        return 0;
                    }
                    (b * s_l..(b + 1) * s_l).map(corr).sum()
                };
                num = ((1i64 << (8 + lvl)) - a) * block(i) + a * block(i + 1);
            }
            *o = sat_i16(requantize(num, mult));
        }
    }
}

/// UFI proposals for left pixel `x`: integer disparities `(d1, d2)` of the highest correlations
/// over `d in [0, min(x, max_d8, MAX_PROPOSAL_D8)]` (`max_d8`: the largest disparity on the 1/8 grid,
/// [`crate::model::config::MaxDisparity::grid8`]), `d2` at least `separation` from `d1` (`d1` again
/// if none is); ties go to the smaller d. `row` is scratch of at least `x + 1` values (the search
/// stops at its end).
pub fn peaks_pixel(f1: &[i8], f2: &[i8], x: usize, separation: usize, max_d8: usize, row: &mut [i32]) -> (u16, u16) {
    let c = f1.len();
    let dmax = x.min(max_d8).min(MAX_PROPOSAL_D8);
    let row = super::head_mut(row, dmax + 1);
    for (d, v) in row.iter_mut().enumerate() {
        *v = corr_at(f1, f2, c, x + 1, (x - d) as i64);
    }
    let row = &*row;
    let best = |skip: Option<usize>| {
        let mut arg: Option<(usize, i32)> = None;
        for (d, &v) in row.iter().enumerate() {
            if skip.is_some_and(|d1| d.abs_diff(d1) < separation) {
                continue;
            }
            if arg.is_none_or(|(_, a)| v > a) {
                arg = Some((d, v));
            }
        }
        arg.map(|(d, _)| d)
    };
    let d1 = best(None).unwrap_or(0);
    let d2 = best(Some(d1)).unwrap_or(d1);
    (d1 as u16, d2 as u16)
}

/// Plain twin of [`peaks_pixel`] (no row buffer: correlations recomputed per comparison).
pub fn peaks_pixel_plain(f1: &[i8], f2: &[i8], x: usize, separation: usize, max_d8: usize) -> (u16, u16) {
    let c = f1.len();
    let corr = |d: usize| corr_at(f1, f2, c, x + 1, (x - d) as i64);
    let dmax = x.min(max_d8).min(MAX_PROPOSAL_D8);
    let mut d1 = 0;
    for d in 1..=dmax {
        if corr(d) > corr(d1) {
            d1 = d;
        }
    }
    let mut d2: Option<usize> = None;
    for d in 0..=dmax {
        if d.abs_diff(d1) >= separation && d2.is_none_or(|b| corr(d) > corr(b)) {
            d2 = Some(d);
        }
    }
    (d1 as u16, d2.unwrap_or(d1) as u16)
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::testutil::Rng;
    use super::*;

    #[test]
    fn tiled_lookup_matches_plain_twin() {
        let mut r = Rng(99);
        for &(levels, radius, post_pool) in &[(4, 4, true), (4, 4, false), (2, 3, true), (3, 2, false)] {
            let (w, c) = (37, 16);
            let f1: Vec<i8> = (0..w * c).map(|_| r.i8()).collect();
            let f2: Vec<i8> = (0..w * c).map(|_| r.i8()).collect();
            let mults: Vec<Multiplier> = (0..levels).map(|l| Multiplier { m: 1 << 30, shift: 14 + l as u8 }).collect();
            let p = LookupParams { levels, radius, post_pool, mults: &mults };
            let wl = window_len(levels, radius);
            let (mut win, mut pre) = (vec![0i32; wl], vec![0i64; wl + 1]);
            let k = levels * (2 * radius + 1);
            let (mut a, mut b) = (vec![0i16; k], vec![0i16; k]);
            for x in 0..w {
                for flow in [0i16, -1, -255, -256, -300, -(x as i16) * 256 - 77, 513, -9000, 9000] {
                    let mut s = LookupScratch { window: &mut win, prefix: &mut pre };
                    lookup_pixel(&p, &f1[x * c..(x + 1) * c], &f2, w, x, flow, &mut s, &mut a);
                    lookup_pixel_plain(&p, &f1[x * c..(x + 1) * c], &f2, w, x, flow, &mut b);
                    assert_eq!(a, b, "x {x} flow {flow} levels {levels} post {post_pool}");
                }
            }
        }
    }

    /// Correlations near the i8 limits (128 channels: up to `2^21` each): the lookup's i32 path
    /// must give way to the i64 one where a box of them could overflow it.
    #[test]
    fn tiled_lookup_large_correlations() {
        let mut r = Rng(7);
        let (w, c, levels, radius) = (24, 128, 4, 4);
        let ext = |r: &mut Rng, i: usize| match (i / c) % 4 {
            0..=2 => -128,
            _ => r.i8(),
        };
        let f1: Vec<i8> = (0..w * c).map(|i| ext(&mut r, i)).collect();
        let f2: Vec<i8> = (0..w * c).map(|i| ext(&mut r, i)).collect();
        let mults: Vec<Multiplier> = (0..levels).map(|l| Multiplier { m: (1 << 30) + 12345, shift: 44 + l as u8 }).collect();
        let p = LookupParams { levels, radius, post_pool: true, mults: &mults };
        let wl = window_len(levels, radius);
        let (mut win, mut pre) = (vec![0i32; wl], vec![0i64; wl + 1]);
        let k = levels * (2 * radius + 1);
        let (mut a, mut b) = (vec![0i16; k], vec![0i16; k]);
        for x in 0..w {
            for flow in [0i16, -77, -256, -700, 300] {
                let mut s = LookupScratch { window: &mut win, prefix: &mut pre };
                lookup_pixel(&p, &f1[x * c..(x + 1) * c], &f2, w, x, flow, &mut s, &mut a);
                lookup_pixel_plain(&p, &f1[x * c..(x + 1) * c], &f2, w, x, flow, &mut b);
                assert_eq!(a, b, "x {x} flow {flow}");
            }
        }
    }

    #[test]
    fn peaks_match_plain_twin() {
        let mut r = Rng(5);
        let (w, c) = (40, 8);
        let f1: Vec<i8> = (0..w * c).map(|_| r.i8() / 16).collect();
        let f2: Vec<i8> = (0..w * c).map(|_| r.i8() / 16).collect();
        let mut row = vec![0i32; w];
        for x in 0..w {
            for sep in [1, 2, 5] {
                for max_d8 in [1, 7, 32, MAX_PROPOSAL_D8] {
                    let a = peaks_pixel(&f1[x * c..(x + 1) * c], &f2, x, sep, max_d8, &mut row);
                    let b = peaks_pixel_plain(&f1[x * c..(x + 1) * c], &f2, x, sep, max_d8);
                    assert_eq!(a, b, "x {x} sep {sep} max {max_d8}");
                    assert!(a.0 as usize <= max_d8.min(x) && a.1 as usize <= max_d8.min(x));
                }
            }
        }
    }

    /// The proposal search stops at the flow format's largest whole disparity: on a row wider than
    /// that, the best match beyond it is not proposed, and the largest proposal the search can
    /// give converts to a flow without saturating (Q7.8: -127 * 256 = -32512 >= i16::MIN).
    #[test]
    fn proposals_stay_inside_the_flow_format() {
        use crate::kernels::eltwise::proposal_flow;
        let (w, c) = (240, 4);
        let x = w - 1;
        // f2 matches f1 best at disparity 200 (beyond the limit), second best at MAX_PROPOSAL_D8.
        let f1 = [100i8; 4];
        let mut f2 = vec![0i8; w * c];
        f2[(x - 200) * c..(x - 199) * c].fill(100);
        f2[(x - MAX_PROPOSAL_D8) * c..(x - MAX_PROPOSAL_D8 + 1) * c].fill(90);
        let mut row = vec![0i32; w];
        let (d1, _) = peaks_pixel(&f1, &f2, x, 2, usize::MAX, &mut row);
        assert_eq!(d1 as usize, MAX_PROPOSAL_D8);
        assert_eq!(peaks_pixel_plain(&f1, &f2, x, 2, usize::MAX).0 as usize, MAX_PROPOSAL_D8);
        // A smaller search range (the default 256 px, 32 on the 1/8 grid) hides both matches.
        let d8 = crate::model::config::MaxDisparity::DEFAULT.grid8();
        assert_eq!(d8, 32);
        assert!(peaks_pixel(&f1, &f2, x, 2, d8, &mut row).0 as usize <= d8);
        assert_eq!(proposal_flow(d1), -(MAX_PROPOSAL_D8 as i16) * 256);
        assert_eq!(proposal_flow(MAX_PROPOSAL_D8 as u16 + 2), i16::MIN, "beyond the format: saturated");
    }
}
