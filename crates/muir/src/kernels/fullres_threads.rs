//! [`super::refine_image`] on the kernel pool (host, `std`, two threads or more): the same
//! integers, each row's work split into tasks.
//!
//! The streaming stage's dependencies run along its paths: the three downward paths of a row
//! need the previous row's, the horizontal paths run along the row. The costs, the downward
//! paths of one row and the final sums are independent per column, the two horizontal paths of
//! a row independent of each other. So each row is three pool jobs:
//!
//! 1. the census codes of row `y + 1` (one task per image) and the decisions of row `y - 1`
//!    (column ranges);
//! 2. the bands, grey levels and costs of row `y` (column ranges) and the median of row `y - 2`;
//! 3. the right-to-left and left-to-right paths of row `y` (a task each, first: the longest) and
//!    its three downward paths (per path and column range).
//!
//! Each task writes its own columns (or row) only, and reads what earlier jobs wrote. The
//! left-to-right path is kept for the whole row here (the streaming stage sums it pixel by
//! pixel as it goes), so the scratch is the streaming stage's plus one row of path costs, in
//! vectors of this function's own (the arena holds the single-thread stage's).
#![deny(clippy::indexing_slicing)]

use core::sync::atomic::{AtomicUsize, Ordering};

use super::super::pool::{self, Shared};
use super::{Band, CENSUS_RADIUS, SLOTS, WINDOW_ROWS, census_row, copy_head, grey_at, median_row, path_step, penalty2, pixel_costs, sum_decide};
use crate::input::ImageView;

/// Columns of one cost, downward-path or decision task.
const COLS: usize = 64;

/// Narrowest image this schedule is used for (narrower rows are too short to split).
pub(super) const MIN_WIDTH: usize = 2 * COLS;

/// A buffer the tasks of a job share: each task takes the elements it alone writes, or reads
/// what no task of the same job writes.
#[derive(Clone, Copy)]
struct Buf<T> {
    at: Shared<T>,
    len: usize,
}

impl<T> Buf<T> {
    fn new(v: &mut [T]) -> Self {
        Buf { at: Shared(v.as_mut_ptr()), len: v.len() }
    }
    /// Elements `start .. start + n` (empty where that is not inside the buffer).
    ///
    /// # Safety
    /// No task of the running job writes them while the slice lives.
    unsafe fn span(&self, start: usize, n: usize) -> &[T] {
        // SAFETY: the caller's guarantee.
        unsafe { self.span_mut(start, n) }
    }
    /// [`Buf::span`], to write.
    ///
    /// # Safety
    /// No other task of the running job reads or writes them while the slice lives.
    #[allow(clippy::mut_from_ref)]
    unsafe fn span_mut(&self, start: usize, n: usize) -> &mut [T] {
        match start.checked_add(n) {
            // SAFETY: inside the buffer; the caller's guarantee for the rest.
            Some(end) if end <= self.len => unsafe { self.at.slice(start, n) },
            _ => &mut [],
        }
    }
    /// Row `i` of rows of `n` elements ([`Buf::span`]).
    ///
    /// # Safety
    /// As [`Buf::span`].
    unsafe fn row(&self, i: usize, n: usize) -> &[T] {
        // SAFETY: the caller's guarantee.
        unsafe { self.span(i.saturating_mul(n), n) }
    }
    /// Row `i` of rows of `n` elements ([`Buf::span_mut`]).
    ///
    /// # Safety
    /// As [`Buf::span_mut`].
    #[allow(clippy::mut_from_ref)]
    unsafe fn row_mut(&self, i: usize, n: usize) -> &mut [T] {
        // SAFETY: the caller's guarantee.
        unsafe { self.span_mut(i.saturating_mul(n), n) }
    }
}

/// [`super::refine_image`]'s result for images at least [`MIN_WIDTH`] wide, `disparity` and
/// `uncertainty` at least `width x height` (the caller checked), on the pool.
pub(super) fn refine(left: &ImageView<'_>, right: &ImageView<'_>, disparity: &mut [i16], uncertainty: Option<&[i16]>) -> usize {
    let (w, h) = (left.width, left.height);
    let sw = SLOTS * w;
    let cg = (2 * CENSUS_RADIUS + 1) * w;
    // Census rings (left, then right), grey scratch per census task, grey levels of the left
    // image's row (two rows, by the row's parity), path costs (costs, right-to-left,
    // left-to-right, then the downward paths: two rows of three planes), bands (two rows of
    // firsts and lengths), decisions (three rows).
    let (mut census, mut cgrey, mut grey) = (vec![0u64; 2 * WINDOW_ROWS * w], vec![0u8; 4 * cg], vec![0u8; 2 * w]);
    let (mut paths, mut bands, mut decisions) = (vec![0u16; 9 * sw], vec![0i16; 4 * w], vec![0i16; 3 * w]);
    let (census, cgrey, grey) = (Buf::new(&mut census), Buf::new(&mut cgrey), Buf::new(&mut grey));
    let (paths, bands, decisions) = (Buf::new(&mut paths), Buf::new(&mut bands), Buf::new(&mut decisions));
    let disp = Buf::new(disparity);
    let chunks = w.div_ceil(COLS);
    let slot = |y: isize| y.rem_euclid(WINDOW_ROWS as isize) as usize;
    // Plane indices in `paths` (`sw` each).
    const COSTS: usize = 0;
    const RL: usize = 1;
    const LR: usize = 2;
    let top = |y: usize, p: usize| 3 + 3 * (y % 2) + p;
    let decided = AtomicUsize::new(0);
    // Census task `t` (0 left, 1 right; `g` its grey scratch) of row `y`.
    let census_task = |t: usize, g: usize, y: isize| {
        let img = if t == 0 { left } else { right };
        // SAFETY: the ring slot of row `y` of image `t` and grey scratch `g` are this task's
        // alone (a job's census tasks differ in image or row, and take different scratch).
        unsafe { census_row(img, y, cgrey.row_mut(g, cg), census.row_mut(t * WINDOW_ROWS + slot(y), w)) };
    };
    // Band of column `x` of row `y`.
    let band = |y: usize, x: usize| {
        // SAFETY: a row of bands is written only by the cost tasks of its own row.
        let b = unsafe { bands.row(y % 2, 2 * w) };
        match (b.get(x), b.get(w + x)) {
            (Some(&first), Some(&len)) => Band { first, len },
            _ => Band::default(),
        }
    };
    // SAFETY (every `grey_of`): a row of grey levels is written only by its row's cost tasks.
    let grey_of = |y: usize, x: usize| unsafe { grey.row(y % 2, w) }.get(x).copied().unwrap_or(0);
    // The decisions of row `y`, columns of chunk `c`.
    let decide_task = |y: usize, c: usize| {
        let (x0, n) = (c * COLS, COLS.min(w.saturating_sub(c * COLS)));
        let mut count = 0;
        let mut sums = [0u32; SLOTS];
        // SAFETY: the path planes of row `y` are complete (job 3 of row `y` is over) and not
        // written before job 3 of row `y + 1`; the disparity row is written by no task of this
        // job (the median tasks run in job 2); the decisions' columns are this task's.
        let (rl, lr, t0, t1, t2, d_row, dec) = unsafe {
            (paths.row(RL, sw), paths.row(LR, sw), paths.row(top(y, 0), sw), paths.row(top(y, 1), sw), paths.row(top(y, 2), sw), disp.row(y, w), decisions.span_mut((y % 3) * w + x0, n))
        };
        for (x, o) in (x0..).zip(dec.iter_mut()) {
            let b = band(y, x);
            let planes = [lr, rl, t0, t1, t2].map(|p| super::chunk(p, x, SLOTS));
            *o = match sum_decide(planes, b, &mut sums) {
                Some(d) => {
                    count += 1;
                    d
                }
                None => d_row.get(x).copied().unwrap_or(0),
            };
        }
        decided.fetch_add(count, Ordering::Relaxed);
    };
    // The median of row `t` (`last`: the bottom row, whose row below is itself).
    let median_task = |t: usize, last: bool| {
        let (above, mid) = (t.saturating_sub(1) % 3, t % 3);
        let below = if last { mid } else { (t + 1) % 3 };
        // SAFETY: the decision rows are not written in this job (job 2); disparity row `t` is
        // read by no task of it (the cost tasks read row `t + 2`).
        unsafe { median_row([decisions.row(above, w), decisions.row(mid, w), decisions.row(below, w)], disp.row_mut(t, w)) };
    };

    // Census rows -1 and 0 of both images.
    pool::run(4, &|t| census_task(t % 2, t, t as isize / 2 - 1));
    for y in 0..h {
        let yi = y as isize;
        // 1. Census row y + 1, the decisions of row y - 1.
        let n_dec = if y >= 1 { chunks } else { 0 };
        pool::run(2 + n_dec, &|t| match t {
            0 | 1 => census_task(t, t, yi + 1),
            _ => decide_task(y - 1, t - 2),
        });
        // 2. Bands, grey levels and costs of row y; the median of row y - 2.
        let n_med = usize::from(y >= 2);
        pool::run(chunks + n_med, &|t| {
            if t == chunks {
                return median_task(y - 2, false);
            }
            let (x0, n) = (t * COLS, COLS.min(w.saturating_sub(t * COLS)));
            // SAFETY: the census rings are written in job 1 only; the disparity and uncertainty
            // rows `y` are read only (the median task writes row `y - 2`); columns `x0 .. x0 + n`
            // of this row's bands, grey levels and costs are this task's.
            let (lrows, rrows, d_row, firsts, lens, g_row, costs) = unsafe {
                let lrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| census.row(slot(yi - 1 + k as isize), w));
                let rrows: [&[u64]; WINDOW_ROWS] = core::array::from_fn(|k| census.row(WINDOW_ROWS + slot(yi - 1 + k as isize), w));
                let b = (y % 2) * 2 * w;
                (lrows, rrows, disp.row(y, w), bands.span_mut(b + x0, n), bands.span_mut(b + w + x0, n), grey.span_mut((y % 2) * w + x0, n), paths.span_mut(COSTS * sw + x0 * SLOTS, n * SLOTS))
            };
            let u_row = uncertainty.map(|u| super::chunk(u, y, w));
            for ((((x, first), len), g), c) in (x0..).zip(firsts).zip(lens).zip(g_row).zip(costs.chunks_exact_mut(SLOTS)) {
                let b = Band::of(d_row.get(x).copied().unwrap_or(0), u_row.and_then(|u| u.get(x)).copied());
                (*first, *len) = (b.first, b.len);
                *g = grey_at(left, x, y);
                costs_of(&lrows, &rrows, w, x, b, c);
            }
        });
        // 3. The horizontal paths (first, the longest tasks), the downward paths.
        pool::run(2 + 3 * chunks, &|t| {
            // SAFETY: the costs, bands and grey levels of rows `y` and `y - 1` are read only
            // here; each task writes its own plane (`RL`, `LR`) or its columns of one downward
            // plane of row `y`, and reads the planes of row `y - 1`.
            let costs = unsafe { paths.row(COSTS, sw) };
            let c_at = |x: usize| super::chunk(costs, x, SLOTS);
            match t {
                0 => {
                    // SAFETY: this plane is this task's.
                    let rl = unsafe { paths.row_mut(RL, sw) };
                    for x in (0..w).rev() {
                        let b = band(y, x);
                        let (out, next) = match rl.get_mut(x * SLOTS..) {
                            Some(s) => s.split_at_mut(SLOTS.min(s.len())),
                            None => break,
                        };
                        if x + 1 == w {
                            copy_head(out, c_at(x), b.n());
                        } else {
                            path_step(next, band(y, x + 1), c_at(x), b, penalty2(grey_of(y, x), grey_of(y, x + 1)), out);
                        }
                    }
                }
                1 => {
                    // SAFETY: this plane is this task's.
                    let lr = unsafe { paths.row_mut(LR, sw) };
                    for x in 0..w {
                        let b = band(y, x);
                        let (prev, out) = match lr.get_mut(..(x + 1) * SLOTS) {
                            Some(s) => s.split_at_mut(x * SLOTS),
                            None => break,
                        };
                        if x == 0 {
                            copy_head(out, c_at(x), b.n());
                        } else {
                            let prev = super::chunk(prev, x - 1, SLOTS);
                            path_step(prev, band(y, x - 1), c_at(x), b, penalty2(grey_of(y, x), grey_of(y, x - 1)), out);
                        }
                    }
                }
                _ => {
                    let (p, c) = ((t - 2) / chunks, (t - 2) % chunks);
                    let (x0, n) = (c * COLS, COLS.min(w.saturating_sub(c * COLS)));
                    // SAFETY: columns `x0 .. x0 + n` of plane `p` of row `y` are this task's; the
                    // planes of row `y - 1` are read only.
                    let (prev_plane, outs) = unsafe { (paths.row(top(y + 1, p), sw), paths.span_mut(top(y, p) * sw + x0 * SLOTS, n * SLOTS)) };
                    for (x, out) in (x0..).zip(outs.chunks_exact_mut(SLOTS)) {
                        let b = band(y, x);
                        if y == 0 {
                            copy_head(out, c_at(x), b.n());
                            continue;
                        }
                        let q = match p {
                            0 => x.saturating_sub(1),
                            1 => x,
                            _ => (x + 1).min(w - 1),
                        };
                        path_step(super::chunk(prev_plane, q, SLOTS), band(y - 1, q), c_at(x), b, penalty2(grey_of(y, x), grey_of(y - 1, q)), out);
                    }
                }
            }
        });
    }
    // The decisions of the last row, then the medians of the last two.
    pool::run(chunks, &|c| decide_task(h - 1, c));
    if h >= 2 {
        median_task(h - 2, false);
    }
    median_task(h - 1, true);
    decided.into_inner()
}

/// [`pixel_costs`], with the POPCNT instruction where the CPU has it (the x86-64 baseline has
/// none: `count_ones` becomes a dozen instructions).
#[inline]
fn costs_of(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, b: Band, out: &mut [u16]) {
    #[cfg(target_arch = "x86_64")]
    if std::is_x86_feature_detected!("popcnt") {
        #[target_feature(enable = "popcnt")]
        unsafe fn with_popcnt(left: &[&[u64]; WINDOW_ROWS], right: &[&[u64]; WINDOW_ROWS], w: usize, x: usize, b: Band, out: &mut [u16]) {
            pixel_costs(left, right, w, x, b, out)
        }
        // SAFETY: the CPU has POPCNT.
        return unsafe { with_popcnt(left, right, w, x, b, out) };
    }
    pixel_costs(left, right, w, x, b, out)
}
