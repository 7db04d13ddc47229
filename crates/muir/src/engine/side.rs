//! Host, two or more threads (feature `std`): an iteration's MUD and MGA value passes on a second
//! thread beside the two 1/16 ConvGRU steps on this one.
//!
//! Why: those passes work on rows of 30-80 pixels at 1/8 and 1/16 resolution. Split over the
//! kernel pool by pixels, each thread streams a layer's whole weights for a handful of pixels
//! and waits on the other once per row: on two cores they ran 1.04-1.15x faster than on one
//! (`muir run --timings`). The two sides have no data in common but what both only read (the
//! features, the context and the 1/8 state), and take about the same time (Teddy, one thread:
//! 34 ms for the 1/16 steps against 33 ms for MUD and the MGA values), so side by side each runs
//! at one thread's speed on its own core.
//!
//! The 1/16 steps read `pool2x(net08)`; this thread computes it into a buffer of its own first,
//! so that the other thread can borrow `net08` (which it only reads) for the whole pass. The
//! other thread's line buffers and per-pixel scratch are its own too (the plan's sizes, laid out
//! as in the arena). The integers are those of the sequential order: each pass computes what it
//! computes there from the same inputs.
#![deny(clippy::indexing_slicing)]

use std::sync::mpsc;
#[cfg(feature = "internals")]
use std::sync::atomic::{AtomicUsize, Ordering};

use super::host_rows;
use super::phase_times::Phase;
use super::plan::{Buf, PixelBufs, Plan};
use super::refine::{self, Ctx};
use super::ring::{Carver, chunk, copy_row};
use crate::kernels::pool::scratch;

/// The second thread's buffers, kept for the frame's iterations.
#[derive(Default)]
pub(super) struct SideBuffers {
    /// Its per-pixel scratch and line buffers (u64: 8-byte aligned).
    own: Vec<u64>,
    /// `pool2x(net08)`, `h16 x w16 x hidden`.
    pooled: Vec<i16>,
    /// The MGA output of the iteration, `h8 x w8 x hidden`.
    glb: Vec<i16>,
    /// The MGA values of the iteration, as the plan's buffer.
    values: Vec<i16>,
}

/// The kernel pool held while both threads run (each one's kernels on its own thread: the
/// pool's workers would only compete with them for the cores), and released by the thread that
/// finishes first: the other one's kernels then have the workers for the rest.
struct Held(std::sync::Mutex<Option<crate::kernels::pool::Hold>>);

impl Held {
    fn new() -> Self {
        Held(std::sync::Mutex::new(Some(crate::kernels::pool::hold())))
    }

    fn release(&self) {
        if let Ok(mut h) = self.0.lock() {
            h.take();
        }
    }

    /// Releases when the returned guard is dropped (also when its thread unwinds).
    fn release_on_drop(&self) -> impl Drop + '_ {
        struct Release<'h>(&'h Held);
        impl Drop for Release<'_> {
            fn drop(&mut self) {
                self.0.release();
            }
        }
        Release(self)
    }
}

/// Starts `f` on the other thread of `s`: it holds its own copies of the layers' re-laid weights
/// (see `Engine::run_iters`) and releases `held` when done (also when it unwinds).
fn spawn_other<'scope, T: Send + 'scope>(s: &'scope std::thread::Scope<'scope, '_>, held: &'scope Held, f: impl FnOnce() -> T + Send + 'scope) -> std::thread::ScopedJoinHandle<'scope, T> {
    s.spawn(move || {
        let _release = held.release_on_drop();
        #[cfg(target_arch = "x86_64")]
        let _frame = crate::kernels::conv::FrameScope::new();
        f()
    })
}

/// What the other thread returned; its panic (a bug in a pass, not a consequence of input) goes
/// on unwinding here.
fn joined<T>(other: std::thread::ScopedJoinHandle<'_, T>) -> T {
    match other.join() {
        Ok(back) => back,
        Err(panic) => std::panic::resume_unwind(panic),
    }
}

/// The other thread's per-pixel scratch and line buffers: the plan's sizes, laid out from 0 in
/// `own`.
fn other_scratch<'s>(plan: &Plan, own: &'s mut Vec<u64>, hidden: usize) -> (refine::Pixel<'s>, &'s mut [u8]) {
    let mut at = 0;
    let mut next = |len: usize| {
        let b = Buf { at, len };
        at = (at + len).div_ceil(8) * 8;
        b
    };
    let p = plan.pixel;
    let px = PixelBufs { patch: next(p.patch.len), window: next(p.window.len), prefix: next(p.prefix.len), peaks_row: next(p.peaks_row.len), attn: next(p.attn.len), logits: next(p.logits.len) };
    let rings = next(plan.refine.rings.len);
    let mut cv = Carver::new(bytemuck::cast_slice_mut(scratch(own, at / 8)));
    let pixel = super::pixel_scratch(&mut cv, &px, hidden);
    (pixel, cv.raw(rings))
}

/// The frame's setup: UFI on this thread, and the MGA keys and softmax statistics (as the model
/// has them) on a second one. They share nothing but what both only read (the context): UFI
/// writes the 1/8 state, the disparity and the uncertainty, the statistics pass the keys, the
/// statistics and the kept softmax weights (moved to this thread afterwards). `lap(phase)` ends a
/// phase of the timer here: ufi when UFI is done, mga setup when the other thread is too.
pub(super) fn setup(c: &mut Ctx<'_, '_, '_>, plan: &Plan, side: &mut SideBuffers, max_d8: usize, mut lap: impl FnMut(Phase)) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (pixel, rings) = other_scratch(plan, &mut side.own, cfg.hidden_dim);
    let inp08 = c.frame.inp08;
    let (keys, stats) = (core::mem::take(&mut c.st.keys), core::mem::take(&mut c.st.stats));
    // This thread's attention state, the previous frame's: its buffers (the kept softmax
    // weights, 15 MB at 450 x 375 and 107 MB at 1242 x 375) go to the other thread to be filled
    // again. A thread started for the pass has none, and allocating them afresh in every frame
    // cost 3,300 page faults a frame at 450 x 375 (`--repeat`, two threads).
    let previous = host_rows::take_attention();
    let held = Held::new();
    let (keys, stats, attention) = std::thread::scope(|s| {
        let other = spawn_other(s, &held, move || {
            host_rows::lend_attention(previous);
            let mut o = Ctx {
                m,
                g,
                frame: refine::Frame { f1: &[], f2: &[], net08: &mut [], net16: &mut [], inp08, inp16: &[] },
                st: refine::State { flow: &mut [], mask: &mut [], u: &mut [], keys: &mut *keys, stats: &mut *stats, values: &mut [] },
                px: pixel,
                rings,
            };
            refine::mga_setup(&mut o);
            (keys, stats, host_rows::take_attention())
        });
        if cfg.ufi {
            refine::ufi(c, max_d8);
        }
        held.release();
        lap(Phase::Ufi);
        let back = joined(other);
        lap(Phase::MgaSetup);
        back
    });
    host_rows::lend_attention(attention);
    (c.st.keys, c.st.stats) = (keys, stats);
}

/// Tests (`internals`): while set, the second thread takes an MGA output row only once this one
/// has taken more than it (this one takes a row whenever it waits for one), so that both
/// threads' rows are tested whatever the timing.
#[cfg(feature = "internals")]
pub static ALTERNATE_GLB_ROWS: std::sync::atomic::AtomicBool = std::sync::atomic::AtomicBool::new(false);

/// One iteration up to the disparity head: the MUD pass and the MGA value pass on a second
/// thread beside the two 1/16 ConvGRU steps, the motion encoder and the 1/8 ConvGRU on this one;
/// the MGA output rows on both. `lap(phase)` ends a phase of the timer here: gru16 when the 1/16
/// steps are done, mud when the other thread has given back the state (MUD and the MGA values
/// done), gru08 at the end.
///
/// The MGA rows: the other thread takes them in order from the top as soon as it has laid out
/// the pass; this one, whenever the 1/8 ConvGRU needs a row not done yet, takes the next row no
/// one has taken rather than wait. (Left to the other thread alone, the rows were the longer
/// side: on KITTI this thread waited 26-28 ms an iteration of 81.) Any row is the same integers
/// on either thread ([`refine::GlbPass::row`]).
pub(super) fn iteration(c: &mut Ctx<'_, '_, '_>, plan: &Plan, side: &mut SideBuffers, mut lap: impl FnMut(Phase)) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let row16 = g.w16 * cfg.hidden_dim;
    let pooled = scratch(&mut side.pooled, g.h16 * row16);
    refine::pool2x_state(m, &g, c.frame.net08, pooled);
    let pooled = &*pooled;
    let row8 = (g.w8 * cfg.hidden_dim).max(1);
    let glb = scratch(&mut side.glb, if cfg.mga { g.h8 * row8 } else { 0 });
    // The other thread's MGA values (the pass writes them, then both threads read them).
    let values = scratch(&mut side.values, c.st.values.len());

    let (pixel, rings) = other_scratch(plan, &mut side.own, cfg.hidden_dim);

    // Lent to the other thread: the state MUD reads and writes (given back when MUD and the MGA
    // values are done).
    let (f1, f2, inp08, inp16) = (c.frame.f1, c.frame.f2, c.frame.inp08, c.frame.inp16);
    let net08 = core::mem::take(&mut c.frame.net08);
    let (flow, mask, u) = (core::mem::take(&mut c.st.flow), core::mem::take(&mut c.st.mask), core::mem::take(&mut c.st.u));
    let (keys_m, stats_m) = (core::mem::take(&mut c.st.keys), core::mem::take(&mut c.st.stats));
    let (keys, stats) = (&*keys_m, &*stats_m);
    // The attention state, moved to the other thread for the MGA rows (none without MGA: it
    // stays this thread's).
    let attention = cfg.mga.then(host_rows::take_attention);
    // The MGA rows not yet taken, and each row once written.
    let todo = std::sync::Mutex::new(glb.chunks_exact_mut(row8).take(g.h8).enumerate());
    let done: Vec<std::sync::OnceLock<&[i16]>> = (0..if cfg.mga { g.h8 } else { 0 }).map(|_| std::sync::OnceLock::new()).collect();
    // The attention state laid out for the pass, and the pass, once the values are written.
    let pass = std::sync::OnceLock::new();
    // Takes the next row no one has taken and writes it; `false` when none is left.
    let take_row = |(att, pass): &(host_rows::AttentionState, refine::GlbPass<'_>)| {
        let next = match todo.lock() {
            Ok(mut t) => t.next(),
            Err(_) => None, // (the other thread panicked holding it: the scope reports that)
        };
        let Some((y, d)) = next else { return false };
        pass.row(Some(att), y, d);
        if let Some(slot) = done.get(y) {
            let _ = slot.set(&*d);
        }
        true
    };
    // Rows each thread has taken ([`ALTERNATE_GLB_ROWS`]).
    #[cfg(feature = "internals")]
    let (main_rows, side_rows) = (AtomicUsize::new(0), AtomicUsize::new(0));
    let held = Held::new();
    let (state_tx, state_rx) = mpsc::channel();
    std::thread::scope(|s| {
        let (pass, take_row) = (&pass, &take_row);
        #[cfg(feature = "internals")]
        let (main_rows, side_rows, todo) = (&main_rows, &side_rows, &todo);
        let other = spawn_other(s, &held, move || {
            let mut o = Ctx {
                m,
                g,
                frame: refine::Frame { f1, f2, net08: &mut *net08, net16: &mut [], inp08, inp16 },
                st: refine::State { flow: &mut *flow, mask: &mut *mask, u: &mut *u, keys: &mut [], stats: &mut [], values: &mut *values },
                px: pixel,
                rings,
            };
            if cfg.mud {
                refine::mud_pass(&mut o);
            }
            if cfg.mga {
                refine::mga_values(&mut o);
            }
            // (A closed channel: the other side panicked, which the scope reports.)
            let _ = state_tx.send((net08, flow, mask, u));
            if let Some(mut attention) = attention {
                let values: &[i16] = values;
                let p = refine::GlbPass::new(m, &g, inp08, keys, stats, values);
                p.lay_out(&mut attention);
                let _ = pass.set((attention, p));
                if let Some(pass) = pass.get() {
                    loop {
                        #[cfg(feature = "internals")]
                        while ALTERNATE_GLB_ROWS.load(Ordering::Relaxed)
                            && side_rows.load(Ordering::Acquire) >= main_rows.load(Ordering::Acquire)
                            && todo.lock().is_ok_and(|t| t.len() > 0)
                        {
                            std::thread::yield_now();
                        }
                        if !take_row(pass) {
                            break;
                        }
                        #[cfg(feature = "internals")]
                        side_rows.fetch_add(1, Ordering::Release);
                    }
                }
            }
        });
        for _ in 0..2 {
            refine::gru16_with(m, &g, inp16, c.frame.net16, c.px.patch, c.rings, |y, out| copy_row(out, chunk(pooled, y, row16)));
        }
        lap(Phase::Gru16);
        if let Ok((net08, flow, mask, u)) = state_rx.recv() {
            c.frame.net08 = net08;
            (c.st.flow, c.st.mask, c.st.u) = (flow, mask, u);
        }
        lap(Phase::Mud);
        let mut glb_row = |y: usize, d: &mut [i16]| {
            let mut idle = 0u32;
            loop {
                if let Some(r) = done.get(y).and_then(|r| r.get()) {
                    copy_row(d, r);
                    return;
                }
                if let Some(p) = pass.get()
                    && take_row(p)
                {
                    #[cfg(feature = "internals")]
                    main_rows.fetch_add(1, Ordering::Release);
                    continue;
                }
                // Every row taken, row `y` by the other thread: it ends soon, or it has
                // panicked (the row is never written; the scope reports the panic).
                if other.is_finished() && done.get(y).and_then(|r| r.get()).is_none() {
                    return;
                }
                idle += 1;
                if idle < 256 {
                    core::hint::spin_loop();
                } else {
                    std::thread::yield_now();
                }
            }
        };
        refine::gru08_with(c, if cfg.mga { Some(&mut glb_row) } else { None });
        held.release();
        joined(other);
        lap(Phase::Gru08);
    });
    if let Some((attention, _)) = pass.into_inner() {
        host_rows::lend_attention(attention);
    }
    (c.st.keys, c.st.stats) = (keys_m, stats_m);
}
