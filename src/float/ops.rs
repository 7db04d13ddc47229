//! Float operators of the reference network: convolution, normalisation, pooling, resampling.
//!
//! Each one matches the PyTorch operator the twin uses (named in its doc). Convolution is im2col +
//! sgemm (`matrixmultiply`), which keeps the reference fast enough for real images on the host.

use super::tensor::Tensor;
use super::weights::FloatConv;

/// Output side of a `k`-kernel, stride-`s`, padding-`k/2` convolution.
pub fn conv_out(n: usize, k: usize, s: usize) -> usize {
    (n + 2 * (k / 2) - k) / s + 1
}

/// `nn.Conv2d(cin, cout, k, stride, padding=k//2)` followed by the layer's BatchNorm (stored
/// statistics) if it has one. InstanceNorm layers are normalised by the caller ([`instance_norm`]).
pub fn conv2d(x: &Tensor, conv: &FloatConv) -> Tensor {
    let s = &conv.shape;
    assert_eq!(x.c, s.cin, "conv input channels");
    let (k, st, pad) = (s.k, s.stride, s.k / 2);
    let (ho, wo) = (conv_out(x.h, k, st), conv_out(x.w, k, st));
    let n = ho * wo;
    let kk = s.cin * k * k;
    COLS.with_borrow_mut(|buf| {
        let cols: &[f32] = if k == 1 && st == 1 {
            &x.data
        } else {
            let need = x.c * k * k * n;
            if buf.len() < need {
                buf.resize(need, 0.0);
            }
            let cols = &mut buf[..need];
            im2col(x, k, st, pad, ho, wo, cols);
            cols
        };
        gemm(conv, cols, ho, wo, kk, n)
    })
}

std::thread_local! {
    /// The im2col matrix, reused from call to call within a frame (a fresh allocation per
    /// convolution cost a page fault per page of it every time: Teddy's float frame 1.68 -> 1.36
    /// s, docs/performance.md); [`release_scratch`] frees it.
    static COLS: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Frees this thread's convolution scratch (`FloatModel::predict` does at the end of a frame).
pub fn release_scratch() {
    COLS.with_borrow_mut(|b| *b = Vec::new());
}

/// The convolution's matrix product over the im2col matrix `cols` (`kk x n`), bias and batch norm.
fn gemm(conv: &FloatConv, cols: &[f32], ho: usize, wo: usize, kk: usize, n: usize) -> Tensor {
    let s = &conv.shape;
    let mut out = Tensor::zeros(s.cout, ho, wo);
    for (o, ch) in out.data.chunks_mut(n).enumerate() {
        ch.fill(conv.bias[o]);
    }
    // SAFETY: a is cout x kk (row-major), b is kk x n, c is cout x n; all slices hold exactly those
    // many elements (checked by the shapes above and by the weight loader).
    unsafe {
        matrixmultiply::sgemm(
            s.cout,
            kk,
            n,
            1.0,
            conv.weight.as_ptr(),
            kk as isize,
            1,
            cols.as_ptr(),
            n as isize,
            1,
            1.0,
            out.data.as_mut_ptr(),
            n as isize,
            1,
        );
    }
    if let Some(bn) = &conv.bn {
        for (o, ch) in out.data.chunks_mut(n).enumerate() {
            let (mean, inv, g, b) = (bn.mean[o], bn.inv_std[o], bn.weight[o], bn.bias[o]);
            ch.iter_mut().for_each(|v| *v = (*v - mean) * inv * g + b);
        }
    }
    out
}

/// `cols` (`c k k x ho wo`, row `(c, ky, kx)`) = the input samples of every output pixel, zeros in
/// the padding. Stride 1 copies each row's valid run at once.
fn im2col(x: &Tensor, k: usize, st: usize, pad: usize, ho: usize, wo: usize, cols: &mut [f32]) {
    let n = ho * wo;
    cols.fill(0.0);
    for c in 0..x.c {
        let src = x.channel(c);
        for ky in 0..k {
            for kx in 0..k {
                let row = &mut cols[((c * k + ky) * k + kx) * n..][..n];
                for oy in 0..ho {
                    let iy = (oy * st + ky) as isize - pad as isize;
                    if iy < 0 || iy >= x.h as isize {
                        continue;
                    }
                    let srow = &src[iy as usize * x.w..][..x.w];
                    let drow = &mut row[oy * wo..][..wo];
                    if st == 1 {
                        // ix = ox + kx - pad in [0, w): ox in [pad - kx, w + pad - kx), within wo.
                        let lo = pad.saturating_sub(kx).min(wo);
                        let hi = (x.w + pad).saturating_sub(kx).min(wo).max(lo);
                        let s0 = lo + kx - pad;
                        drow[lo..hi].copy_from_slice(&srow[s0..s0 + (hi - lo)]);
                        continue;
                    }
                    for (ox, d) in drow.iter_mut().enumerate() {
                        let ix = (ox * st + kx) as isize - pad as isize;
                        if ix >= 0 && ix < x.w as isize {
                            *d = srow[ix as usize];
                        }
                    }
                }
            }
        }
    }
}

/// `nn.InstanceNorm2d` without affine parameters: per channel, biased variance, eps 1e-5.
pub fn instance_norm(mut x: Tensor) -> Tensor {
    let n = x.plane() as f32;
    let p = x.plane();
    for ch in x.data.chunks_mut(p) {
        let mean = ch.iter().sum::<f32>() / n;
        let var = ch.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
        let inv = 1.0 / (var + 1e-5).sqrt();
        ch.iter_mut().for_each(|v| *v = (*v - mean) * inv);
    }
    x
}

/// ReLU.
pub fn relu(x: Tensor) -> Tensor {
    x.map(|v| v.max(0.0))
}

/// Logistic sigmoid.
pub fn sigmoid(v: f32) -> f32 {
    1.0 / (1.0 + (-v).exp())
}

/// `F.avg_pool2d(x, 3, stride=2, padding=1)` (padding counted in the average).
pub fn pool2x(x: &Tensor) -> Tensor {
    let (ho, wo) = (conv_out(x.h, 3, 2), conv_out(x.w, 3, 2));
    let mut out = Tensor::zeros(x.c, ho, wo);
    for c in 0..x.c {
        for oy in 0..ho {
            for ox in 0..wo {
                let mut s = 0.0;
                for dy in 0..3 {
                    for dx in 0..3 {
                        let (iy, ix) = ((2 * oy + dy) as isize - 1, (2 * ox + dx) as isize - 1);
                        if iy >= 0 && ix >= 0 && (iy as usize) < x.h && (ix as usize) < x.w {
                            s += x[(c, iy as usize, ix as usize)];
                        }
                    }
                }
                out[(c, oy, ox)] = s / 9.0;
            }
        }
    }
    out
}

/// `F.interpolate(x, (h, w), mode="bilinear", align_corners=True)`.
pub fn interp(x: &Tensor, h: usize, w: usize) -> Tensor {
    let scale = |i: usize, o: usize| if o > 1 { (i - 1) as f32 / (o - 1) as f32 } else { 0.0 };
    let (sy, sx) = (scale(x.h, h), scale(x.w, w));
    let mut out = Tensor::zeros(x.c, h, w);
    for y in 0..h {
        let fy = y as f32 * sy;
        let y0 = (fy.floor() as usize).min(x.h - 1);
        let y1 = (y0 + 1).min(x.h - 1);
        let ay = fy - y0 as f32;
        for xx in 0..w {
            let fx = xx as f32 * sx;
            let x0 = (fx.floor() as usize).min(x.w - 1);
            let x1 = (x0 + 1).min(x.w - 1);
            let ax = fx - x0 as f32;
            for c in 0..x.c {
                let top = (1.0 - ax) * x[(c, y0, x0)] + ax * x[(c, y0, x1)];
                let bot = (1.0 - ax) * x[(c, y1, x0)] + ax * x[(c, y1, x1)];
                out[(c, y, xx)] = (1.0 - ay) * top + ay * bot;
            }
        }
    }
    out
}

/// RAFT convex upsampling by 8: `x` (D x h x w), `mask` (576 x h x w, channel `k*64 + dy*8 + dx`,
/// softmax over the 9 neighbours `k = ky*3 + kx`), zero padding. Returns D x 8h x 8w.
pub fn convex_upsample(x: &Tensor, mask: &Tensor) -> Tensor {
    let (h, w) = (x.h, x.w);
    assert!(mask.c == 576 && mask.h == h && mask.w == w);
    let mut out = Tensor::zeros(x.c, 8 * h, 8 * w);
    let mut wts = [0.0f32; 9];
    for y in 0..h {
        for xx in 0..w {
            for dy in 0..8 {
                for dx in 0..8 {
                    let mut m = f32::NEG_INFINITY;
                    for (k, wk) in wts.iter_mut().enumerate() {
                        *wk = mask[(k * 64 + dy * 8 + dx, y, xx)];
                        m = m.max(*wk);
                    }
                    let mut sum = 0.0;
                    for wk in wts.iter_mut() {
                        *wk = (*wk - m).exp();
                        sum += *wk;
                    }
                    for c in 0..x.c {
                        let mut acc = 0.0;
                        for (k, wk) in wts.iter().enumerate() {
                            let (ny, nx) = ((y + k / 3) as isize - 1, (xx + k % 3) as isize - 1);
                            if ny >= 0 && nx >= 0 && (ny as usize) < h && (nx as usize) < w {
                                acc += wk / sum * x[(c, ny as usize, nx as usize)];
                            }
                        }
                        out[(c, 8 * y + dy, 8 * xx + dx)] = acc;
                    }
                }
            }
        }
    }
    out
}

/// 2D rotary embedding (twin: `rope_2d`): channel pairs `(2i, 2i+1)`; the first half of the pairs
/// turns with the column, the second half with the row; pair `i` of a half by `pos * base^(-i/n)`.
pub fn rope_2d(mut x: Tensor, base: f32) -> Tensor {
    let pairs = x.c / 2;
    let n = pairs / 2;
    for p in 0..pairs {
        let (i, along_x) = if p < n { (p, true) } else { (p - n, false) };
        let freq = (base as f64).powf(-(i as f64) / n as f64);
        for y in 0..x.h {
            for xx in 0..x.w {
                let pos = if along_x { xx } else { y } as f64;
                let (s, c) = ((pos * freq).sin() as f32, (pos * freq).cos() as f32);
                let (a, b) = (x[(2 * p, y, xx)], x[(2 * p + 1, y, xx)]);
                x[(2 * p, y, xx)] = a * c - b * s;
                x[(2 * p + 1, y, xx)] = a * s + b * c;
            }
        }
    }
    x
}

/// Row-wise softmax attention weights `softmax_j(q_i . k_j / sqrt(c))`, as an N x N row-major
/// matrix (N = h * w).
pub fn attention_matrix(q: &Tensor, k: &Tensor) -> Vec<f32> {
    let n = q.plane();
    let scale = 1.0 / (q.c as f32).sqrt();
    // logits = q^T k: (n x c) . (c x n)
    let mut a = vec![0.0f32; n * n];
    // SAFETY: q.data is c x n (so q^T is n x c with row stride 1, column stride n), k.data is c x n,
    // a is n x n.
    unsafe {
        matrixmultiply::sgemm(
            n,
            q.c,
            n,
            scale,
            q.data.as_ptr(),
            1,
            n as isize,
            k.data.as_ptr(),
            n as isize,
            1,
            0.0,
            a.as_mut_ptr(),
            n as isize,
            1,
        );
    }
    for row in a.chunks_mut(n) {
        let m = row.iter().fold(f32::NEG_INFINITY, |m, v| m.max(*v));
        let mut s = 0.0;
        row.iter_mut().for_each(|v| {
            *v = (*v - m).exp();
            s += *v;
        });
        row.iter_mut().for_each(|v| *v /= s);
    }
    a
}

/// `out(c, i) = sum_j a(i, j) * v(c, j)`: aggregation of `v` (C x h x w) with attention `a` (N x N).
pub fn aggregate(a: &[f32], v: &Tensor) -> Tensor {
    let n = v.plane();
    let mut out = Tensor::zeros(v.c, v.h, v.w);
    // out (c x n) = v (c x n) . a^T (n x n)
    // SAFETY: sizes as documented; a^T is read with row stride 1, column stride n.
    unsafe {
        matrixmultiply::sgemm(
            v.c,
            n,
            n,
            1.0,
            v.data.as_ptr(),
            n as isize,
            1,
            a.as_ptr(),
            1,
            n as isize,
            0.0,
            out.data.as_mut_ptr(),
            n as isize,
            1,
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn pool_and_interp_sizes() {
        let x = Tensor::from_vec(1, 5, 7, (0..35).map(|v| v as f32).collect());
        let p = pool2x(&x);
        assert_eq!((p.h, p.w), (3, 4));
        // centre cell: mean of the 3x3 block around (2, 2)
        let want = [8.0f32, 9., 10., 15., 16., 17., 22., 23., 24.].iter().sum::<f32>() / 9.0;
        assert!((p[(0, 1, 1)] - want).abs() < 1e-5);
        let up = interp(&p, 5, 7);
        assert_eq!(up[(0, 0, 0)], p[(0, 0, 0)]);
        assert_eq!(up[(0, 4, 6)], p[(0, 2, 3)]);
    }

    #[test]
    fn convex_upsample_of_a_constant_is_constant_inside() {
        let x = Tensor::from_vec(1, 3, 3, vec![2.0; 9]);
        let m = Tensor::zeros(576, 3, 3);
        let up = convex_upsample(&x, &m);
        assert!((up[(0, 12, 12)] - 2.0).abs() < 1e-6);
        // border pixels average in zero padding
        assert!(up[(0, 0, 0)] < 2.0);
    }
}
