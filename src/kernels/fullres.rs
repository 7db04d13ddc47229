//! Full-resolution refinement of the network's disparity: integer narrow-band matching around it.
//!
//! The network estimates disparity at 1/8 resolution and upsamples it (convex upsampling): robust,
//! but its sub-pixel precision at full resolution is limited (median error ~0.6 px on held-out
//! Middlebury against ~0.3 px for StereoSGBM). This stage re-matches every pixel in a narrow band
//! around the network's value, with a classical cost that is exact at full resolution, and keeps
//! the network's value wherever the cost cannot decide:
//!
//! * **grey**: `(77 R + 150 G + 29 B) >> 8` (a grey input is used as is);
//! * **census** `c(x, y)`: 48 bits over the 7x7 neighbourhood (row-major, the centre skipped), bit
//!   set when the neighbour is darker than the centre; coordinates clamped to the image;
//! * **cost** of disparity `d` at pixel `p`: `A(p, d) = sum over the 9x9 window of q = clamp(p + o)
//!   of popcount(cL(q) ^ cR(max(q.x - d, 0), q.y))` (an 81-term box sum, borders replicated);
//! * **band**: `base = d0 >> 5` (the network's disparity `d0` in Q10.5, floored), candidates
//!   `base - R ..= base + R + 1`, `d >= 0`, with `R` from the network's predicted error
//!   `sigma = exp(u / 2)`: `R = clamp(ceil(3 sigma), 3, 12)` (the band widens where the network is
//!   unsure), decided on `u` by the integer thresholds [`BAND_U_THRESHOLDS`];
//! * **decision**: `d*` = the first candidate of least cost; refined only if `d*` has candidates on
//!   both sides, the cost curve is curved enough there, `A(d*-1) + A(d*+1) - 2 A(d*) >=`
//!   [`MIN_CURVATURE`] (a flat cost means texture cannot decide: the network's value stays), and
//!   no other candidate (beyond `d* +- 1`) comes within [`UNIQUENESS_PERCENT`] of `A(d*)`;
//! * **sub-pixel**: parabola through the three costs, `d = d* + (A(d*-1) - A(d*+1)) / (2 curv)`,
//!   in Q10.5: `(d* << 5) + div_round(16 (A(d*-1) - A(d*+1)), curv)` (at most half a pixel).
//!
//! Parameters were chosen on the training scenes of `muir.split` (docs/experiments/fullres-refine):
//! held-out figures are reported, never tuned on. The stage needs no volume: per pixel it reads
//! census codes of the 9 rows around it, so the engine keeps a ring of 9 census rows per image.
//! The PyTorch twin's evaluation mirrors it bit for bit (`python/muir/fullres.py`).

use crate::arith::{DISP_FRAC, div_round, sat_i16};
use crate::input::{ImageView, PixelFormat};

/// Census radius (7x7 neighbourhood, 48 bits).
pub const CENSUS_RADIUS: usize = 3;
/// Aggregation window radius (9x9 box).
pub const WINDOW_RADIUS: usize = 4;
/// Rows of census codes one output row needs (per image).
pub const WINDOW_ROWS: usize = 2 * WINDOW_RADIUS + 1;
/// Smallest band radius (px on each side of the network's disparity).
pub const MIN_BAND: usize = 3;
/// Largest band radius.
pub const MAX_BAND: usize = 12;
/// A second minimum (outside the winner's two neighbours) must cost at least this many percent
/// more than the winner, or the network's value stays (repetitive or ambiguous texture).
pub const UNIQUENESS_PERCENT: u64 = 10;
/// Least curvature of the cost at the winner, in summed census bits (2 bits per window pixel).
pub const MIN_CURVATURE: u32 = 2 * (WINDOW_ROWS * WINDOW_ROWS) as u32;
/// `BAND_U_THRESHOLDS[i]`: the band radius is at least `MIN_BAND + 1 + i` when `u` (Q4.11)
/// exceeds it; `floor(2 ln((r - 1) / 3) * 2048)` for `r = 4 ..= 12` (`ceil(3 sigma) >= r` <=>
/// `sigma > (r - 1) / 3`). Written out so that host and target use the same integers (a unit test
/// recomputes them).
pub const BAND_U_THRESHOLDS: [i16; MAX_BAND - MIN_BAND] = [0, 1178, 2092, 2839, 3470, 4017, 4499, 4931, 5321];

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
/// `(2 * CENSUS_RADIUS + 1) * img.width` bytes (the grey rows `y - 3 ..= y + 3`).
pub fn census_row(img: &ImageView<'_>, y: isize, grey: &mut [u8], out: &mut [u64]) {
    let w = img.width;
    let n = 2 * CENSUS_RADIUS + 1;
    let clamp_y = |yy: isize| yy.clamp(0, img.height as isize - 1) as usize;
    // A row outside the image is the edge row's codes (the window replicates borders).
    let y = clamp_y(y) as isize;
    for (k, row) in grey.chunks_exact_mut(w).take(n).enumerate() {
        let yy = clamp_y(y + k as isize - CENSUS_RADIUS as isize);
        for (x, g) in row.iter_mut().enumerate() {
            *g = grey_at(img, x, yy);
        }
    }
    let r = CENSUS_RADIUS as isize;
    for (x, code) in out.iter_mut().enumerate().take(w) {
        let centre = grey[CENSUS_RADIUS * w + x];
        let mut c = 0u64;
        let mut bit = 0;
        for dy in 0..n {
            let row = &grey[dy * w..(dy + 1) * w];
            for dx in -r..=r {
                if dy == CENSUS_RADIUS && dx == 0 {
                    continue;
                }
                let xx = (x as isize + dx).clamp(0, w as isize - 1) as usize;
                c |= ((row[xx] < centre) as u64) << bit;
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

/// Cost of disparity `d` at column `x`: the 9x9 box sum of census Hamming distances; `left` and
/// `right` are the census rows `y - 4 ..= y + 4` (clamped) of the two images.
#[inline(always)]
fn cost(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, d: usize) -> u32 {
    let r = WINDOW_RADIUS as isize;
    let mut s = 0u32;
    for (cl, cr) in left.iter().zip(right.iter()) {
        for dx in -r..=r {
            let q = (x as isize + dx).clamp(0, w as isize - 1) as usize;
            s += (cl[q] ^ cr[q.saturating_sub(d)]).count_ones();
        }
    }
    s
}

/// Refined disparity (Q10.5) of column `x` of a row whose network disparity is `d0` (Q10.5) and
/// uncertainty `u` (Q4.11; `None` without MUD: the narrowest band). `None` where the network's
/// value stays (winner on the band's edge, a flat cost, or a second minimum nearly as good).
#[inline(always)]
pub fn refine_pixel(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, d0: i16, u: Option<i16>) -> Option<i16> {
    let base = (d0 >> DISP_FRAC) as isize;
    let rad = u.map_or(MIN_BAND, band_radius) as isize;
    // Candidates d = first .. first + n - 1 (those >= 0 of the band).
    let first = (base - rad).max(0);
    let last = base + rad + 1;
    if last < first + 2 {
        return None;
    }
    let n = (last - first + 1) as usize;
    let mut costs = [0u32; 2 * MAX_BAND + 2];
    let costs = &mut costs[..n];
    for (k, c) in costs.iter_mut().enumerate() {
        *c = cost(left, right, w, x, (first as usize) + k);
    }
    // First minimum (the smallest d on ties).
    let mut i = 0;
    for (k, c) in costs.iter().enumerate() {
        if *c < costs[i] {
            i = k;
        }
    }
    if i == 0 || i + 1 == n {
        return None;
    }
    let (a0, a1, a2) = (costs[i - 1], costs[i], costs[i + 1]);
    let curv = a0 + a2 - 2 * a1;
    if curv < MIN_CURVATURE {
        return None;
    }
    // Uniqueness: every candidate outside the winner's neighbours costs UNIQUENESS % more.
    let far = costs.iter().enumerate().filter(|(k, _)| k.abs_diff(i) > 1).map(|(_, c)| *c).min();
    if far.is_some_and(|f| (f as u64) * 100 < (a1 as u64) * (100 + UNIQUENESS_PERCENT)) {
        return None;
    }
    let off = div_round(16 * (a0 as i64 - a2 as i64), curv as i64);
    Some(sat_i16((((first as usize + i) as i64) << DISP_FRAC) + off))
}

/// Scratch bytes of [`refine_image`] for an image `width` wide: two rings of [`WINDOW_ROWS`]
/// census rows (u64) and the grey rows of one census row.
pub const fn scratch_bytes(width: usize) -> usize {
    2 * WINDOW_ROWS * width * 8 + (2 * CENSUS_RADIUS + 1) * width
}

/// Refines a whole disparity map in place (`disparity`, Q10.5, `width x height` of the images;
/// `uncertainty` Q4.11 or `None`). Streams over rows with two rings of census rows in `ring`
/// (`2 * WINDOW_ROWS * width` codes) and `grey` scratch (`7 * width` bytes): memory independent of
/// the disparity range. Returns the number of refined pixels.
pub fn refine_image(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, ring: &mut [u64], grey: &mut [u8]) -> usize {
    // The x86-64 baseline has no POPCNT instruction (`count_ones` becomes a dozen instructions):
    // the same code compiled with it where the CPU has it.
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if std::is_x86_feature_detected!("popcnt") {
        #[target_feature(enable = "popcnt")]
        unsafe fn with_popcnt(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, ring: &mut [u64], grey: &mut [u8]) -> usize {
            refine_rows(left, right, disparity, uncertainty, ring, grey)
        }
        // SAFETY: the CPU has POPCNT.
        return unsafe { with_popcnt(left, right, disparity, uncertainty, ring, grey) };
    }
    refine_rows(left, right, disparity, uncertainty, ring, grey)
}

/// [`refine_image`]'s work (inlined into each of its compilations).
#[inline(always)]
fn refine_rows(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>, ring: &mut [u64], grey: &mut [u8]) -> usize {
    let (w, h) = (left.width, left.height);
    let (ring_l, ring_r) = ring.split_at_mut(WINDOW_ROWS * w);
    let slot = |y: isize| (y.rem_euclid(WINDOW_ROWS as isize)) as usize;
    let r = WINDOW_RADIUS as isize;
    // Census rows -4 ..= 3 (clamped rows repeat codes; each ring slot holds the row whose index
    // is congruent to it); then, before output row y, row y + 4.
    for y in -r..r {
        let s = slot(y);
        census_row(left, y, grey, &mut ring_l[s * w..(s + 1) * w]);
        census_row(right, y, grey, &mut ring_r[s * w..(s + 1) * w]);
    }
    let mut refined = 0;
    for y in 0..h as isize {
        let s = slot(y + r);
        census_row(left, y + r, grey, &mut ring_l[s * w..(s + 1) * w]);
        census_row(right, y + r, grey, &mut ring_r[s * w..(s + 1) * w]);
        let slots: [usize; WINDOW_ROWS] = core::array::from_fn(|k| slot(y - r + k as isize));
        let lrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| &ring_l[slots[k] * w..(slots[k] + 1) * w]);
        let rrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| &ring_r[slots[k] * w..(slots[k] + 1) * w]);
        let row = y as usize * w;
        for x in 0..w {
            let u = uncertainty.map(|u| u[row + x]);
            if let Some(d) = refine_pixel(&lrows, &rrows, w, x, disparity[row + x], u) {
                disparity[row + x] = d;
                refined += 1;
            }
        }
    }
    refined
}

/// Plain twin of [`refine_image`]: census codes of both whole images first, then every pixel
/// (host tests and the plain fixed-point reference).
#[cfg(feature = "std")]
pub fn refine_image_plain(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>) -> usize {
    let (w, h) = (left.width, left.height);
    let codes = |img: &ImageView<'_>| {
        let mut grey = vec![0u8; (2 * CENSUS_RADIUS + 1) * w];
        let mut out = vec![0u64; w * h];
        for y in 0..h {
            census_row(img, y as isize, &mut grey, &mut out[y * w..(y + 1) * w]);
        }
        out
    };
    let (cl, cr) = (codes(left), codes(right));
    let mut refined = 0;
    for y in 0..h {
        let row_at = |k: usize| -> usize { (y as isize + k as isize - WINDOW_RADIUS as isize).clamp(0, h as isize - 1) as usize * w };
        let lrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| &cl[row_at(k)..row_at(k) + w]);
        let rrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| &cr[row_at(k)..row_at(k) + w]);
        for x in 0..w {
            let i = y * w + x;
            if let Some(d) = refine_pixel(&lrows, &rrows, w, x, disparity[i], uncertainty.map(|u| u[i])) {
                disparity[i] = d;
                refined += 1;
            }
        }
    }
    refined
}

#[cfg(test)]
mod tests {
    use super::*;

    #[cfg(feature = "std")]
    #[test]
    fn streaming_matches_plain_twin() {
        let mut r = crate::kernels::testutil::Rng(11);
        for &(w, h) in &[(37usize, 23usize), (64, 9), (16, 40)] {
            let l: Vec<u8> = (0..w * h * 3).map(|_| r.i8() as u8).collect();
            let rr: Vec<u8> = (0..w * h * 3).map(|_| r.i8() as u8).collect();
            let (lv, rv) = (ImageView::new(w, h, PixelFormat::Rgb8, &l).unwrap(), ImageView::new(w, h, PixelFormat::Rgb8, &rr).unwrap());
            let d0: Vec<i16> = (0..w * h).map(|_| (r.i16() >> 6).abs()).collect();
            let u: Vec<i16> = (0..w * h).map(|_| r.i16() >> 2).collect();
            let (mut a, mut b) = (d0.clone(), d0.clone());
            let mut ring = vec![0u64; 2 * WINDOW_ROWS * w];
            let mut grey = vec![0u8; 7 * w];
            let na = refine_image(&lv, &rv, &mut a, Some(&u), &mut ring, &mut grey);
            let nb = refine_image_plain(&lv, &rv, &mut b, Some(&u));
            assert_eq!(a, b, "{w}x{h}");
            assert_eq!(na, nb);
        }
    }

    #[test]
    fn band_thresholds_are_the_formula() {
        for (i, t) in BAND_U_THRESHOLDS.iter().enumerate() {
            let r = (MIN_BAND + 1 + i) as f64;
            assert_eq!(*t as f64, (2.0 * ((r - 1.0) / 3.0).ln() * 2048.0).floor(), "r = {r}");
        }
        assert_eq!(band_radius(-5000), MIN_BAND);
        assert_eq!(band_radius(0), MIN_BAND);
        assert_eq!(band_radius(1), MIN_BAND + 1);
        assert_eq!(band_radius(i16::MAX), MAX_BAND);
        // sigma = 2 px: ceil(3 * 2) = 6.
        assert_eq!(band_radius((2.0f64 * 2f64.ln() * 2048.0) as i16), 6);
    }

    /// A textured pair shifted by a known sub-pixel disparity: the stage recovers it from a
    /// network value 2.4 px off, and leaves a textureless region alone.
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
        let mut ring = vec![0u64; 2 * WINDOW_ROWS * w];
        let mut grey = vec![0u8; 7 * w];
        let u = vec![(2.0f64 * 1.2f64.ln() * 2048.0) as i16; w * h]; // sigma 1.2 px: band 4
        let n = refine_image(&lv, &rv, &mut d, Some(&u), &mut ring, &mut grey);
        assert!(n > 0);
        let (y, x) = (20, 40);
        let got = d[y * w + x] as f64 / 32.0;
        assert!((got - d_true).abs() < 0.2, "refined {got} vs {d_true}");
        assert_eq!(d[y * w + 85], d0, "flat region keeps the network's value");
    }
}
