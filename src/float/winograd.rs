//! Winograd F(2x2, 3x3) for the float engine's stride-1 3x3 convolutions: each 2x2 block of
//! outputs from 16 products per input channel instead of 36 (2.25 times fewer multiply-adds).
//!
//! With `g` a 3x3 kernel, `d` a 4x4 input patch (padded coordinates `2ty .. 2ty + 4`,
//! `2tx .. 2tx + 4`) and `Y` the 2x2 outputs at `(2ty, 2tx)`:
//! `U = G g G^T`, `V = B^T d B`, `M = sum_c U(c) (.) V(c)`, `Y = A^T M A`, with
//!
//! ```text
//! G = [1 0 0; 1/2 1/2 1/2; 1/2 -1/2 1/2; 0 0 1]    B^T = [1 0 -1 0; 0 1 1 0; 0 -1 1 0; 0 1 0 -1]
//! A^T = [1 1 1 0; 0 1 -1 -1]
//! ```
//!
//! The sum over channels is 16 matrix products (one per position of the 4x4 transform,
//! [`super::gemm::product16`], `U` packed when the model is built), computed tile by tile so that
//! a tile's 16 blocks go into the output transform while they are in cache; the input transform
//! runs on whole rows of tiles (loops the compiler vectorises). Rounding differs from the direct sum (the
//! transforms add and subtract before and after it): the parity tests' tolerance covers it.
//! Every value is computed by one task in one order, so the results are the same bits for any
//! thread count.

use super::gemm::{Epilogue, Lhs, MR, NR, Packed, product16};
use super::par;
use super::tensor::Tensor;
use muir::kernels::pool;

/// A 3x3 layer's weights transformed, `U = G g G^T`: 16 packed `cout x cin` matrices.
#[derive(Clone, Debug)]
pub struct Weights {
    u: Vec<Packed>,
    cin: usize,
    cout: usize,
}

impl Weights {
    /// From `w` (`cout x (cin 3 3)`, row-major).
    pub fn new(w: &[f32], cout: usize, cin: usize) -> Self {
        assert_eq!(w.len(), cout * cin * 9, "3x3 weights");
        const G: [[f64; 3]; 4] = [[1.0, 0.0, 0.0], [0.5, 0.5, 0.5], [0.5, -0.5, 0.5], [0.0, 0.0, 1.0]];
        let mut u = vec![vec![0.0f32; cout * cin]; 16];
        for o in 0..cout {
            for c in 0..cin {
                let g = &w[(o * cin + c) * 9..][..9];
                // G g (4x3), then (G g) G^T (4x4), in f64, rounded once.
                let mut gg = [[0.0f64; 3]; 4];
                for (i, row) in gg.iter_mut().enumerate() {
                    for (j, v) in row.iter_mut().enumerate() {
                        *v = (0..3).map(|k| G[i][k] * g[k * 3 + j] as f64).sum();
                    }
                }
                for i in 0..4 {
                    for j in 0..4 {
                        let v: f64 = (0..3).map(|k| gg[i][k] * G[j][k]).sum();
                        u[i * 4 + j][o * cin + c] = v as f32;
                    }
                }
            }
        }
        let u = u.iter().map(|m| Packed::new(Lhs { data: m, row: cin, col: 1 }, cout, cin)).collect();
        Self { u, cin, cout }
    }

    /// Output channels.
    pub fn cout(&self) -> usize {
        self.cout
    }
}

std::thread_local! {
    /// Phase-split padded input and transformed input, reused from call to call
    /// ([`release_scratch`] frees them).
    static SCRATCH: std::cell::RefCell<[Vec<f32>; 2]> = const { std::cell::RefCell::new([Vec::new(), Vec::new()]) };
}

/// Frees this thread's scratch.
pub fn release_scratch() {
    SCRATCH.with_borrow_mut(|s| *s = [Vec::new(), Vec::new()]);
}

/// The 3x3, stride-1, padding-1 convolution of the channel concatenation of `parts` with `w`,
/// `epi` applied to every output.
pub fn conv(parts: &[&Tensor], w: &Weights, epi: &Epilogue<'_>) -> Tensor {
    let (h, wd) = (parts[0].h, parts[0].w);
    assert!(parts.iter().all(|t| t.h == h && t.w == wd), "conv input parts of different sizes");
    let chans: Vec<&[f32]> = parts.iter().flat_map(|t| (0..t.c).map(move |c| t.channel(c))).collect();
    assert_eq!(chans.len(), w.cin, "conv input channels");
    let (cin, cout) = (w.cin, w.cout);
    // Tiles of 2x2 outputs; padded rows 0 .. 2 th + 2, each stored as its even and its odd
    // columns (tw + 1 each), so that every patch column is a contiguous run over the tiles.
    let (th, tw) = (h.div_ceil(2), wd.div_ceil(2));
    let (rows, half) = (2 * th + 2, tw + 1);
    let span = rows * 2 * half;
    let tiles = th * tw;
    let mut out = Tensor::zeros(cout, h, wd);
    SCRATCH.with_borrow_mut(|s| {
        let [padded, v] = s;
        let padded = pool::scratch(padded, cin * span);
        par::chunks(padded, span, &|at, chunk| {
            for (i, dst) in chunk.chunks_mut(span).enumerate() {
                let src = chans[at / span + i];
                let (top, rest) = dst.split_at_mut(2 * half);
                top.fill(0.0);
                let (body, bottom) = rest.split_at_mut(h * 2 * half);
                bottom.fill(0.0);
                for (y, row) in body.chunks_exact_mut(2 * half).enumerate() {
                    let (even, odd) = row.split_at_mut(half);
                    // padded column x + 1: odd columns hold x even, even columns x odd
                    let srow = &src[y * wd..][..wd];
                    even.fill(0.0);
                    odd.fill(0.0);
                    let pairs = srow.chunks_exact(2);
                    let last = pairs.remainder();
                    for ((o, e), p) in odd.iter_mut().zip(&mut even[1..]).zip(pairs) {
                        *o = p[0];
                        *e = p[1];
                    }
                    if let [v] = last {
                        odd[wd / 2] = *v;
                    }
                }
            }
        });
        let padded = &*padded;
        // V (16 x cin x tiles): V[xi][c][ty tw + tx].
        let v = pool::scratch(v, 16 * cin * tiles);
        let vp = pool::Shared(v.as_mut_ptr());
        par::each(cin, cin * tiles * 16, &|c| {
            let vp = &vp;
            let src = &padded[c * span..][..span];
            let mut t = vec![0.0f32; 16 * tw];
            for ty in 0..th {
                // d B for the 4 patch rows: t[r][j][tx]
                for r in 0..4 {
                    let row = &src[(2 * ty + r) * 2 * half..][..2 * half];
                    let (e, o) = row.split_at(half);
                    let (t0, rest) = t[r * 4 * tw..][..4 * tw].split_at_mut(tw);
                    let (t1, rest) = rest.split_at_mut(tw);
                    let (t2, t3) = rest.split_at_mut(tw);
                    for tx in 0..tw {
                        let (d0, d1, d2, d3) = (e[tx], o[tx], e[tx + 1], o[tx + 1]);
                        t0[tx] = d0 - d2;
                        t1[tx] = d1 + d2;
                        t2[tx] = d2 - d1;
                        t3[tx] = d1 - d3;
                    }
                }
                // B^T (d B): V[i][j] from rows r = 0..4 of column j
                for j in 0..4 {
                    let col = |r: usize| &t[(r * 4 + j) * tw..][..tw];
                    let (u0, u1, u2, u3) = (col(0), col(1), col(2), col(3));
                    // SAFETY: V[xi][c][ty tw ..][..tw] for this task's c only, inside `v`.
                    let dst = |i: usize| unsafe { vp.slice(((i * 4 + j) * cin + c) * tiles + ty * tw, tw) };
                    let (v0, v1, v2, v3) = (dst(0), dst(1), dst(2), dst(3));
                    for tx in 0..tw {
                        v0[tx] = u0[tx] - u2[tx];
                        v1[tx] = u1[tx] + u2[tx];
                        v2[tx] = u2[tx] - u1[tx];
                        v3[tx] = u1[tx] - u3[tx];
                    }
                }
            }
        });
        let v = &*v;
        // M[xi] (cout x tiles) = U[xi] V[xi], 16 products tile by tile; each tile's 16 blocks go
        // straight into Y = A^T M A and the epilogue, then to the output.
        let rows: Vec<Vec<*const f32>> = (0..16).map(|xi| (0..cin).map(|c| v[(xi * cin + c) * tiles..].as_ptr()).collect()).collect();
        let outp = pool::Shared(out.data.as_mut_ptr());
        let store = |o0: usize, valid: usize, p0: usize, n: usize, sums: &[f32]| {
            let outp = &outp;
            let mut y = [[0.0f32; NR]; 4];
            for o in 0..valid {
                let ms: [&[f32]; 16] = core::array::from_fn(|xi| &sums[(xi * MR + o) * NR..][..n]);
                // a[j] = M0j + M1j + M2j, b[j] = M1j - M2j - M3j (A^T on the rows), then the same
                // on the columns: y0 = a0 + a1 + a2, y1 = a1 - a2 - a3, y2 = b0 + b1 + b2,
                // y3 = b1 - b2 - b3.
                for q in 0..n {
                    let a = |j: usize| ms[j][q] + ms[4 + j][q] + ms[8 + j][q];
                    let b = |j: usize| ms[4 + j][q] - ms[8 + j][q] - ms[12 + j][q];
                    let (a0, a1, a2, a3) = (a(0), a(1), a(2), a(3));
                    let (b0, b1, b2, b3) = (b(0), b(1), b(2), b(3));
                    y[0][q] = a0 + a1 + a2;
                    y[1][q] = a1 - a2 - a3;
                    y[2][q] = b0 + b1 + b2;
                    y[3][q] = b1 - b2 - b3;
                }
                for yr in y.iter_mut() {
                    epi.apply_row(o0 + o, &mut yr[..n]);
                }
                let plane = (o0 + o) * h * wd;
                for q in 0..n {
                    let (ty, tx) = ((p0 + q) / tw, (p0 + q) % tw);
                    for (r, yr) in y.iter().enumerate() {
                        let (oy, ox) = (2 * ty + r / 2, 2 * tx + r % 2);
                        if oy < h && ox < wd {
                            // SAFETY: output (o0 + o, oy, ox) belongs to tile p0 + q of this
                            // block, which no other task has.
                            unsafe { *outp.0.add(plane + oy * wd + ox) = yr[q] };
                        }
                    }
                }
            }
        };
        // SAFETY: row c of product xi is V[xi][c] (`tiles` values of `v`).
        unsafe { product16(&w.u, &rows, tiles, &store) };
    });
    out
}

#[cfg(test)]
mod tests {
    use super::super::ops::conv2d;
    use super::super::weights::FloatConv;
    use super::*;
    use muir::model::layers::{ConvShape, Norm};

    #[test]
    fn matches_the_direct_convolution() {
        let mut seed = 7u32;
        let mut rnd = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        for &(cin, cout, h, w) in &[(1, 1, 1, 1), (3, 5, 4, 4), (8, 16, 7, 9), (19, 11, 10, 13)] {
            let x = Tensor::from_vec(cin, h, w, (0..cin * h * w).map(|_| rnd()).collect());
            let weight: Vec<f32> = (0..cout * cin * 9).map(|_| rnd()).collect();
            let bias: Vec<f32> = (0..cout).map(|_| rnd()).collect();
            let shape = ConvShape { cin, cout, k: 3, stride: 1, norm: Norm::None };
            let layer = FloatConv { shape, weight: weight.clone(), bias: bias.clone(), bn: None };
            let want = conv2d(&x, &layer);
            let got = conv(&[&x], &Weights::new(&weight, cout, cin), &Epilogue { bias: Some(&bias), ..Default::default() });
            assert_eq!((got.c, got.h, got.w), (want.c, want.h, want.w));
            for (g, r) in got.data.iter().zip(&want.data) {
                assert!((g - r).abs() < 1e-5, "{cin}x{cout} {h}x{w}: {g} vs {r}");
            }
        }
    }
}
