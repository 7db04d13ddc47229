//! Joint convex upsampling of disparity and uncertainty (RAFT's 8x upsampler).
//!
//! For each full-resolution pixel `(8y + dy, 8x + dx)` the 9 mask logits `l_k` (channel
//! `k*64 + dy*8 + dx`) give softmax weights `e_k = exp_q11(shift(l_k - max))`; the outputs are
//! `disparity = -div_round(sum e_k flow_k, S)` (Q8 flow at 1/8 is Q5 pixels at full resolution)
//! and `u = div_round(sum e_k u_k, S)`, with `S = sum e_k` and zero padding outside the grid.
#![deny(clippy::indexing_slicing)]

use crate::arith::{div_round, lut, sat_i16, shift_round};

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
    let mut nb_flow = [0i64; 9];
    let mut nb_u = [0i64; 9];
    for (k, (nf, nu)) in nb_flow.iter_mut().zip(&mut nb_u).enumerate() {
        let (ny, nx) = ((y + k / 3) as isize - 1, (x + k % 3) as isize - 1);
        if ny >= 0 && nx >= 0 && (ny as usize) < h && (nx as usize) < w {
            let i = ny as usize * w + nx as usize;
            *nf = flow.get(i).map_or(0, |v| *v as i64);
            *nu = u.and_then(|u| u.get(i)).map_or(0, |v| *v as i64);
        }
    }
    let to_q11 = 11 - mask_frac as i32;
    let mut u_out = u_out;
    for dy in 0..8 {
        for dx in 0..8 {
            let sub = dy * 8 + dx;
            // Logit `k` of sub-pixel `sub`: `logits[k * 64 + sub]` (always there: 576 of them).
            let logit = |k: usize| logits.get(k * 64 + sub).map_or(0, |v| *v as i64);
            let max = (0..9).map(logit).max().unwrap_or(0);
            let mut e = [0i64; 9];
            let mut s = 0i64;
            for (k, ek) in e.iter_mut().enumerate() {
                let d = shift_round(logit(k) - max, to_q11);
                *ek = lut::exp_q11(d.clamp(-32768, 0) as i32) as i64;
                s += *ek;
            }
            let fd: i64 = e.iter().zip(&nb_flow).map(|(a, b)| a * b).sum();
            if let Some(o) = disp_out.get_mut(dy * stride + dx) {
                *o = sat_i16(-div_round(fd, s));
            }
            if let Some(o) = u_out.as_deref_mut().and_then(|uo| uo.get_mut(dy * stride + dx)) {
                let fu: i64 = e.iter().zip(&nb_u).map(|(a, b)| a * b).sum();
                *o = sat_i16(div_round(fu, s));
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
}
