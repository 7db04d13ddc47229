//! The float engine's matrix product, `out[o][p] = epilogue(sum_k w[o][k] * rows[k][p])`, on
//! 512-bit vectors where the CPU has AVX-512 F (checked at run time), else portable loops.
//!
//! The right-hand matrix is given as one pointer per row (`rows[k]`, each valid for `len`
//! values), not as a dense matrix: a convolution points its rows into its zero-padded input
//! (`ops::conv2d`: row `(c, ky, kx)` is the padded plane of channel `c` moved by `(ky, kx)`), so
//! there is no im2col matrix. Only the [`NR`] positions of the tile being computed are copied,
//! every row's side by side (a panel of `kk x NR`), when several blocks of output rows read them:
//! hundreds of scattered rows are more streams than the hardware prefetchers follow (on a
//! Sapphire-Rapids-class Xeon the tiles waited on those loads; KITTI float frame 4.8-5.0 ->
//! 3.7 s). The weights are packed into blocks
//! of [`MR`] output rows, `k`-major: once per model for a layer ([`Packed`]), per call otherwise
//! ([`product`]; `cout x kk` values, small beside the product).
//!
//! A tile is [`MR`] output rows by [`NR`] positions; its sums stay in registers for the whole `k`
//! loop (one fused multiply-add per `k` after the other, in `k` order) and get the epilogue
//! (bias, batch norm, scale, ReLU) before they are stored. Tiles are split into tasks over the
//! kernel pool (`muir::kernels::pool`); which thread computes a tile does not change its sums, so
//! the results are the same bits for any thread count.

use super::weights::BatchNorm;
use muir::kernels::pool;

/// Output rows per tile.
pub const MR: usize = 8;
/// 16-lane vectors per tile row.
const V: usize = 3;
/// Positions per tile.
pub const NR: usize = 16 * V;

/// What is applied to a sum before it is stored, in this order: `+ bias[o]`, the batch norm
/// `((v - mean) * inv_std) * weight + bias` (the operations of the scalar code it replaces),
/// `* scale`, `max(v, 0)`.
#[derive(Clone, Copy, Default)]
pub struct Epilogue<'a> {
    /// Added per output row.
    pub bias: Option<&'a [f32]>,
    /// Batch norm with stored statistics.
    pub bn: Option<&'a BatchNorm>,
    /// Multiplies the sum (`None`: 1).
    pub scale: Option<f32>,
    /// ReLU last.
    pub relu: bool,
}

impl Epilogue<'_> {
    /// The epilogue of output row `o` on the sum `v`.
    pub fn apply(&self, o: usize, v: f32) -> f32 {
        let mut v = v;
        if let Some(b) = self.bias {
            v += b[o];
        }
        if let Some(bn) = self.bn {
            v = (v - bn.mean[o]) * bn.inv_std[o] * bn.weight[o] + bn.bias[o];
        }
        if let Some(s) = self.scale {
            v *= s;
        }
        if self.relu { v.max(0.0) } else { v }
    }

    /// [`Epilogue::apply`] on every value of `vs` (output row `o`), each step a loop of its own.
    pub fn apply_row(&self, o: usize, vs: &mut [f32]) {
        if let Some(b) = self.bias {
            let b = b[o];
            vs.iter_mut().for_each(|v| *v += b);
        }
        if let Some(bn) = self.bn {
            let (mean, inv, g, b) = (bn.mean[o], bn.inv_std[o], bn.weight[o], bn.bias[o]);
            vs.iter_mut().for_each(|v| *v = (*v - mean) * inv * g + b);
        }
        if let Some(s) = self.scale {
            vs.iter_mut().for_each(|v| *v *= s);
        }
        if self.relu {
            vs.iter_mut().for_each(|v| *v = v.max(0.0));
        }
    }
}

/// The left-hand matrix: element `(o, k)` at `data[o * row + k * col]`.
#[derive(Clone, Copy)]
pub struct Lhs<'a> {
    /// Values.
    pub data: &'a [f32],
    /// Stride between output rows.
    pub row: usize,
    /// Stride between `k`.
    pub col: usize,
}

std::thread_local! {
    /// The packed left-hand matrix, reused from call to call ([`release_scratch`] frees it).
    static PACKED: std::cell::RefCell<Vec<f32>> = const { std::cell::RefCell::new(Vec::new()) };
}

/// Frees this thread's packing scratch.
pub fn release_scratch() {
    PACKED.with_borrow_mut(|b| *b = Vec::new());
    PANEL.with_borrow_mut(|p| *p = (Vec::new(), Vec::new()));
}

/// A left-hand matrix in the tiles' layout: blocks of [`MR`] output rows, `k`-major, the
/// rows past `cout` zero. A model packs its layers once ([`super::FloatModel::new`]).
#[derive(Clone, Debug, Default)]
pub struct Packed {
    data: Vec<f32>,
    cout: usize,
    kk: usize,
}

impl Packed {
    /// `w` (`cout x kk`) packed.
    pub fn new(w: Lhs<'_>, cout: usize, kk: usize) -> Self {
        let mut data = Vec::new();
        pack(w, cout, kk, &mut data);
        Self { data, cout, kk }
    }

    /// Output rows.
    pub fn cout(&self) -> usize {
        self.cout
    }

    /// Products per sum.
    pub fn kk(&self) -> usize {
        self.kk
    }
}

fn pack(w: Lhs<'_>, cout: usize, kk: usize, buf: &mut Vec<f32>) {
    assert!(cout == 0 || kk == 0 || (cout - 1) * w.row + (kk - 1) * w.col < w.data.len(), "product weights size");
    let blocks = cout.div_ceil(MR);
    let packed = pool::scratch(buf, blocks * kk * MR);
    for b in 0..blocks {
        let dst = &mut packed[b * kk * MR..][..kk * MR];
        for o in 0..MR {
            let oo = b * MR + o;
            if oo < cout {
                for k in 0..kk {
                    dst[k * MR + o] = w.data[oo * w.row + k * w.col];
                }
            } else {
                for k in 0..kk {
                    dst[k * MR + o] = 0.0;
                }
            }
        }
    }
}

/// `out[o * pitch + p] = epi(sum_k w(o, k) * rows[k][p])` for `o < cout`, `p < len`.
///
/// # Safety
/// Every `rows[k]` is valid for reading `len` values, and none of them overlaps `out`.
pub unsafe fn product(w: Lhs<'_>, cout: usize, rows: &[*const f32], len: usize, epi: &Epilogue<'_>, out: &mut [f32], pitch: usize) {
    PACKED.with_borrow_mut(|buf| {
        pack(w, cout, rows.len(), buf);
        let blocks = cout.div_ceil(MR);
        // SAFETY: the caller's guarantee.
        unsafe { product_blocks(&buf[..blocks * rows.len() * MR], cout, rows, len, epi, out, pitch) };
    });
}

/// [`product`] with a left-hand matrix packed beforehand (`w.kk() == rows.len()`).
///
/// # Safety
/// As [`product`].
pub unsafe fn product_packed(w: &Packed, rows: &[*const f32], len: usize, epi: &Epilogue<'_>, out: &mut [f32], pitch: usize) {
    assert_eq!(w.kk, rows.len(), "product depth");
    // SAFETY: the caller's guarantee.
    unsafe { product_blocks(&w.data, w.cout, rows, len, epi, out, pitch) };
}

/// # Safety
/// As [`product`]; `packed` holds `cout.div_ceil(MR) * rows.len() * MR` values.
unsafe fn product_blocks(packed: &[f32], cout: usize, rows: &[*const f32], len: usize, epi: &Epilogue<'_>, out: &mut [f32], pitch: usize) {
    let kk = rows.len();
    assert!(pitch >= len && (cout == 0 || out.len() >= (cout - 1) * pitch + len), "product output size");
    if cout == 0 || len == 0 {
        return;
    }
    if kk == 0 {
        for o in 0..cout {
            out[o * pitch..][..len].fill(epi.apply(o, 0.0));
        }
        return;
    }
    let blocks = cout.div_ceil(MR);
    assert!(packed.len() >= blocks * kk * MR, "packed weights size");
    let tiles = len.div_ceil(NR);
    // Tasks: runs of tiles (all blocks each) or, with few tiles, tiles times groups of blocks.
    let want = if pool::threads() > 1 { 4 * pool::threads() } else { 1 };
    let (per_task, groups) = if tiles >= want { (tiles.div_ceil(want), 1) } else { (1, (want / tiles).clamp(1, blocks)) };
    let group = blocks.div_ceil(groups);
    let chunks = tiles.div_ceil(per_task);
    let outp = pool::Shared(out.as_mut_ptr());
    let rowsp = pool::Shared(rows.as_ptr() as *mut *const f32);
    let simd = has_avx512();
    pool::run(chunks * groups, &|task| {
        let (chunk, g) = (task / groups, task % groups);
        let (rows, outp) = (rowsp, outp);
        // SAFETY: `rows` outlives `run`; tasks only read it.
        let rows = unsafe { core::slice::from_raw_parts(rows.0 as *const *const f32, kk) };
        let (b0, b1) = (g * group, ((g + 1) * group).min(blocks));
        PANEL.with_borrow_mut(|(panel, ptrs)| {
            for t in chunk * per_task..((chunk + 1) * per_task).min(tiles) {
                let p0 = t * NR;
                let n = (len - p0).min(NR);
                // Several blocks: the tile's rows read from one packed panel (`pack_panel`).
                let (tile_rows, q0): (&[*const f32], usize) = if b1 > b0 + 1 {
                    let dst = pool::scratch(panel, kk * NR);
                    ptrs.clear();
                    // SAFETY: rows[k][p0 .. p0 + n] is valid (the caller's guarantee).
                    unsafe { pack_panel(rows, p0, n, simd, dst, ptrs) };
                    (ptrs.as_slice(), 0)
                } else {
                    (rows, p0)
                };
                for b in b0..b1 {
                    let o0 = b * MR;
                    let valid = (cout - o0).min(MR);
                    let wb = &packed[b * kk * MR..][..kk * MR];
                    // SAFETY: the tile reads tile_rows[k][q0 .. q0 + n] (the panel's, or the
                    // rows' valid by the caller's guarantee) and writes out[(o0 + o) * pitch + p0
                    // ..][..n] for o < valid, inside `out` (asserted above) and written by this
                    // task only (tiles and blocks are split between tasks without overlap).
                    unsafe { tile(simd, wb, tile_rows, q0, n, outp.0.add(o0 * pitch + p0), pitch, valid, o0, epi) };
                }
            }
        });
    });
}

/// Copies `n <= NR` values of every row from `p0` on into `dst` (`rows.len()` slots of
/// [`NR`]) and appends a pointer to each slot to `ptrs`: the tile's rows side by side, which
/// several blocks of output rows then read in order instead of from `rows.len()` scattered
/// places each (the same values, so the same sums).
///
/// # Safety
/// Every `rows[k][p0 .. p0 + n]` is valid for reading; `dst` holds `rows.len() NR` values;
/// `simd` only with AVX-512 F.
unsafe fn pack_panel(rows: &[*const f32], p0: usize, n: usize, simd: bool, dst: &mut [f32], ptrs: &mut Vec<*const f32>) {
    for (d, r) in dst.chunks_exact_mut(NR).zip(rows) {
        // SAFETY: the contract; `d` holds NR >= n values. (Three vector moves, not a call of
        // `memcpy` per row.)
        unsafe {
            #[cfg(target_arch = "x86_64")]
            if simd {
                avx512::copy_tile_row(r.add(p0), d.as_mut_ptr(), n);
                ptrs.push(d.as_ptr());
                continue;
            }
            let _ = simd;
            core::ptr::copy_nonoverlapping(r.add(p0), d.as_mut_ptr(), n);
        }
        ptrs.push(d.as_ptr());
    }
}

std::thread_local! {
    /// A tile's rows copied side by side, and pointers to them ([`pack_panel`]).
    #[allow(clippy::type_complexity)]
    static PANEL: std::cell::RefCell<(Vec<f32>, Vec<*const f32>)> = const { std::cell::RefCell::new((Vec::new(), Vec::new())) };
}

/// One tile, on 512-bit vectors if `simd`.
///
/// # Safety
/// As `portable_tile`; `simd` only where AVX-512 F is present.
#[allow(clippy::too_many_arguments)]
unsafe fn tile(simd: bool, w: &[f32], rows: &[*const f32], p0: usize, n: usize, dst: *mut f32, pitch: usize, valid: usize, o0: usize, epi: &Epilogue<'_>) {
    // SAFETY: the caller's guarantee.
    unsafe {
        #[cfg(target_arch = "x86_64")]
        if simd {
            if n == NR {
                avx512::tile::<true>(w, rows, p0, n, dst, pitch, valid, o0, epi);
            } else {
                avx512::tile::<false>(w, rows, p0, n, dst, pitch, valid, o0, epi);
            }
            return;
        }
        let _ = simd;
        portable_tile(w, rows, p0, n, dst, pitch, valid, o0, epi);
    }
}

/// Sixteen products of the same shape side by side (Winograd's, `super::winograd`): for every
/// block of [`MR`] output rows and tile of [`NR`] positions, `sums[(i * MR + o) * NR + q] =
/// sum_k w[i](o0 + o, k) V[i][k][p0 + q]` for `i < 16`, then `f(o0, valid, p0, n, &sums)` (`valid`
/// rows from `o0`, `n` positions from `p0`; the rest of `sums` is stale). The right-hand sides
/// are made per tile by `fill(p0, n, panel)`: `panel[(i * kk + k) * NR + q] = V[i][k][p0 + q]`
/// for `q < n` (16 panels of `kk x NR`), so that no `16 x kk x len` matrix is ever stored and the
/// tiles read their rows in order from one place. Tasks over the pool as in [`product`] (with
/// few tiles, tasks splitting a tile's blocks each fill its panels); `f` must write only what
/// belongs to its rows and positions.
#[allow(clippy::type_complexity)]
pub fn product16(w: &[Packed], len: usize, fill: &(dyn Fn(usize, usize, &mut [f32]) + Sync), f: &(dyn Fn(usize, usize, usize, usize, &[f32]) + Sync)) {
    assert!(w.len() == 16, "16 products");
    let (cout, kk) = (w[0].cout, w[0].kk);
    assert!(w.iter().all(|w| w.cout == cout && w.kk == kk), "16 products of one shape");
    if cout == 0 || len == 0 || kk == 0 {
        assert!(kk > 0 || cout == 0 || len == 0, "product16 without rows");
        return;
    }
    let blocks = cout.div_ceil(MR);
    let tiles = len.div_ceil(NR);
    let want = if pool::threads() > 1 { 4 * pool::threads() } else { 1 };
    let (per_task, groups) = if tiles >= want { (tiles.div_ceil(want), 1) } else { (1, (want / tiles).clamp(1, blocks)) };
    let group = blocks.div_ceil(groups);
    let chunks = tiles.div_ceil(per_task);
    let simd = has_avx512();
    pool::run(chunks * groups, &|task| {
        let (chunk, g) = (task / groups, task % groups);
        let mut sums = vec![0.0f32; 16 * MR * NR];
        let (b0, b1) = (g * group, ((g + 1) * group).min(blocks));
        PANEL.with_borrow_mut(|(panel, ptrs)| {
            for t in chunk * per_task..((chunk + 1) * per_task).min(tiles) {
                let p0 = t * NR;
                let n = (len - p0).min(NR);
                let panel = pool::scratch(panel, 16 * kk * NR);
                fill(p0, n, panel);
                ptrs.clear();
                ptrs.extend(panel.chunks_exact(NR).map(|r| r.as_ptr()));
                for b in b0..b1 {
                    let o0 = b * MR;
                    let valid = (cout - o0).min(MR);
                    for (i, (wi, ri)) in w.iter().zip(ptrs.chunks_exact(kk)).enumerate() {
                        let wb = &wi.data[b * kk * MR..][..kk * MR];
                        // SAFETY: reads the panel's rows ri[k][0 .. n] (`kk` rows of NR >= n
                        // values); writes sums[i MR NR + o NR ..][..n] for o < valid, inside this
                        // task's `sums`.
                        unsafe { tile(simd, wb, ri, 0, n, sums.as_mut_ptr().add(i * MR * NR), NR, valid, o0, &Epilogue::default()) };
                    }
                    f(o0, valid, p0, n, &sums);
                }
            }
        });
    });
}

/// Whether the 512-bit tile runs here.
fn has_avx512() -> bool {
    #[cfg(target_arch = "x86_64")]
    {
        use std::sync::OnceLock;
        static ON: OnceLock<bool> = OnceLock::new();
        *ON.get_or_init(|| std::env::var("MUIR_FLOAT_SIMD").map_or(true, |v| v != "0") && std::arch::is_x86_feature_detected!("avx512f"))
    }
    #[cfg(not(target_arch = "x86_64"))]
    false
}

/// One tile with plain loops (same order of operations, without fused multiply-adds).
///
/// # Safety
/// As [`product`]'s tile: `rows[k] + p0` readable for `n` values, `dst + o * pitch` writable for
/// `n` values, `o < valid`.
#[allow(clippy::too_many_arguments)]
unsafe fn portable_tile(w: &[f32], rows: &[*const f32], p0: usize, n: usize, dst: *mut f32, pitch: usize, valid: usize, o0: usize, epi: &Epilogue<'_>) {
    let mut acc = [[0.0f32; NR]; MR];
    let mut b = [0.0f32; NR];
    for (k, r) in rows.iter().enumerate() {
        // SAFETY: the caller's guarantee.
        b[..n].copy_from_slice(unsafe { core::slice::from_raw_parts(r.add(p0), n) });
        let wk = &w[k * MR..][..MR];
        for (a, wo) in acc.iter_mut().zip(wk) {
            for (s, x) in a.iter_mut().zip(&b) {
                *s += wo * x;
            }
        }
    }
    for (o, a) in acc.iter().enumerate().take(valid) {
        // SAFETY: the caller's guarantee.
        let d = unsafe { core::slice::from_raw_parts_mut(dst.add(o * pitch), n) };
        for (d, s) in d.iter_mut().zip(a) {
            *d = epi.apply(o0 + o, *s);
        }
    }
}

#[cfg(target_arch = "x86_64")]
mod avx512 {
    use super::{Epilogue, MR, V};
    use core::arch::x86_64::*;

    /// One tile on 512-bit vectors; `FULL`: `n == NR` (no masks).
    ///
    /// # Safety
    /// AVX-512 F present; otherwise as `portable_tile` (masked loads and stores touch only the
    /// first `n` positions).
    /// Copies `n <= NR` values from `src` to `dst` (a tile row into the panel).
    ///
    /// # Safety
    /// AVX-512 F present; `src` readable and `dst` writable for `n` values.
    #[target_feature(enable = "avx512f")]
    pub unsafe fn copy_tile_row(src: *const f32, dst: *mut f32, n: usize) {
        for v in 0..V {
            let left = n.saturating_sub(16 * v).min(16);
            let m = ((1u32 << left) - 1) as u16;
            // SAFETY: masked to the first `n` values (the contract).
            unsafe { _mm512_mask_storeu_ps(dst.add(16 * v), m, _mm512_maskz_loadu_ps(m, src.add(16 * v))) };
        }
    }

    #[allow(clippy::too_many_arguments)]
    #[target_feature(enable = "avx512f")]
    pub unsafe fn tile<const FULL: bool>(
        w: &[f32],
        rows: &[*const f32],
        p0: usize,
        n: usize,
        dst: *mut f32,
        pitch: usize,
        valid: usize,
        o0: usize,
        epi: &Epilogue<'_>,
    ) {
        let mut masks = [0xFFFFu16; V];
        if !FULL {
            for (v, m) in masks.iter_mut().enumerate() {
                let left = n.saturating_sub(16 * v).min(16);
                *m = ((1u32 << left) - 1) as u16;
            }
        }
        // The first k sets the sums (a product rounded once, as a multiply-add onto zero would),
        // so that they are not zeroed in memory first; `product` never calls with no rows.
        let Some((first, rest)) = rows.split_first() else { return };
        let mut acc = [[_mm512_setzero_ps(); V]; MR];
        let mut b = [_mm512_setzero_ps(); V];
        let mut wp = w.as_ptr();
        // SAFETY: the caller's guarantee (masked loads read only the first n positions).
        unsafe {
            let r = first.add(p0);
            for v in 0..V {
                b[v] = if FULL { _mm512_loadu_ps(r.add(16 * v)) } else { _mm512_maskz_loadu_ps(masks[v], r.add(16 * v)) };
            }
            for (o, a) in acc.iter_mut().enumerate() {
                let x = _mm512_set1_ps(*wp.add(o));
                for v in 0..V {
                    a[v] = _mm512_mul_ps(x, b[v]);
                }
            }
            wp = wp.add(MR);
        }
        for r in rest {
            // SAFETY: as above.
            unsafe {
                let r = r.add(p0);
                for v in 0..V {
                    b[v] = if FULL { _mm512_loadu_ps(r.add(16 * v)) } else { _mm512_maskz_loadu_ps(masks[v], r.add(16 * v)) };
                }
                for (o, a) in acc.iter_mut().enumerate() {
                    let x = _mm512_set1_ps(*wp.add(o));
                    for v in 0..V {
                        a[v] = _mm512_fmadd_ps(x, b[v], a[v]);
                    }
                }
                wp = wp.add(MR);
            }
        }
        for (o, a) in acc.iter().enumerate().take(valid) {
            let oo = o0 + o;
            for (v, s) in a.iter().enumerate() {
                let mut x = *s;
                if let Some(b) = epi.bias {
                    x = _mm512_add_ps(x, _mm512_set1_ps(b[oo]));
                }
                if let Some(bn) = epi.bn {
                    x = _mm512_sub_ps(x, _mm512_set1_ps(bn.mean[oo]));
                    x = _mm512_mul_ps(x, _mm512_set1_ps(bn.inv_std[oo]));
                    x = _mm512_mul_ps(x, _mm512_set1_ps(bn.weight[oo]));
                    x = _mm512_add_ps(x, _mm512_set1_ps(bn.bias[oo]));
                }
                if let Some(sc) = epi.scale {
                    x = _mm512_mul_ps(x, _mm512_set1_ps(sc));
                }
                if epi.relu {
                    x = _mm512_max_ps(x, _mm512_setzero_ps());
                }
                // SAFETY: the caller's guarantee.
                unsafe {
                    let d = dst.add(o * pitch + 16 * v);
                    if FULL {
                        _mm512_storeu_ps(d, x);
                    } else {
                        _mm512_mask_storeu_ps(d, masks[v], x);
                    }
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn reference(w: &[f32], cout: usize, kk: usize, b: &[f32], len: usize, epi: &Epilogue<'_>) -> Vec<f32> {
        let mut out = vec![0.0f32; cout * len];
        for o in 0..cout {
            for p in 0..len {
                let mut s = 0.0f64;
                for k in 0..kk {
                    s += w[o * kk + k] as f64 * b[k * len + p] as f64;
                }
                out[o * len + p] = epi.apply(o, s as f32);
            }
        }
        out
    }

    #[test]
    fn product_matches_a_plain_sum_for_ragged_sizes_and_threads() {
        let mut seed = 1u32;
        let mut rnd = || {
            seed = seed.wrapping_mul(1_664_525).wrapping_add(1_013_904_223);
            (seed >> 8) as f32 / (1u32 << 24) as f32 - 0.5
        };
        for &(cout, kk, len) in &[(1, 1, 1), (3, 5, 17), (8, 9, 48), (13, 27, 100), (17, 64, 433), (2, 300, 49)] {
            let w: Vec<f32> = (0..cout * kk).map(|_| rnd()).collect();
            let b: Vec<f32> = (0..kk * len).map(|_| rnd()).collect();
            let bias: Vec<f32> = (0..cout).map(|_| rnd()).collect();
            let epi = Epilogue { bias: Some(&bias), scale: Some(0.5), relu: true, ..Default::default() };
            let rows: Vec<*const f32> = (0..kk).map(|k| b[k * len..].as_ptr()).collect();
            let want = reference(&w, cout, kk, &b, len, &epi);
            let mut first: Option<Vec<f32>> = None;
            for threads in [1, 2, 3] {
                pool::set_threads(threads);
                let mut out = vec![f32::NAN; cout * len];
                // SAFETY: every row is readable for len values.
                unsafe { product(Lhs { data: &w, row: kk, col: 1 }, cout, &rows, len, &epi, &mut out, len) };
                for (g, r) in out.iter().zip(&want) {
                    assert!((g - r).abs() <= 1e-5 * (1.0 + r.abs()), "{cout}x{kk}x{len}: {g} vs {r}");
                }
                match &first {
                    None => first = Some(out),
                    Some(f) => assert!(f.iter().zip(&out).all(|(a, b)| a.to_bits() == b.to_bits()), "{threads} threads"),
                }
            }
            pool::set_threads(1);
            // Several blocks read the tile's rows from a packed panel, one block from the rows
            // themselves: each block's rows alone (one block, no panel) are the same bits.
            let full = first.unwrap_or_default();
            for o0 in (0..cout).step_by(MR) {
                let m = (cout - o0).min(MR);
                let mut out = vec![f32::NAN; m * len];
                let bias_b = &bias[o0..o0 + m];
                let epi_b = Epilogue { bias: Some(bias_b), ..epi };
                // SAFETY: every row is readable for len values.
                unsafe { product(Lhs { data: &w[o0 * kk..], row: kk, col: 1 }, m, &rows, len, &epi_b, &mut out, len) };
                assert!(out.iter().zip(&full[o0 * len..(o0 + m) * len]).all(|(a, b)| a.to_bits() == b.to_bits()), "{cout}x{kk}x{len}: block {o0} alone");
            }
        }
    }
}

#[cfg(test)]
mod speed {
    use super::*;

    /// Throughput of the product on convolution-like shapes (padded-plane rows, 3x3):
    /// `cargo test --release --lib float::gemm::speed -- --ignored --nocapture`.
    #[test]
    #[ignore]
    fn product_speed() {
        for &(cin, cout, h, w) in &[(64usize, 64usize, 144usize, 192usize), (96, 96, 72, 96), (384, 128, 36, 48), (128, 128, 18, 24), (256, 2, 36, 48)] {
            let (hp, wp) = (h + 2, w + 2);
            let x: Vec<f32> = (0..cin * hp * wp + 2 * wp + 8).map(|i| ((i * 7919) % 1000) as f32 / 1000.0 - 0.5).collect();
            let kk = cin * 9;
            let wts: Vec<f32> = (0..cout * kk).map(|i| ((i * 104729) % 1000) as f32 / 1000.0 - 0.5).collect();
            let rows: Vec<*const f32> = (0..cin).flat_map(|c| (0..9).map(move |k| (c, k))).map(|(c, k)| x[c * hp * wp + (k / 3) * wp + k % 3..].as_ptr()).collect();
            let len = (h - 1) * wp + w;
            let packed = Packed::new(Lhs { data: &wts, row: kk, col: 1 }, cout, kk);
            let mut out = vec![0.0f32; cout * len];
            let reps = ((4e9 / (2.0 * (cout * kk * len) as f64)) as usize).max(1);
            let mut best = f64::MAX;
            for _ in 0..3 {
                let t = std::time::Instant::now();
                for _ in 0..reps {
                    // SAFETY: rows lie in x with the slack above.
                    unsafe { product_packed(&packed, &rows, len, &Epilogue::default(), &mut out, len) };
                }
                best = best.min(t.elapsed().as_secs_f64() / reps as f64);
            }
            let gf = 2.0 * (cout * kk * h * w) as f64 / best / 1e9;
            eprintln!("cin {cin:4} cout {cout:4} {h}x{w}: {:.3} ms, {gf:.1} GF/s (useful)", best * 1e3);
        }
    }
}
