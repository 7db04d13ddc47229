//! [`super::conv_row`] on aarch64 NEON (host, Linux-class Cortex-A): a whole output row as
//! matrix products of 8 output pixels x 8 output channels in registers, instead of two pixels and
//! two channels per call.
//!
//! The activations of a tile of [`PIXELS`] output pixels are gathered once per tile, pixels along
//! the vector: with `sdot` (FEAT_DotProd, u8 and i8 activations) as groups of 4 i8 values of one
//! pixel per 32-bit lane (`[group][pixel][4]`, u8 as `x - 128` with `128 sum(w)` added back
//! after), else (i16 activations, and u8/i8 on a CPU without `sdot`) widened to i16, one value of
//! 8 pixels per vector (`[value][pixel]`). The weights are read where the blob has them
//! (`[c][part][ky][kx][c_in]`), one 16-byte (`sdot`) or 8-byte (`smlal`, widened to i16 with one
//! `sxtl`) vector of consecutive values per output channel, and used lane by lane ("by element"
//! forms): `sdot acc.4s, x.16b, w.4b[g]` adds group `g` of the weight vector times each pixel's
//! group into 4 pixels' lanes, `smlal acc.4s, x.4h, w.h[j]` value `j` times 4 pixels' values. A
//! step is 16 values (`sdot`: 4 groups, 2 activation vectors each) or 8 (`smlal`: 1 activation
//! vector each) for 8 channels (8 weight vectors) x 8 pixels (16 accumulators): 25 or 26 of the 32
//! vector registers, each weight loaded once for 8 pixels, each activation once for 8 channels,
//! and no re-layout of the weights at all. The last `< 16` (or `< 8`) values of a part take one
//! more step with their weights copied into a zero-padded vector (the activations there are
//! whatever the buffer holds: times zero). A block of fewer than 8 channels (the last one) runs 4,
//! 2 and 1 channel forms of the same loop.
//!
//! One call is one job of numbered tasks on the kernel pool ([`super::super::pool`]) when the
//! layer is large enough: a task is one tile of 8 pixels (its gather, every channel block, every
//! part, the epilogue and the write-out of its own `8 cout` outputs), so the thread count changes
//! no result.
//!
//! Exactness: neither instruction saturates (`sdot` and `smlal` wrap, and no sum here reaches
//! the wrap). An `sdot` lane adds 4 products of `|w x| <= 128 * 128 = 2^14` per instruction, 4
//! instructions a step (`2^18`), and a chunk at most [`DOT_CHUNK`] steps: `2^12 * 2^18 = 2^30 <
//! 2^31`. An `smlal` lane adds `|w x| <= 128 * 2^15 = 2^22` per instruction, 8 a step (`2^25`), at
//! most [`MLAL_CHUNK`] steps a chunk: `63 * 2^25 < 2^31` (u8 and i8 widened: `|w x| < 2^15`).
//! Each chunk's i32 lanes are then added into i64 sums, so every part sum is the exact integer
//! (the `x - 128` form: `sum w (x - 128) + 128 sum w`, exact in i64; padding columns hold
//! `0 - 128`, so they add `w (0 - 128) + 128 w = 0`, as in the portable path). The epilogue is
//! [`super::finish_with`] of the saturating sum, part by part in order, of the [`requantize`]d
//! part sums: the portable path's formula, so the same integers for every input (the tests compare
//! them).
//!
//! Layers whose tables, rows or buffers are shorter than their parameters say are left to the
//! portable path (the caller's fallback), which defines what happens then.
#![deny(clippy::indexing_slicing)]

use core::arch::aarch64::*;
use core::arch::asm;
use core::cell::RefCell;

use super::super::aarch64::{Level, level};
use super::super::pool::{self, Shared, scratch};
use super::super::{Elem, OutRow, set_at};
use super::{ConvParams, PartRows, column, finish_with, mult_at, whole_row};
use crate::arith::requantize;
use crate::model::graph::MAX_PARTS;

/// Output pixels per tile (and task): two vectors of four i32 lanes.
const PIXELS: usize = 8;
/// Output channels per register block.
const BLOCK_C: usize = 8;
/// Activation values per `sdot` step (four groups of four, one 16-byte weight vector).
const DOT_STEP: usize = 16;
/// Activation values per `smlal` step (one 8-byte weight vector widened to eight i16).
const MLAL_STEP: usize = 8;
/// Most `sdot` steps a chunk sums in i32 lanes (see the module doc).
const DOT_CHUNK: usize = 4096;
/// Most `smlal` steps a chunk sums in i32 lanes (see the module doc).
const MLAL_CHUNK: usize = 63;
const _: () = assert!((DOT_CHUNK as u64) * 4 * 4 * (1 << 14) < 1 << 31);
const _: () = assert!((MLAL_CHUNK as u64) * (MLAL_STEP as u64) * (1 << 22) < 1 << 31);
/// Layers of fewer multiply-accumulates per row stay on the calling thread.
const PARALLEL_MACS: usize = 1 << 16;

/// Per-thread scratch, grown to the largest layer seen.
#[derive(Default)]
struct Scratch {
    /// A tile's activations, `sdot` layout.
    x8: Vec<i8>,
    /// A tile's activations, `smlal` layout.
    x16: Vec<i16>,
}

std::thread_local! {
    /// A task's tile (on the thread that runs it).
    static TILE: RefCell<Scratch> = RefCell::new(Scratch::default());
    /// `128 sum(w)` per (channel, part) for u8 activations on `sdot` (on the calling thread).
    static CORR: RefCell<Vec<i64>> = const { RefCell::new(Vec::new()) };
}

/// The two inner loops.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Kind {
    /// u8 (as `x - 128`) or i8 activations, `sdot`, groups of 4 values.
    Dot,
    /// Activations widened to i16, `smlal`.
    Mlal,
}

impl Kind {
    /// Values per step.
    fn step(self) -> usize {
        match self {
            Kind::Dot => DOT_STEP,
            Kind::Mlal => MLAL_STEP,
        }
    }
    /// Most steps per chunk.
    fn chunk(self) -> usize {
        match self {
            Kind::Dot => DOT_CHUNK,
            Kind::Mlal => MLAL_CHUNK,
        }
    }
}

/// [`super::conv_row`] on NEON (with `sdot` for 8-bit activations where the CPU has it) when the
/// layer's tables, rows and output are as long as its parameters say; `false` (nothing written)
/// otherwise, and under `MUIR_ARM_SIMD=0`.
pub fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>) -> bool {
    conv_row_at(level(), p, inputs, w_in, out)
}

/// [`conv_row`] at a given level (the tests run each one the CPU has).
fn conv_row_at<T: Elem>(level: Level, p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>) -> bool {
    let kind = match (level, T::BITS) {
        (Level::DotProd, 8) => Kind::Dot,
        (Level::DotProd | Level::Neon, 8 | 16) => Kind::Mlal,
        _ => return false,
    };
    let w_out = p.out_width(w_in);
    let whole = whole_row(p, inputs.len(), w_in, out.len())
        && p.parts.len() <= MAX_PARTS
        && inputs.iter().zip(p.parts).all(|(r, &ch)| r.rows.iter().take(p.k).flatten().all(|r| r.len() >= w_in * ch));
    if !whole {
        return false;
    }
    CORR.with_borrow_mut(|corr| run(p, inputs, w_in, w_out, kind, out, corr));
    true
}

/// One input part's place in a tile.
#[derive(Clone, Copy, Debug, Default)]
struct PartPlan {
    /// Channels, and values (`k k ch`).
    ch: usize,
    n: usize,
    /// Offset of the part's weights in a channel's row.
    off: usize,
    /// Offset of the part's activations in the tile buffer (`n` rounded up to whole steps, times
    /// [`PIXELS`]).
    xoff: usize,
}

/// Runs `f(0) .. f(tasks - 1)` on the pool when the layer is large enough, else here.
fn par(big: bool, tasks: usize, f: &(dyn Fn(usize) + Sync)) {
    if big {
        pool::run(tasks, f);
    } else {
        (0..tasks).for_each(f);
    }
}

/// [`conv_row`]'s work: the parts' plan, the `x - 128` corrections, then the tiles of 8 pixels as
/// tasks. The layer passed [`conv_row_at`]'s checks.
#[allow(clippy::too_many_arguments)]
fn run<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, w_out: usize, kind: Kind, out: &mut OutRow<'_>, corr: &mut Vec<i64>) {
    let (cout, kl, np, k) = (p.cout, p.patch_len(), p.parts.len(), p.k);
    let flip = kind == Kind::Dot && T::STORAGE.unsigned;
    let mut plans = [PartPlan::default(); MAX_PARTS];
    let (mut off, mut xlen) = (0, 0);
    for (plan, &ch) in plans.iter_mut().zip(p.parts) {
        let n = k * k * ch;
        *plan = PartPlan { ch, n, off, xoff: xlen };
        off += n;
        xlen += n.next_multiple_of(kind.step()) * PIXELS;
    }
    let plans = plans.get(..np).unwrap_or_default();
    // u8 activations enter `sdot` as `x - 128`: `128 sum(w)` of each (channel, part) goes back.
    let corr = scratch(corr, if flip { cout * np } else { 0 });
    for (w, cr) in p.weights.chunks_exact(kl.max(1)).zip(corr.chunks_exact_mut(np.max(1))) {
        for (plan, v) in plans.iter().zip(cr) {
            let w = w.get(plan.off..plan.off + plan.n).unwrap_or_default();
            *v = 128 * w.iter().map(|w| *w as i32).sum::<i32>() as i64;
        }
    }
    let corr = &*corr;
    let big = w_out * cout * kl >= PARALLEL_MACS;
    macro_rules! tiles {
        ($o:ident, $variant:ident) => {{
            let op = Shared($o.as_mut_ptr());
            par(big, w_out.div_ceil(PIXELS), &|t| {
                let x0 = t * PIXELS;
                let nx = w_out.saturating_sub(x0).min(PIXELS);
                // SAFETY: pixels `x0 .. x0 + nx <= w_out` of the row (`w_out cout <= len`,
                // checked by `conv_row_at`), this task's only.
                let o = unsafe { op.slice(x0 * cout, nx * cout) };
                TILE.with_borrow_mut(|s| tile(p, inputs, w_in, plans, xlen, kind, flip, corr, x0, nx, &mut OutRow::$variant(o), s));
            });
        }};
    }
    match out {
        OutRow::I8(o) => tiles!(o, I8),
        OutRow::U8(o) => tiles!(o, U8),
        OutRow::I16(o) => tiles!(o, I16),
    }
}

/// One tile: output pixels `x0 .. x0 + nx` (`nx <= 8`) of every channel into `out` (`nx cout`
/// values, `[x][c]`): the tile's activations gathered (`xlen` values), then per block of 8
/// channels the parts' exact sums, their requantised contributions and the finished outputs.
#[allow(clippy::too_many_arguments)]
fn tile<T: Elem>(
    p: &ConvParams<'_>,
    inputs: &[PartRows<'_, T>],
    w_in: usize,
    plans: &[PartPlan],
    xlen: usize,
    kind: Kind,
    flip: bool,
    corr: &[i64],
    x0: usize,
    nx: usize,
    out: &mut OutRow<'_>,
    s: &mut Scratch,
) {
    let (cout, kl, np, step) = (p.cout, p.patch_len(), p.parts.len(), kind.step());
    // The activations: every part's region of `n` rounded up to whole steps, times 8 pixels.
    let (x8, x16): (&[i8], &[i16]) = match kind {
        Kind::Dot => {
            let xt = scratch(&mut s.x8, xlen);
            for (rows, plan) in inputs.iter().zip(plans) {
                gather_dot(p, rows, plan.ch, w_in, x0, nx, flip, xt.get_mut(plan.xoff..).unwrap_or_default());
            }
            (xt, &[])
        }
        Kind::Mlal => {
            let xt = scratch(&mut s.x16, xlen);
            for (rows, plan) in inputs.iter().zip(plans) {
                gather_mlal(p, rows, plan.ch, w_in, x0, nx, xt.get_mut(plan.xoff..).unwrap_or_default());
            }
            (&[], xt)
        }
    };
    let mut c0 = 0;
    while c0 < cout {
        let r = (cout - c0).min(BLOCK_C);
        // Sums of the parts' requantised contributions, `[c][pixel]`.
        let mut tot = [[0i64; PIXELS]; BLOCK_C];
        for (part, plan) in plans.iter().enumerate() {
            // The part's exact sums, `[c][pixel]`.
            let mut acc = [[0i64; PIXELS]; BLOCK_C];
            // Each channel's weights of this part, from the blob (`weights.len() >= cout kl`:
            // `conv_row_at`), and the `n % step` last ones zero-padded to a whole step.
            let mut wp = [core::ptr::null::<i8>(); BLOCK_C];
            let mut tail = [[0i8; DOT_STEP]; BLOCK_C];
            let (whole, rest) = (plan.n / step, plan.n % step);
            for (i, (wp, tail)) in wp.iter_mut().zip(tail.iter_mut()).enumerate().take(r) {
                let w = p.weights.get((c0 + i) * kl + plan.off..(c0 + i) * kl + plan.off + plan.n).unwrap_or_default();
                *wp = w.as_ptr();
                let last = w.get(whole * step..).unwrap_or_default();
                tail.iter_mut().zip(last).for_each(|(t, w)| *t = *w);
            }
            // Whole steps in chunks, then the tail step.
            let mut q = 0;
            while q < whole {
                let steps = (whole - q).min(kind.chunk());
                let w = wp.map(|w| w.wrapping_add(q * step));
                // SAFETY: `steps` whole steps from step `q` of each of the `r` channels' weights
                // (`whole step <= n` values from `wp`) and of the part's activations (its region
                // holds `n` rounded up to whole steps, times 8 pixels); at most one chunk.
                unsafe { block_dispatch(kind, r, x8, x16, plan.xoff + q * step * PIXELS, &w, steps, &mut acc) };
                q += steps;
            }
            if rest != 0 {
                let w = core::array::from_fn(|i| tail.get(i).map_or(core::ptr::null(), |t| t.as_ptr()));
                // SAFETY: one step: the zero-padded copies (16 values each) and the region's last
                // step of activations.
                unsafe { block_dispatch(kind, r, x8, x16, plan.xoff + whole * step * PIXELS, &w, 1, &mut acc) };
            }
            // The part's requantised contribution, as the portable path adds it.
            for (i, (acc, tot)) in acc.iter().zip(tot.iter_mut()).enumerate().take(r) {
                let c = c0 + i;
                let m = mult_at(p.mult.0.get(8 * (c * np + part)..).unwrap_or_default());
                let cr = if flip { corr.get(c * np + part).copied().unwrap_or_default() } else { 0 };
                for (a, t) in acc.iter().zip(tot.iter_mut()).take(nx) {
                    *t = t.saturating_add(requantize(*a + cr, m));
                }
            }
        }
        for (i, tot) in tot.iter().enumerate().take(r) {
            let c = c0 + i;
            let bias = p.bias.get(c);
            for (x, t) in tot.iter().enumerate().take(nx) {
                out.set(x * cout + c, finish_with(p.post, bias, *t));
            }
        }
        c0 += r;
    }
}

/// Gathers one part's activations of pixels `x0 .. x0 + nx` for `sdot` into `xt` (the part's
/// region): value `j` of pixel `x0 + px`'s patch (`[ky][kx][c]`) at `32 (j / 4) + 4 px + j % 4`,
/// as i8 (`x - 128` for u8, `flip`); padding columns and rows hold `0` (`-128` with `flip`).
/// Pixels past `nx` and values past the patch are left as they are (their weights or outputs are
/// never used).
#[allow(clippy::too_many_arguments)]
fn gather_dot<T: Elem>(p: &ConvParams<'_>, rows: &PartRows<'_, T>, ch: usize, w_in: usize, x0: usize, nx: usize, flip: bool, xt: &mut [i8]) {
    let (k, pad) = (p.k, (p.k / 2) as isize);
    let off = if flip { 128 } else { 0 };
    let zero = (-off) as i8;
    for px in 0..nx {
        let ox = x0 + px;
        let mut j = 0;
        for ky in 0..k {
            let row = rows.row(ky);
            for kx in 0..k {
                let src = column(row, (ox * p.stride + kx) as isize - pad, w_in, ch);
                let cv = |v: &T| (v.to_i32() - off) as i8;
                if ch.is_multiple_of(4) {
                    // Whole groups (`j` is a multiple of 4 too): group `j / 4 + g` is 32 bytes
                    // from `8 j + 32 g`, this pixel's 4 of them from `4 px`.
                    let dst = xt.get_mut(8 * j..8 * (j + ch)).unwrap_or_default().chunks_exact_mut(32);
                    let dst = dst.filter_map(|d| d.get_mut(4 * px..4 * px + 4));
                    match src {
                        Some(s) => dst.zip(s.chunks_exact(4)).for_each(|(d, s)| {
                            if let ([d0, d1, d2, d3], [s0, s1, s2, s3]) = (d, s) {
                                (*d0, *d1, *d2, *d3) = (cv(s0), cv(s1), cv(s2), cv(s3));
                            }
                        }),
                        None => dst.for_each(|d| d.fill(zero)),
                    }
                } else {
                    for e in j..j + ch {
                        let v = src.and_then(|s| s.get(e - j)).map_or(zero, cv);
                        set_at(xt, 32 * (e / 4) + 4 * px + e % 4, v);
                    }
                }
                j += ch;
            }
        }
    }
}

/// [`gather_dot`] for `smlal`: value `j` of pixel `x0 + px` at `8 j + px`, as i16; padding 0.
#[allow(clippy::too_many_arguments)]
fn gather_mlal<T: Elem>(p: &ConvParams<'_>, rows: &PartRows<'_, T>, ch: usize, w_in: usize, x0: usize, nx: usize, xt: &mut [i16]) {
    let (k, pad) = (p.k, (p.k / 2) as isize);
    for px in 0..nx {
        let ox = x0 + px;
        let mut j = 0;
        for ky in 0..k {
            let row = rows.row(ky);
            for kx in 0..k {
                let src = column(row, (ox * p.stride + kx) as isize - pad, w_in, ch);
                // Value `j + e` is `8 (j + e) + px`.
                let dst = xt.get_mut(PIXELS * j..PIXELS * (j + ch)).unwrap_or_default().chunks_exact_mut(PIXELS);
                match src {
                    Some(s) => dst.zip(s).for_each(|(d, s)| set_at(d, px, s.to_i32() as i16)),
                    None => dst.for_each(|d| set_at(d, px, 0)),
                }
                j += ch;
            }
        }
    }
}

/// [`dot_block`] or [`mlal_block`] for `r` channels (1 to [`BLOCK_C`]): the forms for 8, 4, 2 and
/// 1 channels in turn, from activation `xat` of `x8` or `x16`.
///
/// # Safety
/// As [`dot_block`] (`Kind::Dot`, the CPU has `dotprod`) or [`mlal_block`], for the first `r`
/// pointers of `w` and the activations from `xat`.
#[allow(clippy::too_many_arguments)]
unsafe fn block_dispatch(kind: Kind, r: usize, x8: &[i8], x16: &[i16], xat: usize, w: &[*const i8; BLOCK_C], steps: usize, acc: &mut [[i64; PIXELS]; BLOCK_C]) {
    let mut i = 0;
    while i < r {
        let n = match r - i {
            8.. => 8,
            4..=7 => 4,
            2 | 3 => 2,
            _ => 1,
        };
        let (w, acc) = (w.get(i..).unwrap_or_default(), acc.get_mut(i..).unwrap_or_default());
        // SAFETY: forwarded (`n <= r - i` pointers and sums from `i`).
        unsafe {
            match kind {
                Kind::Dot => {
                    let x = x8.as_ptr().wrapping_add(xat);
                    match n {
                        8 => dot_block::<8>(x, w, steps, acc),
                        4 => dot_block::<4>(x, w, steps, acc),
                        2 => dot_block::<2>(x, w, steps, acc),
                        _ => dot_block::<1>(x, w, steps, acc),
                    }
                }
                Kind::Mlal => {
                    let x = x16.as_ptr().wrapping_add(xat);
                    match n {
                        8 => mlal_block::<8>(x, w, steps, acc),
                        4 => mlal_block::<4>(x, w, steps, acc),
                        2 => mlal_block::<2>(x, w, steps, acc),
                        _ => mlal_block::<1>(x, w, steps, acc),
                    }
                }
            }
        }
        i += n;
    }
}

/// Adds the i32 lanes of `a` (`[c][pixel vector]`) into the i64 sums `acc` (`[c][pixel]`).
#[inline(always)]
fn flush<const R: usize>(a: &[[int32x4_t; 2]; R], acc: &mut [[i64; PIXELS]]) {
    for (a, s) in a.iter().zip(acc.iter_mut()) {
        for (v, s) in a.iter().zip(s.chunks_exact_mut(4)) {
            let mut l = [0i32; 4];
            // SAFETY: `l` holds 4 i32; NEON is part of the aarch64 baseline.
            unsafe { vst1q_s32(l.as_mut_ptr(), *v) };
            s.iter_mut().zip(l).for_each(|(s, l)| *s += l as i64);
        }
    }
}

/// Exact sums of `R` channels over 8 pixels by `sdot`, added into `acc[i][px]` (`i < R`):
/// `steps` steps of 16 values, step `q` of channel `i` being weights `w[i] + 16 q ..` (4 groups)
/// against activations `x + 128 q ..` (`[group][pixel][4]`, 4 groups of 32 bytes).
///
/// # Safety
/// The CPU has `dotprod`; `w` has at least `R` pointers, each to `16 steps` readable bytes; `x`
/// points at `128 steps` readable bytes; `acc` has at least `R` rows; `steps <=` [`DOT_CHUNK`].
#[target_feature(enable = "neon,dotprod")]
unsafe fn dot_block<const R: usize>(x: *const i8, w: &[*const i8], steps: usize, acc: &mut [[i64; PIXELS]]) {
    let mut wp = [core::ptr::null::<i8>(); R];
    wp.iter_mut().zip(w).for_each(|(d, s)| *d = *s);
    let mut a = [[vdupq_n_s32(0); 2]; R];
    let mut xp = x;
    // SAFETY: the function's contract: step `q < steps` reads `w[i] + 16 q .. + 16` and
    // `x + 128 q .. + 128`.
    unsafe {
        for _ in 0..steps {
            let mut wv = [vdupq_n_s8(0); R];
            for (v, p) in wv.iter_mut().zip(wp.iter_mut()) {
                *v = vld1q_s8(*p);
                *p = p.add(DOT_STEP);
            }
            // Group `g` of every channel's weight vector times pixels 0-3 and 4-7.
            macro_rules! group {
                ($g:literal) => {
                    let xs = [vld1q_s8(xp.add(32 * $g)), vld1q_s8(xp.add(32 * $g + 16))];
                    for (a, wv) in a.iter_mut().zip(wv) {
                        for (a, xv) in a.iter_mut().zip(xs) {
                            asm!(
                                ".arch_extension dotprod",
                                "sdot {a:v}.4s, {x:v}.16b, {w:v}.4b[{g}]",
                                a = inout(vreg) *a,
                                x = in(vreg) xv,
                                w = in(vreg) wv,
                                g = const $g,
                                options(pure, nomem, nostack, preserves_flags)
                            );
                        }
                    }
                };
            }
            group!(0);
            group!(1);
            group!(2);
            group!(3);
            xp = xp.add(PIXELS * DOT_STEP);
        }
    }
    flush(&a, acc);
}

/// Exact sums of `R` channels over 8 pixels by `smlal`, added into `acc[i][px]` (`i < R`):
/// `steps` steps of 8 values, step `q` of channel `i` being weights `w[i] + 8 q ..` (i8, widened)
/// against activations `x + 64 q ..` (`[value][pixel]`, i16).
///
/// # Safety
/// `w` has at least `R` pointers, each to `8 steps` readable bytes; `x` points at `64 steps`
/// readable i16; `acc` has at least `R` rows; `steps <=` [`MLAL_CHUNK`].
#[target_feature(enable = "neon")]
unsafe fn mlal_block<const R: usize>(x: *const i16, w: &[*const i8], steps: usize, acc: &mut [[i64; PIXELS]]) {
    let mut wp = [core::ptr::null::<i8>(); R];
    wp.iter_mut().zip(w).for_each(|(d, s)| *d = *s);
    let mut a = [[vdupq_n_s32(0); 2]; R];
    let mut xp = x;
    // SAFETY: the function's contract: step `q < steps` reads `w[i] + 8 q .. + 8` and
    // `x + 64 q .. + 64`.
    unsafe {
        for _ in 0..steps {
            let mut wv = [vdupq_n_s16(0); R];
            for (v, p) in wv.iter_mut().zip(wp.iter_mut()) {
                *v = vmovl_s8(vld1_s8(*p));
                *p = p.add(MLAL_STEP);
            }
            // Value `j` of every channel's weight vector times pixels 0-3 and 4-7.
            macro_rules! value {
                ($j:literal) => {
                    let xv = vld1q_s16(xp.add(PIXELS * $j));
                    let lo = vget_low_s16(xv);
                    for (a, wv) in a.iter_mut().zip(wv) {
                        let [a0, a1] = a;
                        *a0 = vmlal_laneq_s16::<$j>(*a0, lo, wv);
                        *a1 = vmlal_high_laneq_s16::<$j>(*a1, xv, wv);
                    }
                };
            }
            value!(0);
            value!(1);
            value!(2);
            value!(3);
            value!(4);
            value!(5);
            value!(6);
            value!(7);
            xp = xp.add(PIXELS * MLAL_STEP);
        }
    }
    flush(&a, acc);
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::super::aarch64::cpu_level;
    use super::super::super::testutil::Rng;
    use super::super::{BiasRef, MultRef, conv_plain, encode_bias, encode_mults};
    use super::*;
    use crate::arith::Multiplier;
    use crate::model::graph::PostOp;

    /// The levels this CPU runs: NEON always, `sdot` where it has it.
    fn levels() -> Vec<Level> {
        [Level::Neon, Level::DotProd].into_iter().filter(|l| *l <= cpu_level()).collect()
    }

    /// Weights, activations and tables of a test layer.
    #[derive(Clone, Copy, PartialEq)]
    enum Values {
        /// Random weights, multipliers with shifts 20 to 39, biases below `2^20`.
        Random,
        /// Every weight -128 (the largest products), random tables as above.
        Extreme,
        /// Random weights; multipliers with any shift (1 to 126, the 128-bit `requantize`) and
        /// biases up to `2^62` (saturating sums) on some channels.
        Wild,
        /// Weights -128 (even channels) or 127 (odd), multipliers `(2^31 - 1) / 2`, biases up to
        /// `2^62`: long parts' contributions beyond `2^62`, whose sum saturates.
        Huge,
    }

    /// The NEON row against the plain twin on one layer, at every level the CPU has, for each
    /// output type (its saturation) and 1 and 3 threads.
    fn check<T: Elem>(seed: u64, make: &dyn Fn(&mut Rng) -> T, k: usize, stride: usize, parts: &[usize], cout: usize, post: PostOp, w: usize, values: Values) {
        let mut r = Rng(seed);
        let h = 5;
        let kl = k * k * parts.iter().sum::<usize>();
        let wts: Vec<i8> = (0..cout * kl)
            .map(|i| match values {
                Values::Extreme => -128,
                Values::Huge => [-128, 127][i / kl % 2],
                _ => r.i8(),
            })
            .collect();
        let wild = |r: &mut Rng| values == Values::Huge || values == Values::Wild && r.next() % 2 == 0;
        let b: Vec<i64> = (0..cout).map(|_| if wild(&mut r) { (r.next() as i64) >> (1 + r.below(40)) } else { (r.next() as i64) >> 44 }).collect();
        let m: Vec<Multiplier> = (0..cout * parts.len())
            .map(|_| {
                if values == Values::Huge {
                    return Multiplier { m: i32::MAX, shift: 1 };
                }
                let shift = if wild(&mut r) { 1 + r.below(126) as u8 } else { 20 + r.below(20) as u8 };
                Multiplier { m: (1 << 30) + (r.below(1 << 30) as i32), shift }
            })
            .collect();
        let (bias, mult) = (encode_bias(&b), encode_mults(&m));
        let p = ConvParams { k, stride, parts, cout, weights: &wts, bias: BiasRef(&bias), mult: MultRef(&mult), post };
        let tensors: Vec<Vec<T>> = parts.iter().map(|&c| (0..h * w * c).map(|_| make(&mut r)).collect()).collect();
        let refs: Vec<&[T]> = tensors.iter().map(|t| t.as_slice()).collect();
        let (ho, wo) = ((h + 2 * (k / 2) - k) / stride + 1, p.out_width(w));
        let mut nonzero = vec![];
        macro_rules! each_type {
            ($t:ty, $variant:ident, $level:expr) => {{
                let len = ho * wo * cout;
                let (mut want, mut got) = (vec![<$t>::default(); len], vec![<$t>::default(); len]);
                conv_plain(&p, &refs, h, w, &mut OutRow::$variant(&mut want));
                for (oy, o) in got.chunks_exact_mut(wo * cout).enumerate() {
                    let rows: Vec<PartRows<T>> =
                        tensors.iter().zip(parts).map(|(t, &c)| PartRows::of_tensor(t, h, w * c, oy, k, stride)).collect();
                    assert!(conv_row_at($level, &p, &rows, w, &mut OutRow::$variant(o)), "path not taken");
                }
                let what = format!(
                    "{:?} k {k} s {stride} parts {parts:?} cout {cout} w {w} {post:?} {} in, {} out",
                    $level,
                    core::any::type_name::<T>(),
                    stringify!($t)
                );
                assert_eq!(want, got, "{what}");
                nonzero.push(want.iter().any(|v| *v != 0));
            }};
        }
        // One thread, then several (the tiles as tasks): the same integers.
        for level in levels() {
            for threads in [1, 3] {
                pool::set_threads(threads);
                each_type!(i16, I16, level);
                each_type!(i8, I8, level);
                each_type!(u8, U8, level);
            }
        }
        pool::set_threads(1);
        // (Saturated biases and large shifts may zero a whole wild layer.)
        assert!(values == Values::Wild || nonzero.iter().any(|n| *n), "all zero: seed {seed} k {k} s {stride} parts {parts:?} cout {cout} w {w} {post:?}");
    }

    #[test]
    fn levels_of_this_cpu() {
        // Under qemu-aarch64's default CPU both; with `-cpu cortex-a72` (no `dotprod`) NEON only.
        eprintln!("levels tested: {:?}", levels());
        assert!(levels().contains(&Level::Neon));
        // The portable level is no NEON kernel.
        let p = ConvParams { k: 1, stride: 1, parts: &[1], cout: 1, weights: &[1], bias: BiasRef(&[0; 8]), mult: MultRef(&[0; 8]), post: PostOp::None };
        let rows = [PartRows { rows: [Some(&[1u8][..]), None, None, None, None, None, None] }];
        assert!(!conv_row_at(Level::Portable, &p, &rows, 1, &mut OutRow::U8(&mut [0])));
        assert!(conv_row_at(Level::Neon, &p, &rows, 1, &mut OutRow::U8(&mut [0])));
    }

    #[test]
    fn matrix_product_matches_plain_twin() {
        let u8s = |r: &mut Rng| r.i8() as u8;
        let i8s = |r: &mut Rng| r.i8();
        let i16s = |r: &mut Rng| r.i16();
        let mut seed = 1;
        for post in [PostOp::None, PostOp::Relu, PostOp::Tanh, PostOp::Sigmoid] {
            for w in [1, 8, 9, 17, 33] {
                for (k, stride, parts, cout) in [
                    (3, 1, &[8, 1, 16][..], 5),
                    (3, 2, &[6][..], 9),
                    (1, 1, &[12][..], 17),
                    (7, 2, &[3][..], 4),
                    (7, 1, &[1][..], 3),
                    (3, 1, &[64, 4][..], 24),
                    (3, 2, &[8, 4][..], 7),
                    (1, 2, &[16][..], 5),
                    (5, 2, &[12, 2][..], 3),
                    (3, 1, &[2, 3, 1, 4, 5, 2][..], 11),
                ] {
                    seed += 1;
                    let values = if seed % 3 == 0 { Values::Wild } else { Values::Random };
                    check(seed, &u8s, k, stride, parts, cout, post, w, values);
                    check(seed, &i8s, k, stride, parts, cout, post, w, values);
                    check(seed, &i16s, k, stride, parts, cout, post, w, values);
                }
            }
        }
    }

    #[test]
    fn extremes_and_chunk_bounds() {
        // Every weight -128 against activations at their most negative (the largest products:
        // i16 2^22, i8 2^14, u8 0 -> -128 on `sdot`: 2^14) and largest, over parts of one, two
        // and several `smlal` chunks (3 3 64 = 576 = 63 + 9 steps; 1 1 520 = 65 steps, 63 + 2;
        // 3 3 128 = 144 steps) and their tails.
        for w in [7, 40] {
            check(7, &|_| i16::MIN, 3, 1, &[64], 8, PostOp::None, w, Values::Extreme);
            check(8, &|r: &mut Rng| if r.next() % 2 == 0 { i16::MIN } else { i16::MAX }, 3, 1, &[128, 2], 3, PostOp::None, w, Values::Extreme);
            check(9, &|_| -i16::MAX, 1, 1, &[520], 4, PostOp::None, w, Values::Extreme);
            check(10, &|_| i16::MIN, 1, 1, &[520], 9, PostOp::None, w, Values::Extreme);
            check(11, &|_| u8::MAX, 3, 1, &[128], 8, PostOp::None, w, Values::Extreme);
            check(12, &|_| 0u8, 3, 2, &[128, 7], 8, PostOp::None, w, Values::Extreme);
            check(13, &|_| i8::MIN, 3, 1, &[64], 11, PostOp::None, w, Values::Extreme);
            check(14, &|r: &mut Rng| if r.next() % 2 == 0 { i8::MIN } else { i8::MAX }, 3, 2, &[61], 2, PostOp::None, w, Values::Extreme);
            check(15, &|r: &mut Rng| [0u8, 255][r.below(2) as usize], 1, 1, &[33], 17, PostOp::Relu, w, Values::Wild);
        }
        // Three parts of `|sum| > 2^33` each: contributions near `2^63` whose sum saturates (the
        // parts added in order, saturating, as the portable path does).
        check(18, &|_| i16::MIN, 3, 1, &[256, 256, 256], 6, PostOp::None, 9, Values::Huge);
        check(19, &|r: &mut Rng| [i16::MIN, i16::MAX][r.below(2) as usize], 1, 1, &[2400, 2400, 2400], 4, PostOp::Relu, 5, Values::Huge);
        // One part longer than an `sdot` chunk (4096 steps of 16 values: 65536), twice over, and
        // a tail: the largest products throughout (`2^17 2^14 = 2^31` would wrap in one chunk).
        let n = 2 * 65536 + 3 * 16 + 5;
        check(16, &|_| i8::MIN, 1, 1, &[n], 3, PostOp::None, 2, Values::Extreme);
        check(17, &|_| 0u8, 1, 1, &[n], 2, PostOp::None, 3, Values::Extreme);
    }
}
