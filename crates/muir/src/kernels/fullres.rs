//! Full-resolution refinement of the network's disparity: integer semi-global matching in a narrow
//! band around it.
//!
//! The network estimates disparity at 1/8 resolution and upsamples it (convex upsampling): robust,
//! but object boundaries are smeared and its sub-pixel precision is limited. This stage re-matches
//! every pixel at full resolution in a band around the network's value, with a classical cost,
//! semi-global aggregation along five image paths (Hirschmueller's SGM restricted to the band, so
//! no `h x w x D` volume) and a median, and keeps the network's value where the matching cannot
//! decide:
//!
//! * **grey**: `(77 R + 150 G + 29 B) >> 8` (a grey input is used as is);
//! * **census** `c(x, y)`: 48 bits over the 7x7 neighbourhood (row-major, the centre skipped), bit
//!   set when the neighbour is darker than the centre; coordinates clamped to the image;
//! * **cost** of disparity `d` at pixel `p`: `C(p, d) = sum over the 3x3 window of q = clamp(p + o)
//!   of popcount(cL(q) ^ cR(max(q.x - d, 0), q.y))` (at most 432);
//! * **band**: `base = d0 >> 5` (the network's disparity `d0` in Q10.5, floored), candidates
//!   `max(base - R, 0) ..= base + R + 1` (at most [`SLOTS`]), with `R` from the network's predicted
//!   error `sigma = exp(u / 2)`: `R = clamp(ceil(3 sigma), 3, 12) + BAND_MARGIN` (the band widens
//!   where the network is unsure), decided on `u` by the integer thresholds [`BAND_U_THRESHOLDS`];
//! * **paths**: along each of five directions `r` (from the left, from the right, from above, from
//!   above-left, from above-right; the predecessor `p - r` has its column clamped to the image),
//!   `L_r(p, d) = C(p, d) + min(L_r(q, d), L_r(q, d +- 1) + P1, m_q + P2'(p, q)) - m_q` with
//!   `q = p - r`, `m_q = min_k L_r(q, k)` over `q`'s own band (a `d` outside it has no term), and
//!   `P2'(p, q) = max(P1 + 1, P2 * EDGE_SCALE / (EDGE_SCALE + |grey(p) - grey(q)|))` (integer
//!   division: jumps are cheaper across image edges); a path starts (`L_r = C`) at the image border
//!   or after a pixel without candidates. Every `L_r < 432 + P2 < 2^12`;
//! * **decision**: `S(p, d) = sum_r L_r(p, d)`; `d*` = the first candidate of least `S`; decided
//!   only if `d*` has candidates on both sides and `S(d*-1) + S(d*+1) - 2 S(d*) > 0`; then the
//!   equiangular (V) fit through the three sums, in Q10.5: `(d* << 5) + div_round(16 (S(d*-1) -
//!   S(d*+1)), max(S(d*-1), S(d*+1)) - S(d*))` (at most half a pixel; a parabola pulls census-like
//!   costs towards whole pixels: median error 0.241 -> 0.230 px on the training scenes with the V);
//!   elsewhere the network's `d0` stays;
//! * **median**: the 3x3 median of those values (borders replicated) is the output.
//!
//! Parameters were chosen on the training scenes of `muir.split` (docs/experiments/fullres-refine):
//! held-out figures are reported, never tuned on. The stage streams over rows: per image a ring of
//! 3 census rows, per column [`SLOTS`] costs for the current row, the right-to-left path of the
//! row and the three downward paths of the previous and current rows ([`ScratchLen`]), so its
//! memory grows with the width only. The PyTorch twin's evaluation mirrors it bit for bit
//! (`python/muir/fullres.py`).
//!
//! No input reaches a panic: rows and per-column slots are taken with checked reads, and a map or
//! scratch shorter than the image needs leaves the map as it is ([`refine_image`] returns 0).
#![deny(clippy::indexing_slicing)]

use super::{chunk, chunk_mut, head, head_mut, set_at};
#[cfg(feature = "std")]
#[path = "fullres_threads.rs"]
mod threads;
#[cfg(all(target_arch = "x86_64", feature = "std"))]
#[path = "fullres_avx512.rs"]
mod avx512;
use crate::arith::{DISP_FRAC, div_round, sat_i16};
use crate::input::{ImageView, PixelFormat};

/// Census radius (7x7 neighbourhood, 48 bits).
pub const CENSUS_RADIUS: usize = 3;
/// Cost window radius (3x3 box of census distances).
pub const WINDOW_RADIUS: usize = 1;
/// Rows of census codes one output row needs (per image).
pub const WINDOW_ROWS: usize = 2 * WINDOW_RADIUS + 1;
/// Pixels added to every band radius beyond `ceil(3 sigma)` (clamped to 3 ..= 12): the fixed-point
/// and float engines' network outputs differ by fractions of a pixel, and where the network is
/// unsure those fractions move a narrow band's edge past the match the float engine finds.
/// Chosen on the training scenes (docs/experiments/fullres-refine, "Band margin"): margin 2
/// lowers Bad2.0 (7.40 -> 7.32 %) and the median error and raises EPE in occlusions (0.816 ->
/// 0.836 px); the engines' final outputs agree within 1 px on 99.22 % of the five
/// `fixed_vs_float` crops' pixels instead of 98.90 %.
pub const BAND_MARGIN: usize = 2;
/// Smallest band radius (px on each side of the network's disparity).
pub const MIN_BAND: usize = 3 + BAND_MARGIN;
/// Largest band radius.
pub const MAX_BAND: usize = 12 + BAND_MARGIN;
/// Most candidates of one pixel: `2 MAX_BAND + 2`.
pub const SLOTS: usize = 2 * MAX_BAND + 2;
/// Penalty of a one-pixel disparity step between neighbours on a path.
pub const P1: u32 = 256;
/// Penalty of a larger jump on a flat image.
pub const P2: u32 = 2048;
/// `P2` is divided by `1 + |grey step| / EDGE_SCALE`.
pub const EDGE_SCALE: u32 = 8;
/// `BAND_U_THRESHOLDS[i]`: the band radius is at least `MIN_BAND + 1 + i` when `u` (Q4.11)
/// exceeds it; `floor(2 ln((r - 1) / 3) * 2048)` for `r = 4 ..= 12` (`ceil(3 sigma) >= r` <=>
/// `sigma > (r - 1) / 3`; the radius is then `r + BAND_MARGIN`). Written out so that host and target use the same integers (a unit test
/// recomputes them).
pub const BAND_U_THRESHOLDS: [i16; MAX_BAND - MIN_BAND] = [0, 1178, 2092, 2839, 3470, 4017, 4499, 4931, 5321];

/// The path costs fit in `u16` and their five-way sum in `u32` with room: the largest cost plus
/// the largest penalty, times five, stays below `u16::MAX`.
const _: () = assert!(5 * ((WINDOW_ROWS * WINDOW_ROWS * 48) as u32 + P2) < u16::MAX as u32);
const _: () = assert!(P1 < P2 && EDGE_SCALE > 0);

/// Integer grey level of pixel `(x, y)` (coordinates clamped to the image).
#[inline]
pub fn grey_at(img: &ImageView<'_>, x: usize, y: usize) -> u8 {
    match img.format {
        PixelFormat::Gray8 => img.at_clamped(0, x, y),
        PixelFormat::Rgb8 => {
            let (r, g, b) = (img.at_clamped(0, x, y) as u32, img.at_clamped(1, x, y) as u32, img.at_clamped(2, x, y) as u32);
            ((77 * r + 150 * g + 29 * b) >> 8) as u8
        }
    }
}

/// Census codes of image row `clamp(y)` into `out` (`img.width` codes). `grey` is scratch of
/// `(2 * CENSUS_RADIUS + 1) * img.width` bytes (the grey rows `y - 3 ..= y + 3`; with less, the
/// codes stop where the centre row does). On Cortex-M55 with Helium the interior pixels' codes
/// come from `mve::census`, the same integers as [`census_row_portable`].
pub fn census_row(img: &ImageView<'_>, y: isize, grey: &mut [u8], out: &mut [u64]) {
    let w = img.width;
    if !grey_rows(img, y, grey) {
        return;
    }
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    if w > 2 * CENSUS_RADIUS && grey.len() >= (2 * CENSUS_RADIUS + 1) * w && out.len() >= w {
        super::mve::census(grey, w, out);
        census_codes(grey, w, (0..CENSUS_RADIUS).chain(w - CENSUS_RADIUS..w), out);
        return;
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    if w > 2 * CENSUS_RADIUS && grey.len() >= (2 * CENSUS_RADIUS + 1) * w && out.len() >= w {
        let done = census_interior_dsp(grey, w, out);
        // The columns near the ends four at a time on clamped copies (`census_edge_dsp`).
        for x0 in core::iter::once(0).chain((done..w).step_by(4)) {
            census_edge_dsp(grey, w, x0, out);
        }
        return;
    }
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    {
        let done = avx512::census_interior(grey, w, out);
        census_codes(grey, w, (0..CENSUS_RADIUS.min(w)).chain(done..w), out);
        return;
    }
    #[allow(unreachable_code)]
    census_codes(grey, w, 0..w, out);
}

/// The census codes of columns `3 .. done` (returned; `done - 3` a multiple of 4, no column
/// past `w - 4` needing a clamped neighbour) from the seven grey rows, four columns at a time
/// with the Armv7E-M byte instructions: per neighbour one word of four grey levels against the
/// four centres (`USUB8` sets a byte's GE flag where the neighbour is not darker, `SEL` makes
/// the darker ones' bytes `0xFF`), its top bits shifted into four byte accumulators, so that
/// eight neighbours make one byte of each of the four codes (neighbour order, first in bit 0).
/// About 5 instructions per neighbour and 4 pixels, against some 30 per neighbour and pixel for
/// [`census_codes`].
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn census_interior_dsp(grey: &[u8], w: usize, out: &mut [u64]) -> usize {
    let r = CENSUS_RADIUS;
    // The 48 neighbours (row-major, centre skipped) as offsets from column `x - 3` of row 0.
    let mut offs = [0usize; 48];
    let mut n = 0;
    for dy in 0..=2 * r {
        for dx in 0..=2 * r {
            if (dy, dx) != (r, r) {
                if let Some(o) = offs.get_mut(n) {
                    *o = dy * w + dx;
                }
                n += 1;
            }
        }
    }
    let mut x = r;
    // Pixels `x .. x + 4` read columns `x - 3 .. x + 7` of rows 0 ..= 6: within `7 w` bytes.
    while x + 4 + r <= w && grey.len() >= (2 * r + 1) * w && out.len() >= x + 4 {
        let base = grey.as_ptr().wrapping_add(x - r);
        // SAFETY: row 3, columns `x .. x + 4` (`x + 4 <= w`).
        let c = unsafe { base.add(r * w + r).cast::<u32>().read_unaligned() };
        let mut acc = [0u32; 6];
        for (a, group) in acc.iter_mut().zip(offs.chunks_exact(8)) {
            for &o in group {
                // SAFETY: row `dy <= 6`, columns `x - 3 + dx .. x + 1 + dx` with `dx <= 6`: below
                // `x + 7 <= w` (the loop's condition), inside `grey`'s `7 w` bytes.
                let nb = unsafe { base.add(o).cast::<u32>().read_unaligned() };
                // SAFETY: register-only DSP instructions (the GE flags they set are not read
                // after the block).
                unsafe {
                    core::arch::asm!(
                        "usub8 {t}, {n}, {c}",
                        "sel {t}, {z}, {f}",
                        "and {t}, {t}, #0x80808080",
                        "orr {a}, {t}, {a}, lsr #1",
                        t = out(reg) _, n = in(reg) nb, c = in(reg) c, z = in(reg) 0u32, f = in(reg) u32::MAX, a = inout(reg) *a,
                        options(pure, nomem, nostack),
                    );
                }
            }
        }
        for (j, code) in out.iter_mut().skip(x).take(4).enumerate() {
            let byte = |g: usize| ((acc.get(g).copied().unwrap_or(0) >> (8 * j)) & 0xFF) as u64;
            *code = (0..6).fold(0u64, |v, g| v | byte(g) << (8 * g));
        }
        x += 4;
    }
    x
}

/// The census codes of columns `x0 .. x0 + 4` (those below `w`) by [`census_interior_dsp`] on a
/// copy of the seven grey rows' columns `x0 - 3 .. x0 + 7`, each clamped to the image as
/// [`census_codes`] clamps its neighbours (the three first and the last three to six columns of
/// a row; [`census_codes`]' per-neighbour clamps and tests took 1.6 M more at 160x120).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
fn census_edge_dsp(grey: &[u8], w: usize, x0: usize, out: &mut [u64]) {
    const TW: usize = 4 + 2 * CENSUS_RADIUS;
    let mut t = [0u8; (2 * CENSUS_RADIUS + 1) * TW];
    for (dy, row) in t.chunks_exact_mut(TW).enumerate() {
        let src = chunk(grey, dy, w);
        for (k, v) in row.iter_mut().enumerate() {
            let x = (x0 + k).saturating_sub(CENSUS_RADIUS).min(w.saturating_sub(1));
            *v = src.get(x).copied().unwrap_or(0);
        }
    }
    let mut codes = [0u64; TW];
    if census_interior_dsp(&t, TW, &mut codes) == CENSUS_RADIUS + 4 {
        for (j, c) in codes.iter().skip(CENSUS_RADIUS).take(4).enumerate() {
            if x0 + j < w {
                set_at(out, x0 + j, *c);
            }
        }
    }
}

/// [`census_row`] without vector kernels: the specification.
pub fn census_row_portable(img: &ImageView<'_>, y: isize, grey: &mut [u8], out: &mut [u64]) {
    if grey_rows(img, y, grey) {
        census_codes(grey, img.width, 0..img.width, out);
    }
}

/// The grey rows `clamp(y) - 3 ..= clamp(y) + 3` (clamped) of [`census_row`] into `grey`;
/// `false` for an empty image (no codes).
#[inline(always)]
fn grey_rows(img: &ImageView<'_>, y: isize, grey: &mut [u8]) -> bool {
    let w = img.width;
    let n = 2 * CENSUS_RADIUS + 1;
    if w == 0 || img.height == 0 {
        return false; // an empty image has no codes
    }
    let clamp_y = |yy: isize| yy.clamp(0, (img.height as isize - 1).max(0)) as usize;
    // A row outside the image is the edge row's codes (the window replicates borders).
    let y = clamp_y(y) as isize;
    for (k, row) in grey.chunks_exact_mut(w).take(n).enumerate() {
        let yy = clamp_y(y + k as isize - CENSUS_RADIUS as isize);
        let ch = img.format.channels();
        // A whole row of the image: a grey image's row is its bytes (a copy), an RGB row is
        // converted pixel by pixel as `grey_at` does; a row the buffer lacks goes through
        // `grey_at` (0 past its end).
        match (img.format, img.data.get(yy * w * ch..(yy + 1) * w * ch)) {
            (PixelFormat::Gray8, Some(src)) => {
                #[cfg(all(target_arch = "arm", feature = "mve"))]
                super::mve::copy(row, src);
                #[cfg(not(all(target_arch = "arm", feature = "mve")))]
                row.iter_mut().zip(src).for_each(|(g, s)| *g = *s);
            }
            (PixelFormat::Rgb8, Some(src)) => {
                for (g, p) in row.iter_mut().zip(src.chunks_exact(3)) {
                    if let &[r, gg, b] = p {
                        *g = ((77 * r as u32 + 150 * gg as u32 + 29 * b as u32) >> 8) as u8;
                    }
                }
            }
            _ => {
                for (x, g) in row.iter_mut().enumerate() {
                    *g = grey_at(img, x, yy);
                }
            }
        }
    }
    true
}

/// The census codes of the columns `xs` (each below `w`) from the seven grey rows in `grey`.
#[inline(always)]
fn census_codes(grey: &[u8], w: usize, xs: impl Iterator<Item = usize>, out: &mut [u64]) {
    let n = 2 * CENSUS_RADIUS + 1;
    let r = CENSUS_RADIUS as isize;
    for x in xs {
        let (Some(&centre), Some(code)) = (grey.get(CENSUS_RADIUS * w + x), out.get_mut(x)) else {
            break;
        };
        let mut c = 0u64;
        let mut bit = 0;
        for dy in 0..n {
            let row = chunk(grey, dy, w);
            for dx in -r..=r {
                if dy == CENSUS_RADIUS && dx == 0 {
                    continue;
                }
                let xx = (x as isize + dx).clamp(0, (w as isize - 1).max(0)) as usize;
                c |= (row.get(xx).is_some_and(|g| *g < centre) as u64) << bit;
                bit += 1;
            }
        }
        *code = c;
    }
}

/// Band radius for an uncertainty `u` (Q4.11).
#[inline]
pub fn band_radius(u: i16) -> usize {
    MIN_BAND + BAND_U_THRESHOLDS.iter().filter(|t| u > **t).count()
}

/// Cost of disparity `d` at column `x`: the 3x3 box sum of census Hamming distances; `left` and
/// `right` are the census rows `y - 1 ..= y + 1` (clamped) of the two images (`w` codes each; a
/// code past the end of a shorter row adds nothing).
#[inline(always)]
fn cost(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, d: usize) -> u16 {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    {
        let cols = [x.saturating_sub(1), x, (x + 1).min(w.saturating_sub(1))];
        // Helium: the nine distances' codes as words, one vector popcount (`mve::popcount20`).
        let mut words = [0u32; 20];
        let mut slots = words.chunks_exact_mut(2);
        for (cl, cr) in left.iter().zip(right.iter()) {
            for q in cols {
                let (Some(slot), Some(a), Some(b)) = (slots.next(), cl.get(q), cr.get(q.saturating_sub(d))) else {
                    continue;
                };
                let v = a ^ b;
                if let [lo, hi] = slot {
                    (*lo, *hi) = (v as u32, (v >> 32) as u32);
                }
            }
        }
        return super::mve::popcount20(&words) as u16;
    }
    #[allow(unreachable_code)]
    cost_plain(left, right, w, x, d)
}

/// [`cost`] by `count_ones`: the specification.
#[inline(always)]
fn cost_plain(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, d: usize) -> u16 {
    let cols = [x.saturating_sub(1), x, (x + 1).min(w.saturating_sub(1))];
    let mut s = 0u32;
    for (cl, cr) in left.iter().zip(right.iter()) {
        for q in cols {
            if let (Some(a), Some(b)) = (cl.get(q), cr.get(q.saturating_sub(d))) {
                s += (a ^ b).count_ones();
            }
        }
    }
    s as u16
}

/// The costs of the candidates of band `b` at column `x` into `out[..b.n()]` (as far as `out`
/// reaches): `out[k] = cost(first + k)`. On Cortex-M55 with Helium the candidates whose columns
/// need no clamping go two at a time through `mve::cost_pairs`, the same integers.
#[inline(always)]
pub fn pixel_costs(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, b: Band, out: &mut [u16]) {
    let out = head_mut(out, b.n());
    #[allow(unused_mut, unused_assignments)]
    let mut done = 0;
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    if b.first >= 0 && x >= 1 {
        // Pairs `(d, d + 1)` with `d + 2 <= x`: no right column clamped at 0.
        let pairs = out.len().min(x.saturating_sub(b.first as usize)) / 2;
        let [l0, l1, l2] = *left;
        let [r0, r1, r2] = *right;
        if pairs > 0 && super::mve::cost_pairs([l0, l1, l2], [r0, r1, r2], w, x, b.first as usize, pairs, out) {
            done = 2 * pairs;
        }
    }
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    {
        done = avx512::costs(left, right, w, x, b, out);
    }
    for (k, c) in out.iter_mut().enumerate().skip(done) {
        *c = cost(left, right, w, x, b.first as usize + k);
    }
}

/// Whether [`refine_rows`] computes a row's costs by [`row_costs`]: where no vector kernel
/// computes a pixel's candidates at once (Helium, AVX-512), e.g. on a Cortex-M7.
const ROW_COSTS: bool = !cfg!(any(all(target_arch = "arm", feature = "mve"), all(target_arch = "x86_64", feature = "std")));

/// Most disparities of one column's sums in [`row_costs`] (the union of three neighbours'
/// bands; a wider union leaves the pixels that need the column to [`cost_plain`]).
const COLUMN_SPAN: usize = 2 * SLOTS;

/// The census distances of one column over the window's three rows at disparities `lo .. lo +
/// n` (`n <= COLUMN_SPAN`; `n = 0`: not computed, see [`row_costs`]).
#[derive(Clone, Copy)]
struct Column {
    lo: usize,
    n: usize,
    v: [u16; COLUMN_SPAN],
}

/// The Hamming distance of three pairs of 64-bit codes (`count_ones` of the XORs, summed) from
/// 4-bit partial counts: six XORs, each reduced to nibble counts (at most 4), three of them added
/// (at most 12), the two sums folded to bytes (at most 48) and the four bytes added by one
/// multiply (at most 192). About 50 ALU instructions on an Armv7-M core, which has no popcount
/// instruction, against about 20 per word for `count_ones`.
#[inline(always)]
fn hamming3(a: [u64; 3], b: [u64; 3]) -> u32 {
    #[inline(always)]
    fn nibbles(x: u32) -> u32 {
        let x = x - ((x >> 1) & 0x5555_5555);
        (x & 0x3333_3333) + ((x >> 2) & 0x3333_3333)
    }
    let [a0, a1, a2] = a;
    let [b0, b1, b2] = b;
    let (x0, x1, x2) = (a0 ^ b0, a1 ^ b1, a2 ^ b2);
    let lo = nibbles(x0 as u32) + nibbles(x1 as u32) + nibbles(x2 as u32);
    let hi = nibbles((x0 >> 32) as u32) + nibbles((x1 >> 32) as u32) + nibbles((x2 >> 32) as u32);
    let bytes = (lo & 0x0F0F_0F0F) + ((lo >> 4) & 0x0F0F_0F0F) + (hi & 0x0F0F_0F0F) + ((hi >> 4) & 0x0F0F_0F0F);
    bytes.wrapping_mul(0x0101_0101) >> 24
}

/// The costs of a whole row, [`pixel_costs`]' integers for every column `x` (`bands`: the row's
/// firsts, then its lengths; `costs`: [`SLOTS`] per column). A pixel's cost is the sum over the
/// three columns of its window (clamped) of per-column sums over the three rows, and each
/// column's sums serve the three pixels whose windows hold it: computed once per column over the
/// union of those pixels' bands, they take about a third of the popcounts of
/// [`pixel_costs_portable`] (which sums nine distances per candidate).
pub fn row_costs(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, bands: &[i16], costs: &mut [u16]) {
    let band = |x: usize| match (bands.get(x), bands.get(w + x)) {
        (Some(&first), Some(&len)) => Band { first, len },
        _ => Band::default(),
    };
    // Column `q`'s sums into `col`: the union of the bands of pixels `q - 1 ..= q + 1` (in place:
    // a `Column` returned by value was cleared and copied, a library call each).
    let [l0, l1, l2] = left;
    let [r0, r1, r2] = right;
    let column = |q: usize, col: &mut Column| {
        col.n = 0;
        let (mut lo, mut hi) = (usize::MAX, 0);
        for x in q.saturating_sub(1)..(q + 2).min(w) {
            let b = band(x);
            if b.n() > 0 {
                lo = lo.min(b.first as usize);
                hi = hi.max(b.first as usize + b.n());
            }
        }
        if lo >= hi || hi - lo > COLUMN_SPAN {
            return; // no candidates, or too wide: the pixels compute their own
        }
        let n = hi - lo;
        col.lo = lo;
        // Whole rows (the engine's): the right codes of candidates `d <= q` are columns `q - d`,
        // walked down by slices, those of `d > q` all column 0 (clamped): one sum.
        if let (Some(&a0), Some(&a1), Some(&a2), Some(&z0), Some(&z1), Some(&z2)) = (l0.get(q), l1.get(q), l2.get(q), r0.first(), r1.first(), r2.first())
            && let Some(v) = col.v.get_mut(..n)
        {
            let a = [a0, a1, a2];
            let m = if lo <= q { n.min(q - lo + 1) } else { 0 };
            let top = q.wrapping_sub(lo);
            let rows = if m > 0 {
                let first = top + 1 - m;
                match (r0.get(first..=top), r1.get(first..=top), r2.get(first..=top)) {
                    (Some(s0), Some(s1), Some(s2)) => Some((s0, s1, s2)),
                    _ => None,
                }
            } else {
                Some((&[][..], &[][..], &[][..]))
            };
            if let Some((s0, s1, s2)) = rows {
                let (near, far) = v.split_at_mut(m.min(n));
                for (((o, b0), b1), b2) in near.iter_mut().zip(s0.iter().rev()).zip(s1.iter().rev()).zip(s2.iter().rev()) {
                    *o = hamming3(a, [*b0, *b1, *b2]) as u16;
                }
                if !far.is_empty() {
                    let h = hamming3(a, [z0, z1, z2]) as u16;
                    far.iter_mut().for_each(|o| *o = h);
                }
                col.n = n;
                return;
            }
        }
        let a = [l0.get(q), l1.get(q), l2.get(q)];
        for (k, v) in col.v.iter_mut().enumerate().take(n) {
            let qr = q.saturating_sub(lo + k);
            let b = [r0.get(qr), r1.get(qr), r2.get(qr)];
            // A code missing from a shorter row adds nothing (as in `cost_plain`).
            let pair = |i: usize| match (a.get(i).copied().flatten(), b.get(i).copied().flatten()) {
                (Some(&x), Some(&y)) => (x, y),
                _ => (0, 0),
            };
            let (p0, p1, p2) = (pair(0), pair(1), pair(2));
            *v = hamming3([p0.0, p1.0, p2.0], [p0.1, p1.1, p2.1]) as u16;
        }
        col.n = n;
    };
    let mut ring = [Column { lo: 0, n: 0, v: [0; COLUMN_SPAN] }; 3];
    if let Some(c) = ring.get_mut(0) {
        column(0, c);
    }
    for (x, out) in costs.chunks_exact_mut(SLOTS).enumerate().take(w) {
        if let (true, Some(c)) = (x + 1 < w, ring.get_mut((x + 1) % 3)) {
            column(x + 1, c);
        }
        let b = band(x);
        let cols = [x.saturating_sub(1), x, (x + 1).min(w - 1)];
        let [c0, c1, c2] = cols.map(|q| ring.get(q % 3));
        let out = head_mut(out, b.n());
        // Every column holds the pixel's band (its union includes it) unless it was too wide:
        // the three columns' runs added.
        #[inline(always)]
        fn run(c: Option<&Column>, first: i16, n: usize) -> Option<&[u16]> {
            let d0 = first as usize;
            c.filter(|c| first >= 0 && d0 >= c.lo && d0 + n <= c.lo + c.n).and_then(|c| c.v.get(d0 - c.lo..d0 - c.lo + n))
        }
        let n = out.len();
        if let (Some(v0), Some(v1), Some(v2)) = (run(c0, b.first, n), run(c1, b.first, n), run(c2, b.first, n)) {
            for (((o, a), b), c) in out.iter_mut().zip(v0).zip(v1).zip(v2) {
                *o = *a + *b + *c;
            }
            continue;
        }
        for (k, o) in out.iter_mut().enumerate() {
            let d = b.first as usize + k;
            let at = |c: Option<&Column>| c.filter(|c| d >= c.lo && d < c.lo + c.n).and_then(|c| c.v.get(d - c.lo)).map(|v| *v as u32);
            *o = match (at(c0), at(c1), at(c2)) {
                (Some(a), Some(b), Some(c)) => (a + b + c) as u16,
                _ => cost_plain(left, right, w, x, d),
            };
        }
    }
}

/// [`pixel_costs`] by `count_ones`, candidate by candidate: the specification.
pub fn pixel_costs_portable(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, b: Band, out: &mut [u16]) {
    for (k, c) in head_mut(out, b.n()).iter_mut().enumerate() {
        *c = cost_plain(left, right, w, x, b.first as usize + k);
    }
}

/// The large-jump penalty between neighbours of grey levels `a` and `b`:
/// `max(P2 * EDGE_SCALE / (EDGE_SCALE + |a - b|), P1 + 1)` (integer division), read from a table
/// of the 256 grey steps (five path steps a pixel would otherwise each divide).
#[inline(always)]
pub fn penalty2(a: u8, b: u8) -> u32 {
    PENALTY2.get(a.abs_diff(b) as usize).map_or(P1 + 1, |p| *p as u32)
}

/// [`penalty2`] by grey step (a compile-time loop: the index is below 256).
#[allow(clippy::indexing_slicing)]
static PENALTY2: [u16; 256] = {
    let mut t = [0u16; 256];
    let mut d = 0;
    while d < 256 {
        let p = P2 * EDGE_SCALE / (EDGE_SCALE + d as u32);
        t[d] = if p > P1 + 1 { p } else { P1 + 1 } as u16;
        d += 1;
    }
    t
};
const _: () = assert!(P2 < u16::MAX as u32);
// The DSP path step's window (`dsp::ones_u16_36`) holds `SLOTS + 6` values.
const _: () = assert!(SLOTS + 6 == 36);

/// A pixel's candidates: disparities `first .. first + len` (px).
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct Band {
    /// Smallest candidate.
    pub first: i16,
    /// Number of candidates (0 ..= [`SLOTS`]).
    pub len: i16,
}

impl Band {
    /// The band of a pixel whose network disparity is `d0` (Q10.5) and uncertainty `u` (Q4.11;
    /// `None` without MUD: the narrowest band).
    #[inline]
    pub fn of(d0: i16, u: Option<i16>) -> Band {
        let base = (d0 >> DISP_FRAC) as i32;
        let rad = u.map_or(MIN_BAND, band_radius) as i32;
        let first = (base - rad).max(0);
        let last = base + rad + 1;
        Band { first: first as i16, len: (last - first + 1).max(0) as i16 }
    }
    #[inline(always)]
    fn n(self) -> usize {
        (self.len as usize).min(SLOTS)
    }
}

/// `out[..n] = src[..n]` (as far as both reach).
#[inline(always)]
fn copy_head(out: &mut [u16], src: &[u16], n: usize) {
    for (o, s) in out.iter_mut().zip(src).take(n) {
        *o = *s;
    }
}

/// One step along a path: `out` (the current pixel's `L_r`, `band.len` values) from the
/// predecessor's `prev` (`pband.len` values) and the current costs `cost` (each slice read or
/// written only as far as it reaches). On Cortex-M55 with Helium eight candidates a vector
/// (`mve::path_update`), the same integers as [`path_step_portable`].
#[inline(always)]
pub fn path_step(prev: &[u16], pband: Band, cost: &[u16], band: Band, p2: u32, out: &mut [u16]) {
    #[cfg(all(target_arch = "arm", feature = "mve"))]
    {
        let (prev, cost) = (head(prev, pband.n()), head(cost, band.n()));
        let out = head_mut(out, band.n());
        if let Some(m) = super::mve::min_u16(prev) {
            let mp2 = (m as u32).saturating_add(p2);
            // (larger values: the portable step, whose u32 sums the u16 lanes would not hold)
            if mp2 <= u16::MAX as u32 - P1 {
                // `win[i] = prev[i - 1 + shift]` for `i < n + 2` where that exists, `u16::MAX`
                // (no term: it never beats `m + p2`) elsewhere.
                let n = out.len().min(cost.len());
                let shift = band.first as isize - pband.first as isize;
                // (filled by one vector loop: `[u16::MAX; N]` became a `memset` call)
                let mut win = [core::mem::MaybeUninit::<u16>::uninit(); SLOTS + 2];
                super::mve::fill_ones(&mut win);
                // SAFETY: `fill_ones` initialised every value.
                let mut win: [u16; SLOTS + 2] = unsafe { core::mem::transmute(win) };
                let lo = (1 - shift).max(0);
                let hi = (n as isize + 2).min(prev.len() as isize + 1 - shift);
                if lo < hi {
                    let (lo, hi) = (lo as usize, hi as usize);
                    if let (Some(dst), Some(src)) = (win.get_mut(lo..hi), prev.get((lo as isize - 1 + shift) as usize..)) {
                        super::mve::copy(dst, src);
                    }
                }
                super::mve::path_update(&win, cost, P1 as u16, m, mp2 as u16, out);
                return;
            }
        }
    }
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    {
        let (prev, cost) = (head(prev, pband.n()), head(cost, band.n()));
        let out = head_mut(out, band.n());
        if let Some(m) = super::dsp::min_u16(prev) {
            let mp2 = (m as u32).saturating_add(p2);
            // (as the Helium step: larger values take the portable one)
            if mp2 <= u16::MAX as u32 - P1 {
                let n = out.len().min(cost.len());
                let shift = band.first as isize - pband.first as isize;
                // `win[i] = prev[i - 1 + shift]` where that exists, `u16::MAX` elsewhere.
                let mut ones = core::mem::MaybeUninit::uninit();
                let win = super::dsp::ones_u16_36(&mut ones);
                let lo = (1 - shift).max(0);
                let hi = (n as isize + 2).min(prev.len() as isize + 1 - shift);
                if lo < hi {
                    let (lo, hi) = (lo as usize, hi as usize);
                    if let (Some(dst), Some(src)) = (win.get_mut(lo..hi), prev.get((lo as isize - 1 + shift) as usize..)) {
                        // Two values a word (a `memcpy` call of some 30 halfwords cost about 200
                        // instructions: the library's byte loop for unaligned ends).
                        super::dsp::copy_u16(dst, src);
                    }
                }
                path_update_dsp(win, cost, m, mp2 as u16, out);
                return;
            }
        }
    }
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if avx512::path_step(prev, pband, cost, band, p2, out) {
        return;
    }
    #[allow(unreachable_code)]
    path_step_portable(prev, pband, cost, band, p2, out)
}

/// [`path_step`]'s update once the predecessor's costs are laid out as a window (`win[k + 1]` the
/// predecessor's cost at the candidate of `out[k]`, `u16::MAX` where it has none), two candidates
/// a word with the Armv7E-M halfword instructions: `out[k] = cost[k] + min(win[k + 1], min(win[k],
/// win[k + 2], mp2) + P1, mp2) - m` (`min16` by `USUB16` + `SEL`; with `mp2 + P1 <= 0xFFFF` no
/// halfword overflows, `min(.., mp2) >= m`), for `k < min(cost.len(), out.len())`
/// (`win.len() >= k + 4`).
///
/// Out of line, by unaligned word loads and stores after one length check (each window word read
/// once: a pair's third word is the next pair's first); inlined into the refinement with checked
/// slices the loop took about 30 instructions a pair.
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(never)]
fn path_update_dsp(win: &[u16; SLOTS + 6], cost: &[u16], m: u16, mp2: u16, out: &mut [u16]) {
    let n = cost.len().min(out.len()).min(SLOTS + 2);
    let pair = |v: u16| v as u32 * 0x0001_0001;
    let (mm, mp2s, p1s) = (pair(m), pair(mp2), pair(P1 as u16));
    let (wp, cp, op) = (win.as_ptr(), cost.as_ptr(), out.as_mut_ptr());
    // SAFETY: `win` has `SLOTS + 6 >= 2` values.
    let mut a = unsafe { wp.cast::<u32>().read_unaligned() };
    let mut k = 0;
    while k + 2 <= n {
        // SAFETY: `k + 2 <= n`, so `k + 4 <= SLOTS + 4 < win.len()` and `k + 2 <= cost.len()`.
        let (b, c, cs) = unsafe { (wp.add(k + 1).cast::<u32>().read_unaligned(), wp.add(k + 2).cast::<u32>().read_unaligned(), cp.add(k).cast::<u32>().read_unaligned()) };
        let r: u32;
        // SAFETY: register-only DSP instructions (the GE flags they set are not read after the
        // block).
        unsafe {
            core::arch::asm!(
                "usub16 {t}, {a}, {c}",
                "sel {t}, {c}, {a}",
                "usub16 {a}, {t}, {mp2}",
                "sel {t}, {mp2}, {t}",
                "uadd16 {t}, {t}, {p1}",
                "usub16 {a}, {t}, {b}",
                "sel {t}, {b}, {t}",
                "usub16 {a}, {t}, {mp2}",
                "sel {t}, {mp2}, {t}",
                "usub16 {t}, {t}, {m}",
                "uadd16 {t}, {t}, {cs}",
                t = out(reg) r, a = inout(reg) a => _, b = in(reg) b, c = in(reg) c, cs = in(reg) cs,
                mp2 = in(reg) mp2s, p1 = in(reg) p1s, m = in(reg) mm,
                options(pure, nomem, nostack),
            );
        }
        // SAFETY: `k + 2 <= n <= out.len()`.
        unsafe { op.add(k).cast::<u32>().write_unaligned(r) };
        a = c;
        k += 2;
    }
    if k < n {
        let w = |i: usize| win.get(i).copied().unwrap_or(u16::MAX) as u32;
        let best = (w(k).min(w(k + 2)).min(mp2 as u32) + P1).min(w(k + 1)).min(mp2 as u32);
        if let (Some(o), Some(&c)) = (out.get_mut(k), cost.get(k)) {
            *o = (c as u32 + best - m as u32) as u16;
        }
    }
}

/// [`path_step`] value by value: the specification.
#[inline(always)]
pub fn path_step_portable(prev: &[u16], pband: Band, cost: &[u16], band: Band, p2: u32, out: &mut [u16]) {
    let (prev, cost) = (head(prev, pband.n()), head(cost, band.n()));
    let out = head_mut(out, band.n());
    let Some(m) = prev.iter().min().map(|m| *m as u32) else {
        copy_head(out, cost, band.n());
        return;
    };
    let at = |j: isize| if j >= 0 { prev.get(j as usize).map(|v| *v as u32) } else { None };
    let shift = band.first as isize - pband.first as isize;
    for (k, (o, c)) in out.iter_mut().zip(cost).enumerate() {
        let j = k as isize + shift;
        let mut best = m + p2;
        if let Some(v) = at(j) {
            best = best.min(v);
        }
        if let Some(v) = at(j - 1) {
            best = best.min(v + P1);
        }
        if let Some(v) = at(j + 1) {
            best = best.min(v + P1);
        }
        *o = (*c as u32 + best - m) as u16;
    }
}

/// The decision ([`decide`]) on the sums of the five paths' costs `p` of a pixel of band `band`
/// (as far as each slice reaches); on the x86-64 host the sums and their first least value by one
/// vector.
/// `sum` is scratch (its values past the band's are left as they were: the caller keeps one
/// array for a whole image, where one per pixel was cleared by a library call each time).
#[inline(always)]
fn sum_decide(p: [&[u16]; 5], band: Band, sum: &mut [u32; SLOTS]) -> Option<i16> {
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if let Some(i) = avx512::path_sums(p, band.n(), sum) {
        return decide_at(head(sum, band.n()), band, i);
    }
    // Armv7E-M: two candidates a word (`UADD16`): every path cost is below `432 + P2`, so the
    // five-way sum fits a halfword (the `const` assertion on `P2` above; `refine_rows` writes
    // only such costs into the planes).
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    if let Some(i) = path_sums_dsp(p, band.n(), sum) {
        return decide_at(head(sum, band.n()), band, i);
    }
    // The sums and their first least value in one pass (as [`decide`]: the first of the least).
    let [a, r, t0, t1, t2] = p;
    let (mut i, mut least, mut n) = (0, u32::MAX, 0);
    for (k, (((((s, a), r), t0), t1), t2)) in sum.iter_mut().zip(a).zip(r).zip(t0).zip(t1).zip(t2).take(band.n()).enumerate() {
        let v = *a as u32 + *r as u32 + *t0 as u32 + *t1 as u32 + *t2 as u32;
        *s = v;
        if v < least {
            (i, least) = (k, v);
        }
        n = k + 1;
    }
    // (every sum is below `5 * 2^16`, so the first is below `least`'s start)
    if n < band.n() {
        // A path shorter than the band (never in [`refine_rows`]): zeros after it, as [`decide`].
        sum.iter_mut().take(band.n()).skip(n).for_each(|s| *s = 0);
        return decide(sum, band);
    }
    decide_at(head(sum, n), band, i)
}

/// [`sum_decide`]'s sums of the first `n` candidates into `sum` two a word (`UADD16` of the five
/// paths' unaligned words) and the index of their first least value; `None` (nothing written)
/// where a path is shorter than `n` or `n` is 0. The paths' values must be below `2^16 / 5`
/// (path costs are below `432 + P2`).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
#[inline(always)]
fn path_sums_dsp(p: [&[u16]; 5], n: usize, sum: &mut [u32; SLOTS]) -> Option<usize> {
    let n = n.min(SLOTS);
    if n == 0 || p.iter().any(|s| s.len() < n) {
        return None;
    }
    let [a, r, t0, t1, t2] = p.map(|s| s.as_ptr());
    let (mut i, mut least) = (0, u32::MAX);
    let mut k = 0;
    while k + 2 <= n {
        // SAFETY: `k + 2 <= n` values of each path (checked above); unaligned words (Cortex-M7).
        let w = unsafe { [a, r, t0, t1, t2].map(|s| s.add(k).cast::<u32>().read_unaligned()) };
        let v: u32;
        // SAFETY: register-only DSP instructions (the GE flags they set are not read after).
        unsafe {
            core::arch::asm!(
                "uadd16 {v}, {a}, {b}",
                "uadd16 {v}, {v}, {c}",
                "uadd16 {v}, {v}, {d}",
                "uadd16 {v}, {v}, {e}",
                v = out(reg) v, a = in(reg) w[0], b = in(reg) w[1], c = in(reg) w[2], d = in(reg) w[3], e = in(reg) w[4],
                options(pure, nomem, nostack),
            );
        }
        let (v0, v1) = (v & 0xFFFF, v >> 16);
        if let Some([s0, s1]) = sum.get_mut(k..k + 2).and_then(|s| <&mut [u32; 2]>::try_from(s).ok()) {
            (*s0, *s1) = (v0, v1);
        }
        if v0 < least {
            (i, least) = (k, v0);
        }
        if v1 < least {
            (i, least) = (k + 1, v1);
        }
        k += 2;
    }
    if k < n {
        // SAFETY: `k < n`.
        let v = unsafe { [a, r, t0, t1, t2].map(|s| *s.add(k) as u32) }.iter().sum::<u32>();
        if let Some(s) = sum.get_mut(k) {
            *s = v;
        }
        if v < least {
            i = k;
        }
    }
    Some(i)
}

/// [`sum_decide`] as this build runs it, and its portable form (the five paths summed value by
/// value, then [`decide`]): the on-target check of [`path_sums_dsp`] (`boards/qemu-mps3-m55`'s
/// kernel binary).
#[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
pub fn sum_decide_twins(p: [&[u16]; 5], band: Band) -> (Option<i16>, Option<i16>) {
    let mut sum = [0u32; SLOTS];
    let got = sum_decide(p, band, &mut sum);
    let mut plain = [0u32; SLOTS];
    let [a, r, t0, t1, t2] = p;
    for (((((s, a), r), t0), t1), t2) in plain.iter_mut().zip(a).zip(r).zip(t0).zip(t1).zip(t2).take(band.n()) {
        *s = *a as u32 + *r as u32 + *t0 as u32 + *t1 as u32 + *t2 as u32;
    }
    (got, decide(&plain, band))
}

/// The decision on summed path costs `s` (`band.len` values): the refined disparity (Q10.5), or
/// `None` where the network's value stays.
#[inline(always)]
fn decide(s: &[u32], band: Band) -> Option<i16> {
    let s = head(s, band.n());
    let (mut i, mut least) = (0, *s.first()?);
    for (k, v) in s.iter().enumerate() {
        if *v < least {
            (i, least) = (k, *v);
        }
    }
    decide_at(s, band, i)
}

/// [`decide`] once the first least sum `s[i]` is known (`s`: the band's sums).
#[inline(always)]
fn decide_at(s: &[u32], band: Band, i: usize) -> Option<i16> {
    if i == 0 {
        return None;
    }
    // `S(d*-1), S(d*), S(d*+1)`; none where `d*` is the last candidate.
    let &[a0, a1, a2] = s.get(i - 1..i + 2)? else {
        return None;
    };
    let (a0, a1, a2) = (a0 as i64, a1 as i64, a2 as i64);
    let curv = a0 + a2 - 2 * a1;
    if curv <= 0 {
        return None;
    }
    // Equiangular fit: the two lines through the minimum with the steeper side's slope. `a0 > a1`
    // (`i` is the first minimum), so the divisor is at least 1 and |off| <= 16 (half a pixel).
    let off = div_round(16 * (a0 - a2), (a0 - a1).max(a2 - a1));
    Some(sat_i16(((band.first as i64 + i as i64) << DISP_FRAC) + off))
}

/// The median of nine values: a selection network of 19 compare-exchanges (the middle value
/// only; branch-free minima and maxima instead of a sort per pixel; the tests check it against a
/// sort on every order of nine distinct values and every 0/1 input).
#[inline(always)]
#[allow(unused_assignments)] // the network's last exchanges also order values that are not the median
fn median9(v: [i16; 9]) -> i16 {
    let [mut p0, mut p1, mut p2, mut p3, mut p4, mut p5, mut p6, mut p7, mut p8] = v;
    macro_rules! order {
        ($a:ident, $b:ident) => {
            ($a, $b) = ($a.min($b), $a.max($b));
        };
    }
    order!(p1, p2);
    order!(p4, p5);
    order!(p7, p8);
    order!(p0, p1);
    order!(p3, p4);
    order!(p6, p7);
    order!(p1, p2);
    order!(p4, p5);
    order!(p7, p8);
    order!(p0, p3);
    order!(p5, p8);
    order!(p4, p7);
    order!(p3, p6);
    order!(p1, p4);
    order!(p2, p5);
    order!(p4, p7);
    order!(p2, p4);
    order!(p4, p6);
    order!(p2, p4);
    p4
}

/// Row `y` of the 3x3 median of `rows` (`[above, row, below]`, each `w` values, borders
/// replicated) into `out`.
#[inline(always)]
fn median_row(rows: [&[i16]; 3], out: &mut [i16]) {
    let w = out.len();
    for (x, o) in out.iter_mut().enumerate() {
        let cols = [x.saturating_sub(1), x, (x + 1).min(w - 1)];
        let mut v = [0i16; 9];
        for (vr, row) in v.chunks_exact_mut(3).zip(rows) {
            for (slot, q) in vr.iter_mut().zip(cols) {
                // (0 past the end of a row shorter than `out`: never, all rows are `w` long)
                *slot = row.get(q).copied().unwrap_or(0);
            }
        }
        *o = median9(v);
    }
}

/// Element counts of [`refine_image`]'s scratch for an image `width` wide.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct ScratchLen {
    /// Census rings of both images (`u64`).
    pub census: usize,
    /// Grey rows: those of one census row, then the previous and current rows of the left image.
    pub grey: usize,
    /// Path costs (`u16`): costs of the row, its right-to-left path, the three downward paths of
    /// the previous and of the current row, [`SLOTS`] per column each.
    pub paths: usize,
    /// `i16` rows: bands (first, len) of the previous and current rows, three rows of decisions.
    pub rows: usize,
}

impl ScratchLen {
    /// The counts for `width` columns.
    pub const fn new(width: usize) -> Self {
        ScratchLen {
            census: 2 * WINDOW_ROWS * width,
            grey: (2 * CENSUS_RADIUS + 1) * width + 2 * width,
            paths: 8 * SLOTS * width,
            rows: 7 * width,
        }
    }
    /// Total bytes.
    pub const fn bytes(&self) -> usize {
        8 * self.census + self.grey + 2 * self.paths + 2 * self.rows
    }
}

/// Borrowed scratch of [`refine_image`] (lengths at least [`ScratchLen::new`]).
pub struct Scratch<'a> {
    /// Census rings (`ScratchLen::census`).
    pub census: &'a mut [u64],
    /// Grey rows (`ScratchLen::grey`).
    pub grey: &'a mut [u8],
    /// Path costs (`ScratchLen::paths`).
    pub paths: &'a mut [u16],
    /// Band and decision rows (`ScratchLen::rows`).
    pub rows: &'a mut [i16],
}

/// Owned scratch for host callers.
#[cfg(feature = "std")]
pub struct ScratchVec {
    census: Vec<u64>,
    grey: Vec<u8>,
    paths: Vec<u16>,
    rows: Vec<i16>,
}

#[cfg(feature = "std")]
impl ScratchVec {
    /// Scratch for images `width` wide.
    pub fn new(width: usize) -> Self {
        let n = ScratchLen::new(width);
        ScratchVec { census: vec![0; n.census], grey: vec![0; n.grey], paths: vec![0; n.paths], rows: vec![0; n.rows] }
    }
    /// Borrows it.
    pub fn view(&mut self) -> Scratch<'_> {
        Scratch { census: &mut self.census, grey: &mut self.grey, paths: &mut self.paths, rows: &mut self.rows }
    }
}

/// Refines a whole disparity map in place (`disparity`, Q10.5, `width x height` of the images;
/// `uncertainty` Q4.11 or `None`), streaming over rows in `scratch` (lengths from
/// [`ScratchLen::new`] for the width). Returns the number of pixels the matching decided.
pub fn refine_image(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, scratch: Scratch<'_>) -> usize {
    // On the host's kernel pool when it has several threads (the same integers, each row's work
    // split into tasks; scratch of its own).
    #[cfg(feature = "std")]
    {
        let (w, h) = (left.width, left.height);
        let fits = right.width == w && right.height == h && disparity.len() >= w * h && uncertainty.is_none_or(|u| u.len() >= w * h);
        if super::pool::threads() > 1 && w >= threads::MIN_WIDTH && h >= 1 && fits {
            return threads::refine(left, right, disparity, uncertainty);
        }
    }
    // The x86-64 baseline has no POPCNT instruction (`count_ones` becomes a dozen instructions):
    // the same code compiled with it where the CPU has it.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if std::is_x86_feature_detected!("popcnt") {
        #[target_feature(enable = "popcnt")]
        unsafe fn with_popcnt(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, scratch: Scratch<'_>) -> usize {
            refine_rows(left, right, disparity, uncertainty, scratch)
        }
        // SAFETY: the CPU has POPCNT.
        return unsafe { with_popcnt(left, right, disparity, uncertainty, scratch) };
    }
    refine_rows(left, right, disparity, uncertainty, scratch)
}

/// [`refine_image`]'s work (inlined into each of its compilations).
#[inline(always)]
fn refine_rows(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, scratch: Scratch<'_>) -> usize {
    let (w, h) = (left.width, left.height);
    if w == 0 || h == 0 || disparity.len() < w * h || uncertainty.is_some_and(|u| u.len() < w * h) {
        return 0;
    }
    // The buffers, carved from the scratch (shorter than `ScratchLen::new(w)`: nothing is done).
    let Scratch { mut census, mut grey, mut paths, mut rows } = scratch;
    // `w >= 1` here; `max` keeps the per-row chunking free of a zero-size path (an overflowing
    // product).
    let sw = (SLOTS * w).max(1);
    let (Some(ring_l), Some(ring_r)) = (take(&mut census, WINDOW_ROWS * w), take(&mut census, WINDOW_ROWS * w)) else {
        return 0;
    };
    let (Some(cgrey), Some(mut g_prev), Some(mut g_cur)) = (take(&mut grey, (2 * CENSUS_RADIUS + 1) * w), take(&mut grey, w), take(&mut grey, w)) else {
        return 0;
    };
    let (Some(costs), Some(rl), Some(mut top_prev), Some(mut top_cur)) = (take(&mut paths, sw), take(&mut paths, sw), take(&mut paths, 3 * sw), take(&mut paths, 3 * sw)) else {
        return 0;
    };
    let (Some(mut b_prev), Some(mut b_cur), Some(decided_rows)) = (take(&mut rows, 2 * w), take(&mut rows, 2 * w), take(&mut rows, 3 * w)) else {
        return 0;
    };

    let slot = |y: isize| (y.rem_euclid(WINDOW_ROWS as isize)) as usize;
    let r = WINDOW_RADIUS as isize;
    // Census rows -1 ..= 0 (clamped rows repeat codes; each ring slot holds the row whose index
    // is congruent to it); then, before output row y, row y + 1.
    for y in -r..r {
        let s = slot(y);
        census_row(left, y, cgrey, chunk_mut(ring_l, s, w));
        census_row(right, y, cgrey, chunk_mut(ring_r, s, w));
    }
    let mut decided = 0;
    // Band of column `x` from a row of bands (firsts, then lengths); no candidates past its end.
    let band_at = |b: &[i16], x: usize| match (b.get(x), b.get(w + x)) {
        (Some(&first), Some(&len)) => Band { first, len },
        _ => Band::default(),
    };
    let grey_of = |g: &[u8], x: usize| g.get(x).copied().unwrap_or(0);
    let mut sums = [0u32; SLOTS];
    for y in 0..h {
        let yi = y as isize;
        let s = slot(yi + r);
        census_row(left, yi + r, cgrey, chunk_mut(ring_l, s, w));
        census_row(right, yi + r, cgrey, chunk_mut(ring_r, s, w));
        let lrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| chunk(ring_l, slot(yi - r + k as isize), w));
        let rrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| chunk(ring_r, slot(yi - r + k as isize), w));
        let d_row = chunk(disparity, y, w);
        let u_row = uncertainty.map(|u| chunk(u, y, w));
        // Bands, grey levels and costs of the row.
        for (x, (&d0, c)) in d_row.iter().zip(costs.chunks_exact_mut(SLOTS)).enumerate() {
            let b = Band::of(d0, u_row.and_then(|u| u.get(x)).copied());
            set_at(b_cur, x, b.first);
            set_at(b_cur, w + x, b.len);
            set_at(g_cur, x, grey_at(left, x, y));
            if !ROW_COSTS {
                pixel_costs(&lrows, &rrows, w, x, b, c);
            }
        }
        if ROW_COSTS {
            row_costs(&lrows, &rrows, w, b_cur, costs);
        }
        // The three downward paths (from above-left, above, above-right).
        for (p, (prev_plane, cur_plane)) in top_prev.chunks_exact(sw).zip(top_cur.chunks_exact_mut(sw)).enumerate() {
            for (x, (c, out)) in costs.chunks_exact(SLOTS).zip(cur_plane.chunks_exact_mut(SLOTS)).enumerate() {
                let b = band_at(b_cur, x);
                if y == 0 {
                    copy_head(out, c, b.n());
                    continue;
                }
                let q = match p {
                    0 => x.saturating_sub(1),
                    1 => x,
                    _ => (x + 1).min(w - 1),
                };
                path_step(chunk(prev_plane, q, SLOTS), band_at(b_prev, q), c, b, penalty2(grey_of(g_cur, x), grey_of(g_prev, q)), out);
            }
        }
        // Right to left (`next`: the path at the column to the right).
        let mut next: Option<&[u16]> = None;
        for (x, (c, out)) in costs.chunks_exact(SLOTS).zip(rl.chunks_exact_mut(SLOTS)).enumerate().rev() {
            let b = band_at(b_cur, x);
            match next {
                None => copy_head(out, c, b.n()),
                Some(prev) => path_step(prev, band_at(b_cur, x + 1), c, b, penalty2(grey_of(g_cur, x), grey_of(g_cur, x + 1)), out),
            }
            next = Some(out);
        }
        // Left to right, the sum of the five paths and the decision.
        let dec_row = chunk_mut(decided_rows, y % 3, w);
        let (mut lr_prev, mut lr_cur) = ([0u16; SLOTS], [0u16; SLOTS]);
        for (x, (c, dec)) in costs.chunks_exact(SLOTS).zip(dec_row.iter_mut()).enumerate() {
            let b = band_at(b_cur, x);
            if x == 0 {
                copy_head(&mut lr_cur, c, b.n());
            } else {
                path_step(&lr_prev, band_at(b_cur, x - 1), c, b, penalty2(grey_of(g_cur, x), grey_of(g_cur, x - 1)), &mut lr_cur);
            }
            let (rl_x, t0, t1, t2) = (chunk(rl, x, SLOTS), chunk(top_cur, x, SLOTS), chunk(top_cur, w + x, SLOTS), chunk(top_cur, 2 * w + x, SLOTS));
            *dec = match sum_decide([&lr_cur, rl_x, t0, t1, t2], b, &mut sums) {
                Some(d) => {
                    decided += 1;
                    d
                }
                None => d_row.get(x).copied().unwrap_or(0),
            };
            core::mem::swap(&mut lr_prev, &mut lr_cur);
        }
        // The median of row y - 1 (its inputs are no longer needed).
        if y >= 1 {
            let (above, mid, below) = ((y.saturating_sub(2)) % 3, (y - 1) % 3, y % 3);
            let at = |k: usize| chunk(decided_rows, k, w);
            median_row([at(above), at(mid), at(below)], chunk_mut(disparity, y - 1, w));
        }
        core::mem::swap(&mut top_prev, &mut top_cur);
        core::mem::swap(&mut b_prev, &mut b_cur);
        core::mem::swap(&mut g_prev, &mut g_cur);
    }
    let (above, mid) = ((h.saturating_sub(2)) % 3, (h - 1) % 3);
    let at = |k: usize| chunk(decided_rows, k, w);
    median_row([at(above), at(mid), at(mid)], chunk_mut(disparity, h - 1, w));
    decided
}

/// The first `n` values split off the front of `*rest` (`None`, and `*rest` empty, when it is
/// shorter).
#[inline(always)]
fn take<'a, T>(rest: &mut &'a mut [T], n: usize) -> Option<&'a mut [T]> {
    let (head, tail) = core::mem::take(rest).split_at_mut_checked(n)?;
    *rest = tail;
    Some(head)
}

/// Plain twin of [`refine_image`]: census codes, bands and costs of the whole image first, each
/// path over the whole image, then the decisions and the median (host tests and the plain
/// fixed-point reference).
#[cfg(feature = "std")]
pub fn refine_image_plain(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>) -> usize {
    let (w, h) = (left.width, left.height);
    // The same refusal as the streaming kernel's.
    if w == 0 || h == 0 || disparity.len() < w * h || uncertainty.is_some_and(|u| u.len() < w * h) {
        return 0;
    }
    let codes = |img: &ImageView<'_>| {
        let mut grey = vec![0u8; (2 * CENSUS_RADIUS + 1) * w];
        let mut out = vec![0u64; w * h];
        for (y, row) in out.chunks_exact_mut(w).enumerate() {
            census_row(img, y as isize, &mut grey, row);
        }
        out
    };
    let (cl, cr) = (codes(left), codes(right));
    let g: Vec<u8> = (0..w * h).map(|i| grey_at(left, i % w, i / w)).collect();
    let bands: Vec<Band> = disparity.iter().take(w * h).enumerate().map(|(i, d)| Band::of(*d, uncertainty.and_then(|u| u.get(i)).copied())).collect();
    let band = |i: usize| bands.get(i).copied().unwrap_or_default();
    let grey_of = |i: usize| g.get(i).copied().unwrap_or(0);
    let mut c = vec![0u16; w * h * SLOTS];
    for (y, c_row) in c.chunks_exact_mut(w * SLOTS).enumerate() {
        let row_at = |k: usize| (y as isize + k as isize - WINDOW_RADIUS as isize).clamp(0, h as isize - 1) as usize;
        let lrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| chunk(&cl, row_at(k), w));
        let rrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| chunk(&cr, row_at(k), w));
        for (x, ci) in c_row.chunks_exact_mut(SLOTS).enumerate() {
            let b = band(y * w + x);
            for (k, ck) in head_mut(ci, b.n()).iter_mut().enumerate() {
                *ck = cost(&lrows, &rrows, w, x, b.first as usize + k);
            }
        }
    }
    // Each path: pixels in an order where the predecessor comes first.
    let mut sum = vec![0u32; w * h * SLOTS];
    type Pred<'a> = &'a dyn Fn(usize, usize) -> Option<(usize, usize)>;
    let pred: [Pred<'_>; 5] = [
        &|x, y| (x > 0).then(|| (x - 1, y)),
        &|x, y| (x + 1 < w).then(|| (x + 1, y)),
        &|x, y| (y > 0).then(|| (x, y - 1)),
        &|x, y| (y > 0).then(|| (x.saturating_sub(1), y - 1)),
        &|x, y| (y > 0).then(|| ((x + 1).min(w - 1), y - 1)),
    ];
    for (p, pred) in pred.iter().enumerate() {
        let mut l = vec![0u16; w * h * SLOTS];
        for y in 0..h {
            for k in 0..w {
                let x = if p == 1 { w - 1 - k } else { k };
                let i = y * w + x;
                let b = band(i);
                let mut out = [0u16; SLOTS];
                match pred(x, y) {
                    None => copy_head(&mut out, chunk(&c, i, SLOTS), b.n()),
                    Some((qx, qy)) => {
                        let j = qy * w + qx;
                        path_step(chunk(&l, j, SLOTS), band(j), chunk(&c, i, SLOTS), b, penalty2(grey_of(i), grey_of(j)), &mut out);
                    }
                }
                copy_head(chunk_mut(&mut l, i, SLOTS), &out, SLOTS);
                for (s, o) in chunk_mut(&mut sum, i, SLOTS).iter_mut().zip(&out).take(b.n()) {
                    *s += *o as u32;
                }
            }
        }
    }
    let mut decided = 0;
    let dec: Vec<i16> = disparity
        .iter()
        .take(w * h)
        .enumerate()
        .map(|(i, d0)| match decide(chunk(&sum, i, SLOTS), band(i)) {
            Some(d) => {
                decided += 1;
                d
            }
            None => *d0,
        })
        .collect();
    for (y, out) in disparity.chunks_exact_mut(w).take(h).enumerate() {
        let at = |yy: usize| chunk(&dec, yy, w);
        median_row([at(y.saturating_sub(1)), at(y), at((y + 1).min(h - 1))], out);
    }
    decided
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    /// [`row_costs`] (shared column sums) against [`pixel_costs_portable`] on random codes:
    /// neighbouring bands that overlap, jump apart (unions wider than a column holds) or are
    /// empty, rows of 1 to 40 columns, a right row shorter than the left one.
    #[test]
    fn row_costs_match_pixel_costs() {
        let mut r = crate::kernels::testutil::Rng(23);
        for &w in &[1usize, 2, 3, 17, 40] {
            for trial in 0..20 {
                let code = |r: &mut crate::kernels::testutil::Rng| if trial % 5 == 0 { u64::MAX } else { r.next() & ((1 << 48) - 1) };
                let rows: Vec<Vec<u64>> = (0..6).map(|i| (0..if i == 5 && trial % 3 == 1 { w.saturating_sub(1) } else { w }).map(|_| code(&mut r)).collect()).collect();
                let left: [&[u64]; WINDOW_ROWS] = [&rows[0], &rows[1], &rows[2]];
                let right: [&[u64]; WINDOW_ROWS] = [&rows[3], &rows[4], &rows[5]];
                let mut bands = vec![0i16; 2 * w];
                for x in 0..w {
                    let (first, len) = match r.below(8) {
                        0 => (0, 0),
                        1 => (r.below(200) as i16, r.below(SLOTS as u64 + 1) as i16),
                        _ => ((20 + x / 3 + r.below(3) as usize) as i16, (8 + r.below(12)) as i16),
                    };
                    (bands[x], bands[w + x]) = (first, len);
                }
                let mut got = vec![0xFFFFu16; SLOTS * w];
                row_costs(&left, &right, w, &bands, &mut got);
                for x in 0..w {
                    let b = Band { first: bands[x], len: bands[w + x] };
                    let mut want = [0u16; SLOTS];
                    pixel_costs_portable(&left, &right, w, x, b, &mut want);
                    assert_eq!(&got[x * SLOTS..x * SLOTS + b.n()], &want[..b.n()], "w {w} trial {trial} x {x} {b:?}");
                }
            }
        }
    }

    #[cfg(feature = "std")]
    #[test]
    fn streaming_matches_plain_twin() {
        let mut r = crate::kernels::testutil::Rng(11);
        for &(w, h) in &[(37usize, 23usize), (64, 9), (16, 40), (1, 1), (1, 7), (9, 1), (2, 2)] {
            let l: Vec<u8> = (0..w * h * 3).map(|_| r.i8() as u8).collect();
            let rr: Vec<u8> = (0..w * h * 3).map(|_| r.i8() as u8).collect();
            let (lv, rv) = (ImageView::new(w, h, PixelFormat::Rgb8, &l).unwrap(), ImageView::new(w, h, PixelFormat::Rgb8, &rr).unwrap());
            // mostly small disparities (bands overlapping between neighbours), some negative
            // (no candidates), some large
            let d0: Vec<i16> = (0..w * h).map(|i| if i % 7 == 3 { r.i16() >> 6 } else { 320 + (r.i16() >> 11) }).collect();
            let u: Vec<i16> = (0..w * h).map(|_| r.i16() >> 2).collect();
            let (mut a, mut b) = (d0.clone(), d0.clone());
            let mut scratch = ScratchVec::new(w);
            let na = refine_image(&lv, &rv, &mut a, Some(&u), scratch.view());
            let nb = refine_image_plain(&lv, &rv, &mut b, Some(&u));
            assert_eq!(a, b, "{w}x{h}");
            assert_eq!(na, nb);
        }
    }

    /// The pool's schedule ([`threads::refine`]) against the plain twin, on 1 to 3 threads:
    /// textured pairs shifted by a few pixels plus noise (many decided pixels), widths that are
    /// and are not multiples of its column ranges, 1 to 17 rows, with and without uncertainty.
    #[cfg(feature = "std")]
    #[test]
    fn threads_match_plain_twin() {
        let mut r = crate::kernels::testutil::Rng(5);
        for &(w, h, rgb, with_u) in &[(128usize, 1usize, false, true), (128, 2, true, true), (130, 3, false, false), (200, 17, true, true), (333, 12, false, true), (257, 5, true, false)] {
            let ch = if rgb { 3 } else { 1 };
            let shift = 3 + (r.i16() & 7) as usize;
            let tex = |x: usize, y: usize, c: usize| (128.0 + 70.0 * ((x * (c + 2)) as f64 * 0.37).sin() * ((y as f64) * 0.29 + 0.5).cos()) as i32;
            let mut img = |dx: usize| -> Vec<u8> {
                let mut v = Vec::with_capacity(w * h * ch);
                for y in 0..h {
                    for x in 0..w {
                        for c in 0..ch {
                            v.push((tex(x + dx, y, c) + (r.i16() >> 12) as i32).clamp(0, 255) as u8);
                        }
                    }
                }
                v
            };
            let (l, rr) = (img(0), img(shift));
            let fmt = if rgb { PixelFormat::Rgb8 } else { PixelFormat::Gray8 };
            let (lv, rv) = (ImageView::new(w, h, fmt, &l).unwrap(), ImageView::new(w, h, fmt, &rr).unwrap());
            let d0: Vec<i16> = (0..w * h).map(|i| if i % 11 == 3 { r.i16() >> 6 } else { (shift as i16) * 32 + (r.i16() >> 10) }).collect();
            let u: Vec<i16> = (0..w * h).map(|_| r.i16() >> 2).collect();
            let u = with_u.then_some(&u[..]);
            let mut want = d0.clone();
            let n_want = refine_image_plain(&lv, &rv, &mut want, u);
            assert!(n_want > w * h / 4, "{w}x{h}: {n_want} decided");
            for t in 1..=3 {
                crate::kernels::pool::set_threads(t);
                let mut got = d0.clone();
                let n = threads::refine(&lv, &rv, &mut got, u);
                assert_eq!((n, &got), (n_want, &want), "{w}x{h}, {t} threads");
                let mut got = d0.clone();
                let n = refine_image(&lv, &rv, &mut got, u, ScratchVec::new(w).view());
                assert_eq!((n, &got), (n_want, &want), "{w}x{h}, {t} threads, refine_image");
            }
            crate::kernels::pool::set_threads(1);
        }
    }

    /// [`census_row`] (vector kernels where the target has them) against the portable codes:
    /// random rows, flat rows (ties are not darker) and rows of extremes, every width from 1 to
    /// 80 and a few rows near the borders.
    #[cfg(feature = "std")]
    #[test]
    fn census_matches_portable() {
        let mut r = crate::kernels::testutil::Rng(3);
        for w in (1..=80).chain([127, 128, 129, 450]) {
            let h = 9;
            for kind in 0..3 {
                let img: Vec<u8> = (0..w * h)
                    .map(|i| match kind {
                        0 => r.i8() as u8,
                        1 => 100 + (i % 2) as u8,
                        _ => if r.i16() > 0 { 255 } else { 0 },
                    })
                    .collect();
                let v = ImageView::new(w, h, PixelFormat::Gray8, &img).unwrap();
                let mut grey = vec![0u8; 7 * w];
                for y in [-1isize, 0, 2, 4, 8, 9] {
                    let (mut a, mut b) = (vec![1u64; w], vec![2u64; w]);
                    census_row(&v, y, &mut grey, &mut a);
                    census_row_portable(&v, y, &mut grey, &mut b);
                    assert_eq!(a, b, "w {w} kind {kind} y {y}");
                }
            }
        }
    }

    /// The selection network against a sort: every 0/1 input (the 0-1 principle), every
    /// permutation of nine distinct values, random values with ties and extremes.
    #[test]
    fn median9_is_the_middle_value() {
        let by_sort = |mut v: [i16; 9]| {
            v.sort_unstable();
            v[4]
        };
        for bits in 0u32..512 {
            let v: [i16; 9] = core::array::from_fn(|i| ((bits >> i) & 1) as i16);
            assert_eq!(median9(v), by_sort(v), "{v:?}");
        }
        // Heap's algorithm over the 9! orders of 0..9.
        let mut v: [i16; 9] = core::array::from_fn(|i| i as i16 * 3 - 12);
        let mut c = [0usize; 9];
        assert_eq!(median9(v), by_sort(v));
        let mut i = 1;
        while i < 9 {
            if c[i] < i {
                if i % 2 == 0 { v.swap(0, i) } else { v.swap(c[i], i) }
                assert_eq!(median9(v), by_sort(v), "{v:?}");
                c[i] += 1;
                i = 1;
            } else {
                c[i] = 0;
                i += 1;
            }
        }
        let mut r = crate::kernels::testutil::Rng(9);
        for _ in 0..20000 {
            let v: [i16; 9] = core::array::from_fn(|_| match r.below(4) {
                0 => i16::MIN,
                1 => i16::MAX,
                _ => r.i16() >> r.below(14),
            });
            assert_eq!(median9(v), by_sort(v), "{v:?}");
        }
    }

    /// [`path_step`] (vector kernels where the target has them) against the portable step: bands
    /// of every length and relative offset (overlapping, adjacent, disjoint), costs and
    /// predecessor values across their range and beyond the stage's (the vector step's u16 limit).
    #[test]
    fn path_step_matches_portable() {
        let mut r = crate::kernels::testutil::Rng(17);
        let mut cases = 0;
        for np in 0..=SLOTS {
            for n in 0..=SLOTS {
                for _ in 0..40 {
                    let pfirst = r.below(60) as i16;
                    let first = (pfirst as i64 + r.below(80) as i64 - 40).max(0) as i16;
                    let (pband, band) = (Band { first: pfirst, len: np as i16 }, Band { first, len: n as i16 });
                    let big = r.below(8) == 0;
                    let prev: Vec<u16> = (0..SLOTS).map(|_| if big { u16::MAX - r.below(3000) as u16 } else { r.below(4500) as u16 }).collect();
                    let cost: Vec<u16> = (0..SLOTS).map(|_| r.below(433) as u16).collect();
                    let p2 = penalty2(r.below(256) as u8, r.below(256) as u8);
                    let (mut a, mut b) = (vec![7u16; SLOTS], vec![7u16; SLOTS]);
                    path_step(&prev, pband, &cost, band, p2, &mut a);
                    path_step_portable(&prev, pband, &cost, band, p2, &mut b);
                    assert_eq!(a, b, "pband {pband:?} band {band:?} p2 {p2}");
                    cases += 1;
                }
            }
        }
        assert!(cases > 30_000);
    }

    /// [`pixel_costs`] (vector kernels where the target has them) against the portable costs:
    /// random codes, every column of rows 1 to 90 wide, bands from 0 to past the column (right
    /// columns clamped at 0 or not), the longest band.
    #[test]
    fn costs_match_portable() {
        let mut r = crate::kernels::testutil::Rng(23);
        for w in [1usize, 2, 9, 17, 40, 90] {
            let rows: Vec<Vec<u64>> = (0..6).map(|_| (0..w).map(|_| r.next() & ((1 << 48) - 1)).collect()).collect();
            let left: [&[u64]; WINDOW_ROWS] = [&rows[0], &rows[1], &rows[2]];
            let right: [&[u64]; WINDOW_ROWS] = [&rows[3], &rows[4], &rows[5]];
            for x in 0..w {
                for first in [0i16, 1, 3, 8, 20, x as i16 - 9, x as i16 - 8, x as i16 - 40, x as i16] {
                    for len in [1i16, 7, 8, 9, 16, 17, SLOTS as i16] {
                        let b = Band { first: first.max(0), len };
                        let (mut a, mut c) = (vec![9u16; SLOTS], vec![9u16; SLOTS]);
                        pixel_costs(&left, &right, w, x, b, &mut a);
                        pixel_costs_portable(&left, &right, w, x, b, &mut c);
                        assert_eq!(a, c, "w {w} x {x} band {b:?}");
                    }
                }
            }
        }
    }

    /// The penalty table is the formula for every pair of grey levels.
    #[test]
    fn penalty2_is_the_formula() {
        for a in 0..=255u8 {
            for b in 0..=255u8 {
                assert_eq!(penalty2(a, b), (P2 * EDGE_SCALE / (EDGE_SCALE + a.abs_diff(b) as u32)).max(P1 + 1), "{a} {b}");
            }
        }
    }

    #[test]
    fn band_thresholds_are_the_formula() {
        for (i, t) in BAND_U_THRESHOLDS.iter().enumerate() {
            let r = (MIN_BAND - BAND_MARGIN + 1 + i) as f64;
            assert_eq!(*t as f64, (2.0 * ((r - 1.0) / 3.0).ln() * 2048.0).floor(), "r = {r}");
        }
        assert_eq!(band_radius(-5000), MIN_BAND);
        assert_eq!(band_radius(0), MIN_BAND);
        assert_eq!(band_radius(1), MIN_BAND + 1);
        assert_eq!(band_radius(i16::MAX), MAX_BAND);
        // sigma = 2 px: ceil(3 * 2) = 6.
        assert_eq!(band_radius((2.0f64 * 2f64.ln() * 2048.0) as i16), 6 + BAND_MARGIN);
    }

    /// A textured pair shifted by a known sub-pixel disparity: the stage recovers it to within a
    /// quarter pixel from a network value 2.4 px off, and leaves a textureless pair alone.
    #[cfg(feature = "std")]
    #[test]
    fn recovers_a_known_shift_and_keeps_flat_regions() {
        let (w, h) = (96usize, 40usize);
        let tex = |x: f64, y: f64| 128.0 + 60.0 * (x * 0.7).sin() * (y * 0.45 + 1.0).cos() + 40.0 * (x * 0.23 + y * 0.31).sin();
        let d_true = 10.25f64;
        let mut l = vec![0u8; w * h];
        let mut r = vec![0u8; w * h];
        for y in 0..h {
            for x in 0..w {
                let flat = x >= 70; // right part textureless in both views
                l[y * w + x] = if flat { 128 } else { tex(x as f64, y as f64) as u8 };
                r[y * w + x] = if flat { 128 } else { tex(x as f64 + d_true, y as f64) as u8 };
            }
        }
        let lv = ImageView::new(w, h, PixelFormat::Gray8, &l).unwrap();
        let rv = ImageView::new(w, h, PixelFormat::Gray8, &r).unwrap();
        let d0 = ((d_true + 2.4) * 32.0) as i16;
        let mut d = vec![d0; w * h];
        let mut scratch = ScratchVec::new(w);
        let u = vec![(2.0f64 * 1.2f64.ln() * 2048.0) as i16; w * h]; // sigma 1.2 px: band 4
        let n = refine_image(&lv, &rv, &mut d, Some(&u), scratch.view());
        assert!(n > 0);
        let (y, x) = (20, 40);
        let got = d[y * w + x] as f64 / 32.0;
        // (a parabola through the aggregated costs pulled towards whole pixels: 10.03 here)
        assert!((got - d_true).abs() < 0.25, "refined {got} vs {d_true}");
        // Nothing to match anywhere: every cost is 0, no pixel is decided, the network's values stay
        let flat = vec![128u8; w * h];
        let fv = ImageView::new(w, h, PixelFormat::Gray8, &flat).unwrap();
        let d_in: Vec<i16> = (0..w * h).map(|i| 300 + (i % 5) as i16).collect();
        let mut d = d_in.clone();
        assert_eq!(refine_image(&fv, &fv, &mut d, Some(&u), scratch.view()), 0);
        let mut want = d_in.clone();
        refine_image_plain(&fv, &fv, &mut want, Some(&u));
        assert_eq!(d, want);
        // (the median still smooths the network's values: a constant map stays constant)
        let mut c = vec![d0; w * h];
        refine_image(&fv, &fv, &mut c, Some(&u), scratch.view());
        assert!(c.iter().all(|v| *v == d0));
    }
}
