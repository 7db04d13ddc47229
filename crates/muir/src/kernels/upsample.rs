//! Joint convex upsampling of disparity and uncertainty (RAFT's 8x upsampler).
//!
//! For each full-resolution pixel `(8y + dy, 8x + dx)` the 9 mask logits `l_k` (channel
//! `k*64 + dy*8 + dx`) give softmax weights `e_k = exp_q11(shift(l_k - max))`; the outputs are
//! `disparity = -div_round(sum e_k flow_k, S)` (Q8 flow at 1/8 is Q5 pixels at full resolution)
//! and `u = div_round(sum e_k u_k, S)`, with `S = sum e_k` and zero padding outside the grid.
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, lut, sat_i16};

/// Upsamples one 1/8 pixel `(y, x)` into its 8x8 block: `logits` are its 576 mask values
/// (format `mask_frac`), `flow` / `u` the whole 1/8 maps (`h x w`, one channel; `u` optional).
/// `disp_out` / `u_out` receive 8 rows of 8 values each at `out[dy * stride + dx]`.
///
/// With fewer than 576 logits nothing is written; a neighbour outside a too-short `flow` / `u`
/// counts as 0 and outputs past the end of `disp_out` / `u_out` are skipped.
#[allow(clippy::too_many_arguments)]
pub fn upsample_pixel(logits: &[i16], mask_frac: i8, flow: &[i16], u: Option<&[i16]>, h: usize, w: usize, y: usize, x: usize, disp_out: &mut [i16], u_out: Option<&mut [i16]>, stride: usize) {
    let Some(logits) = logits.get(..576) else {
        return;
    };
    let mut nb_flow = [0i32; 9];
    let mut nb_u = [0i32; 9];
    for (k, (nf, nu)) in nb_flow.iter_mut().zip(&mut nb_u).enumerate() {
        let (ny, nx) = ((y + k / 3) as isize - 1, (x + k % 3) as isize - 1);
        if ny >= 0 && nx >= 0 && (ny as usize) < h && (nx as usize) < w {
            let i = ny as usize * w + nx as usize;
            *nf = flow.get(i).map_or(0, |v| *v as i32);
            *nu = u.and_then(|u| u.get(i)).map_or(0, |v| *v as i32);
        }
    }
    // `clamp(shift_round(l - max, 11 - mask_frac), -32768, 0)` in i32: `l - max` is in
    // `-65535..=0`, so a left shift by more than 15 and a right one by more than 20 give the
    // same clamped values as 15 and 20 (every non-zero difference reaches -32768, resp. rounds
    // to 0), and neither overflows i32.
    let to_q11 = 11 - mask_frac as i32;
    let (lsh, rsh) = if to_q11 >= 0 { (to_q11.min(15) as u32, 0u32) } else { (0u32, (-to_q11).min(20) as u32) };
    let half = if rsh > 0 { 1i32 << (rsh - 1) } else { 0 };
    let mut u_out = u_out;
    for dy in 0..8 {
        for dx in 0..8 {
            let sub = dy * 8 + dx;
            // Logit `k` of sub-pixel `sub`: `logits[k * 64 + sub]` (always there: 576 of them).
            let mut l = [0i32; 9];
            for (k, lk) in l.iter_mut().enumerate() {
                *lk = logits.get(k * 64 + sub).map_or(0, |v| *v as i32);
            }
            let max = l.iter().copied().max().unwrap_or(0);
            // Weights `e_k <= 32768` (Q0.15), so `S <= 9 * 2^15` and `|e_k v_k| <= 2^30`.
            let mut e = [0i32; 9];
            let mut s = 0i32;
            for (ek, lk) in e.iter_mut().zip(&l) {
                let v = *lk - max;
                let d = if rsh == 0 { v << lsh } else { (v + half) >> rsh };
                *ek = lut::exp_q11(d.max(-32768));
                s += *ek;
            }
            // (each product below 2^30 in magnitude: the i64 products are the i32 ones, one
            // `SMLAL` each where a product widened after an i32 multiply took three)
            let fd: i64 = e.iter().zip(&nb_flow).map(|(a, b)| *a as i64 * *b as i64).sum();
            if let Some(o) = disp_out.get_mut(dy * stride + dx) {
                *o = sat_i16(-div_round(fd, s as i64));
            }
            if let Some(o) = u_out.as_deref_mut().and_then(|uo| uo.get_mut(dy * stride + dx)) {
                let fu: i64 = e.iter().zip(&nb_u).map(|(a, b)| *a as i64 * *b as i64).sum();
                *o = sat_i16(div_round(fu, s as i64));
            }
        }
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn uniform_mask_averages_neighbours() {
        let flow = [-256i16; 9]; // 3x3 grid, disparity 8 px everywhere
        let u = [2048i16; 9];
        let logits = [0i16; 576];
        let mut d = [0i16; 64];
        let mut uo = [0i16; 64];
        upsample_pixel(&logits, 4, &flow, Some(&u), 3, 3, 1, 1, &mut d, Some(&mut uo), 8);
        assert!(d.iter().all(|v| *v == 256)); // 8 px in Q5
        assert!(uo.iter().all(|v| *v == 2048));
        // corner pixel: 4 of 9 neighbours inside
        upsample_pixel(&logits, 4, &flow, Some(&u), 3, 3, 0, 0, &mut d, Some(&mut uo), 8);
        assert_eq!(d[0], div_round(256 * 4, 9) as i16);
    }

    /// The i32 weights against the former i64 formulas (`shift_round` of `l - max` by any
    /// `11 - mask_frac`, products and sums in i64), random and extreme logits and neighbours.
    #[test]
    fn matches_i64_formulas() {
        use crate::arith::shift_round;
        let mut r = super::super::testutil::Rng(0x9E37_79B9_7F4A_7C15);
        let mut next = || r.next();
        for case in 0..400 {
            let mask_frac = (case % 80) as i8 - 40;
            let kind = case / 80;
            let mut logits = [0i16; 576];
            for l in logits.iter_mut() {
                let v = (next() >> 48) as i16;
                *l = match kind {
                    0 => v,
                    1 => if v & 1 == 0 { i16::MIN } else { i16::MAX },
                    2 => v >> 10,
                    3 => v >> 4,
                    _ => if v & 3 == 0 { i16::MIN } else { v >> 12 },
                };
            }
            let mut flow = [0i16; 9];
            let mut u = [0i16; 9];
            for (f, uu) in flow.iter_mut().zip(&mut u) {
                let v = next();
                (*f, *uu) = if kind == 1 { (if v & 1 == 0 { i16::MIN } else { i16::MAX }, i16::MAX) } else { ((v >> 48) as i16, (v >> 32) as i16) };
            }
            let (y, x) = (case % 3, (case / 3) % 3);
            let (mut d, mut uo) = ([0i16; 64], [0i16; 64]);
            upsample_pixel(&logits, mask_frac, &flow, Some(&u), 3, 3, y, x, &mut d, Some(&mut uo), 8);
            for sub in 0..64 {
                let l = |k: usize| logits[k * 64 + sub] as i64;
                let max = (0..9).map(l).max().unwrap();
                let mut e = [0i64; 9];
                for (k, ek) in e.iter_mut().enumerate() {
                    *ek = lut::exp_q11(shift_round(l(k) - max, 11 - mask_frac as i32).clamp(-32768, 0) as i32) as i64;
                }
                let s: i64 = e.iter().sum();
                let (mut fd, mut fu) = (0i64, 0i64);
                for (k, ek) in e.iter().enumerate() {
                    let (ny, nx) = ((y + k / 3) as isize - 1, (x + k % 3) as isize - 1);
                    if (0..3).contains(&ny) && (0..3).contains(&nx) {
                        let i = ny as usize * 3 + nx as usize;
                        fd += ek * flow[i] as i64;
                        fu += ek * u[i] as i64;
                    }
                }
                assert_eq!(d[sub], sat_i16(-div_round(fd, s)), "case {case} sub {sub}");
                assert_eq!(uo[sub], sat_i16(div_round(fu, s)), "case {case} sub {sub}");
            }
        }
    }
}
