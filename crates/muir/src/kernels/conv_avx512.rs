//! [`super::conv_row`] on AVX-512 VNNI (host, x86-64): a whole output row as one matrix product
//! per input part, 16 output pixels per vector, instead of two pixels and two channels per call.
//!
//! Activations are packed in groups of 4 u8 (`vpdpbusd`, u8 x i8, four products a lane; i8
//! activations as `x + 128`, with `128 sum(w)` taken off after) or 2 i16 (`vpdpwssd`, two
//! products a lane; the i8 weights of a block of channels widened to i16 per call), one group per
//! i32, and laid out with output pixels along the vector. A weight group of one output channel is
//! broadcast to all 16 lanes; 8 channels x 32 pixels stay in registers, so each activation
//! vector is loaded once for 8 channels and each weight once for 32 pixels. The u8 path reads the
//! weights where the blob has them (`[c][part][ky][kx][c_in]`): the vectors run along pixels, not
//! channels, so no re-layout is needed (a part whose channels are not a multiple of 4 gets a
//! copy padded with zero weights).
//!
//! The activations: each of a part's `k` input rows is transposed once per call (`[stride
//! phase][group][column]`, 16 columns x 16 groups at a time in registers, zero columns on both
//! sides, channels padded with zeros to whole groups), so tap `(ky, kx)` of pixels `x .. x + 16`
//! is one load at column offset `kx` ([`Tap`]): no patch is gathered at all.
//!
//! Threads ([`super::super::pool`]): when the layer is large enough, the row is at least two
//! blocks of 16 pixels and the pool is free, one job of one task per thread, each a range of
//! output pixels of every channel from its own transposed input columns to its written outputs
//! ([`split_task`]: what a thread writes, it reads; across cores the reads of another core's
//! writes cost as much as the products). Otherwise one call is three phases, run on the pool
//! when the layer is large enough: the transposition (planes x column ranges), the matrix
//! products with their epilogue (blocks of 8 output channels, every part in turn), the write-out
//! in `[x][c]` order (16 pixels a task, a 16 x 16 transposition in registers). Each task writes
//! its own entries only, so the thread count changes no result.
//!
//! Exactness: neither instruction saturates. A u8 lane adds at most `4 * 255 * 128 < 2^17` per
//! group and a chunk at most [`U8_CHUNK`] groups (`< 2^30`); an i16 lane at most
//! `2 * 2^15 * 2^7 = 2^23` per group, [`I16_CHUNK`] groups (`255 * 2^23 < 2^31`). Each chunk's
//! i32 lanes are then added into i64 sums, so every part sum is the exact integer, and the
//! epilogue is [`super::finish_with`] of the saturating sum of [`requantize`]d parts, the
//! portable path's formula: the same integers for every input (the tests compare them).
//!
//! Most rows never reach this layout: the trunk's u8 3x3 rows ([`direct`]) and, inside an engine
//! frame, the i16 rows of 16 or more channels out ([`direct16`]) run with the output channels
//! along the vector instead. What is left here: rows of fewer than 16 channels out (the heads'
//! last convolutions), the i8 rows and the u8 ones other than one-part 3x3 rows, and the i16 rows
//! outside an engine frame.
//!
//! Layers whose tables or buffers are shorter than their parameters say are left to the portable
//! path (the caller's fallback), which defines what happens then.
#![deny(clippy::indexing_slicing)]

use core::arch::x86_64::*;
use core::cell::RefCell;

use super::super::pool::{self, Shared, scratch};
use super::super::x86::{cast, has_avx512};
use super::super::{Elem, OutRow};
use super::{ConvParams, PartRows, finish_with, mult_at, whole_row};
use crate::model::graph::MAX_PARTS;
use crate::arith::requantize;
use crate::model::graph::PostOp;

/// Pixels per vector.
const LANES: usize = 16;
/// Output channels per register block.
const BLOCK_C: usize = 8;
/// Most groups a u8 chunk sums in i32 lanes (see the module doc).
const U8_CHUNK: usize = 8192;
/// Most groups an i16 chunk sums in i32 lanes (see the module doc).
const I16_CHUNK: usize = 255;
/// Layers of fewer multiply-accumulates per row stay on the calling thread (256K: a few
/// microseconds, no more than a pool job costs in hand-over, wake-up and tail).
const PARALLEL_MACS: usize = 1 << 18;
/// Rows of fewer outputs are written out on the calling thread: a job costs the pool a hand-over
/// and a wait, more than these few microseconds of 16 x 16 transpositions.
const PARALLEL_OUTPUTS: usize = 1 << 14;

/// Where a run of consecutive weight groups finds its activations: group `w + g` (`g < groups`)
/// of pixel `x` is `xt[x + g gstride + x]`.
#[derive(Clone, Copy, Debug)]
struct Tap {
    /// Offset of group `w`'s pixel 0 in the activation buffer.
    x: usize,
    /// Distance between consecutive groups.
    gstride: usize,
    /// Groups in this run (at most one chunk).
    groups: usize,
    /// First weight group.
    w: usize,
}

/// Per-thread scratch, grown to the largest layer seen.
#[derive(Default)]
struct Scratch {
    /// Every part's transposed input rows.
    xt: Vec<i32>,
    /// Every part's taps.
    taps: Vec<Tap>,
    /// One part's exact sums `[c][pixel]`.
    part: Vec<i64>,
    /// Sums of the parts' requantised contributions `[c][pixel]`.
    sums: Vec<i64>,
    /// Finished outputs `[c][pixel]`, in the output type's range.
    fin: Vec<i32>,
}

std::thread_local! {
    static SCRATCH: RefCell<Scratch> = RefCell::new(Scratch::default());
    /// [`split_task`]'s scratch (the caller's [`SCRATCH`] is borrowed while it runs one).
    static SPLIT: RefCell<Scratch> = RefCell::new(Scratch::default());
    /// A task's weights (padded or widened), on the thread that runs it.
    static WEIGHTS: RefCell<Vec<i16>> = const { RefCell::new(Vec::new()) };
}

/// A layer's weights as the matrix product reads them (padded or widened, see [`copy_weights`]),
/// kept for the rest of an engine frame ([`FrameScope`]).
struct Relaid {
    /// The layer: its weight table's address and length, the activation kind, its output
    /// channels, kernel size and parts.
    key: (usize, usize, Kind, usize, usize, [usize; MAX_PARTS]),
    /// This frame's copy (else the buffer waits for reuse).
    valid: bool,
    /// Per part (where it needs a copy): `cout` channel rows of `k k chp` values.
    buf: Vec<i16>,
    /// Where each part's rows start in `buf`.
    at: [usize; MAX_PARTS],
    /// Exact sums of a part that is the same all frame ([`with_constant_part`]), per row.
    memo: Vec<Memo>,
}

/// One output row's exact sums of a constant part ([`with_constant_part`]), as `S` (i64 here,
/// i32 in [`direct16`]).
struct Memo<S = i64> {
    /// The part and the output row.
    part: usize,
    row: usize,
    /// Computed in this frame (else the buffers wait for reuse).
    valid: bool,
    /// The part's input rows as they were: per row its length in bytes (`u64::MAX` for a
    /// padding row) as 8 bytes, then its bytes.
    src: Vec<u8>,
    /// The sums, `cout` rows of `pixpad` (laid out `[x][c]` in [`direct16`]).
    sums: Vec<S>,
    pixpad: usize,
}

impl<S> Memo<S> {
    /// Whether `rows` (the first `k`) are the rows `src` holds.
    fn same_rows<T: Elem>(&self, rows: &[Option<&[T]>]) -> bool {
        let mut at = 0;
        for r in rows {
            let b = r.map(bytes_of);
            let len = b.map_or(u64::MAX, |b| b.len() as u64);
            if self.src.get(at..at + 8) != Some(&len.to_le_bytes()[..]) {
                return false;
            }
            at += 8;
            if let Some(b) = b {
                if self.src.get(at..at + b.len()) != Some(b) {
                    return false;
                }
                at += b.len();
            }
        }
        at == self.src.len()
    }

    /// The entry of `memos` that holds this frame's sums of `part` for output row `row` (`pixpad`
    /// pixels) and whose rows are `rows` (the first `k`), and `true`; else a free entry (one of an
    /// earlier frame, or a new one) set up to receive them, `len` sums, and `false`.
    fn entry<T: Elem>(memos: &mut Vec<Self>, part: usize, row: usize, pixpad: usize, rows: &[Option<&[T]>], len: usize) -> Option<(usize, bool)>
    where
        S: Copy + Default,
    {
        if let Some(i) = memos.iter().position(|m| m.valid && (m.part, m.row, m.pixpad) == (part, row, pixpad) && m.same_rows(rows)) {
            return Some((i, true));
        }
        let i = free_slot(memos, |m| m.valid, || Memo { part, row, valid: false, src: Vec::new(), sums: Vec::new(), pixpad });
        let m = memos.get_mut(i)?;
        (m.part, m.row, m.pixpad, m.valid) = (part, row, pixpad, false);
        m.keep_rows(rows);
        scratch(&mut m.sums, len);
        Some((i, false))
    }

    /// Keeps `rows` (the first `k`) as [`Memo::same_rows`] reads them.
    fn keep_rows<T: Elem>(&mut self, rows: &[Option<&[T]>]) {
        self.src.clear();
        for r in rows {
            let b = r.map(bytes_of);
            self.src.extend_from_slice(&b.map_or(u64::MAX, |b| b.len() as u64).to_le_bytes());
            self.src.extend_from_slice(b.unwrap_or_default());
        }
    }
}

std::thread_local! {
    /// The next convolution's part that stays the same all frame, and its output row.
    static CONSTANT: core::cell::Cell<Option<(usize, usize)>> = const { core::cell::Cell::new(None) };
}

/// Runs `f`, one convolution row call, telling the host kernels that its input part `part` is
/// the same in every call for output row `row` during the engine frame (the ConvGRU gates'
/// context). Inside a [`FrameScope`] that part's exact sums are then computed once per frame and
/// row, and reused only where its input rows equal a copy kept with them.
pub fn with_constant_part<R>(part: usize, row: usize, f: impl FnOnce() -> R) -> R {
    CONSTANT.with(|c| c.set(Some((part, row))));
    let r = f();
    CONSTANT.with(|c| c.set(None));
    r
}

std::thread_local! {
    /// The relaid layers of the frame that runs on this thread; `None` outside a frame.
    static FRAME: RefCell<Option<Vec<Relaid>>> = const { RefCell::new(None) };
}

impl Relaid {
    /// Leaves the buffers for reuse: nothing of this frame is kept.
    fn invalidate(&mut self) {
        self.valid = false;
        self.memo.iter_mut().for_each(|m| m.valid = false);
    }
}

/// While it lives, the convolutions called on this thread copy a layer's padded or widened
/// weights once and reuse them, instead of once per output row and channel block. An engine
/// frame holds one: the model's tables cannot change during it (the engine borrows them), and
/// the copies are dropped from use when it ends, so a table freed and another allocated at its
/// address is never mistaken for it. The buffers stay for the next frame (no allocation once
/// the first frame has run).
pub struct FrameScope(());

impl FrameScope {
    /// A frame on this thread unless one is on already (a task of the kernel pool that may run
    /// on the engine's own thread, inside its frame, or on a worker, outside any).
    pub fn unless_on() -> Option<Self> {
        if FRAME_ON.with(|on| on.get()) { None } else { Some(Self::new()) }
    }

    /// Starts a frame on this thread.
    pub fn new() -> Self {
        FRAME.with_borrow_mut(|f| match f {
            Some(layers) => layers.iter_mut().for_each(Relaid::invalidate),
            None => *f = Some(Vec::new()),
        });
        direct::invalidate();
        direct16::invalidate();
        FRAME_ON.with(|on| on.set(true));
        FrameScope(())
    }
}

impl Default for FrameScope {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for FrameScope {
    fn drop(&mut self) {
        FRAME.with_borrow_mut(|f| {
            if let Some(layers) = f {
                layers.iter_mut().for_each(Relaid::invalidate);
            }
        });
        direct::invalidate();
        direct16::invalidate();
        FRAME_ON.with(|on| on.set(false));
    }
}

std::thread_local! {
    /// A [`FrameScope`] lives on this thread.
    static FRAME_ON: core::cell::Cell<bool> = const { core::cell::Cell::new(false) };
}

/// Activation kinds of the matrix product.
#[derive(Clone, Copy, PartialEq)]
enum Kind {
    /// u8 (or i8) activations, `vpdpbusd`, 4 values a group.
    U8,
    /// i16 activations, `vpdpwssd`, 2 values a group.
    I16,
}

impl Kind {
    /// Values per group.
    fn per(self) -> usize {
        match self {
            Kind::U8 => 4,
            Kind::I16 => 2,
        }
    }
    /// Most groups per chunk.
    fn chunk(self) -> usize {
        match self {
            Kind::U8 => U8_CHUNK,
            Kind::I16 => I16_CHUNK,
        }
    }
}

/// `T`'s values as bytes (`T` is u8, i8 or i16 here: [`conv_row`] checked).
fn bytes_of<T: Elem>(v: &[T]) -> &[u8] {
    if let Some(b) = cast::<T, u8>(v) {
        b
    } else if let Some(b) = cast::<T, i8>(v) {
        bytemuck::cast_slice(b)
    } else if let Some(b) = cast::<T, i16>(v) {
        bytemuck::cast_slice(b)
    } else {
        &[]
    }
}

/// [`super::conv_row`] when the CPU has AVX-512 VNNI and the layer's tables and output are as
/// long as its parameters say; `false` (nothing written) otherwise.
pub fn conv_row<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>) -> bool {
    let kind = if cast::<T, u8>(&[]).is_some() || cast::<T, i8>(&[]).is_some() {
        Kind::U8
    } else if cast::<T, i16>(&[]).is_some() {
        Kind::I16
    } else {
        return false;
    };
    let constant = CONSTANT.with(|c| c.take());
    let w_out = p.out_width(w_in);
    if !whole_row(p, inputs.len(), w_in, out.len()) || w_in >= 1 << 20 || !has_avx512() {
        return false;
    }
    // The 3x3 stride-1 rows of one u8 part with the output channels along the vector
    // (`direct`), unless a part's sums are kept for the frame.
    // SAFETY: the CPU has AVX-512 F/BW/VNNI (`has_avx512`); the layer passed the checks above.
    if constant.is_none() && unsafe { direct::conv_row(p, inputs, w_in, out) } {
        return true;
    }
    // The i16 rows with fewer than 16 output channels, the vector along the patch (`few`; a
    // constant part's sums are not kept there: such layers have none).
    // SAFETY: as above.
    if unsafe { few::conv_row(p, inputs, w_in, out) } {
        return true;
    }
    // The i16 rows likewise (`direct16`), the constant part's sums kept there.
    // SAFETY: as above.
    if unsafe { direct16::conv_row(p, inputs, w_in, out, constant) } {
        return true;
    }
    // SAFETY: as above.
    SCRATCH.with_borrow_mut(|s| unsafe { run(p, inputs, w_in, w_out, kind, out, s, constant) });
    true
}

#[path = "conv_avx512_direct.rs"]
mod direct;
#[path = "conv_avx512_direct16.rs"]
mod direct16;
#[path = "conv_avx512_few.rs"]
mod few;

/// One input part's place in the row's work.
#[derive(Clone, Copy, Debug, Default)]
struct PartPlan {
    /// Channels, and channels padded to whole groups.
    ch: usize,
    chp: usize,
    /// Offset of the part's weights in a channel's row.
    off: usize,
    /// Offset of the part's transposed rows in the activation buffer, and indices a plane.
    xt_at: usize,
    tw: usize,
    /// Every part's taps.in the tap list.
    taps: (usize, usize),
    /// Its first transposition task, and how many it has (planes x index chunks).
    task0: usize,
    tasks: usize,
}

impl PartPlan {
    /// Whether the product reads a copy of the part's weights (widened to i16, or padded to whole
    /// groups) rather than the blob's own.
    fn copied(&self, kind: Kind) -> bool {
        kind == Kind::I16 || self.ch != self.chp
    }
}

/// Indices of a plane per transposition task.
const INDICES: usize = 64;

/// Runs `f(0) .. f(tasks - 1)` on the pool when the layer is large enough, else here.
fn par(big: bool, tasks: usize, f: &(dyn Fn(usize) + Sync)) {
    if big {
        pool::run(tasks, f);
    } else {
        (0..tasks).for_each(f);
    }
}

/// [`conv_row`]'s work, with the scratch: the input rows transposed (tasks over planes and
/// column ranges), the matrix products and epilogue (tasks over channel blocks, every part in
/// turn), the row written in its `[x][c]` order (tasks over pixel ranges).
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; the layer passed [`conv_row`]'s checks.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn run<T: Elem>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, w_out: usize, kind: Kind, out: &mut OutRow<'_>, s: &mut Scratch, constant: Option<(usize, usize)>) {
    let np = p.parts.len();
    let pixpad = w_out.div_ceil(LANES) * LANES;
    s.taps.clear();
    let (plans, xt_len, tasks) = part_plans(p, kind, pixpad, &mut s.taps);
    let plans = plans.get(..np).unwrap_or_default();
    if FRAME_ON.with(|on| on.get()) {
        FRAME.with_borrow_mut(|f| {
            // SAFETY: the CPU has AVX-512 F and BW (this function's contract).
            let Some(l) = f.as_mut().and_then(|layers| unsafe { layer(layers, p, plans, kind) }) else {
                // SAFETY: forwarded (this function's contract).
                return unsafe { run_with(p, inputs, w_in, w_out, kind, out, s, plans, xt_len, tasks, None, None) };
            };
            let weights = plans.iter().any(|pl| pl.copied(kind)).then_some((l.buf.as_slice(), l.at));
            let memo = constant.and_then(|(part, row)| {
                let rows = inputs.get(part)?.rows.get(..p.k)?;
                let (i, hit) = Memo::entry(&mut l.memo, part, row, pixpad, rows, p.cout * pixpad)?;
                Some((l.memo.get_mut(i)?, hit, part))
            });
            // SAFETY: forwarded (this function's contract); a memo's sums hold `cout pixpad`.
            unsafe { run_with(p, inputs, w_in, w_out, kind, out, s, plans, xt_len, tasks, weights, memo) }
        });
    } else {
        // SAFETY: forwarded.
        unsafe { run_with(p, inputs, w_in, w_out, kind, out, s, plans, xt_len, tasks, None, None) }
    }
}

/// The parts' layout for `pixpad` output pixels: their transposed rows (see `transpose_task`)
/// and taps (appended to `taps`), the activation buffer's length and the transposition tasks.
fn part_plans(p: &ConvParams<'_>, kind: Kind, pixpad: usize, taps: &mut Vec<Tap>) -> ([PartPlan; MAX_PARTS], usize, usize) {
    let (k, stride) = (p.k, p.stride);
    let (pad, lead) = (k / 2, (k / 2).div_ceil(stride) * stride);
    let mut plans = [PartPlan::default(); MAX_PARTS];
    let (mut off, mut xt_len, mut tasks) = (0, 0, 0);
    for (plan, &ch) in plans.iter_mut().zip(p.parts) {
        let chp = ch.next_multiple_of(kind.per());
        let cg = chp / kind.per();
        let tw = pixpad + (k - 1 + lead - pad) / stride + 1;
        let t0 = taps.len();
        for ky in 0..k {
            for kx in 0..k {
                let d = kx + lead - pad;
                let (phase, q) = (d % stride, d / stride);
                let (x, w) = (xt_len + (ky * stride + phase) * cg * tw + q, (ky * k + kx) * cg);
                let mut g = 0;
                while g < cg {
                    let groups = (cg - g).min(kind.chunk());
                    taps.push(Tap { x: x + g * tw, gstride: tw, groups, w: w + g });
                    g += groups;
                }
            }
        }
        let part_tasks = k * stride * tw.div_ceil(INDICES);
        *plan = PartPlan { ch, chp, off, xt_at: xt_len, tw, taps: (t0, taps.len()), task0: tasks, tasks: part_tasks };
        off += k * k * ch;
        xt_len += k * stride * cg * tw;
        tasks += part_tasks;
    }
    (plans, xt_len, tasks)
}

/// The first entry of `v` not `used` in this frame (its buffers for reuse), else a `new` one
/// pushed: its index.
fn free_slot<E>(v: &mut Vec<E>, used: impl Fn(&E) -> bool, new: impl FnOnce() -> E) -> usize {
    v.iter().position(|e| !used(e)).unwrap_or_else(|| {
        v.push(new());
        v.len() - 1
    })
}

/// This frame's entry of layer `p`: its weights re-laid (built on first use in the frame, into a
/// buffer of an earlier frame where one is free) where a part needs a copy, and its memos.
///
/// # Safety
/// The CPU has AVX-512 F and BW.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn layer<'a>(layers: &'a mut Vec<Relaid>, p: &ConvParams<'_>, plans: &[PartPlan], kind: Kind) -> Option<&'a mut Relaid> {
    let mut parts = [0; MAX_PARTS];
    parts.iter_mut().zip(plans).for_each(|(c, pl)| *c = pl.ch);
    let key = (p.weights.as_ptr() as usize, p.weights.len(), kind, p.cout, p.k, parts);
    let i = match layers.iter().position(|l| l.key == key) {
        Some(i) => i,
        None => {
            // A buffer of a layer this frame has not used, else a new one.
            let i = free_slot(layers, |l| l.valid, || Relaid { key, valid: false, buf: Vec::new(), at: [0; MAX_PARTS], memo: Vec::new() });
            let l = layers.get_mut(i)?;
            l.invalidate();
            l.key = key;
            i
        }
    };
    let l = layers.get_mut(i)?;
    if !l.valid {
        let (cout, kl, taps) = (p.cout, p.patch_len(), p.k * p.k);
        let mut len = 0;
        for (at, pl) in l.at.iter_mut().zip(plans) {
            *at = len;
            if pl.copied(kind) {
                len += cout * taps * pl.chp;
            }
        }
        let mut part = Vec::new();
        core::mem::swap(&mut part, &mut l.buf);
        let buf = scratch(&mut part, len);
        for (&at, pl) in l.at.iter().zip(plans).filter(|(_, pl)| pl.copied(kind)) {
            let n = cout * taps * pl.chp;
            if let Some(dst) = buf.get_mut(at..at + n) {
                // SAFETY: the CPU has AVX-512 F and BW (this function's contract).
                unsafe { copy_weights_into(p.weights, kl, pl.off, pl.ch, pl.chp, taps, cout, kind, dst) };
            }
        }
        l.buf = part;
        l.valid = true;
    }
    Some(l)
}

/// [`run`] after the part plans, with this frame's relaid weights where there are some.
///
/// # Safety
/// As [`run`].
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn run_with<T: Elem>(
    p: &ConvParams<'_>,
    inputs: &[PartRows<'_, T>],
    w_in: usize,
    w_out: usize,
    kind: Kind,
    out: &mut OutRow<'_>,
    s: &mut Scratch,
    plans: &[PartPlan],
    xt_len: usize,
    tasks: usize,
    relaid: Option<(&[i16], [usize; MAX_PARTS])>,
    mut memo: Option<(&mut Memo, bool, usize)>,
) {
    // The constant part's sums: reused (`hit`: its transposition and products skipped), or
    // computed and kept.
    let (memo_sums, hit, memo_part) = match &mut memo {
        Some((m, hit, part)) => (Shared(m.sums.as_mut_ptr()), *hit, Some(*part)),
        None => (Shared(core::ptr::null_mut()), false, None),
    };
    let (cout, kl, k, stride) = (p.cout, p.patch_len(), p.k, p.stride);
    let pixpad = w_out.div_ceil(LANES) * LANES;
    let signed8 = cast::<T, i8>(&[]).is_some();
    let flip = if signed8 { 0x8080_8080u32 as i32 } else { 0 };
    let big = w_out * cout * kl >= PARALLEL_MACS;
    let cx = BlockCtx { p, kind, signed8, relaid, memo: (memo_sums.0, pixpad), hit, memo_part, out_range: out_range(out) };
    let nblk = pixpad / LANES;
    let ranges = split_ranges(big, nblk);
    if ranges > 0 {
        // Several threads: each a range of pixels, every channel (see `split_task`).
        let (op, size) = out_ptr(out);
        pool::run(ranges, &|t| {
            let (b0, b1) = (t * nblk / ranges, (t + 1) * nblk / ranges);
            let (x0, x1) = (b0 * LANES, (b1 * LANES).min(w_out));
            if x1 > x0 {
                // SAFETY: pixels `x0 .. x1` of the row and of the memo, this task's only; the
                // layer passed `conv_row`'s checks; the CPU features (this function's contract).
                SPLIT.with_borrow_mut(|s| unsafe { split_task(&cx, inputs, w_in, x0, x1 - x0, &op, size, s) });
            }
        });
        if let Some((m, false, _)) = memo {
            m.valid = true; // computed by every range above
        }
        return;
    }
    let lead = (k / 2).div_ceil(stride) * stride;
    let xt = scratch(&mut s.xt, xt_len);
    // 1. The input rows, transposed.
    let xtp = Shared(xt.as_mut_ptr());
    par(big, tasks, &|t| {
        let Some((part, plan)) = plans.iter().enumerate().find(|(_, pl)| (pl.task0..pl.task0 + pl.tasks).contains(&t)) else {
            return;
        };
        if hit && memo_part == Some(part) {
            return; // its products are not computed
        }
        let chunks = plan.tw.div_ceil(INDICES);
        let (plane, chunk) = ((t - plan.task0) / chunks, (t - plan.task0) % chunks);
        let (i0, i1) = (chunk * INDICES, ((chunk + 1) * INDICES).min(plan.tw));
        let row = inputs.get(part).and_then(|r| r.rows.get(plane / stride)).copied().flatten();
        // SAFETY: this task's entries only (plane `plane`, indices `i0..i1` of every group); the
        // CPU has AVX-512 F and BW (this function's contract).
        unsafe { transpose_task(row, plan, kind, stride, lead, w_in, 0, plane, i0, i1, flip, &xtp) };
    });
    let (xt, taps) = (&*xt, &*s.taps);
    // 2. The exact sums per part, their requantised contributions and the finished outputs, per
    // block of `BLOCK_C` channels.
    let sp = scratch(&mut s.part, cout * pixpad);
    let sums = scratch(&mut s.sums, cout * pixpad);
    let fin = scratch(&mut s.fin, cout * pixpad);
    let (spp, sump, finp) = (Shared(sp.as_mut_ptr()), Shared(sums.as_mut_ptr()), Shared(fin.as_mut_ptr()));
    par(big, cout.div_ceil(BLOCK_C), &|b| {
        let c0 = b * BLOCK_C;
        let r = cout.saturating_sub(c0).min(BLOCK_C);
        // SAFETY: block `b`'s `r` channel rows of `sp`, `sums`, `fin` (each `cout pixpad` long),
        // touched by no other task; the memo's rows `c0 .. c0 + r` likewise; `xt` and `taps` as
        // laid out for `pixpad` pixels (`run`); the CPU features (this function's contract).
        unsafe {
            let (sp, sums, fin) = (spp.slice(c0 * pixpad, r * pixpad), sump.slice(c0 * pixpad, r * pixpad), finp.slice(c0 * pixpad, r * pixpad));
            channel_block(&cx, xt.as_ptr(), taps, plans, 0, pixpad, c0, r, sp, sums, fin);
        }
    });
    if let Some((m, false, _)) = memo {
        m.valid = true; // computed by every channel block above
    }
    // 3. The row in its `[x][c]` order, per range of 16 pixels.
    let fin = &*fin;
    let (op, size) = out_ptr(out);
    par(big && w_out * cout >= PARALLEL_OUTPUTS, w_out.div_ceil(LANES), &|t| {
        let x0 = t * LANES;
        let nx = w_out.saturating_sub(x0).min(LANES);
        // SAFETY: `fin` holds `cout` rows of `pixpad >= x0 + 16`; pixels `x0 .. x0 + nx <=
        // w_out` of the row (`w_out cout <= len`, checked by `conv_row`), this task's only; the
        // CPU has AVX-512 F and BW (this function's contract).
        unsafe { transpose_out(fin, pixpad, cout, x0, nx, op.slice(x0 * cout * size, nx * cout * size).as_mut_ptr(), size) };
    });
}

/// Ranges of pixels a row is split into ([`split_task`]), 0 for the one-thread path: a row of
/// enough multiply-accumulates (`big`) and at least two blocks of 16 pixels when the pool is free.
fn split_ranges(big: bool, nblk: usize) -> usize {
    #[cfg(test)]
    if let Some(r) = FORCE_RANGES.with(|f| f.get()) {
        return r.clamp(1, nblk.max(1));
    }
    if big && nblk >= 2 && pool::free() { pool::threads().min(nblk) } else { 0 }
}

/// One tap's products for the rows with the output channels along the vector ([`direct`],
/// [`direct16`]): for each of `g_n` groups of 4 bytes (4 u8, or 2 i16), each of the `P` pixels'
/// group (`pixel` bytes apart from `x`) broadcast against `16 NV` channels' weights, added into
/// `acc` by `vpdpbusd` (`U8`: the weights `w` are groups of 4 i8, an i32 a channel, `wrow`
/// channels a group) or `vpdpwssd` (the weights are pairs of i8, 2 bytes a channel, widened to
/// i16 pairs in the loop: half the bytes of i16 pairs, so that a ConvGRU's three gates stay in
/// the L2 cache from one row to the next; the widening costs nothing beside `vpdpwssd`,
/// docs/performance.md, twelfth session).
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; for every `q < P` and `g < g_n`, the 4 bytes at `x + q
/// pixel + 4 g` and the `16 NV` channels' weights of group `g` (from `w + (4 or 2) g wrow`) are
/// readable.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
unsafe fn tap_products<const U8: bool, const NV: usize, const P: usize>(acc: &mut [[__m512i; NV]; P], x: *const u8, pixel: usize, w: *const u8, wrow: usize, g_n: usize) {
    for g in 0..g_n {
        let mut wv = [_mm512_setzero_si512(); NV];
        for (v, wv) in wv.iter_mut().enumerate() {
            let at = g * wrow + 16 * v;
            // SAFETY: the contract.
            *wv = unsafe { if U8 { _mm512_loadu_si512(w.add(4 * at).cast()) } else { _mm512_cvtepi8_epi16(_mm256_loadu_si256(w.add(2 * at).cast())) } };
        }
        for (q, acc) in acc.iter_mut().enumerate() {
            // SAFETY: the contract.
            let a = _mm512_set1_epi32(unsafe { x.add(q * pixel + 4 * g).cast::<i32>().read_unaligned() });
            for (acc, wv) in acc.iter_mut().zip(wv) {
                *acc = if U8 { _mm512_dpbusd_epi32(*acc, a, wv) } else { _mm512_dpwssd_epi32(*acc, a, wv) };
            }
        }
    }
}

/// Ranges of pixel blocks a row with the output channels along the vector ([`direct`],
/// [`direct16`]) is split into: one a thread for a row of enough multiply-accumulates (`big`) and
/// at least two blocks when the pool is free, else 1.
fn block_ranges(big: bool, blocks: usize) -> usize {
    #[cfg(test)]
    if let Some(r) = FORCE_RANGES.with(|f| f.get()) {
        return r.clamp(1, blocks.max(1));
    }
    if big && blocks >= 2 && pool::free() { pool::threads().min(blocks) } else { 1 }
}

#[cfg(test)]
std::thread_local! {
    /// Tests: the split path with this many ranges whatever the row and the pool.
    static FORCE_RANGES: core::cell::Cell<Option<usize>> = const { core::cell::Cell::new(None) };
}

/// One thread's share of a convolution row on several threads: output pixels `x0 .. x0 + nx`
/// (`x0` a multiple of 16) of every channel, from the input columns they read (transposed into
/// this thread's own layout, `col0 = s x0`) to the written pixels. Splitting the row's channels
/// instead (the one-thread path's tasks) made every thread read the whole transposed row the
/// caller wrote and the caller read every thread's finished outputs: on this VM a 40 KB buffer
/// another core wrote takes 7 us to read against 1 us from one's own cache, as long as a task's
/// products. By pixels, a thread reads the input columns it wrote in the layer before (for the
/// range's halo and for rows other kernels wrote, the other core's), and its memo sums stay in
/// its cache from one iteration to the next.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; the layer passed [`conv_row`]'s checks; `x0 + nx <=
/// w_out`; no other thread touches pixels `x0 .. x0 + nx` of the output row (`out`, `size`
/// bytes an element) or of the memo meanwhile.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn split_task<T: Elem>(cx: &BlockCtx<'_, '_>, inputs: &[PartRows<'_, T>], w_in: usize, x0: usize, nx: usize, out: &Shared<u8>, size: usize, s: &mut Scratch) {
    let (p, kind) = (cx.p, cx.kind);
    let (cout, k, stride) = (p.cout, p.k, p.stride);
    let n = nx.div_ceil(LANES) * LANES;
    let Scratch { xt, taps, part, sums, fin } = s;
    taps.clear();
    let (plans, xt_len, _) = part_plans(p, kind, n, taps);
    let plans = plans.get(..p.parts.len()).unwrap_or_default();
    let xt = scratch(xt, xt_len);
    let xtp = Shared(xt.as_mut_ptr());
    let lead = (k / 2).div_ceil(stride) * stride;
    let flip = if cx.signed8 { 0x8080_8080u32 as i32 } else { 0 };
    for (pi, plan) in plans.iter().enumerate() {
        if cx.hit && cx.memo_part == Some(pi) {
            continue; // its products are not computed
        }
        for plane in 0..k * stride {
            let row = inputs.get(pi).and_then(|r| r.rows.get(plane / stride)).copied().flatten();
            // SAFETY: the plane's indices `0 .. tw` of this layout (`part_plans`), in this
            // thread's buffer; the CPU has AVX-512 F and BW.
            unsafe { transpose_task(row, plan, kind, stride, lead, w_in, stride * x0, plane, 0, plan.tw, flip, &xtp) };
        }
    }
    let (sp, sums, fin) = (scratch(part, BLOCK_C * n), scratch(sums, BLOCK_C * n), scratch(fin, cout * n));
    for (b, fin) in fin.chunks_mut(BLOCK_C * n).enumerate() {
        let c0 = b * BLOCK_C;
        let r = cout.saturating_sub(c0).min(BLOCK_C);
        // SAFETY: `xt` and `taps` laid out for `n` pixels; the memo's pixels `x0 .. x0 + n <=
        // pixpad` (`x0 + nx <= w_out`, both multiples of 16 after rounding) are this task's.
        unsafe { channel_block(cx, xt.as_ptr(), taps, plans, x0, n, c0, r, sp, sums, fin) };
    }
    let mut j = 0;
    while j < nx {
        let m = (nx - j).min(LANES);
        // SAFETY: `fin` holds `cout` rows of `n >= j + 16` values; pixels `x0 + j .. x0 + j + m`
        // of the output row are this task's (the contract).
        unsafe { transpose_out(fin, n, cout, j, m, out.slice((x0 + j) * cout * size, m * cout * size).as_mut_ptr(), size) };
        j += LANES;
    }
}

/// The output type's range.
fn out_range(out: &OutRow<'_>) -> (i32, i32) {
    match out {
        OutRow::I8(_) => (i8::MIN as i32, i8::MAX as i32),
        OutRow::U8(_) => (0, u8::MAX as i32),
        OutRow::I16(_) => (i16::MIN as i32, i16::MAX as i32),
    }
}

/// The output row's first byte and its bytes an element.
fn out_ptr(out: &mut OutRow<'_>) -> (Shared<u8>, usize) {
    match out {
        OutRow::I8(o) => (Shared(o.as_mut_ptr().cast()), 1),
        OutRow::U8(o) => (Shared(o.as_mut_ptr()), 1),
        OutRow::I16(o) => (Shared(o.as_mut_ptr().cast()), 2),
    }
}

/// What every channel block of a convolution row shares (see [`channel_block`]).
struct BlockCtx<'a, 'p> {
    p: &'a ConvParams<'p>,
    kind: Kind,
    /// i8 activations, packed as `x + 128`.
    signed8: bool,
    /// This frame's re-laid weights (see [`layer`]).
    relaid: Option<(&'a [i16], [usize; MAX_PARTS])>,
    /// The constant part's memo sums (`cout` rows of the given length; null without a memo),
    /// whether they hold this row's sums (`hit`), and the part.
    memo: (*mut i64, usize),
    hit: bool,
    memo_part: Option<usize>,
    /// The output type's range.
    out_range: (i32, i32),
}

// SAFETY: the memo pointer is written only at the rows and pixels of one task (see
// [`channel_block`]'s contract), the rest is read-only.
unsafe impl Sync for BlockCtx<'_, '_> {}

/// Channels `c0 .. c0 + r` (`r <= BLOCK_C`) of a convolution row over `n` pixels (a multiple of
/// 16) from pixel `x0` of the row on: each part's exact sums (the memo's rows for the constant
/// part, kept or computed into them, else `sp`), their requantised contributions into `sums`
/// and the finished outputs into `fin` (`r` rows of `n` each; channel `c0 + i`'s at `i n`).
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; `xt` and `taps` are laid out (`part_plans`) for `n`
/// pixels, `plans` with them; `x0 + n` is at most the memo rows' length; no other thread touches
/// the memo's rows `c0 .. c0 + r` at pixels `x0 .. x0 + n` meanwhile.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[allow(clippy::too_many_arguments)]
unsafe fn channel_block(cx: &BlockCtx<'_, '_>, xt: *const i32, taps: &[Tap], plans: &[PartPlan], x0: usize, n: usize, c0: usize, r: usize, sp: &mut [i64], sums: &mut [i64], fin: &mut [i32]) {
    let (p, kind) = (cx.p, cx.kind);
    let (k, kl, np) = (p.k, p.patch_len(), p.parts.len());
    let (memo_sums, memo_len) = cx.memo;
    let (lo, hi) = cx.out_range;
    // Per channel: some contribution took the scalar path (see `add_part`).
    let mut wild = [false; BLOCK_C];
    for (part, plan) in plans.iter().enumerate() {
        let (ch, chp, off) = (plan.ch, plan.chp, plan.off);
        let nk = k * k * ch;
        let taps = taps.get(plan.taps.0..plan.taps.1).unwrap_or_default();
        // The exact sums of the part: the memo's rows for the constant part (kept, or computed
        // into them), else `sp`.
        let memo_rows = (cx.memo_part == Some(part) && !memo_sums.is_null()).then(|| {
            // SAFETY: the contract (rows `c0 .. c0 + r`, pixels `x0 .. x0 + n` of the memo).
            unsafe { memo_sums.add(c0 * memo_len + x0) }
        });
        let (dst, stride) = match memo_rows {
            Some(m) => (m, memo_len),
            None => (sp.as_mut_ptr(), n),
        };
        WEIGHTS.with_borrow_mut(|buf| {
            if cx.hit && memo_rows.is_some() {
                return; // this frame's sums of the row, kept
            }
            // The block's weights of this part, `[ky][kx][c]` with `chp` values a tap (4 bytes
            // a group): the blob's own (u8 of whole groups), else a copy with the channels
            // padded (u8) or widened to i16: this frame's, or made here in this thread's buffer.
            let mut wp = [core::ptr::null::<u8>(); BLOCK_C];
            let kept = cx.relaid.and_then(|(buf, at)| Some((buf, *at.get(part)?)));
            if let (Some((buf, at)), true) = (kept, plan.copied(kind)) {
                // This frame's copy: `cout` rows of `k k chp` i16 (or i8 in their first half).
                let bytes: &[u8] = bytemuck::cast_slice(buf);
                let wrow = 2 * k * k * chp;
                for (i, wp) in wp.iter_mut().enumerate().take(r) {
                    *wp = bytes.get(2 * at + (c0 + i) * wrow..).unwrap_or_default().as_ptr();
                }
            } else if kind == Kind::U8 && ch == chp {
                for (i, wp) in wp.iter_mut().enumerate().take(r) {
                    *wp = p.weights.get((c0 + i) * kl + off..).unwrap_or_default().as_ptr().cast();
                }
            } else {
                let w = p.weights.get(c0 * kl..).unwrap_or_default();
                // SAFETY: the CPU has AVX-512 F and BW (this function's contract).
                let wrow = unsafe { copy_weights(w, kl, off, ch, chp, k * k, r, kind, buf) };
                let bytes: &[u8] = bytemuck::cast_slice(buf.as_slice());
                for (i, wp) in wp.iter_mut().enumerate().take(r) {
                    *wp = bytes.get(i * wrow..).unwrap_or_default().as_ptr();
                }
            }
            // SAFETY: the CPU has AVX-512 F/BW/VNNI (this function's contract); each `wp`
            // points at `k k chp` weights of its channel (the blob's, `weights.len() >= cout
            // kl` checked, or a copy), which the taps' groups cover; the taps lie inside `xt`
            // for every pixel below `n` (`part_plans`, `transpose_task`); `dst` holds `r` rows
            // of `stride >= n`.
            unsafe {
                match kind {
                    Kind::U8 => block_dispatch::<true>(r, xt, taps, n, stride, &wp, dst),
                    Kind::I16 => block_dispatch::<false>(r, xt, taps, n, stride, &wp, dst),
                }
            }
        });
        for (i, (sum, wild)) in sums.chunks_exact_mut(n).zip(wild.iter_mut()).take(r).enumerate() {
            // SAFETY: row `i < r` of `dst`: `n` sums at `i stride` (the contract for the memo's,
            // `sp` holds `r n`).
            let acc: &[i64] = unsafe { core::slice::from_raw_parts(dst.add(i * stride), n) };
            let c = c0 + i;
            // i8 activations were packed as `x + 128` (u8): `128 sum(w)` comes off.
            let corr = if cx.signed8 { 128 * p.weights.get(c * kl + off..c * kl + off + nk).unwrap_or_default().iter().map(|w| *w as i64).sum::<i64>() } else { 0 };
            // The part's requantised contribution, as the portable path adds it.
            let m = mult_at(p.mult.0.get(8 * (c * np + part)..).unwrap_or_default());
            // SAFETY: the CPU has AVX-512 F (this function's contract).
            *wild = unsafe { add_part(acc, corr, sum, m, *wild, part == 0) };
        }
    }
    for (i, ((sum, fin), wild)) in sums.chunks_exact(n).zip(fin.chunks_exact_mut(n)).zip(wild).take(r).enumerate() {
        // Bias, rounding, activation and the output type's saturation (`fin[c][x]`).
        // SAFETY: as above.
        unsafe { finish_channel(p.post, p.bias.get(c0 + i), wild, sum, fin, lo, hi) };
    }
}

/// The 16 x 16 transposition of `r` (16 rows of 16 i32): unpacks of 32 and 64 bits, then two
/// rounds of 128-bit lane shuffles.
#[target_feature(enable = "avx512f")]
#[inline]
fn transpose16(r: [__m512i; 16]) -> [__m512i; 16] {
    let mut t = [_mm512_setzero_si512(); 16];
    for (rs, ts) in r.chunks_exact(4).zip(t.chunks_exact_mut(4)) {
        if let (&[a, b, c, d], [t0, t1, t2, t3]) = (rs, ts) {
            let (ab_lo, ab_hi, cd_lo, cd_hi) = (_mm512_unpacklo_epi32(a, b), _mm512_unpackhi_epi32(a, b), _mm512_unpacklo_epi32(c, d), _mm512_unpackhi_epi32(c, d));
            // Column `4L + k` of these four rows in 128-bit lane `L` of `tk`.
            *t0 = _mm512_unpacklo_epi64(ab_lo, cd_lo);
            *t1 = _mm512_unpackhi_epi64(ab_lo, cd_lo);
            *t2 = _mm512_unpacklo_epi64(ab_hi, cd_hi);
            *t3 = _mm512_unpackhi_epi64(ab_hi, cd_hi);
        }
    }
    let [t0, t1, t2, t3, t4, t5, t6, t7, t8, t9, t10, t11, t12, t13, t14, t15] = t;
    // Columns `k`, `4 + k`, `8 + k`, `12 + k`: lane `L` of the four row groups' `t`.
    macro_rules! columns {
        ($a:expr, $b:expr, $c:expr, $d:expr) => {{
            let (lo02, lo13) = (_mm512_shuffle_i32x4::<0x88>($a, $b), _mm512_shuffle_i32x4::<0xDD>($a, $b));
            let (hi02, hi13) = (_mm512_shuffle_i32x4::<0x88>($c, $d), _mm512_shuffle_i32x4::<0xDD>($c, $d));
            (
                _mm512_shuffle_i32x4::<0x88>(lo02, hi02),
                _mm512_shuffle_i32x4::<0x88>(lo13, hi13),
                _mm512_shuffle_i32x4::<0xDD>(lo02, hi02),
                _mm512_shuffle_i32x4::<0xDD>(lo13, hi13),
            )
        }};
    }
    let (p0, p4, p8, p12) = columns!(t0, t4, t8, t12);
    let (p1, p5, p9, p13) = columns!(t1, t5, t9, t13);
    let (p2, p6, p10, p14) = columns!(t2, t6, t10, t14);
    let (p3, p7, p11, p15) = columns!(t3, t7, t11, t15);
    [p0, p1, p2, p3, p4, p5, p6, p7, p8, p9, p10, p11, p12, p13, p14, p15]
}

/// Writes pixels `x0 .. x0 + nx` (`nx <= 16`) of the finished outputs `fin` (`[c][pixel]`,
/// `pixpad` a row, already in the output type's range) to `out` in `[x][c]` order, `size` bytes
/// an element (1: i8/u8, 2: i16): 16 channels at a time by a 16 x 16 transposition in registers
/// (unpacks of 32 and 64 bits, then two rounds of 128-bit lane shuffles) and a narrowing store,
/// the channels past the last multiple of 16 one by one.
///
/// # Safety
/// The CPU has AVX-512 F and BW; `fin` holds `cout` rows of `pixpad >= x0 + 16` values; `out`
/// points at `nx cout` writable elements of `size` bytes.
#[target_feature(enable = "avx512f,avx512bw")]
unsafe fn transpose_out(fin: &[i32], pixpad: usize, cout: usize, x0: usize, nx: usize, out: *mut u8, size: usize) {
    let f = fin.as_ptr();
    let mut c0 = 0;
    // SAFETY (whole body): reads of `fin` rows `c0 .. c0 + 16 <= cout` at pixels `x0 .. x0 + 16
    // <= pixpad`, writes of elements `x cout + c < nx cout` (the contract).
    unsafe {
        while c0 + 16 <= cout {
            let mut r = [_mm512_setzero_si512(); 16];
            for (i, r) in r.iter_mut().enumerate() {
                *r = _mm512_loadu_si512(f.add((c0 + i) * pixpad + x0).cast());
            }
            // Pixel `j`'s 16 channels.
            let px = transpose16(r);
            for (j, v) in px.iter().enumerate().take(nx) {
                let d = out.add((j * cout + c0) * size);
                if size == 2 {
                    _mm256_storeu_si256(d.cast(), _mm512_cvtepi32_epi16(*v));
                } else {
                    _mm_storeu_si128(d.cast(), _mm512_cvtepi32_epi8(*v));
                }
            }
            c0 += 16;
        }
        for c in c0..cout {
            for j in 0..nx {
                let v = *f.add(c * pixpad + x0 + j);
                let d = out.add((j * cout + c) * size);
                if size == 2 {
                    d.cast::<i16>().write_unaligned(v as i16);
                } else {
                    d.write(v as u8);
                }
            }
        }
    }
}

/// Copies the weights of `r` channels (rows of `kl` from `w`, this part's `ch` a tap from `off`)
/// into `buf`, `[c][ky][kx][chp]` with the channels past `ch` zero: i8 (u8 path; the first half of
/// each channel's row) or i16 (i16 path). Returns the bytes per channel.
///
/// # Safety
/// The CPU has AVX-512 F and BW (for the compiler's vectorisation only).
#[target_feature(enable = "avx512f,avx512bw")]
#[allow(clippy::too_many_arguments)]
unsafe fn copy_weights(w: &[i8], kl: usize, off: usize, ch: usize, chp: usize, taps: usize, r: usize, kind: Kind, buf: &mut Vec<i16>) -> usize {
    let row = taps * chp; // values per channel
    let dst = scratch(buf, r * row);
    // SAFETY: the CPU has AVX-512 F and BW (this function's contract).
    unsafe { copy_weights_into(w, kl, off, ch, chp, taps, r, kind, dst) };
    2 * row
}

/// [`copy_weights`] into `dst` (`r k k chp` values).
///
/// # Safety
/// The CPU has AVX-512 F and BW (for the compiler's vectorisation only).
#[target_feature(enable = "avx512f,avx512bw")]
#[allow(clippy::too_many_arguments)]
unsafe fn copy_weights_into(w: &[i8], kl: usize, off: usize, ch: usize, chp: usize, taps: usize, r: usize, kind: Kind, dst: &mut [i16]) {
    let row = taps * chp; // values per channel
    let dst = dst.get_mut(..r * row).unwrap_or_default();
    if ch != chp {
        // The padding channels' zeros, in one go (the copies below fill the rest).
        dst.fill(0);
    }
    let rows = w.chunks(kl.max(1)).zip(dst.chunks_exact_mut(row.max(1)));
    match kind {
        Kind::U8 => {
            // Bytes: `row` of them at the start of each channel's `2 row`.
            for (src, dst) in rows {
                let src = src.get(off..off + taps * ch).unwrap_or_default();
                let dst: &mut [i8] = bytemuck::cast_slice_mut(dst);
                for (s, d) in src.chunks_exact(ch.max(1)).zip(dst.chunks_exact_mut(chp.max(1))) {
                    let head = d.get_mut(..ch).unwrap_or_default();
                    head.copy_from_slice(s.get(..head.len()).unwrap_or_default());
                }
            }
        }
        Kind::I16 => {
            for (src, dst) in rows {
                let src = src.get(off..off + taps * ch).unwrap_or_default();
                for (s, d) in src.chunks_exact(ch.max(1)).zip(dst.chunks_exact_mut(chp.max(1))) {
                    d.iter_mut().zip(s).for_each(|(d, s)| *d = *s as i16);
                }
            }
        }
    }
}

/// `fin[x] = clamp(finish_with(post, bias, sum[x]), lo, hi)` for every pixel (`lo..=hi` the output
/// type's range, as [`OutRow::set`] saturates). Eight pixels at a time when the sums are small
/// (`!wild`, see [`add_part`]) and `|bias| <` [`super::SHORT_MAX_BIAS`]: then `sum + bias + 2^7`
/// cannot overflow, so `>> 8` of it is [`finish_with`]'s rounding. `Sigmoid` and `Tanh` then read
/// their tables as [`crate::arith::lut`] does: the value saturated to i16, `u = v + 2^15`, the
/// entry pair at `u >> 6` by one 32-bit gather, `a + ((b - a) (u & 63) + 32) >> 6`.
///
/// # Safety
/// The CPU has AVX-512 F.
#[target_feature(enable = "avx512f")]
unsafe fn finish_channel(post: PostOp, bias: i64, wild: bool, sum: &[i64], fin: &mut [i32], lo: i32, hi: i32) {
    let fast = !wild && bias.unsigned_abs() < super::SHORT_MAX_BIAS;
    let table = match post {
        PostOp::None | PostOp::Relu => None,
        PostOp::Sigmoid => Some(crate::arith::lut::sigmoid_table().as_ptr()),
        PostOp::Tanh => Some(crate::arith::lut::tanh_table().as_ptr()),
    };
    let lo_v = if post == PostOp::Relu { lo.max(0) } else { lo };
    let (b, l, h) = (_mm512_set1_epi64(bias + (1 << (super::EXTRA_BITS - 1))), _mm512_set1_epi64(lo_v as i64), _mm512_set1_epi64(hi as i64));
    let (lo8, hi8) = (_mm256_set1_epi32(lo), _mm256_set1_epi32(hi));
    let n = sum.len().min(fin.len());
    let mut x = 0;
    if fast {
        let (sp, fp) = (sum.as_ptr(), fin.as_mut_ptr());
        while x + 8 <= n {
            // SAFETY: `x + 8 <= n` values of both; the CPU has AVX-512 F (and so AVX2); a table
            // holds 1025 i16 and each gather reads the 4 bytes at `2 i` for `i <= 1023`.
            unsafe {
                let v = _mm512_srai_epi64::<{ super::EXTRA_BITS }>(_mm512_add_epi64(_mm512_loadu_si512(sp.add(x).cast()), b));
                let out = match table {
                    None => _mm512_cvtepi64_epi32(_mm512_min_epi64(_mm512_max_epi64(v, l), h)),
                    Some(t) => _mm256_min_epi32(_mm256_max_epi32(table8(t, v), lo8), hi8),
                };
                _mm256_storeu_si256(fp.add(x).cast(), out);
            }
            x += 8;
        }
    }
    for (s, f) in sum.iter().zip(fin.iter_mut()).skip(x) {
        *f = finish_with(post, bias, *s).clamp(lo as i64, hi as i64) as i32;
    }
}

/// The sigmoid or tanh table `t` (1025 i16, [`crate::arith::lut`]'s) at 8 values `v` (i64), as
/// [`crate::arith::lut`] reads it: the value saturated to i16, `u = v + 2^15`, the entry pair at
/// `u >> 6` by one 32-bit gather, `a + ((b - a) (u & 63) + 32) >> 6`.
///
/// # Safety
/// The CPU has AVX-512 F; `t` points at 1025 i16 (each gather reads the 4 bytes at `2 i` for
/// `i <= 1023`).
#[target_feature(enable = "avx512f")]
#[inline]
unsafe fn table8(t: *const i16, v: __m512i) -> __m256i {
    let (i16_lo, i16_hi) = (_mm512_set1_epi64(i16::MIN as i64), _mm512_set1_epi64(i16::MAX as i64));
    let u = _mm256_add_epi32(_mm512_cvtepi64_epi32(_mm512_min_epi64(_mm512_max_epi64(v, i16_lo), i16_hi)), _mm256_set1_epi32(1 << 15));
    // SAFETY: indices `u >> 6 <= 1023` (the contract).
    let pair = unsafe { _mm256_i32gather_epi32::<2>(t.cast(), _mm256_srli_epi32::<6>(u)) };
    let (a, b) = (_mm256_srai_epi32::<16>(_mm256_slli_epi32::<16>(pair)), _mm256_srai_epi32::<16>(pair));
    let frac = _mm256_and_si256(u, _mm256_set1_epi32(63));
    let step = _mm256_srai_epi32::<6>(_mm256_add_epi32(_mm256_mullo_epi32(_mm256_sub_epi32(b, a), frac), _mm256_set1_epi32(32)));
    _mm256_add_epi32(a, step)
}

/// `sum[x] = sum[x].saturating_add(requantize(acc[x] - corr, m))` for every pixel (`sum[x] =
/// requantize(acc[x] - corr, m)` for the `first` part: the sums need no zeroing; `corr` takes
/// the `x + 128` packing of i8 activations back); returns whether a sum
/// may now be large (`wild`: some contribution took the scalar path).
///
/// Eight pixels at a time when `m` is short ([`super::short_ok`]), the eight accumulators fit in
/// i32 and no earlier contribution to this channel was wild: then `requantize` is
/// `(acc m + 2^(s-1)) >> s` in i64 (`vpmuldq`, an add, `vpsraq`), below `2^54` in magnitude, and
/// the sums stay below `2^63` for up to 511 parts, so a plain add is the saturating one.
///
/// # Safety
/// The CPU has AVX-512 F.
#[target_feature(enable = "avx512f")]
unsafe fn add_part(acc: &[i64], corr: i64, sum: &mut [i64], m: crate::arith::Multiplier, mut wild: bool, first: bool) -> bool {
    let short = super::short_ok(m);
    let n = acc.len().min(sum.len());
    // Vectors while the contributions are short (the first accumulator beyond i32 ends them:
    // from there on the sums may be large, so the rest takes the saturating formula).
    let mut x = 0;
    if short && !wild {
        let (mv, half, count) = (_mm512_set1_epi64(m.m as i64), _mm512_set1_epi64(1i64 << (m.shift - 1)), _mm_cvtsi64_si128(m.shift as i64));
        let (a, s, cv) = (acc.as_ptr(), sum.as_mut_ptr(), _mm512_set1_epi64(corr));
        while x + 8 <= n {
            // SAFETY: `x + 8 <= n` values of both; the CPU has AVX-512 F.
            unsafe {
                let v = _mm512_sub_epi64(_mm512_loadu_si512(a.add(x).cast()), cv);
                if _mm512_cmpeq_epi64_mask(v, _mm512_cvtepi32_epi64(_mm512_cvtepi64_epi32(v))) != 0xFF {
                    break;
                }
                let r = _mm512_sra_epi64(_mm512_add_epi64(_mm512_mul_epi32(v, mv), half), count);
                let r = if first { r } else { _mm512_add_epi64(_mm512_loadu_si512(s.add(x).cast()), r) };
                _mm512_storeu_si512(s.add(x).cast(), r);
            }
            x += 8;
        }
    }
    for (a, s) in acc.iter().zip(sum.iter_mut()).skip(x) {
        let a = a - corr;
        let r = requantize(a, m);
        wild |= !short || a != a as i32 as i64;
        *s = if first { r } else { s.saturating_add(r) };
    }
    wild
}

/// [`block`] for `r` channels (1 to [`BLOCK_C`]).
///
/// # Safety
/// As [`block`], for the first `r` pointers of `w`.
#[inline]
unsafe fn block_dispatch<const U8: bool>(r: usize, xt: *const i32, taps: &[Tap], n: usize, stride: usize, w: &[*const u8; BLOCK_C], s: *mut i64) {
    // SAFETY: forwarded.
    unsafe {
        match r {
            8 => block::<8, U8>(xt, taps, n, stride, w, s),
            4..=7 => {
                block::<4, U8>(xt, taps, n, stride, w, s);
                block_dispatch::<U8>(r - 4, xt, taps, n, stride, &shifted(w, 4), s.add(4 * stride));
            }
            2 | 3 => {
                block::<2, U8>(xt, taps, n, stride, w, s);
                block_dispatch::<U8>(r - 2, xt, taps, n, stride, &shifted(w, 2), s.add(2 * stride));
            }
            1 => block::<1, U8>(xt, taps, n, stride, w, s),
            _ => {}
        }
    }
}

/// `a` from element `by` on (the rest repeated from the start; never read).
fn shifted<T: Copy>(a: &[T; BLOCK_C], by: usize) -> [T; BLOCK_C] {
    let mut b = *a;
    b.rotate_left(by.min(BLOCK_C));
    b
}

/// Exact sums of `R` output channels over pixels `0 .. n`: for channel `i`, `s[i stride + x]`
/// is set to the dot products of its weight groups `w_i[t.w + g]` with activations
/// `xt[t.x + g t.gstride + x]` over every tap `t`, four u8 x i8 products a
/// group (`U8`) or two i16 x i16.
///
/// # Safety
/// The CPU has AVX-512 F, BW and VNNI; `n` is a multiple of 16 and at most `stride`; every
/// tap's activations for pixels below `n` lie in `xt`; `w[i]` for `i < R` points at
/// `4 (t.w + t.groups)` readable bytes for every tap `t`; each tap has at most one chunk of
/// groups; `s` points at `R` rows of `stride` i64.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
unsafe fn block<const R: usize, const U8: bool>(xt: *const i32, taps: &[Tap], n: usize, stride: usize, w: &[*const u8; BLOCK_C], s: *mut i64) {
    let mut x = 0;
    // SAFETY: the function's contract, for pixels `x .. x + 16 P <= n`.
    unsafe {
        while x + 2 * LANES <= n {
            tile::<R, 2, U8>(xt, taps, stride, x, w, s);
            x += 2 * LANES;
        }
        if x < n {
            tile::<R, 1, U8>(xt, taps, stride, x, w, s);
        }
    }
}

/// [`block`] for pixels `x .. x + 16 P`.
#[target_feature(enable = "avx512f,avx512bw,avx512vnni")]
#[inline]
#[allow(unused_assignments)] // the last flush sets `first` for nothing
unsafe fn tile<const R: usize, const P: usize, const U8: bool>(xt: *const i32, taps: &[Tap], stride: usize, x: usize, w: &[*const u8; BLOCK_C], s: *mut i64) {
    let chunk = if U8 { U8_CHUNK } else { I16_CHUNK };
    // SAFETY: see `block`. (Macros, not closures: a closure does not inherit the target
    // features, and its intrinsics would become calls.)
    unsafe {
        macro_rules! step {
            ($acc:ident, $at:expr, $wv:ident) => {
                let mut xs = [_mm512_setzero_si512(); P];
                for (v, xv) in xs.iter_mut().enumerate() {
                    *xv = _mm512_loadu_si512(xt.add($at + LANES * v).cast());
                }
                for (a, wv) in $acc.iter_mut().zip($wv) {
                    let wv = _mm512_set1_epi32(wv);
                    for (a, xv) in a.iter_mut().zip(xs) {
                        *a = if U8 { _mm512_dpbusd_epi32(*a, xv, wv) } else { _mm512_dpwssd_epi32(*a, xv, wv) };
                    }
                }
            };
        }
        // The first flush stores, later ones add (the sums need no zeroing first).
        let mut first = true;
        macro_rules! flush {
            ($acc:ident) => {
                for (i, a) in $acc.iter().enumerate() {
                    for (v, a) in a.iter().enumerate() {
                        let d = s.add(i * stride + x + LANES * v);
                        let mut lo = _mm512_cvtepi32_epi64(_mm512_castsi512_si256(*a));
                        let mut hi = _mm512_cvtepi32_epi64(_mm512_extracti64x4_epi64::<1>(*a));
                        if !first {
                            lo = _mm512_add_epi64(_mm512_loadu_si512(d.cast()), lo);
                            hi = _mm512_add_epi64(_mm512_loadu_si512(d.add(8).cast()), hi);
                        }
                        _mm512_storeu_si512(d.cast(), lo);
                        _mm512_storeu_si512(d.add(8).cast(), hi);
                    }
                }
                first = false;
            };
        }
        let mut acc = [[_mm512_setzero_si512(); P]; R];
        let mut count = 0;
        for t in taps {
            if count + t.groups > chunk {
                flush!(acc);
                acc = [[_mm512_setzero_si512(); P]; R];
                count = 0;
            }
            let base = t.x + x;
            for g in 0..t.groups {
                let mut wv = [0i32; R];
                for (i, wv) in wv.iter_mut().enumerate() {
                    *wv = w.as_ptr().add(i).read().add(4 * (t.w + g)).cast::<i32>().read_unaligned();
                }
                step!(acc, base + g * t.gstride, wv);
            }
            count += t.groups;
        }
        flush!(acc);
    }
}

/// One transposition task: indices `i0..i1` of plane `plane` (`ky stride + phase`) of a part's
/// transposed rows. A column's `ch` values, padded with zeros to `chp` (a multiple of the group
/// size), make `cg = chp / per` groups. With `lead` zero columns in front (`pad` rounded up to a
/// multiple of the stride `s`), padded column `pc = col + lead` goes to phase `pc % s`, index
/// `pc / s`; output pixel `x` of tap `kx` reads padded column `s x + d` (`d = kx + lead - pad`):
/// phase `d % s`, index `x + d / s`. So group `g` of index `i` is at
/// `xt_at + (plane cg + g) tw + i` (zeros where no real column is), and tap `(ky, kx)` starts at
/// index `d / s` of its plane: `x + d / s < tw` for every pixel below `pixpad` ([`run`]). A
/// layout for a range of output pixels from `x0` on ([`split_task`]) starts at column `col0 = s
/// x0` of the row: its columns are the row's shifted by `col0`, real ones where the row has them.
///
/// # Safety
/// The CPU has AVX-512 F and BW (for the compiler's vectorisation only); the entries lie in the
/// buffer behind `xt` and no other task touches them.
#[target_feature(enable = "avx512f,avx512bw")]
#[allow(clippy::too_many_arguments)]
#[inline(never)]
unsafe fn transpose_task<T: Elem>(row: Option<&[T]>, plan: &PartPlan, kind: Kind, stride: usize, lead: usize, w_in: usize, col0: usize, plane: usize, i0: usize, i1: usize, zero: i32, xt: &Shared<i32>) {
    let (ch, tw) = (plan.ch, plan.tw);
    let cg = plan.chp / kind.per();
    let phase = plane % stride;
    let base = plan.xt_at + plane * cg * tw;
    // Zeros for indices `a .. b` of every group (padding columns and a missing row).
    let zeros = |a: usize, b: usize| {
        for g in 0..cg {
            // SAFETY: the caller's guarantee (`i0 <= a <= b <= i1`).
            unsafe { xt.slice(base + g * tw + a, b - a) }.fill(zero);
        }
    };
    let Some(row) = row else {
        zeros(i0, i1);
        return;
    };
    let cb = ch * core::mem::size_of::<T>(); // bytes a column
    let bytes = bytes_of(row);
    let cols = w_in.min(bytes.len() / cb.max(1));
    // Column of index `i` (`None` in the padding; the layout's column 0 is the row's `col0`).
    let col_of = |i: usize| (i * stride + phase + col0).checked_sub(lead).filter(|c| *c < cols);
    // Blocks of 16 indices whose columns are all real, 16 whole groups at a time: 16 columns
    // loaded, transposed in registers, one store per group.
    // Whole groups (`cb = 4 cg`: 16 x 16 transpositions, then gathers), or a last group shorter
    // than 4 bytes (e.g. 3 u8 channels: gathers whose last group is masked; a block then also
    // needs the 1 to 3 bytes after its last column, which the row's last columns lack).
    let whole = cb == 4 * cg;
    let vector = cb.div_ceil(4) == cg && cg > 0 && bytes.len() < i32::MAX as usize;
    let readable = |c: usize| c * cb + 4 * cg <= bytes.len();
    let mut i = i0;
    while i < i1 {
        let blk = (i1 - i).min(16);
        // The block's real columns: a run of indices (`col_of` rises with `i`), those in the
        // padding (a row's first and last blocks) read as zero.
        let real: u16 = (0..blk).filter(|&j| col_of(i + j).is_some()).fold(0, |m, j| m | 1 << j);
        let last_real = (0..blk).rev().find_map(|j| col_of(i + j));
        // (A vector block writes every entry it covers: 16 indices, all `cg` groups.)
        if vector && blk == 16 && last_real.is_some_and(readable) {
            let mut gb = 0;
            while whole && gb + 16 <= cg {
                let mut r = [_mm512_set1_epi32(zero); 16];
                for (j, r) in r.iter_mut().enumerate() {
                    let Some(col) = col_of(i + j) else {
                        continue; // padding: the zero value
                    };
                    let at = col * cb + 4 * gb;
                    if let Some(src) = bytes.get(at..at + 64) {
                        // SAFETY: 64 readable bytes.
                        *r = _mm512_xor_si512(unsafe { _mm512_loadu_si512(src.as_ptr().cast()) }, _mm512_set1_epi32(zero));
                    }
                }
                for (g, v) in transpose16(r).iter().enumerate() {
                    // SAFETY: group `gb + g < cg`, indices `i .. i + 16 <= i1`: this task's entries.
                    unsafe { _mm512_storeu_si512(xt.0.add(base + (gb + g) * tw + i).cast(), *v) };
                }
                gb += 16;
            }
            // The groups past the last multiple of 16 (all of them for fewer than 16 groups,
            // e.g. 32 u8 channels): one gather of the 16 columns per group.
            if gb < cg {
                let mut at = [0i32; 16];
                for (j, a) in at.iter_mut().enumerate() {
                    // (`bytes.len() < 2^31`: `vector`; padding lanes are masked off.)
                    *a = (col_of(i + j).unwrap_or(0) * cb) as i32;
                }
                // SAFETY: 64 readable bytes.
                let mut idx = _mm512_add_epi32(unsafe { _mm512_loadu_si512(at.as_ptr().cast()) }, _mm512_set1_epi32(4 * gb as i32));
                for g in gb..cg {
                    // The bytes of group `g` that belong to the column (the rest reads as zero).
                    let have = (cb - 4 * g).min(4);
                    let mask = _mm512_set1_epi32((u32::MAX >> (32 - 8 * have as u32)) as i32);
                    // SAFETY: each lane of a real column (`real`; the others read nothing and
                    // give 0) reads 4 bytes at `col cb + 4 g`, with `col cb + 4 cg <=
                    // bytes.len()` (`readable` of the last, columns ascending in `i`): inside
                    // `bytes`; the store writes group `g < cg`, indices `i .. i + 16 <= i1`: this
                    // task's entries.
                    unsafe {
                        let got = _mm512_mask_i32gather_epi32::<1>(_mm512_setzero_si512(), real, idx, bytes.as_ptr().cast());
                        let v = _mm512_and_si512(got, mask);
                        _mm512_storeu_si512(xt.0.add(base + g * tw + i).cast(), _mm512_xor_si512(v, _mm512_set1_epi32(zero)));
                    }
                    idx = _mm512_add_epi32(idx, _mm512_set1_epi32(4));
                }
            }
        } else {
            zeros(i, i + blk);
            for i in i..i + blk {
                let Some(col) = col_of(i) else {
                    continue;
                };
                let src = bytes.get(col * cb..(col + 1) * cb).unwrap_or_default();
                // SAFETY: the caller's guarantee (group `g < cg` of index `i`).
                let put = |g: usize, v: u32| unsafe { xt.0.add(base + g * tw + i).write((v ^ zero as u32) as i32) };
                if cb.is_multiple_of(4) {
                    for (g, v) in src.chunks_exact(4).enumerate().take(cg) {
                        if let &[a, b, c, e] = v {
                            put(g, u32::from_le_bytes([a, b, c, e]));
                        }
                    }
                } else {
                    // A last group past the column's values: zero bytes there.
                    for (g, v) in src.chunks(4).enumerate().take(cg) {
                        let mut b = [0u8; 4];
                        b.iter_mut().zip(v).for_each(|(b, v)| *b = *v);
                        put(g, u32::from_le_bytes(b));
                    }
                }
            }
        }
        i += blk;
    }
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::super::super::testutil::Rng;
    use super::super::{BiasRef, MultRef, conv_plain, encode_bias, encode_mults};
    use super::*;
    use crate::arith::Multiplier;
    use crate::model::graph::PostOp;

    /// The matrix product against the plain twin on random and extreme layers: u8, i8 and i16
    /// activations, parts of whole and partial groups, strides 1 and 2, odd channel counts,
    /// patches long enough for several i16 chunks.
    fn check<T: Elem>(seed: u64, make: &dyn Fn(&mut Rng) -> T, k: usize, stride: usize, parts: &[usize], cout: usize, post: PostOp, w: usize, extreme: bool) {
        let mut r = Rng(seed);
        let h = 5;
        let kl = k * k * parts.iter().sum::<usize>();
        let wts: Vec<i8> = (0..cout * kl).map(|_| if extreme { -128 } else { r.i8() }).collect();
        let b: Vec<i64> = (0..cout).map(|_| (r.next() as i64) >> 44).collect();
        // (Extreme sums, beyond i32, need shifts up to 62 to come out unsaturated: the
        // requantisation of such sums is then seen in the outputs.)
        let shifts = if extreme { 43 } else { 20 };
        let m: Vec<Multiplier> =
            (0..cout * parts.len()).map(|_| Multiplier { m: (1 << 30) + (r.below(1 << 30) as i32), shift: 20 + r.below(shifts) as u8 }).collect();
        let (bias, mult) = (encode_bias(&b), encode_mults(&m));
        let p = ConvParams { k, stride, parts, cout, weights: &wts, bias: BiasRef(&bias), mult: MultRef(&mult), post };
        let tensors: Vec<Vec<T>> = parts.iter().map(|&c| (0..h * w * c).map(|_| make(&mut r)).collect()).collect();
        let refs: Vec<&[T]> = tensors.iter().map(|t| t.as_slice()).collect();
        let (ho, wo) = ((h + 2 * (k / 2) - k) / stride + 1, p.out_width(w));
        // Each output type (its saturation): i16, i8, u8.
        macro_rules! each_type {
            ($t:ty, $variant:ident) => {{
                let len = ho * wo * cout;
                let (mut want, mut got) = (vec![<$t>::default(); len], vec![<$t>::default(); len]);
                conv_plain(&p, &refs, h, w, &mut OutRow::$variant(&mut want));
                // Outside an engine frame (weights re-laid per call), then inside one (once).
                for scoped in [false, true] {
                    let _frame = scoped.then(FrameScope::new);
                    got.fill(<$t>::default());
                    for (oy, o) in got.chunks_exact_mut(wo * cout).enumerate() {
                        let rows: Vec<PartRows<T>> =
                            tensors.iter().zip(parts).map(|(t, &c)| PartRows::of_tensor(t, h, w * c, oy, k, stride)).collect();
                        assert!(conv_row(&p, &rows, w, &mut OutRow::$variant(o)), "path not taken");
                    }
                    let what = format!("k {k} s {stride} parts {parts:?} cout {cout} w {w} extreme {extreme} {post:?} {} frame {scoped}", stringify!($t));
                    assert_eq!(want, got, "{what}");
                }
                want.iter().any(|v| *v != 0)
            }};
        }
        // One thread, then several (the channel blocks as tasks, or ranges of pixels when the
        // pool is free), then ranges of pixels forced (1 to 5 of them, on 1 to 3 threads): the
        // same integers.
        let mut nonzero = vec![];
        for (threads, ranges) in [(1, None), (3, None), (1, Some(1)), (3, Some(2)), (2, Some(3)), (1, Some(5))] {
            pool::set_threads(threads);
            FORCE_RANGES.with(|f| f.set(ranges));
            nonzero.extend([each_type!(i16, I16), each_type!(i8, I8), each_type!(u8, U8)]);
        }
        FORCE_RANGES.with(|f| f.set(None));
        pool::set_threads(1);
        assert!(nonzero.iter().any(|n| *n), "all zero: k {k} s {stride} parts {parts:?} cout {cout} w {w} {post:?}");
    }

    /// The epilogue against [`finish_with`] for every activation, on sums whose rounded value
    /// sweeps the whole i16 range and beyond (the tables' every entry pair and fraction, the
    /// saturation to i16 before them), for each output type's range.
    #[test]
    fn finish_matches_the_formula() {
        if !has_avx512() {
            return;
        }
        let sums: Vec<i64> = (-(40_000i64 << 8)..(40_000i64 << 8)).step_by(37).chain([i64::MIN / 4, i64::MAX / 4, 1 << 40, -(1 << 40)]).collect();
        let mut fin = vec![0i32; sums.len()];
        for post in [PostOp::None, PostOp::Relu, PostOp::Sigmoid, PostOp::Tanh] {
            for (lo, hi) in [(i16::MIN as i32, i16::MAX as i32), (i8::MIN as i32, i8::MAX as i32), (0, 255)] {
                for bias in [0, -300, 77 << 8] {
                    // SAFETY: the CPU has AVX-512 F (checked).
                    unsafe { finish_channel(post, bias, false, &sums, &mut fin, lo, hi) };
                    for (s, f) in sums.iter().zip(&fin) {
                        assert_eq!(*f as i64, finish_with(post, bias, *s).clamp(lo as i64, hi as i64), "{post:?} sum {s} bias {bias}");
                    }
                }
            }
        }
    }

    /// A frame's re-laid weights are its own: the next frame sees a table changed in place (the
    /// same address and length), and two layers of one frame do not share copies.
    #[test]
    fn frames_relay_weights_of_their_own() {
        if !has_avx512() {
            return;
        }
        // 9 channels out: the transposing path; 18: `direct16`.
        for cout in [9, 18] {
            relay_case(cout);
        }
    }

    fn relay_case(cout: usize) {
        let mut r = Rng(5);
        let (k, parts, w) = (3, &[8usize, 3][..], 20);
        let kl = k * k * parts.iter().sum::<usize>();
        let b: Vec<i64> = (0..cout).map(|_| (r.next() as i64) >> 50).collect();
        let m: Vec<Multiplier> = (0..cout * parts.len()).map(|_| Multiplier { m: 1 << 30, shift: 24 }).collect();
        let (bias, mult) = (encode_bias(&b), encode_mults(&m));
        let x: Vec<Vec<i16>> = parts.iter().map(|&c| (0..3 * w * c).map(|_| r.i16() >> 4).collect()).collect();
        let mut wts: Vec<i8> = (0..cout * kl).map(|_| r.i8()).collect();
        let other: Vec<i8> = (0..cout * kl).map(|_| r.i8()).collect();
        let row = |wts: &[i8]| {
            let p = ConvParams { k, stride: 1, parts, cout, weights: wts, bias: BiasRef(&bias), mult: MultRef(&mult), post: PostOp::None };
            let rows: Vec<PartRows<i16>> = x.iter().zip(parts).map(|(t, &c)| PartRows::of_tensor(t, 3, w * c, 1, k, 1)).collect();
            let mut o = vec![0i16; w * cout];
            assert!(conv_row(&p, &rows, w, &mut OutRow::I16(&mut o)));
            o
        };
        let (want_a, want_b) = (row(&wts), row(&other));
        assert_ne!(want_a, want_b);
        {
            let _frame = FrameScope::new();
            assert_eq!(row(&wts), want_a);
            assert_eq!(row(&other), want_b, "another layer in the same frame");
            assert_eq!(row(&wts), want_a, "the first layer again");
        }
        wts.copy_from_slice(&other);
        let _frame = FrameScope::new();
        assert_eq!(row(&wts), want_b, "a table changed in place between frames");
    }

    /// A constant part's kept sums ([`with_constant_part`]) give the sums computed afresh, and
    /// are not reused where the part's rows changed, in the frame or the next one.
    #[test]
    fn constant_parts_are_reused_only_for_the_same_rows() {
        if !has_avx512() {
            return;
        }
        // 10 channels out: the transposing path; 20: `direct16`.
        for cout in [10, 20] {
            constant_parts_case(cout, 6, false);
        }
        // A context of 128 channels at -2^15 against weights of -128, sums beyond i32: a wide
        // part, which `direct16` does not keep (computed in every call, the portable formula for
        // those blocks).
        constant_parts_case(16, 128, true);
    }

    fn constant_parts_case(cout: usize, cc: usize, extreme: bool) {
        let mut r = Rng(6);
        let (k, parts, w, h) = (3, &[8usize, cc][..], 37, 4);
        let kl = k * k * parts.iter().sum::<usize>();
        let wts: Vec<i8> = (0..cout * kl).map(|_| if extreme { -128 } else { r.i8() }).collect();
        let b: Vec<i64> = (0..cout).map(|_| (r.next() as i64) >> 50).collect();
        let shift = if extreme { 50 } else { 24 };
        let m: Vec<Multiplier> = (0..cout * parts.len()).map(|_| Multiplier { m: 1 << 30, shift }).collect();
        let (bias, mult) = (encode_bias(&b), encode_mults(&m));
        let p = ConvParams { k, stride: 1, parts, cout, weights: &wts, bias: BiasRef(&bias), mult: MultRef(&mult), post: PostOp::None };
        let a: Vec<i16> = (0..h * w * 8).map(|_| r.i16() >> 2).collect();
        let ctx: Vec<i16> = (0..h * w * cc).map(|_| if extreme { i16::MIN } else { r.i16() >> 2 }).collect();
        // Every output row, the context part marked constant or not.
        let frame = |ctx: &[i16], constant: bool| {
            let mut o = vec![0i16; h * w * cout];
            for (y, o) in o.chunks_exact_mut(w * cout).enumerate() {
                let rows = [PartRows::of_tensor(&a, h, w * 8, y, k, 1), PartRows::of_tensor(ctx, h, w * cc, y, k, 1)];
                let mut call = || assert!(conv_row(&p, &rows, w, &mut OutRow::I16(o)));
                if constant { with_constant_part(1, y, call) } else { call() }
            }
            o
        };
        // The one-thread path, then ranges of pixels (whose memo rows are a range's pixels).
        for ranges in [None, Some(2), Some(3)] {
            FORCE_RANGES.with(|f| f.set(ranges));
            let mut ctx = ctx.clone();
            let want = frame(&ctx, false);
            let _f = FrameScope::new();
            assert_eq!(frame(&ctx, true), want, "sums computed and kept");
            assert_eq!(frame(&ctx, true), want, "sums reused");
            // The context changes in the same frame (one value of row 2, or the whole row for
            // the extreme one, whose single values do not show): rows 1 to 3 read it.
            if extreme {
                ctx[2 * w * cc..3 * w * cc].fill(i16::MAX);
            } else {
                ctx[2 * w * cc + 5] ^= 0x155;
            }
            let want2 = frame(&ctx, false);
            assert_ne!(want, want2);
            assert_eq!(frame(&ctx, true), want2, "changed rows recomputed");
            drop(_f);
            let _f = FrameScope::new();
            ctx[5] ^= 0x2A;
            assert_eq!(frame(&ctx, true), frame(&ctx, false), "the next frame");
        }
        FORCE_RANGES.with(|f| f.set(None));
    }

    /// Rows longer than the layer's width (a buffer with more columns) are read to `w_in`
    /// columns only: the columns past it are padding, as in the portable path.
    #[test]
    fn columns_past_the_width_are_padding() {
        if !has_avx512() {
            return;
        }
        let mut r = Rng(9);
        for (k, stride, parts, cout) in [(3, 1, &[8usize, 3][..], 32), (3, 1, &[16][..], 16), (5, 2, &[4, 1][..], 20)] {
            let (h, w, extra) = (4, 19, 3);
            let kl = k * k * parts.iter().sum::<usize>();
            let wts: Vec<i8> = (0..cout * kl).map(|_| r.i8()).collect();
            let b: Vec<i64> = (0..cout).map(|_| (r.next() as i64) >> 50).collect();
            let m: Vec<Multiplier> = (0..cout * parts.len()).map(|_| Multiplier { m: 1 << 30, shift: 24 }).collect();
            let (bias, mult) = (encode_bias(&b), encode_mults(&m));
            let p = ConvParams { k, stride, parts, cout, weights: &wts, bias: BiasRef(&bias), mult: MultRef(&mult), post: PostOp::None };
            // Each part `w + extra` columns wide (no zero in them), and its first `w` columns.
            let wide: Vec<Vec<i16>> = parts.iter().map(|&c| (0..h * (w + extra) * c).map(|_| r.i16() | 1).collect()).collect();
            let narrow: Vec<Vec<i16>> = wide.iter().zip(parts).map(|(t, &c)| t.chunks_exact((w + extra) * c).flat_map(|row| row[..w * c].to_vec()).collect()).collect();
            let refs: Vec<&[i16]> = narrow.iter().map(|t| t.as_slice()).collect();
            let (ho, wo) = ((h + 2 * (k / 2) - k) / stride + 1, p.out_width(w));
            let mut want = vec![0i16; ho * wo * cout];
            conv_plain(&p, &refs, h, w, &mut OutRow::I16(&mut want));
            let mut got = vec![0i16; ho * wo * cout];
            for (oy, o) in got.chunks_exact_mut(wo * cout).enumerate() {
                let rows: Vec<PartRows<i16>> = wide.iter().zip(parts).map(|(t, &c)| PartRows::of_tensor(t, h, (w + extra) * c, oy, k, stride)).collect();
                assert!(conv_row(&p, &rows, w, &mut OutRow::I16(o)));
            }
            assert_eq!(want, got, "k {k} s {stride} parts {parts:?} cout {cout}");
        }
    }

    #[test]
    fn matrix_product_matches_plain_twin() {
        if !has_avx512() {
            eprintln!("no AVX-512 VNNI: the 512-bit convolution is not taken on this CPU");
            return;
        }
        let u8s = |r: &mut Rng| r.i8() as u8;
        let i8s = |r: &mut Rng| r.i8();
        let i16s = |r: &mut Rng| r.i16();
        let mut seed = 1;
        for post in [PostOp::None, PostOp::Relu, PostOp::Tanh, PostOp::Sigmoid] {
            for w in [1, 9, 16, 33, 57] {
                for (k, stride, parts, cout) in
                    [
                    (3, 1, &[8, 1, 16][..], 5),
                    (3, 2, &[6][..], 9),
                    (1, 1, &[12][..], 17),
                    (7, 2, &[3][..], 4),
                    (3, 1, &[64, 4][..], 24),
                    (3, 2, &[8, 4][..], 7),
                    (3, 2, &[64, 36][..], 9),
                    (1, 2, &[16][..], 5),
                    (5, 2, &[12, 2][..], 3),
                    // Parts of 7 to 15 groups whose last one is partial: u8 7 and 8 groups,
                    // i16 13 and 15.
                    (3, 1, &[25, 30][..], 6),
                    // One u8 part, 3x3, stride 1 or 2, channels out in sixteens: the rows with the
                    // output channels along the vector (`direct`; 16, 32 and 48 channels out:
                    // blocks of 32, then one of 16).
                    (3, 1, &[32][..], 32),
                    (3, 1, &[64][..], 48),
                    (3, 1, &[4][..], 16),
                    (3, 2, &[32][..], 48),
                    (3, 2, &[4][..], 16),
                    // ... and 1x1, stride 1 or 2 (the trunk's strided shortcuts, the MGA keys).
                    (1, 2, &[32][..], 48),
                    (1, 1, &[64][..], 32),
                    (1, 2, &[12][..], 16),
                    // i16 rows with the output channels along the vector (`direct16`): the GRU
                    // gates' six parts with odd counts (a pair reads the next pixel's first
                    // value), channels out not a multiple of 16 (a partial last vector), kernels
                    // 1, 5 and 7, stride 2.
                    (3, 1, &[8, 7, 1, 8, 6, 9][..], 20),
                    (3, 1, &[3, 1][..], 31),
                    (1, 1, &[5][..], 16),
                    (7, 2, &[3][..], 32),
                    (5, 2, &[12, 2][..], 17),
                    // i16 rows with 1 to 15 channels out (`few`): the heads' last layers (the
                    // MGA mask's parts, 1 and 2 channels out), four channels at a time then the
                    // rest, kernel rows longer than a vector, stride 2.
                    (3, 1, &[64, 36, 1, 1][..], 1),
                    (3, 1, &[41][..], 2),
                    (3, 1, &[13, 2][..], 7),
                    (1, 1, &[33][..], 15),
                    (3, 2, &[20][..], 3),
                ]
                {
                    seed += 1;
                    check(seed, &u8s, k, stride, parts, cout, post, w, false);
                    check(seed, &i8s, k, stride, parts, cout, post, w, false);
                    check(seed, &i16s, k, stride, parts, cout, post, w, false);
                }
            }
        }
        // A row long enough for the write-out on the pool (`PARALLEL_OUTPUTS`).
        check(90, &u8s, 1, 1, &[8], 64, PostOp::Relu, 260, false);
        check(91, &i16s, 3, 1, &[16, 2], 70, PostOp::None, 240, false);
        // Extremes: every weight -128, activations at their most negative (i16: the products'
        // largest magnitude, 2^22) and largest, over patches of several i16 chunks (3 3 128).
        for w in [7, 40] {
            check(7, &|_| i16::MIN, 3, 1, &[128], 8, PostOp::None, w, true);
            check(8, &|r: &mut Rng| if r.next() % 2 == 0 { i16::MIN } else { i16::MAX }, 3, 1, &[128, 2], 3, PostOp::None, w, true);
            check(9, &|_| u8::MAX, 3, 1, &[128], 8, PostOp::None, w, true);
            check(10, &|_| i8::MIN, 3, 1, &[64], 11, PostOp::None, w, true);
            // One tap of more than an i16 chunk (520 / 2 = 260 groups > 255).
            check(11, &|_| i16::MIN, 1, 1, &[520], 4, PostOp::None, w, true);
            // A tame first part (sums within i32: `add_part`'s vector formula), then an extreme
            // one (totals beyond i32: the scalar formula, added to the first part's).
            check(12, &|_| i16::MIN, 3, 1, &[2, 128], 8, PostOp::None, w, true);
            check(13, &|r: &mut Rng| if r.next() % 2 == 0 { i16::MIN } else { i16::MAX }, 3, 1, &[2, 128], 16, PostOp::None, w, true);
            // The `direct` rows at their extremes: u8 255 against weights -128 over 128
            // channels, sums near -2^22.
            check(14, &|_| u8::MAX, 3, 1, &[128], 32, PostOp::None, w, true);
            check(15, &|r: &mut Rng| if r.next() % 2 == 0 { 0 } else { u8::MAX }, 3, 1, &[128], 16, PostOp::Relu, w, true);
            check(19, &|_| u8::MAX, 1, 2, &[1152], 32, PostOp::None, w, true);
            // The `direct16` rows at their extremes: sums beyond i32 in some blocks (every
            // value -2^15 against -128: the scalar formula for those blocks), several i32 chunks
            // a part (3 3 128 / 2 = 576 pairs), a tame part before an extreme one.
            check(16, &|_| i16::MIN, 3, 1, &[128], 32, PostOp::None, w, true);
            check(17, &|r: &mut Rng| if r.next() % 2 == 0 { i16::MIN } else { i16::MAX }, 3, 1, &[2, 128, 1], 48, PostOp::Tanh, w, true);
            check(18, &|r: &mut Rng| if r.next() % 3 == 0 { i16::MIN } else { r.i16() }, 3, 1, &[64, 96], 16, PostOp::Relu, w, true);
        }
    }
}
