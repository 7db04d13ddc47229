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
//! a tile's 16 blocks go into the output transform while they are in cache. The input transform
//! runs per tile of [`NR`] positions, straight into the products' panels (runs of positions on
//! one row of tiles, loops the compiler vectorises): no `16 x cin x tiles` matrix is stored and
//! read back from scattered rows. Rounding differs from the direct sum (the
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
    /// The phase-split padded input, reused from call to call
    /// ([`release_scratch`] frees it).
    static SCRATCH: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Frees this thread's scratch.
pub fn release_scratch() {
    SCRATCH.with_borrow_mut(|s| *s = Vec::new());
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
    SCRATCH.with_borrow_mut(|padded| {
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
        // V = B^T d B of tiles p0 .. p0 + n (n <= NR) for every channel, as product16's panels
        // (`panel[(xi cin + c) NR + q]`, V[xi][c] of tile p0 + q): the tile's patches are read
        // from the padded planes (4 rows of the even and odd columns) run by run of tiles on one
        // row of tiles.
        let fill = |p0: usize, n: usize, panel: &mut [f32]| {
            let mut q = 0;
            while q < n {
                let (ty, tx0) = ((p0 + q) / tw, (p0 + q) % tw);
                let run = (n - q).min(tw - tx0);
                for c in 0..cin {
                    let src = &padded[c * span..][..span];
                    // d B for the 4 patch rows: t[r][j][x], x < run
                    let mut t = [[[0.0f32; NR]; 4]; 4];
                    for (r, tr) in t.iter_mut().enumerate() {
                        let row = &src[(2 * ty + r) * 2 * half..][..2 * half];
                        let (e, o) = row.split_at(half);
                        let (e, o) = (&e[tx0..tx0 + run + 1], &o[tx0..tx0 + run + 1]);
                        let [t0, t1, t2, t3] = tr;
                        for x in 0..run {
                            let (d0, d1, d2, d3) = (e[x], o[x], e[x + 1], o[x + 1]);
                            t0[x] = d0 - d2;
                            t1[x] = d1 + d2;
                            t2[x] = d2 - d1;
                            t3[x] = d1 - d3;
                        }
                    }
                    // B^T (d B): V[i][j] from rows r = 0..4 of column j
                    #[allow(clippy::needless_range_loop)] // `j` picks a column of all four rows
                    for j in 0..4 {
                        let (u0, u1, u2, u3) = (&t[0][j], &t[1][j], &t[2][j], &t[3][j]);
                        let at = |i: usize| ((i * 4 + j) * cin + c) * NR + q;
                        for (x, v) in panel[at(0)..at(0) + run].iter_mut().enumerate() {
                            *v = u0[x] - u2[x];
                        }
                        for (x, v) in panel[at(1)..at(1) + run].iter_mut().enumerate() {
                            *v = u1[x] + u2[x];
                        }
                        for (x, v) in panel[at(2)..at(2) + run].iter_mut().enumerate() {
                            *v = u2[x] - u1[x];
                        }
                        for (x, v) in panel[at(3)..at(3) + run].iter_mut().enumerate() {
                            *v = u1[x] - u3[x];
                        }
                    }
                }
                q += run;
            }
        };
        // M[xi] (cout x tiles) = U[xi] V[xi], 16 products tile by tile; each tile's 16 blocks go
        // straight into Y = A^T M A and the epilogue, then to the output.
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
        product16(&w.u, tiles, &fill, &store);
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
