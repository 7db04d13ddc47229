//! Pooling and resizing between the 1/8 and 1/16 grids.
//!
//! Reads past the end of a too-short `src` count as 0 and writes past the end of `out` are
//! skipped (the engine's buffers always fit).
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, sat_i16};

/// One row of `avg_pool2d(x, 3, stride=2, padding=1)` (padding counted, so the sum is divided by
/// 9) of an HWC i16 tensor `src` (`h x w x c`). Output row `y` has `ceil(w/2) * c` values.
pub fn pool2x_row(src: &[i16], h: usize, w: usize, c: usize, y: usize, out: &mut [i16]) {
    let wo = w.div_ceil(2);
    for ox in 0..wo {
        for ch in 0..c {
            let mut s = 0i64;
            for dy in 0..3 {
                let iy = (2 * y + dy) as isize - 1;
                if iy < 0 || iy as usize >= h {
                    continue;
                }
                for dx in 0..3 {
                    let ix = (2 * ox + dx) as isize - 1;
                    if ix >= 0 && (ix as usize) < w {
                        s += src.get((iy as usize * w + ix as usize) * c + ch).map_or(0, |v| *v as i64);
                    }
                }
            }
            if let Some(o) = out.get_mut(ox * c + ch) {
                *o = sat_i16(div_round(s, 9));
            }
        }
    }
}

/// Source index and remainder of output `i` of an align_corners resize from `n_in` to `n_out`:
/// position `i * (n_in - 1) / (n_out - 1)` as integer part and numerator over `n_out - 1`.
#[inline]
fn align_corners(i: usize, n_in: usize, n_out: usize) -> (usize, i64, i64) {
    if n_out <= 1 || n_in <= 1 {
        return (0, 0, 1);
    }
    let num = (i * (n_in - 1)) as i64;
    let den = (n_out - 1) as i64;
    ((num / den) as usize, num % den, den)
}

/// One row of `F.interpolate(src, (h_out, w_out), mode="bilinear", align_corners=True)` for an HWC
/// i16 tensor `src` (`h x w x c`), with exact rational weights and one rounding.
#[allow(clippy::too_many_arguments)]
pub fn interp_row(src: &[i16], h: usize, w: usize, c: usize, h_out: usize, w_out: usize, y: usize, out: &mut [i16]) {
    let (y0, ry, dy) = align_corners(y, h, h_out);
    let y1 = (y0 + 1).min(h.saturating_sub(1));
    for x in 0..w_out {
        let (x0, rx, dx) = align_corners(x, w, w_out);
        let x1 = (x0 + 1).min(w.saturating_sub(1));
        for ch in 0..c {
            let at = |yy: usize, xx: usize| src.get((yy * w + xx) * c + ch).map_or(0, |v| *v as i64);
            let top = (dx - rx) * at(y0, x0) + rx * at(y0, x1);
            let bot = (dx - rx) * at(y1, x0) + rx * at(y1, x1);
            if let Some(o) = out.get_mut(x * c + ch) {
                *o = sat_i16(div_round((dy - ry) * top + ry * bot, dy * dx));
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn pool_and_interp() {
        // 3x3 of ones: the centre output (0,0) sees 4 inside pixels of 9.
        let src = [900i16; 9];
        let mut o = [0i16; 2];
        pool2x_row(&src, 3, 3, 1, 0, &mut o);
        assert_eq!(o, [400, 400]);
        let small = [0i16, 100, 200, 300]; // 2x2
        let mut r = [0i16; 3];
        interp_row(&small, 2, 2, 1, 3, 3, 1, &mut r);
        assert_eq!(r, [100, 150, 200]);
        interp_row(&small, 2, 2, 1, 3, 3, 2, &mut r);
        assert_eq!(r, [200, 250, 300]);
    }
}
