//! Correlation lookup and UFI correlation peaks, computed row by row from the feature rows.
//!
//! No correlation volume is kept: a lookup computes the correlations of one row at a time,
//! `C(x1, x2) = <f1(x1), f2(x2)> / sqrt(c)` for every pair of columns, as one matrix product
//! ([`corr_block`]), and samples them. (The twin builds the full volume; the two are compared in
//! the parity tests.)

use super::gemm::{Epilogue, Lhs, product};
use super::tensor::Tensor;
use muir::kernels::pool;
use muir::model::config::Config;

/// Correlations of row `y`: `block[x1 * w + x2] = C(x1, x2)`, the left pixel `(y, x1)` with
/// every right column, as one matrix product (`w x c` times `c x w`, [`super::gemm::product`]).
pub fn corr_block(f1: &Tensor, f2: &Tensor, y: usize, block: &mut [f32]) {
    let (h, w, c) = (f1.h, f1.w, f1.c);
    assert!(f2.c == c && f2.h == h && f2.w == w && block.len() == w * w, "correlation shapes");
    let rows: Vec<*const f32> = (0..c).map(|ch| f2.channel(ch)[y * w..].as_ptr()).collect();
    let epi = Epilogue { scale: Some(1.0 / (c as f32).sqrt()), ..Default::default() };
    // Left-hand (x1, ch) = f1(ch, y, x1).
    let lhs = Lhs { data: &f1.data[y * w..], row: 1, col: h * w };
    // SAFETY: each row is row y of a channel of f2 (w values), distinct from `block`.
    unsafe { product(lhs, w, &rows, w, &epi, block, w) };
}

/// Linear interpolation of `row` at `pos`, zero outside `[0, len-1]`.
fn sample(row: &[f32], pos: f32) -> f32 {
    let i0 = pos.floor();
    let a = pos - i0;
    let at = |i: f32| if i >= 0.0 && (i as usize) < row.len() { row[i as usize] } else { 0.0 };
    (1.0 - a) * at(i0) + a * at(i0 + 1.0)
}

/// Correlation features at disparity `-flow` (flow: 1/8-grid x "flow", channel 0 used), `L*(2r+1)`
/// channels level-major, as the twin's `lookup`.
///
/// * RAFT pyramid: level l averages the row in blocks of `2^l` (floor), samples at
///   `(x + flow) / 2^l + j`.
/// * post-pooling: level l samples at `x + flow + j 2^l`, each sample the mean of the linearly
///   interpolated correlation at the `2^l` positions centred there.
pub fn lookup(f1: &Tensor, f2: &Tensor, flow: &Tensor, cfg: &Config) -> Tensor {
    let (h, w) = (f1.h, f1.w);
    let r = cfg.corr_radius as isize;
    let k = 2 * cfg.corr_radius + 1;
    let chans = cfg.corr_channels();
    let mut out = Tensor::zeros(chans, h, w);
    let outp = pool::Shared(out.data.as_mut_ptr());
    // One task per row y: it writes out(., y, .) only.
    super::par::each(h, w * chans * f1.c, &|y| {
        let outp = &outp;
        let mut block = vec![0.0f32; w * w];
        corr_block(f1, f2, y, &mut block);
        // RAFT pyramid: level l of the row, iterated 2-wide average pooling with floor
        // (avg_pool1d), level after level.
        let mut pooled = vec![0.0f32; 2 * w];
        for x in 0..w {
            let row = &block[x * w..][..w];
            let centre = x as f32 + flow[(0, y, x)];
            let mut wl = w;
            for lvl in 0..cfg.corr_levels {
                let s = 1usize << lvl;
                if !cfg.post_pool {
                    if lvl == 0 {
                        pooled[..w].copy_from_slice(row);
                    } else {
                        wl /= 2;
                        for q in 0..wl {
                            pooled[q] = (pooled[2 * q] + pooled[2 * q + 1]) / 2.0;
                        }
                    }
                }
                for (jj, j) in (-r..=r).enumerate() {
                    let v = if cfg.post_pool {
                        let base = centre + (j * s as isize) as f32;
                        let mut acc = 0.0;
                        for i in 0..s {
                            acc += sample(row, base + (i as f32 - (s as f32 - 1.0) / 2.0));
                        }
                        acc / s as f32
                    } else {
                        sample(&pooled[..wl], centre / s as f32 + j as f32)
                    };
                    // SAFETY: element (lvl k + jj, y, x) of `out`, written by row y's task only.
                    unsafe { *outp.0.add(((lvl * k + jj) * h + y) * w + x) = v };
                }
            }
        }
    });
    out
}

/// UFI proposals: per left pixel the integer disparities (1/8 grid) of the two highest
/// correlations over `d in [0, min(x, max_d8, MAX_PROPOSAL_D8)]`, the second at least `separation`
/// from the first (the first again if no such d exists); ties go to the smaller d. Returns a
/// 2-channel tensor.
pub fn peaks(f1: &Tensor, f2: &Tensor, separation: usize, max_d8: usize) -> Tensor {
    let (h, w) = (f1.h, f1.w);
    let mut out = Tensor::zeros(2, h, w);
    let outp = pool::Shared(out.data.as_mut_ptr());
    // One task per row y: it writes out(., y, .) only.
    super::par::each(h, w * w * f1.c, &|y| {
        let outp = &outp;
        let mut block = vec![0.0f32; w * w];
        corr_block(f1, f2, y, &mut block);
        for x in 0..w {
            let row = &block[x * w..][..w];
            let best = |skip: Option<usize>| {
                let mut arg: Option<usize> = None;
                for d in 0..=x.min(max_d8).min(muir::arith::MAX_PROPOSAL_D8) {
                    if skip.is_some_and(|d1| d.abs_diff(d1) < separation) {
                        continue;
                    }
                    if arg.is_none_or(|a| row[x - d] > row[x - a]) {
                        arg = Some(d);
                    }
                }
                arg
            };
            let d1 = best(None).unwrap_or(0);
            let d2 = best(Some(d1)).unwrap_or(d1);
            // SAFETY: elements (0, y, x) and (1, y, x) of `out`, written by row y's task only.
            unsafe {
                *outp.0.add(y * w + x) = d1 as f32;
                *outp.0.add((h + y) * w + x) = d2 as f32;
            }
        }
    });
    out
}
