//! Float operators of the reference network: convolution, normalisation, pooling, resampling.
//!
//! Each one matches the PyTorch operator the twin uses (named in its doc). Convolution is a matrix
//! product ([`super::gemm::product`]) whose right-hand rows point into the zero-padded input, with
//! bias, batch norm and ReLU applied to the sums before they are stored.

use super::gemm::{Epilogue, Lhs, Packed, product, product_packed};
use super::tensor::Tensor;
use super::weights::FloatConv;
use muir::model::layers::ConvShape;

/// Output side of a `k`-kernel, stride-`s`, padding-`k/2` convolution.
pub fn conv_out(n: usize, k: usize, s: usize) -> usize {
    (n + 2 * (k / 2) - k) / s + 1
}

/// `nn.Conv2d(cin, cout, k, stride, padding=k//2)` followed by the layer's BatchNorm (stored
/// statistics) if it has one. InstanceNorm layers are normalised by the caller ([`instance_norm`]).
pub fn conv2d(x: &Tensor, conv: &FloatConv) -> Tensor {
    conv2d_cat(&[x], conv, false)
}

/// [`conv2d`] of the channel concatenation of `parts` (without building it), then ReLU if `relu`.
pub fn conv2d_cat(parts: &[&Tensor], conv: &FloatConv, relu: bool) -> Tensor {
    let epi = Epilogue { bias: Some(&conv.bias), bn: conv.bn.as_ref(), scale: None, relu };
    let kk = conv.shape.cin * conv.shape.k * conv.shape.k;
    conv_with(parts, &conv.shape, Weights::Plain(Lhs { data: &conv.weight, row: kk, col: 1 }), &epi)
}

/// A convolution's weights: as stored (`cout x (cin k k)`), or packed beforehand.
#[derive(Clone, Copy)]
pub enum Weights<'a> {
    /// Packed for this call.
    Plain(Lhs<'a>),
    /// Packed once.
    Packed(&'a Packed),
}

/// The convolution of the channel concatenation of `parts` (shape `shape`, `shape.cout` output
/// channels, or the packed matrix's rows) with `w`, `epi` applied to the sums.
pub fn conv_with(parts: &[&Tensor], shape: &ConvShape, w: Weights<'_>, epi: &Epilogue<'_>) -> Tensor {
    let s = shape;
    let (h, w_) = (parts[0].h, parts[0].w);
    assert!(parts.iter().all(|t| t.h == h && t.w == w_), "conv input parts of different sizes");
    assert_eq!(parts.iter().map(|t| t.c).sum::<usize>(), s.cin, "conv input channels");
    let (k, st, pad) = (s.k, s.stride, s.k / 2);
    let (ho, wo) = (conv_out(h, k, st), conv_out(w_, k, st));
    let kk = s.cin * k * k;
    let cout = match w {
        Weights::Plain(_) => s.cout,
        Weights::Packed(p) => p.cout(),
    };
    // SAFETY (both calls): the caller of `run` passes rows valid for `len` values, apart from `out`.
    let run = |rows: &[*const f32], len: usize, out: &mut [f32]| unsafe {
        match w {
            Weights::Plain(l) => product(l, cout, rows, len, epi, out, len),
            Weights::Packed(p) => product_packed(p, rows, len, epi, out, len),
        }
    };
    let mut out = Tensor::zeros(cout, ho, wo);
    if k == 1 && st == 1 {
        // The input planes themselves are the rows.
        let rows: Vec<*const f32> = parts.iter().flat_map(|t| (0..t.c).map(move |c| t.channel(c).as_ptr())).collect();
        // Each row is a whole channel (h * w values) of a part, distinct from `out`.
        run(&rows, ho * wo, &mut out.data);
        return out;
    }
    // The input, zero-padded by `pad` and split into `st * st` phases (phase (py, px) holds the
    // padded samples (st i + py, st j + px)): row (c, ky, kx) of the product is phase
    // (ky % st, kx % st) of channel c moved by (ky / st, kx / st), read at position
    // oy * wq + ox. Positions with ox >= wo are computed and dropped. With stride 1 a row's right
    // padding is the next row's left padding (row pitch w + pad, not w + 2 pad: fewer dropped
    // positions), and the plane has `pad` more zeros for the last row's.
    let (hp, wp) = (h + 2 * pad, w_ + 2 * pad);
    let (hq, wq) = if st == 1 { (hp, w_ + pad) } else { (hp.div_ceil(st), wp.div_ceil(st)) };
    let plane = hq * wq + if st == 1 { pad } else { 0 };
    let len = (ho - 1) * wq + wo;
    PADDED.with_borrow_mut(|bufs| {
        let (padded, outs) = &mut *bufs;
        // Slack past the last plane: the last rows' reads reach (k - 1) / st rows and columns
        // further than the plane's own positions.
        let need = s.cin * st * st * plane + (k / st + 1) * (wq + 1);
        let padded = muir::kernels::pool::scratch(padded, need);
        let chans: Vec<&[f32]> = parts.iter().flat_map(|t| (0..t.c).map(move |c| t.channel(c))).collect();
        let span = st * st * plane;
        padded[s.cin * span..].fill(0.0);
        // Channel c's phases fill padded[c span ..][..span]: one chunk each.
        super::par::chunks(&mut padded[..s.cin * span], span, &|at, chunk| {
            for (i, dst) in chunk.chunks_mut(span).enumerate() {
                dst.fill(0.0);
                let src = chans[at / span + i];
                for y in 0..h {
                    let (py, iy) = ((y + pad) % st, (y + pad) / st);
                    let srow = &src[y * w_..][..w_];
                    if st == 1 {
                        dst[iy * wq + pad..][..w_].copy_from_slice(srow);
                        continue;
                    }
                    for (x, v) in srow.iter().enumerate() {
                        let (px, ix) = ((x + pad) % st, (x + pad) / st);
                        dst[(py * st + px) * plane + iy * wq + ix] = *v;
                    }
                }
            }
        });
        let mut rows = Vec::with_capacity(kk);
        for c in 0..s.cin {
            for ky in 0..k {
                for kx in 0..k {
                    let at = (c * st * st + (ky % st) * st + kx % st) * plane + (ky / st) * wq + kx / st;
                    debug_assert!(at + len <= padded.len());
                    rows.push(padded[at..].as_ptr());
                }
            }
        }
        let outs = muir::kernels::pool::scratch(outs, cout * len);
        // Row (c, ky, kx) starts at `at` and is read for `len` values: at + len <= need (the
        // slack covers the reach of the last rows), and `outs` is another buffer.
        run(&rows, len, outs);
        let outs = &*outs;
        super::par::chunks(&mut out.data, ho * wo, &|at, chunk| {
            for (i, dst) in chunk.chunks_mut(ho * wo).enumerate() {
                let o = at / (ho * wo) + i;
                for (oy, d) in dst.chunks_mut(wo).enumerate() {
                    d.copy_from_slice(&outs[o * len + oy * wq..][..wo]);
                }
            }
        });
    });
    out
}

std::thread_local! {
    /// The padded input and the product's output before its padding columns are dropped,
    /// reused from call to call within a frame (a fresh allocation per convolution cost a page
    /// fault per page every time, docs/performance.md); [`release_scratch`] frees them.
    static PADDED: std::cell::RefCell<(Vec<f32>, Vec<f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// Frees this thread's convolution scratch (`FloatModel::predict` does at the end of a frame).
pub fn release_scratch() {
    PADDED.with_borrow_mut(|b| *b = (Vec::new(), Vec::new()));
    super::gemm::release_scratch();
    super::winograd::release_scratch();
}

/// `nn.InstanceNorm2d` without affine parameters: per channel, biased variance, eps 1e-5.
pub fn instance_norm(mut x: Tensor) -> Tensor {
    let n = x.plane() as f32;
    let p = x.plane();
    super::par::chunks(&mut x.data, p, &|_, chunk| {
        for ch in chunk.chunks_mut(p) {
            let mean = ch.iter().sum::<f32>() / n;
            let var = ch.iter().map(|v| (v - mean) * (v - mean)).sum::<f32>() / n;
            let inv = 1.0 / (var + 1e-5).sqrt();
            ch.iter_mut().for_each(|v| *v = (*v - mean) * inv);
        }
    });
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
    let outp = muir::kernels::pool::Shared(out.data.as_mut_ptr());
    // One task per row y: it writes output rows 8y .. 8y + 8 only.
    super::par::each(h, 64 * w * (9 + 9 * x.c), &|y| {
        let outp = &outp;
        let mut wts = [0.0f32; 9];
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
                        // SAFETY: element (c, 8y + dy, 8xx + dx) of `out`, written by row y's task only.
                        unsafe { *outp.0.add((c * 8 * h + 8 * y + dy) * 8 * w + 8 * xx + dx) = acc };
                    }
                }
            }
        }
    });
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

/// Row-wise softmax attention weights `a(i, j) = softmax_j(q_i . k_j / sqrt(c))`, returned
/// transposed: an N x N row-major matrix whose row `j` holds `a(0..N, j)` (N = h * w), the layout
/// [`aggregate`] reads.
pub fn attention_matrix(q: &Tensor, k: &Tensor) -> Vec<f32> {
    let n = q.plane();
    let scale = 1.0 / (q.c as f32).sqrt();
    // logits^T (n x n) = k^T (n x c) . q (c x n): left-hand (j, ch) = k(ch, j).
    let mut at = vec![0.0f32; n * n];
    let rows: Vec<*const f32> = (0..q.c).map(|c| q.channel(c).as_ptr()).collect();
    let epi = Epilogue { scale: Some(scale), ..Default::default() };
    // SAFETY: each row is a whole channel of q (n values), distinct from `at`.
    unsafe { product(Lhs { data: &k.data, row: 1, col: n }, n, &rows, n, &epi, &mut at, n) };
    // Softmax over j for every i: down the columns, in j order (the sums add in the order the
    // row-wise loop added them); one task per block of columns.
    const COLS: usize = 256;
    let atp = muir::kernels::pool::Shared(at.as_mut_ptr());
    super::par::each(n.div_ceil(COLS), n * n, &|b| {
        let atp = &atp;
        let (i0, i1) = (b * COLS, ((b + 1) * COLS).min(n));
        // SAFETY: columns i0 .. i1 of row j, written by this block's task only.
        let row = |j: usize| unsafe { atp.slice(j * n + i0, i1 - i0) };
        let mut m = vec![f32::NEG_INFINITY; i1 - i0];
        for j in 0..n {
            m.iter_mut().zip(row(j).iter()).for_each(|(m, v)| *m = m.max(*v));
        }
        let mut s = vec![0.0f32; i1 - i0];
        for j in 0..n {
            for ((v, m), s) in row(j).iter_mut().zip(&m).zip(s.iter_mut()) {
                *v = (*v - m).exp();
                *s += *v;
            }
        }
        for j in 0..n {
            row(j).iter_mut().zip(&s).for_each(|(v, s)| *v /= s);
        }
    });
    at
}

/// `out(c, i) = sum_j a(i, j) * v(c, j)`: aggregation of `v` (C x h x w) with the attention
/// [`attention_matrix`] returned (`a` transposed, N x N).
pub fn aggregate(at: &[f32], v: &Tensor) -> Tensor {
    let n = v.plane();
    assert_eq!(at.len(), n * n, "attention size");
    let mut out = Tensor::zeros(v.c, v.h, v.w);
    // out (c x n) = v (c x n) . a^T (n x n): right-hand row j is row j of `at`.
    let rows: Vec<*const f32> = at.chunks(n).map(|r| r.as_ptr()).collect();
    // SAFETY: each row is a row of `at` (n values), distinct from `out`.
    unsafe { product(Lhs { data: &v.data, row: n, col: 1 }, v.c, &rows, n, &Epilogue::default(), &mut out.data, n) };
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
