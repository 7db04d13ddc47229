//! Host forms (feature `std`) of the refinement's per-pixel 1x1 convolutions: a row's outputs by
//! one convolution call over the whole row (the same integers as one pixel at a time, and a
//! matrix product wide enough for the SIMD kernels), in this thread's scratch rather than the
//! plan's memory. The MGA passes then run the row's pixels as tasks on the kernel pool
//! ([`crate::kernels::pool`]), each with its thread's own scratch. The firmware keeps the
//! pixel-by-pixel loops in `refine`; the firmware tests compare both.
#![deny(clippy::indexing_slicing)]

use core::cell::RefCell;

use super::encoder::run_conv;
use crate::arith::Multiplier;
use crate::kernels::OutRow;
use crate::kernels::attention::{aggregate_query, query_stats, rope_pixel};
#[cfg(target_arch = "x86_64")]
use crate::kernels::attention::avx512::Prepared;
use crate::kernels::conv::{ConvParams, MAX_K, PartRows};
use crate::kernels::corr::{LookupParams, LookupScratch, lookup_with, window};
use crate::kernels::pool::{self, Shared, scratch};

/// Pixels per task.
const PIXELS: usize = 4;

/// Runs `f(pixels)` for the tasks' ranges of `PIXELS` pixels covering `0..n`, on the kernel pool.
fn per_pixels(n: usize, f: &(dyn Fn(core::ops::Range<usize>) + Sync)) {
    pool::run(n.div_ceil(PIXELS), &|t| f(t * PIXELS..((t + 1) * PIXELS).min(n)));
}

std::thread_local! {
    /// A row's queries and the conv's patch scratch (on the calling thread).
    static ROW: RefCell<(Vec<i16>, Vec<u8>)> = const { RefCell::new((Vec::new(), Vec::new())) };
    /// A row of upsampling-mask logits.
    static LOGITS: RefCell<Vec<i16>> = const { RefCell::new(Vec::new()) };
    /// Keys and values laid out for the batched attention (on the calling thread).
    /// The keys laid out for the batched statistics, `true` while they are this frame's.
    #[cfg(target_arch = "x86_64")]
    static KEYS_T: RefCell<(Prepared, bool)> = const { RefCell::new((Prepared::new(), false)) };
    /// The frame's softmax weights, kept by the statistics pass for every iteration's
    /// aggregation (on the calling thread).
    #[cfg(target_arch = "x86_64")]
    static KEPT: RefCell<Kept> = const { RefCell::new(Kept { w: Vec::new(), row: 0, filled: Vec::new() }) };
    /// `true` while it holds this pass's keys and values.
    #[cfg(target_arch = "x86_64")]
    static PREPARED: RefCell<(Prepared, bool)> = const { RefCell::new((Prepared::new(), false)) };
    /// A task's accumulator (on the thread that runs it).
    static ACC: RefCell<Vec<i64>> = const { RefCell::new(Vec::new()) };
    /// The right feature row laid out for the AVX-512 windows (on the calling thread).
    #[cfg(target_arch = "x86_64")]
    static F2: RefCell<crate::kernels::corr::avx512::Row> = const { RefCell::new(crate::kernels::corr::avx512::Row::new()) };
    #[cfg(not(target_arch = "x86_64"))]
    static F2: RefCell<()> = const { RefCell::new(()) };
    /// A task's correlation window and its prefix sums (on the thread that runs it).
    static WINDOW: RefCell<(Vec<i32>, Vec<i64>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// Most bytes of softmax weights kept for a frame (`n^2 / 2` u32 for `n` pixels at 1/8
/// resolution: 15 MB at 450 x 375, 107 MB at 1242 x 375). Larger frames compute the weights
/// again in every iteration, as the microcontroller does.
#[cfg(target_arch = "x86_64")]
const KEPT_BYTES: usize = 256 << 20;

/// Every query's softmax weights against every key ([`Prepared::stats_keep`]'s rows), so that
/// the iterations aggregate values without computing queries, logits and weights again: they
/// depend on the context alone, which a frame does not change.
#[cfg(target_arch = "x86_64")]
#[derive(Default)]
struct Kept {
    /// `row` key pairs per query, queries in pixel order.
    w: Vec<u32>,
    row: usize,
    /// Queries whose row holds this frame's weights.
    filled: Vec<bool>,
}

/// Queries (or keys) of row `y` (after RoPE) into `q` (`w qk` values): the 1x1 conv `p` over the
/// row's context.
#[allow(clippy::too_many_arguments)]
fn queries(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, y: usize, w: usize, phases: &[u32], q: &mut Vec<i16>, patch: &mut Vec<u8>) -> usize {
    let qk = p.cout;
    qk_row(p, inp08, ctx, y, w, phases, scratch(q, w * qk), patch);
    qk
}

/// [`queries`] into `out` (`w qk` values).
#[allow(clippy::too_many_arguments)]
fn qk_row(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, y: usize, w: usize, phases: &[u32], out: &mut [i16], patch: &mut Vec<u8>) {
    let patch = scratch(patch, 4 * p.patch_len().max(1));
    let mut rows = [None; MAX_K];
    if let Some(r) = rows.first_mut() {
        *r = inp08.get(y * w * ctx..(y + 1) * w * ctx);
    }
    run_conv(p, &[PartRows { rows }], w, &mut OutRow::I16(out), patch);
    for (x, q) in out.chunks_exact_mut(p.cout.max(1)).enumerate() {
        rope_pixel(q, x, y, phases);
    }
}

/// The keys of row `y` (after RoPE) into `keys` (`w qk`).
pub fn keys_row(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, y: usize, w: usize, phases: &[u32], keys: &mut [i16]) {
    ROW.with_borrow_mut(|(_, patch)| qk_row(p, inp08, ctx, y, w, phases, keys, patch));
}

/// Starts a frame's [`stats_row`] calls: the keys are final (written just before).
pub fn new_keys() {
    #[cfg(target_arch = "x86_64")]
    KEYS_T.with_borrow_mut(|(_, fresh)| *fresh = false);
    #[cfg(target_arch = "x86_64")]
    KEPT.with_borrow_mut(|k| {
        k.filled.clear();
        k.row = 0;
    });
}

/// Softmax statistics (`max`, `sum`) of every query of row `y` into `stats` (`2 w`). Call
/// [`new_keys`] once the keys are written.
#[allow(clippy::too_many_arguments)]
pub fn stats_row(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, y: usize, w: usize, phases: &[u32], keys: &[i16], m: Multiplier, stats: &mut [i64]) {
    ROW.with_borrow_mut(|(q, patch)| {
        let qk = queries(p, inp08, ctx, y, w, phases, q, patch);
        let (q, out) = (&*q, Shared(stats.as_mut_ptr()));
        let n = w.min(stats.len() / 2);
        #[cfg(target_arch = "x86_64")]
        let batched = KEYS_T.with_borrow_mut(|(prep, fresh)| {
            // Laid out once per frame (`new_keys`).
            if !*fresh {
                if !prep.fill_keys(keys, qk) {
                    return false;
                }
                *fresh = true;
            }
            let prep = &*prep;
            KEPT.with_borrow_mut(|kept| {
                // The weights of the row's queries `y w .. y w + n` are kept where the frame's
                // (`prep.n` queries, one a key) fit in `KEPT_BYTES`.
                let (row, nq) = (prep.kept_row(), prep.keys());
                let keep = row > 0 && nq.saturating_mul(row) <= KEPT_BYTES / 4 && y * w + n <= nq;
                if keep && kept.row != row {
                    kept.row = row;
                    kept.filled.clear();
                }
                if keep && kept.w.len() < nq * row {
                    // Zeroed by the OS, not by a serial fill of up to `KEPT_BYTES` here; its
                    // pages mapped in one call rather than one fault each.
                    kept.w = std::vec![0; nq * row];
                    pool::populate(&mut kept.w);
                }
                let (wk, base) = if keep { (Shared(scratch(&mut kept.w, nq * row).as_mut_ptr()), y * w) } else { (Shared(core::ptr::null_mut()), 0) };
                let fine = core::sync::atomic::AtomicBool::new(true);
                per_pixels(n, &|px| {
                    let (x0, x1) = (px.start, px.end);
                    // SAFETY: entries `2 x0 .. 2 x1 <= stats.len()`, this task's pixels only.
                    let o = unsafe { out.slice(2 * x0, 2 * (x1 - x0)) };
                    // SAFETY: rows `base + x0 .. base + x1 <= nq` of the kept weights (`nq
                    // row` long), this task's queries only.
                    let k = if keep { unsafe { wk.slice((base + x0) * row, (x1 - x0) * row) } } else { &mut [][..] };
                    if !prep.stats_keep(q.get(x0 * qk..x1 * qk).unwrap_or_default(), m, o, k) {
                        fine.store(false, core::sync::atomic::Ordering::Relaxed);
                    }
                });
                if keep && fine.into_inner() {
                    let f = scratch(&mut kept.filled, nq);
                    f.get_mut(base..base + n).unwrap_or_default().fill(true);
                }
            });
            true
        });
        #[cfg(not(target_arch = "x86_64"))]
        let batched = false;
        if batched {
            return;
        }
        per_pixels(n, &|px| {
            for x in px {
                let st = query_stats(q.get(x * qk..(x + 1) * qk).unwrap_or_default(), keys, m);
                // SAFETY: entries `2x, 2x + 1 < stats.len()`, this task's pixels only.
                let o = unsafe { out.slice(2 * x, 2) };
                if let [a, b] = o {
                    (*a, *b) = st;
                }
            }
        });
    });
}

/// This thread's frame state of the attention (the kept softmax weights and the pass's layout of
/// keys and values), moved out so that another thread can aggregate with it ([`lend_attention`]
/// there), and back with [`lend_attention`] here.
pub struct AttentionState {
    #[cfg(target_arch = "x86_64")]
    kept: Kept,
    #[cfg(target_arch = "x86_64")]
    prepared: (Prepared, bool),
}

/// Takes this thread's [`AttentionState`] (it is left empty: a pass here would lay out and
/// compute afresh).
pub fn take_attention() -> AttentionState {
    AttentionState {
        #[cfg(target_arch = "x86_64")]
        kept: KEPT.with_borrow_mut(core::mem::take),
        #[cfg(target_arch = "x86_64")]
        prepared: PREPARED.with_borrow_mut(core::mem::take),
    }
}

/// Makes `s` this thread's [`AttentionState`] (what it had is dropped).
pub fn lend_attention(s: AttentionState) {
    #[cfg(target_arch = "x86_64")]
    {
        KEPT.with_borrow_mut(|k| *k = s.kept);
        PREPARED.with_borrow_mut(|p| *p = s.prepared);
    }
    #[cfg(not(target_arch = "x86_64"))]
    let _ = s;
}

/// Starts a pass of [`aggregate_row`] calls over keys and values that stay as they are until the
/// next call of this function (the GRU pass: values are written before it, keys once a frame).
pub fn new_values() {
    #[cfg(target_arch = "x86_64")]
    PREPARED.with_borrow_mut(|(_, fresh)| *fresh = false);
}

/// The aggregated values of every query of row `y` into `d` (`w cv`); `stats` are the row's
/// softmax statistics (`2 w`). With `att`, that attention state (laid out for the pass by
/// [`AttentionState::lay_out_pass`]: a pass's rows on several threads at once); without, this
/// thread's (call [`new_values`] before each pass). The same integers either way.
#[allow(clippy::too_many_arguments)]
pub fn aggregate_row(
    att: Option<&AttentionState>,
    p: &ConvParams<'_>,
    inp08: &[u8],
    ctx: usize,
    y: usize,
    w: usize,
    phases: &[u32],
    keys: &[i16],
    values: &[i16],
    cv: usize,
    stats: &[i64],
    m: Multiplier,
    shift: i8,
    d: &mut [i16],
) {
    with_layouts(att, keys, values, p.cout, cv, |l| {
        #[cfg(target_arch = "x86_64")]
        if aggregate_kept(l, y, w, cv, stats, shift, d) {
            return;
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = l;
        ROW.with_borrow_mut(|(q, patch)| {
            let qk = queries(p, inp08, ctx, y, w, phases, q, patch);
            let (q, out) = (&*q, Shared(d.as_mut_ptr()));
            let n = w.min(d.len() / cv.max(1)).min(stats.len() / 2);
            #[cfg(target_arch = "x86_64")]
            if let Some(prep) = l.prep {
                // Four queries a task, two at a time in the kernel.
                per_pixels(n, &|px| {
                    let (x0, x1) = (px.start, px.end);
                    // SAFETY: values `x0 cv .. x1 cv <= d.len()`, this task's pixels only.
                    let o = unsafe { out.slice(x0 * cv, (x1 - x0) * cv) };
                    prep.aggregate(q.get(x0 * qk..x1 * qk).unwrap_or_default(), stats.get(2 * x0..2 * x1).unwrap_or_default(), m, shift, o);
                });
                return;
            }
            per_pixels(n, &|px| {
                ACC.with_borrow_mut(|acc| {
                    let acc = scratch(acc, cv);
                    for x in px {
                        let st = match stats.get(2 * x..2 * x + 2) {
                            Some(&[a, b]) => (a, b),
                            _ => (0, 0),
                        };
                        // SAFETY: values `x cv .. (x + 1) cv <= d.len()`, this task's pixels only.
                        let o = unsafe { out.slice(x * cv, cv) };
                        aggregate_query(q.get(x * qk..(x + 1) * qk).unwrap_or_default(), keys, values, cv, st, m, shift, acc, o);
                    }
                });
            });
        });
    });
}

/// `f` of the attention state `att`, or of this thread's (its pass's layout made on the pass's
/// first call, [`new_values`]: the keys and values do not change in it).
fn with_layouts<R>(att: Option<&AttentionState>, keys: &[i16], values: &[i16], qk: usize, cv: usize, f: impl FnOnce(Layouts<'_>) -> R) -> R {
    #[cfg(target_arch = "x86_64")]
    match att {
        Some(a) => f(Layouts { kept: &a.kept, prep: a.prepared.1.then_some(&a.prepared.0) }),
        None => KEPT.with_borrow(|kept| {
            PREPARED.with_borrow_mut(|(prep, fresh)| {
                if !*fresh {
                    *fresh = prep.fill(keys, values, qk, cv);
                }
                f(Layouts { kept, prep: fresh.then_some(&*prep) })
            })
        }),
    }
    #[cfg(not(target_arch = "x86_64"))]
    {
        let _ = (att, keys, values, qk, cv);
        f(Layouts { none: core::marker::PhantomData })
    }
}

impl AttentionState {
    /// Lays out the pass's keys and values (`qk` channels a key, `cv` a value), as the pass's
    /// first [`aggregate_row`] does on the thread whose state it is, for [`aggregate_row`] with
    /// this state.
    pub fn lay_out_pass(&mut self, keys: &[i16], values: &[i16], qk: usize, cv: usize) {
        #[cfg(target_arch = "x86_64")]
        {
            let (prep, fresh) = &mut self.prepared;
            *fresh = prep.fill(keys, values, qk, cv);
        }
        #[cfg(not(target_arch = "x86_64"))]
        let _ = (keys, values, qk, cv);
    }
}

/// What a row's aggregation reads of an [`AttentionState`]: the kept softmax weights, and the
/// pass's keys and values laid out for the batched aggregation (`None` where that layout does
/// not apply, see [`Prepared::fill`]).
#[derive(Clone, Copy)]
struct Layouts<'a> {
    #[cfg(target_arch = "x86_64")]
    kept: &'a Kept,
    #[cfg(target_arch = "x86_64")]
    prep: Option<&'a Prepared>,
    #[cfg(not(target_arch = "x86_64"))]
    none: core::marker::PhantomData<&'a ()>,
}

/// [`aggregate_row`] from the weights the statistics pass kept for row `y`'s queries; `false`
/// (nothing written) where they were not kept or the pass's layout does not match them.
#[cfg(target_arch = "x86_64")]
fn aggregate_kept(l: Layouts<'_>, y: usize, w: usize, cv: usize, stats: &[i64], shift: i8, d: &mut [i16]) -> bool {
    let n = w.min(d.len() / cv.max(1)).min(stats.len() / 2);
    let (kept, Some(prep)) = (l.kept, l.prep) else { return false };
    let (base, row) = (y * w, kept.row);
    if row == 0 || prep.kept_row() != row || !kept.filled.get(base..base + n).is_some_and(|f| f.iter().all(|&f| f)) {
        return false;
    }
    let out = Shared(d.as_mut_ptr());
    per_pixels(n, &|px| {
        let (x0, x1) = (px.start, px.end);
        // SAFETY: values `x0 cv .. x1 cv <= d.len()`, this task's pixels only.
        let o = unsafe { out.slice(x0 * cv, (x1 - x0) * cv) };
        let rows = kept.w.get((base + x0) * row..(base + x1) * row).unwrap_or_default();
        prep.aggregate_kept(rows, stats.get(2 * x0..2 * x1).unwrap_or_default(), shift, o);
    });
    true
}

/// [`crate::kernels::resample::interp_row`] with the row's pixels on the kernel pool.
#[allow(clippy::too_many_arguments)]
pub fn interp_row(src: &[i16], h: usize, w: usize, c: usize, h_out: usize, w_out: usize, y: usize, out: &mut [i16]) {
    let o = Shared(out.as_mut_ptr());
    let n = w_out.min(out.len() / c.max(1));
    per_pixels(n, &|xs| {
        // SAFETY: values `xs.start c .. xs.end c <= out.len()`, this task's pixels only.
        let d = unsafe { o.slice(xs.start * c, xs.len() * c) };
        crate::kernels::resample::interp_cols(src, h, w, c, h_out, w_out, y, xs, d);
    });
}

/// The upsampling mask's logits of a row: the 1x1 conv `p` over `mid` (`w` pixels of `mh`), then
/// `pixel(x, logits of x)` for every pixel, the row's pixels as tasks on the kernel pool.
pub fn mask_logits_row(p: &ConvParams<'_>, mid: &[i16], w: usize, mh: usize, pixel: &(dyn Fn(usize, &[i16]) + Sync)) {
    ROW.with_borrow_mut(|(_, patch)| {
        LOGITS.with_borrow_mut(|logits| {
            let n = p.cout;
            let logits = scratch(logits, w * n);
            let patch = scratch(patch, 4 * p.patch_len().max(1));
            let mut rows = [None; MAX_K];
            if let Some(r) = rows.first_mut() {
                *r = mid.get(..w * mh);
            }
            run_conv(p, &[PartRows { rows }], w, &mut OutRow::I16(logits), patch);
            let logits = &*logits;
            per_pixels(w.min(logits.len() / n.max(1)), &|xs| {
                for x in xs {
                    pixel(x, logits.get(x * n..(x + 1) * n).unwrap_or_default());
                }
            });
        });
    });
}

/// The correlation lookup of row `y` into `out` (`w cc`): `f1` the left features (`fd` a pixel),
/// `f2row` the right features' row, `flow` the disparity state (`fc` a pixel); `lens` the
/// lengths of the engine's window and prefix buffers.
#[allow(clippy::too_many_arguments)]
pub fn lookup_row(p: &LookupParams<'_>, f1: &[i8], f2row: &[i8], flow: &[i16], fc: usize, w: usize, y: usize, fd: usize, cc: usize, lens: (usize, usize), out: &mut [i16]) {
    // The row's inputs: its pixels' disparities, their left features, the right row.
    let n = w.min(out.len() / cc.max(1));
    let key = LookupKey {
        levels: p.levels,
        radius: p.radius,
        post_pool: p.post_pool,
        mults: p.mults,
        flow: flow.get(y * w * fc..(y * w + n) * fc).unwrap_or_default(),
        fc,
        f1: f1.get(y * w * fd..(y * w + n) * fd).unwrap_or_default(),
        f2: f2row,
    };
    let out = out.get_mut(..n * cc).unwrap_or_default();
    if LOOKUPS.lookup(y, &key, out) {
        return;
    }
    lookup_pixels(p, f1, f2row, flow, fc, w, y, fd, cc, lens, out);
    LOOKUPS.keep(y, &key, out);
}

/// [`lookup_row`]'s computation: the row's pixels as tasks on the kernel pool.
#[allow(clippy::too_many_arguments)]
fn lookup_pixels(p: &LookupParams<'_>, f1: &[i8], f2row: &[i8], flow: &[i16], fc: usize, w: usize, y: usize, fd: usize, cc: usize, lens: (usize, usize), out: &mut [i16]) {
    let out_p = Shared(out.as_mut_ptr());
    let n = w.min(out.len() / cc.max(1));
    F2.with_borrow_mut(|row| {
        // The right row transposed once for the AVX-512 windows (x86-64 with AVX-512 VNNI).
        #[cfg(target_arch = "x86_64")]
        let row = row.fill(f2row, w, fd).then_some(&*row);
        #[cfg(not(target_arch = "x86_64"))]
        let _ = row;
        per_pixels(n, &|xs| {
            WINDOW.with_borrow_mut(|(win, pre)| {
                let mut s = LookupScratch { window: scratch(win, lens.0), prefix: scratch(pre, lens.1) };
                for x in xs {
                    let px = y * w + x;
                    let d = flow.get(px * fc).copied().unwrap_or(0);
                    let f1 = f1.get(px * fd..(px + 1) * fd).unwrap_or_default();
                    // SAFETY: values `x cc .. (x + 1) cc <= out.len()`, this task's pixels only.
                    let o = unsafe { out_p.slice(x * cc, cc) };
                    lookup_with(p, w, x, d, &mut s, o, |lo, win| {
                        #[cfg(target_arch = "x86_64")]
                        if row.is_some_and(|r| r.window(f1, lo, win)) {
                            return;
                        }
                        window(f1, f2row, w, lo, win);
                    });
                }
            });
        });
    });
}

std::thread_local! {
    /// UFI's proposal features kept for its decoder ([`with_ufi_features`]).
    static UFI_FEATURES: RefCell<Vec<i16>> = const { RefCell::new(Vec::new()) };
}

/// Runs `f` with `len` values of this thread's scratch for UFI's proposal features
/// (`refine::ufi`).
pub fn with_ufi_features<R>(len: usize, f: impl FnOnce(&mut [i16]) -> R) -> R {
    UFI_FEATURES.with_borrow_mut(|v| f(scratch(v, len)))
}

/// What a correlation row is a function of ([`lookup_row`]): the lookup's parameters and the
/// row's inputs.
struct LookupKey<'a> {
    levels: usize,
    radius: usize,
    post_pool: bool,
    mults: &'a [Multiplier],
    /// The row's disparity state (`fc` channels a pixel; channel 0 is read).
    flow: &'a [i16],
    fc: usize,
    /// The row's left features, and the right feature row.
    f1: &'a [i8],
    f2: &'a [i8],
}

/// A correlation row as computed, with a copy of its inputs.
struct KeptLookup {
    y: usize,
    levels: usize,
    radius: usize,
    post_pool: bool,
    mults: Vec<Multiplier>,
    flow: Vec<i16>,
    fc: usize,
    f1: Vec<i8>,
    f2: Vec<i8>,
    out: Vec<i16>,
    /// When it was last read or written ([`Lookups::clock`]).
    used: u64,
}

impl KeptLookup {
    /// Whether this is row `y` of the inputs `k`, with `len` outputs.
    fn holds(&self, y: usize, k: &LookupKey<'_>, len: usize) -> bool {
        self.y == y
            && (self.levels, self.radius, self.post_pool, self.fc) == (k.levels, k.radius, k.post_pool, k.fc)
            && self.out.len() == len
            && self.mults == k.mults
            && self.flow == k.flow
            && self.f1 == k.f1
            && self.f2 == k.f2
    }
}

/// Correlation rows kept for reuse (host): an iteration's MUD, MGA-value and 1/8-ConvGRU passes
/// each look up every row at the same disparity state (the microcontroller computes each row
/// three times rather than hold the frame's), and UFI's decoder looks up its proposals' rows
/// again. A row is reused only where every input it is computed from (the lookup's parameters,
/// the row's disparities and left features, the right feature row) equals the copy kept with it,
/// so the result is the integers a new computation gives. Up to [`KEPT_PER_ROW`] rows a row
/// index (UFI's three proposals), the least recently used replaced; shared by the threads (the
/// MUD pass may run on the other one).
struct Lookups {
    rows: std::sync::Mutex<(Vec<KeptLookup>, u64)>,
}

/// Kept correlation rows per row index.
const KEPT_PER_ROW: usize = 4;

static LOOKUPS: Lookups = Lookups { rows: std::sync::Mutex::new((Vec::new(), 0)) };

impl Lookups {
    /// Copies row `y` of the inputs `k` into `out` where it is kept; `false` (nothing written)
    /// where it is not.
    fn lookup(&self, y: usize, k: &LookupKey<'_>, out: &mut [i16]) -> bool {
        let Ok(mut g) = self.rows.lock() else { return false };
        let (rows, clock) = &mut *g;
        *clock += 1;
        match rows.iter_mut().find(|r| r.holds(y, k, out.len())) {
            Some(r) => {
                out.copy_from_slice(&r.out);
                r.used = *clock;
                true
            }
            None => false,
        }
    }

    /// Keeps row `y` of the inputs `k`, computed as `out`.
    fn keep(&self, y: usize, k: &LookupKey<'_>, out: &[i16]) {
        let Ok(mut g) = self.rows.lock() else { return };
        let (rows, clock) = &mut *g;
        *clock += 1;
        if rows.iter().any(|r| r.holds(y, k, out.len())) {
            return; // (the other thread kept it meanwhile)
        }
        // The least recently used of row `y`'s entries once it has its share (its buffers
        // reused), else a new one.
        let same_y = rows.iter().filter(|r| r.y == y).count();
        let oldest = rows.iter().enumerate().filter(|(_, r)| r.y == y).min_by_key(|(_, r)| r.used).map(|(i, _)| i);
        let i = match oldest {
            Some(i) if same_y >= KEPT_PER_ROW => i,
            _ => {
                rows.push(KeptLookup { y, levels: 0, radius: 0, post_pool: false, mults: Vec::new(), flow: Vec::new(), fc: 0, f1: Vec::new(), f2: Vec::new(), out: Vec::new(), used: 0 });
                rows.len() - 1
            }
        };
        let Some(r) = rows.get_mut(i) else { return };
        (r.y, r.levels, r.radius, r.post_pool, r.fc, r.used) = (y, k.levels, k.radius, k.post_pool, k.fc, *clock);
        for (d, s) in [(&mut r.f1, k.f1), (&mut r.f2, k.f2)] {
            d.clear();
            d.extend_from_slice(s);
        }
        for (d, s) in [(&mut r.flow, k.flow), (&mut r.out, out)] {
            d.clear();
            d.extend_from_slice(s);
        }
        r.mults.clear();
        r.mults.extend_from_slice(k.mults);
    }
}

std::thread_local! {
    /// A band of the disparity head: its hidden rows, a row of its output, the conv's patch (on
    /// the thread that runs it).
    static HEAD: RefCell<(Vec<i16>, Vec<i16>, Vec<u8>)> = const { RefCell::new((Vec::new(), Vec::new(), Vec::new())) };
}

/// The disparity head ([`super::refine::flow_head`]) in two bands of rows as two tasks on the
/// kernel pool, each band's convolutions on the thread that runs it: the same integers (each
/// band computes the hidden rows it reads: its own and the one beyond its inner edge, the one
/// row both compute). Split row by row over the pool by pixels instead, the head ran 1.2-1.4x
/// faster on two threads than on one (`scripts/phase_times.py`). Returns the pixels that moved
/// by more than `settled`.
pub fn flow_head_bands(m: &crate::format::QuantModel<'_>, g: &crate::model::grid::Grid, net08: &[i16], flow: &mut [i16], settled: u16) -> usize {
    let cfg = *m.config();
    let (w, h8, fc) = (g.w8, g.h8, cfg.flow_channels);
    let split = h8 / 2;
    let (top, bottom) = flow.split_at_mut((split * w * fc).min(flow.len()));
    let bands = [std::sync::Mutex::new(Some((top, 0..split))), std::sync::Mutex::new(Some((bottom, split..h8)))];
    let moved = core::sync::atomic::AtomicUsize::new(0);
    pool::run(2, &|t| {
        let Some((flow, rows)) = bands.get(t).and_then(|b| b.lock().ok()).and_then(|mut b| b.take()) else { return };
        // A worker's own copies of the layers' re-laid weights (the engine's thread has its frame's).
        #[cfg(target_arch = "x86_64")]
        let _frame = crate::kernels::conv::FrameScope::unless_on();
        let n = HEAD.with_borrow_mut(|(hidden, out, patch)| head_band(m, g, net08, flow, rows, settled, hidden, out, patch));
        moved.fetch_add(n, core::sync::atomic::Ordering::Relaxed);
    });
    moved.into_inner()
}

/// [`flow_head_bands`]' band: output rows `rows` into `flow` (those rows of the disparity state).
#[allow(clippy::too_many_arguments)]
fn head_band(
    m: &crate::format::QuantModel<'_>,
    g: &crate::model::grid::Grid,
    net08: &[i16],
    flow: &mut [i16],
    rows: core::ops::Range<usize>,
    settled: u16,
    hidden: &mut Vec<i16>,
    out: &mut Vec<i16>,
    patch: &mut Vec<u8>,
) -> usize {
    use crate::model::layers::ConvId;
    let cfg = *m.config();
    let (w, h8, hd, fc) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels);
    let len = w * cfg.flow_head_dim;
    let (p1, p2) = (super::encoder::conv(m, ConvId::Flow1), super::encoder::conv(m, ConvId::Flow2));
    let patch = scratch(patch, 4 * p1.patch_len().max(p2.patch_len()).max(1));
    // The hidden rows the band's outputs read.
    let (h0, h1) = (rows.start.saturating_sub(1), (rows.end + 1).min(h8));
    let hidden = scratch(hidden, h1.saturating_sub(h0) * len);
    for (y, row) in (h0..h1).zip(hidden.chunks_exact_mut(len.max(1))) {
        super::refine::conv16(&p1, &[PartRows::of_tensor(net08, h8, w * hd, y, 3, 1)], w, row, patch);
    }
    let hidden = &*hidden;
    let out = scratch(out, w * fc);
    let mut moved = 0;
    for (r, flow) in rows.zip(flow.chunks_exact_mut((w * fc).max(1))) {
        // Hidden rows r - 1 .. r + 1 (zero padding outside the grid), from the band's.
        let mut parts = [None; MAX_K];
        for (ky, part) in parts.iter_mut().enumerate().take(3) {
            let y = (r + ky).checked_sub(1).filter(|&y| y < h8);
            *part = y.and_then(|y| hidden.get((y - h0) * len..(y - h0 + 1) * len));
        }
        super::refine::conv16(&p2, &[PartRows { rows: parts }], w, out, patch);
        moved += super::refine::add_update(flow, out, w, fc, settled);
    }
    moved
}

std::thread_local! {
    /// A band's row buffer and conv patch ([`row_bands`], on the thread that runs it).
    static BAND: RefCell<(Vec<i16>, Vec<u8>)> = const { RefCell::new((Vec::new(), Vec::new())) };
}

/// A row of [`row_bands`]: `row(y, buf, patch)`.
pub type BandRow<'a> = dyn Fn(usize, &mut [i16], &mut [u8]) + Sync + 'a;

/// Runs `row(y, buf, patch)` for every row `y < rows`, the rows in as many bands as the kernel
/// pool has threads, each band a task (its rows in order on the thread that runs it, with that
/// thread's `buf` of `len` values and a patch for convolutions of `patch_len`): for passes whose
/// rows are independent (the upsampling's), so each thread streams a layer's weights for its
/// own rows instead of every row's pixels being split between the threads.
pub fn row_bands(rows: usize, len: usize, patch_len: usize, row: &BandRow<'_>) {
    let bands = pool::threads().min(rows).max(1);
    pool::run(bands, &|t| {
        // A worker's own copies of the layers' re-laid weights (the engine's thread has its frame's).
        #[cfg(target_arch = "x86_64")]
        let _frame = crate::kernels::conv::FrameScope::unless_on();
        BAND.with_borrow_mut(|(buf, patch)| {
            let (buf, patch) = (scratch(buf, len), scratch(patch, 4 * patch_len.max(1)));
            for y in t * rows / bands..(t + 1) * rows / bands {
                row(y, buf, patch);
            }
        });
    });
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;
    use crate::kernels::corr::{lookup_pixel_plain, window_len};

    /// Deterministic bytes.
    fn bytes(seed: u32, n: usize) -> Vec<i8> {
        (0..n as u32).map(|i| ((i.wrapping_add(seed).wrapping_mul(2_654_435_761)) >> 11) as i8).collect()
    }

    /// Kept correlation rows are the integers a new computation gives: a row looked up again with
    /// the same inputs, and after any one input changed (a pixel's disparity, a left feature, a
    /// right feature, a level's multiplier) or for another row index, is the portable pixel
    /// lookup's row each time.
    #[test]
    fn kept_lookups_match_new_ones() {
        let (w, h, fd, fc, levels, radius) = (29, 3, 16, 2, 4, 4);
        let cc = levels * (2 * radius + 1);
        let lens = (window_len(levels, radius), window_len(levels, radius) + 1);
        let mut f1 = bytes(1, h * w * fd);
        let mut f2 = bytes(2, h * w * fd);
        let mut flow: Vec<i16> = (0..h * w * fc).map(|i| ((i * 37) % 900) as i16 - 300).collect();
        let mut mults: Vec<Multiplier> = (0..levels).map(|l| Multiplier { m: (1 << 30) + 999, shift: 42 + l as u8 }).collect();
        let want = |f1: &[i8], f2: &[i8], flow: &[i16], mults: &[Multiplier], y: usize| {
            let p = LookupParams { levels, radius, post_pool: true, mults };
            let mut row = vec![0i16; w * cc];
            for x in 0..w {
                let px = y * w + x;
                lookup_pixel_plain(&p, &f1[px * fd..(px + 1) * fd], &f2[y * w * fd..(y + 1) * w * fd], w, x, flow[px * fc], &mut row[x * cc..(x + 1) * cc]);
            }
            row
        };
        let got = |f1: &[i8], f2: &[i8], flow: &[i16], mults: &[Multiplier], y: usize| {
            let p = LookupParams { levels, radius, post_pool: true, mults };
            let mut row = vec![0i16; w * cc];
            lookup_row(&p, f1, &f2[y * w * fd..(y + 1) * w * fd], flow, fc, w, y, fd, cc, lens, &mut row);
            row
        };
        let check = |f1: &[i8], f2: &[i8], flow: &[i16], mults: &[Multiplier], what: &str| {
            for y in 0..h {
                let a = want(f1, f2, flow, mults, y);
                assert_eq!(got(f1, f2, flow, mults, y), a, "{what}, row {y}, first");
                assert_eq!(got(f1, f2, flow, mults, y), a, "{what}, row {y}, again");
            }
        };
        check(&f1, &f2, &flow, &mults, "start");
        flow[w * fc + 5 * fc] += 77;
        check(&f1, &f2, &flow, &mults, "a disparity");
        // Channel 1 of the state is not read: the kept row still holds.
        flow[w * fc + 6 * fc + 1] += 5;
        check(&f1, &f2, &flow, &mults, "a second channel");
        f1[w * fd + 3] = f1[w * fd + 3].wrapping_add(9);
        check(&f1, &f2, &flow, &mults, "a left feature");
        f2[2 * w * fd + 20 * fd + 7] = f2[2 * w * fd + 20 * fd + 7].wrapping_sub(50);
        check(&f1, &f2, &flow, &mults, "a right feature");
        mults[2].m += 1 << 20;
        check(&f1, &f2, &flow, &mults, "a multiplier");
        // Back to an earlier state (several kept a row index).
        f2[2 * w * fd + 20 * fd + 7] = f2[2 * w * fd + 20 * fd + 7].wrapping_add(50);
        check(&f1, &f2, &flow, &mults, "an earlier right row");
    }
}
