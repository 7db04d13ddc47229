//! The fixed-point engine: `no_std`, no heap, every byte of working memory in one caller-provided
//! arena sized by the static [`Plan`].
//!
//! ```ignore
//! const PLAN: Plan = Plan::new(&Config::MUIR_SLIM, 160, 120);
//! static mut ARENA: Arena<{ PLAN.ram_bytes }> = Arena::new();
//! let model = QuantModel::parse(MODEL_BYTES)?;             // &'static [u8] in flash
//! let mut engine = Engine::new(&model, arena_bytes)?;
//! engine.run(&left, &right, &mut Output { disparity: &mut d, uncertainty: Some(&mut u) })?;
//! ```
//!
//! Order of work per pair: right image encoder (features), left image encoder (features and
//! context), UFI, MGA keys and statistics, `iters` x (MUD, MGA values, 1/16 GRU twice, motion +
//! 1/8 GRU, disparity head), final MUD, upsampling. Results equal the plain fixed-point engine
//! (`crate::reference`) bit for bit.
#![deny(clippy::indexing_slicing)]

// The engine's parts are internal; with the `internals` feature they are public for the host
// tools' benches (which time the phases one by one) and tests.
#[cfg(feature = "internals")]
pub mod encoder;
#[cfg(not(feature = "internals"))]
mod encoder;
#[cfg(feature = "hal")]
pub mod hal;
#[cfg(feature = "std")]
mod host_rows;
#[cfg(feature = "std")]
mod phase_times;
#[cfg(all(feature = "std", feature = "internals"))]
pub mod side;
#[cfg(all(feature = "std", not(feature = "internals")))]
mod side;
#[cfg(feature = "internals")]
pub mod layout;
#[cfg(not(feature = "internals"))]
mod layout;
mod plan;
#[cfg(feature = "internals")]
pub mod refine;
#[cfg(not(feature = "internals"))]
mod refine;
#[cfg(feature = "internals")]
pub mod ring;
#[cfg(not(feature = "internals"))]
mod ring;

use core::fmt;

pub use plan::{Grid, Plan, STACK_BUDGET, ram_bytes};
#[cfg(feature = "std")]
pub use phase_times::{Phase, PhaseTimes};

use crate::format::QuantModel;
use crate::model::config::MaxDisparity;
use crate::input::{ImageView, InputError, check_pair};
use ring::{Carver, first_n_mut};

/// Working memory with the alignment the engine needs; `N` from [`Plan::ram_bytes`].
#[repr(C, align(8))]
pub struct Arena<const N: usize>(pub [u8; N]);

impl<const N: usize> Arena<N> {
    /// A zeroed arena (usable in a `static`).
    pub const fn new() -> Self {
        Self([0; N])
    }
}

impl<const N: usize> Default for Arena<N> {
    fn default() -> Self {
        Self::new()
    }
}

/// Why a run was refused.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum EngineError {
    /// The image pair is invalid.
    Input(InputError),
    /// The arena is smaller than the plan for this image size.
    ArenaTooSmall {
        /// Bytes needed.
        needed: usize,
        /// Bytes given.
        given: usize,
    },
    /// The arena is not 8-byte aligned.
    ArenaAlignment,
    /// An output buffer has the wrong length.
    OutputSize {
        /// Values needed (width x height).
        needed: usize,
        /// Values given.
        given: usize,
    },
    /// Uncertainty was asked of a model without MUD.
    NoUncertainty,
    /// The status pin driven around a frame (`hal::run_with_busy_pin`, feature `hal`) failed.
    Pin,
}

impl fmt::Display for EngineError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::Input(e) => write!(f, "{e}"),
            Self::ArenaTooSmall { needed, given } => {
                write!(f, "working memory too small: {given} bytes, the plan needs {needed}")
            }
            Self::ArenaAlignment => write!(f, "working memory must be 8-byte aligned"),
            Self::OutputSize { needed, given } => write!(f, "output buffer holds {given} values, {needed} needed"),
            Self::NoUncertainty => write!(f, "this model has no MUD: it predicts no uncertainty"),
            Self::Pin => write!(f, "the busy pin could not be driven"),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for EngineError {}

impl From<InputError> for EngineError {
    fn from(e: InputError) -> Self {
        Self::Input(e)
    }
}

/// Caller-provided outputs, `width x height` each (the input size), row-major.
///
/// The values are the raw bits of fixed-point numbers whose fraction bits the types [`Disparity`]
/// and [`LogVariance`] carry: `Disparity::from_bits(d)` is a disparity in pixels that prints,
/// compares and converts as a number (`to_num::<f32>()`), with no float on the device unless the
/// caller converts. Rejected pixels ([`reject`]) hold [`REJECTED`].
pub struct Output<'o> {
    /// Left-view disparity, Q10.5 pixels (1/32 px): [`Disparity`]'s bits.
    pub disparity: &'o mut [i16],
    /// Uncertainty `u = log(beta^2)` in Q4.11: [`LogVariance`]'s bits; predicted error `exp(u/2)`
    /// px. Needs a model with MUD.
    pub uncertainty: Option<&'o mut [i16]>,
}

/// A disparity in pixels as the engine writes it: 16 bits, [`crate::arith::DISP_FRAC`] = 5
/// fraction bits (1/32 px, range +-1024 px).
pub type Disparity = fixed::types::I11F5;

/// An uncertainty `u = log(beta^2)` as the engine writes it: 16 bits, [`crate::arith::LOG_FRAC`] =
/// 11 fraction bits (range [-16, 16)); the predicted error is `exp(u/2)` px.
pub type LogVariance = fixed::types::I5F11;

// The types and the integer spec name the same formats.
const _: () = assert!(Disparity::FRAC_NBITS == crate::arith::DISP_FRAC as u32 && Disparity::INT_NBITS + Disparity::FRAC_NBITS == 16);
const _: () = assert!(LogVariance::FRAC_NBITS == crate::arith::LOG_FRAC as u32 && LogVariance::INT_NBITS + LogVariance::FRAC_NBITS == 16);

/// Adaptive iterations: stop refining a frame once its disparity has settled.
///
/// After each iteration (from `min_iters` on) the engine counts the 1/8-grid pixels whose
/// disparity moved by more than `settled` (Q7.8 at 1/8 resolution: 1/256 px there, 1/32 px at
/// full resolution) and stops when they are at most `max_moving_per_mille` of the grid: an integer
/// test, so host and target stop at the same iteration. A share rather than a mean, because a few
/// pixels (occlusions, textureless patches) keep wandering after the rest has settled. The
/// config's iteration count (or `run_iters`'s) stays the maximum.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub struct EarlyStop {
    /// Iterations always run.
    pub min_iters: usize,
    /// Largest update (Q7.8 at 1/8 resolution) of a settled pixel.
    pub settled: u16,
    /// Largest share of unsettled pixels, per mille of the 1/8 grid.
    pub max_moving_per_mille: u16,
}

impl EarlyStop {
    /// The criterion chosen on the training scenes (docs/experiments/adaptive-iterations): stop
    /// once at most 100 per mille of the grid moved by more than 1 px (full resolution), after
    /// at least 2 iterations. There, 2.67 of 7 iterations on average for +0.003 px EPE and +0.04
    /// points of Bad2.0; the held-out figures are in that record. The firmware's `early-stop`
    /// builds and `muir run --adaptive` use it.
    pub const RECOMMENDED: EarlyStop = EarlyStop { min_iters: 2, settled: 32, max_moving_per_mille: 100 };
}

/// The engine: a parsed model and working memory.
pub struct Engine<'m, 'a, 'w> {
    model: &'m QuantModel<'a>,
    arena: &'w mut [u8],
    full_res: bool,
    early_stop: Option<EarlyStop>,
    max_disparity: MaxDisparity,
    last_iters: usize,
    #[cfg(feature = "std")]
    threads: usize,
    #[cfg(feature = "std")]
    phase_times: PhaseTimes,
}

impl<'m, 'a, 'w> Engine<'m, 'a, 'w> {
    /// Binds a model and an arena (8-byte aligned; at least [`Plan::ram_bytes`] for the image
    /// size it will run on).
    pub fn new(model: &'m QuantModel<'a>, arena: &'w mut [u8]) -> Result<Self, EngineError> {
        if !(arena.as_ptr() as usize).is_multiple_of(8) {
            return Err(EngineError::ArenaAlignment);
        }
        Ok(Self {
            model,
            arena,
            full_res: true,
            early_stop: None,
            max_disparity: MaxDisparity::DEFAULT,
            last_iters: 0,
            #[cfg(feature = "std")]
            threads: 1,
            #[cfg(feature = "std")]
            phase_times: PhaseTimes::default(),
        })
    }

    /// Threads for a frame (host builds, feature `std`; default 1). With 2 or more, work runs in
    /// two streams, each on a thread of its own with scratch of its own (allocated per frame; the
    /// firmware path allocates nothing): the two image encoders; UFI beside the MGA keys and
    /// softmax statistics; in each iteration MUD, the MGA values and the MGA aggregation beside
    /// the 1/16 and 1/8 ConvGRUs (`side`). The kernel pool is held while both streams run and
    /// released by the first to finish. The other kernels split their work over the
    /// process-wide worker pool ([`crate::kernels::pool`], sized to this count when a frame
    /// starts). The same integers for any count.
    #[cfg(feature = "std")]
    pub fn set_threads(&mut self, n: usize) {
        self.threads = n.max(1);
    }

    /// Turns adaptive iterations on ([`EarlyStop`]) or off (`None`, the default: every iteration).
    pub fn set_early_stop(&mut self, stop: Option<EarlyStop>) {
        self.early_stop = stop;
    }

    /// Sets the largest disparity of UFI's proposal search ([`MaxDisparity`], default 256 px; the
    /// float reference and the PyTorch twin take the same setting).
    pub fn set_max_disparity(&mut self, max: MaxDisparity) {
        self.max_disparity = max;
    }

    /// Refinement iterations the last successful run used.
    pub fn last_iterations(&self) -> usize {
        self.last_iters
    }

    /// Wall time of each phase of the last successful run (host builds, feature `std`).
    #[cfg(feature = "std")]
    pub fn last_phase_times(&self) -> PhaseTimes {
        self.phase_times
    }

    /// Turns the full-resolution refinement (semi-global matching in a band around the network's disparity, `kernels::fullres`) on (the default) or off
    /// (the network's upsampled disparity as it is). It runs after the network in memory the
    /// network no longer needs, so it adds no RAM beyond the plan (about 490 bytes per image column,
    /// less than the network's own peak); per pixel it costs 9 census comparisons and five path
    /// updates per candidate, (2R + 2) candidates with a band radius R of 3 to 12 px.
    pub fn set_full_res_refinement(&mut self, on: bool) {
        self.full_res = on;
    }

    /// The memory plan for a `width x height` pair with this model.
    pub fn plan(&self, width: usize, height: usize) -> Plan {
        Plan::new(self.model.config(), width, height)
    }

    /// Runs the network on a rectified pair, then the full-resolution refinement (unless turned
    /// off with [`Engine::set_full_res_refinement`]).
    ///
    /// # Errors
    /// Invalid images, an arena smaller than the plan, output buffers of the wrong size, or
    /// uncertainty asked of a model without MUD. Nothing is written on error.
    pub fn run(&mut self, left: &ImageView<'_>, right: &ImageView<'_>, out: &mut Output<'_>) -> Result<(), EngineError> {
        self.run_iters(left, right, self.model.config().iters, out)
    }

    /// [`Engine::run`] with `iters` refinement iterations.
    pub fn run_iters(&mut self, left: &ImageView<'_>, right: &ImageView<'_>, iters: usize, out: &mut Output<'_>) -> Result<(), EngineError> {
        // Host: the convolutions re-lay a layer's weights once per frame, not once per row.
        #[cfg(all(target_arch = "x86_64", feature = "std"))]
        let _frame = crate::kernels::conv::FrameScope::new();
        let m = self.model;
        let cfg = *m.config();
        check_pair(left, right)?;
        let (width, height) = (left.width, left.height);
        let plan = Plan::new(&cfg, width, height);
        if self.arena.len() < plan.ram_bytes {
            return Err(EngineError::ArenaTooSmall { needed: plan.ram_bytes, given: self.arena.len() });
        }
        let n = width * height;
        if out.disparity.len() != n {
            return Err(EngineError::OutputSize { needed: n, given: out.disparity.len() });
        }
        match &out.uncertainty {
            Some(_) if !cfg.mud => return Err(EngineError::NoUncertainty),
            Some(u) if u.len() != n => return Err(EngineError::OutputSize { needed: n, given: u.len() }),
            _ => {}
        }
        // The kernels' threads (host): this engine's count.
        #[cfg(feature = "std")]
        crate::kernels::pool::set_threads(self.threads);
        // Host: the phases' wall times ([`Engine::last_phase_times`]); nothing on a target.
        #[cfg(feature = "std")]
        let mut clock = phase_times::Stopwatch::new();
        #[cfg(feature = "std")]
        macro_rules! lap {
            ($p:ident) => {
                clock.lap(Phase::$p)
            };
        }
        #[cfg(not(feature = "std"))]
        macro_rules! lap {
            ($p:ident) => {};
        }
        // Encoder: right image first (features only), then the left (features and context).
        #[cfg(feature = "std")]
        // With threads, both encoders side by side (the kernel pool held meanwhile: each
        // encoder's kernels run on its own thread).
        let threaded = self.threads > 1;
        #[cfg(not(feature = "std"))]
        let threaded = false;
        if threaded {
            #[cfg(feature = "std")]
            encode_pair_threaded(m, &plan, self.arena, left, right);
        } else {
            encode_image(m, &plan, self.arena, right, false);
            encode_image(m, &plan, self.arena, left, true);
        }
        lap!(Encoders);
        // Refinement.
        let mut c = refine_ctx(m, &plan, self.arena);
        c.st.flow.fill(0);
        // With threads, the refinement's passes in two streams, each on a thread of its own
        // (`side`): the passes of one iteration work on rows too short to split well over the
        // kernel pool.
        #[cfg(feature = "std")]
        let mut side = threaded.then(side::SideBuffers::default);
        #[cfg(feature = "std")]
        let beside = match side.as_mut() {
            Some(side) if cfg.mga => {
                side::setup(&mut c, &plan, side, self.max_disparity.grid8(), |p| clock.lap(p));
                true
            }
            _ => false,
        };
        #[cfg(not(feature = "std"))]
        let beside = false;
        if !beside {
            if cfg.ufi {
                refine::ufi(&mut c, self.max_disparity.grid8());
            }
            lap!(Ufi);
            if cfg.mga {
                refine::mga_setup(&mut c);
            }
            lap!(MgaSetup);
        }
        let n8 = plan.grid.n8() as u64;
        let mut used = 0;
        for it in 0..iters {
            #[cfg(feature = "std")]
            let beside = match side.as_mut() {
                Some(side) if cfg.mud || cfg.mga => {
                    side::iteration(&mut c, &plan, side, |p| clock.lap(p));
                    true
                }
                _ => false,
            };
            #[cfg(not(feature = "std"))]
            let beside = false;
            if !beside {
                if cfg.mud {
                    refine::mud_pass(&mut c);
                }
                lap!(Mud);
                if cfg.mga {
                    refine::mga_values(&mut c);
                }
                lap!(MgaValues);
                refine::gru16(&mut c);
                refine::gru16(&mut c);
                lap!(Gru16);
                #[cfg(feature = "std")]
                refine::gru08_after_glb(&mut c);
                #[cfg(not(feature = "std"))]
                refine::gru08(&mut c);
                lap!(Gru08);
            }
            let settled = self.early_stop.map_or(0, |s| s.settled);
            // Host, with threads: in two bands of rows, a band a thread.
            #[cfg(feature = "std")]
            let moved = if threaded && plan.grid.h8 >= 4 {
                host_rows::flow_head_bands(m, &plan.grid, c.frame.net08, c.st.flow, settled)
            } else {
                refine::flow_head(&mut c, settled)
            };
            #[cfg(not(feature = "std"))]
            let moved = refine::flow_head(&mut c, settled);
            lap!(FlowHead);
            used = it + 1;
            if let Some(stop) = self.early_stop
                && used >= stop.min_iters
                && 1000 * moved as u64 <= stop.max_moving_per_mille as u64 * n8
            {
                break;
            }
        }
        self.last_iters = used;
        if cfg.mud {
            refine::mud_pass(&mut c);
        }
        refine::upsample(&mut c, width, height, out.disparity, out.uncertainty.as_deref_mut());
        lap!(Output);
        if self.full_res {
            let mut cv = Carver::new(first_n_mut(self.arena, plan.ram_bytes));
            let b = plan.fullres;
            let scratch = crate::kernels::fullres::Scratch { census: cv.u64(b.census), paths: cv.u16(b.paths), rows: cv.i16(b.rows), grey: cv.u8(b.grey) };
            crate::kernels::fullres::refine_image(left, right, out.disparity, out.uncertainty.as_deref(), scratch);
        }
        lap!(FullRes);
        #[cfg(feature = "std")]
        {
            self.phase_times = clock.times;
        }
        Ok(())
    }
}

/// Both encoders at once (host): the right image's on a scoped thread with scratch of its own,
/// the left image's on this one with the arena's. The left one has more to do (the context
/// heads and layer4 after the same trunk and features), so the right thread, once its features
/// are done, computes the larger part of the left image's context ([`encoder::context_rest`],
/// from the left layer3 this thread hands it after its trunk) while this one computes its
/// features and the 1/8 hidden state's head. Left to the pool's workers instead, the heads'
/// short rows ran slower on two threads than on one (Teddy: 7-12 ms against 6 ms). Every part
/// writes outputs of its own and reads only the model, its image and a layer3 no one writes any
/// more, so the frame zone is what a sequential [`encode_image`] pair leaves.
#[cfg(feature = "std")]
fn encode_pair_threaded(m: &QuantModel<'_>, plan: &Plan, arena: &mut [u8], left: &ImageView<'_>, right: &ImageView<'_>) {
    let (px, e) = (plan.pixel, plan.encoder);
    // The right encoder's scratch: the same buffers laid out from 0, 8-byte aligned.
    let mut at = 0;
    let mut next = |len: usize| {
        let b = plan::Buf { at, len };
        at = (at + len).div_ceil(8) * 8;
        b
    };
    let (p2, l3, l4, norm, rings) = (next(px.patch.len), next(e.l3.len), next(e.l4.len), next(e.norm.len), next(e.rings.len));
    let mut own = std::vec![0u64; at / 8];
    let mut cr = Carver::new(bytemuck::cast_slice_mut(&mut own));
    let patch_r = cr.raw(p2);
    let (l3_r, l4_r, norms_r, rings_r) = (cr.u8(l3), cr.u8(l4), cr.i64(norm), cr.raw(rings));

    let (f1, ctx, f2, scratch_l) = encoder_zone(plan, arena);
    let encoder::ContextOut { net08, net16, inp08, inp16 } = ctx;
    let encoder::EncoderScratch { l3: l3_l, l4: _, norms: norms_l, rings: rings_l, patch: patch_l } = scratch_l;
    let grid = &plan.grid;
    // The left layer3, handed over once this thread's trunk is done.
    let (send_l3, take_l3) = std::sync::mpsc::sync_channel::<&[u8]>(1);
    // The pool is held while both encoders run (their kernels on their own threads; the workers
    // would only compete for the cores), and released when the right thread is done.
    let held = crate::kernels::pool::hold();
    std::thread::scope(|s| {
        s.spawn(move || {
            let _held = held;
            // This thread's own frame of re-laid weights (see `run_iters`).
            #[cfg(target_arch = "x86_64")]
            let _frame = crate::kernels::conv::FrameScope::new();
            let scratch = encoder::EncoderScratch { l3: &mut *l3_r, l4: &mut *l4_r, norms: norms_r, rings: &mut *rings_r, patch: &mut *patch_r };
            encoder::encode(m, right, grid, scratch, encoder::EncoderOut { features: f2, context: None });
            // (No layer3: the other thread panicked before its trunk was done; the scope
            // reports it.)
            if let Ok(l3) = take_l3.recv() {
                encoder::context_rest(m, l3, grid, rings_r, patch_r, l4_r, inp08, net16, inp16);
            }
        });
        encoder::trunk(m, left, grid, rings_l, patch_l, l3_l);
        let l3: &[u8] = l3_l;
        // (The right thread has gone only if it panicked: the scope reports it.)
        let _ = send_l3.send(l3);
        encoder::image_features(m, l3, grid, rings_l, patch_l, norms_l, f1);
        encoder::hidden08(m, l3, grid, rings_l, patch_l, net08);
    });
}

/// Encodes one image into the frame zone of an arena laid out by `plan`: matching features, and
/// for the left image the hidden states and context. Public for the benches, which time phases.
#[doc(hidden)]
pub fn encode_image(m: &QuantModel<'_>, plan: &Plan, arena: &mut [u8], img: &ImageView<'_>, left: bool) {
    let (f1, ctx, f2, scratch) = encoder_zone(plan, arena);
    let out = if left { encoder::EncoderOut { features: f1, context: Some(ctx) } } else { encoder::EncoderOut { features: f2, context: None } };
    encoder::encode(m, img, &plan.grid, scratch, out);
}

/// The encoders' buffers in an arena laid out by `plan`: the left image's outputs (matching
/// features and context), the right image's (features) and the arena's encoder scratch.
fn encoder_zone<'a>(plan: &Plan, arena: &'a mut [u8]) -> (&'a mut [i8], encoder::ContextOut<'a>, &'a mut [i8], encoder::EncoderScratch<'a>) {
    let (fr, px, e) = (plan.frame, plan.pixel, plan.encoder);
    let mut cv = Carver::new(first_n_mut(arena, plan.ram_bytes));
    let (f1, f2) = (cv.i8(fr.f1), cv.i8(fr.f2));
    let (net08, net16, inp08, inp16) = (cv.i16(fr.net08), cv.i16(fr.net16), cv.u8(fr.inp08), cv.u8(fr.inp16));
    let patch = cv.raw(px.patch);
    let scratch = encoder::EncoderScratch { l3: cv.u8(e.l3), l4: cv.u8(e.l4), norms: cv.i64(e.norm), rings: cv.raw(e.rings), patch };
    (f1, encoder::ContextOut { net08, net16, inp08, inp16 }, f2, scratch)
}

/// The refinement context over an arena laid out by `plan`: the frame zone the encoder filled,
/// the refinement zone and the per-pixel scratch. [`Engine::run_iters`] refines through it;
/// public for the benches, which call the phases one by one.
#[doc(hidden)]
pub fn refine_ctx<'f, 'm, 'a>(m: &'m QuantModel<'a>, plan: &Plan, arena: &'f mut [u8]) -> refine::Ctx<'f, 'm, 'a> {
    let cfg = *m.config();
    let (fr, px, r) = (plan.frame, plan.pixel, plan.refine);
    let mut cv = Carver::new(first_n_mut(arena, plan.ram_bytes));
    let frame = refine::Frame {
        f1: cv.i8(fr.f1),
        f2: cv.i8(fr.f2),
        net08: cv.i16(fr.net08),
        net16: cv.i16(fr.net16),
        inp08: cv.u8(fr.inp08),
        inp16: cv.u8(fr.inp16),
    };
    let pixel = pixel_scratch(&mut cv, &px, cfg.hidden_dim);
    let st = refine::State {
        flow: cv.i16(r.flow),
        mask: cv.i16(r.mask),
        u: cv.i16(r.u),
        keys: cv.i16(r.keys),
        stats: cv.i64(r.stats),
        values: cv.i16(r.values),
    };
    refine::Ctx { m, g: plan.grid, frame, st, px: pixel, rings: cv.raw(r.rings) }
}

/// The per-pixel scratch laid out by `px`, carved from `cv` (next after what it carved before).
fn pixel_scratch<'f>(cv: &mut Carver<'f>, px: &plan::PixelBufs, hidden: usize) -> refine::Pixel<'f> {
    let (patch, window, prefix, peaks_row) = (cv.raw(px.patch), cv.i32(px.window), cv.i64(px.prefix), cv.i32(px.peaks_row));
    let attn = cv.raw(px.attn);
    // Both splits lie inside their plan-sized buffers; a shorter buffer (never, for a checked
    // arena) leaves the second part empty.
    let split = 8 * hidden;
    let (acc, query) = if attn.len() >= split { attn.split_at_mut(split) } else { (attn, &mut [][..]) };
    let logits = cv.i16(px.logits);
    let split = crate::model::layers::MASK_CHANNELS;
    let (logits, mask_px) = if logits.len() >= split { logits.split_at_mut(split) } else { (logits, &mut [][..]) };
    refine::Pixel {
        patch,
        window,
        prefix,
        peaks_row,
        acc: bytemuck::cast_slice_mut(acc),
        query: bytemuck::cast_slice_mut(query),
        logits,
        mask_px,
    }
}

/// The predicted-error limits (px) at which the firmware and the host test compare rejection
/// (`MUIR-RESULT ... u_thresholds=... kept=...`): from well below to well above the typical error,
/// where an inexact `ln` would show first.
#[doc(hidden)]
pub const CHECKED_TAUS: [f32; 7] = [0.05, 0.25, 0.5, 1.0, 2.0, 4.0, 16.0];

/// Rejection threshold for a predicted-error limit `tau` pixels: a pixel is rejected when its
/// `u` (Q4.11) exceeds the returned value (`exp(u/2) > tau` <=> `u > 2 ln tau`). Setup-time
/// conversion (not used inside the engine), the same integer on every target.
pub fn u_threshold(tau_px: f32) -> i16 {
    // The threshold must be the same integer on host and target: std's `ln` exists only on the
    // host and micromath's is off by up to ~4 % (hundreds of LSB at tau = 0.05), so `ln_exact`
    // uses only IEEE-exact operations. Rounding by hand for the same reason.
    let tau = if tau_px.is_nan() || tau_px < 1e-6 { 1e-6 } else { tau_px };
    let v = 2.0 * ln_exact(tau as f64) * (1 << crate::arith::LOG_FRAC) as f64;
    if v >= 32767.0 {
        32767
    } else if v <= -32768.0 {
        -32768
    } else if v >= 0.0 {
        (v + 0.5) as i16
    } else {
        (v - 0.5) as i16
    }
}

/// Predicted error `exp(u / 2)` in pixels of an uncertainty value (Q4.11), for display and
/// logging on a device without `std` (micromath's `exp`, within 0.5 % of the true value; the
/// engine's decisions never use it: rejection compares integers, see [`u_threshold`]).
pub fn predicted_error_px(u: i16) -> f32 {
    micromath::F32Ext::exp(u as f32 / (2u32 << crate::arith::LOG_FRAC) as f32)
}

/// Natural logarithm of a positive, finite `x` from IEEE-exact operations only (exponent split,
/// then `ln m = 2 atanh((m - 1) / (m + 1))` by its series for `m` in [1, 2)): the same bits on
/// every target, within 1e-15 of the true value.
fn ln_exact(x: f64) -> f64 {
    if x.is_nan() || x <= 0.0 || !x.is_finite() {
        return if x == f64::INFINITY { f64::MAX } else { -745.0 };
    }
    let bits = x.to_bits();
    let mut e = ((bits >> 52) & 0x7ff) as i64 - 1023;
    let mut m = f64::from_bits((bits & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    if e == -1023 {
        // subnormal: renormalise
        let y = x * (1u64 << 60) as f64;
        let b = y.to_bits();
        e = ((b >> 52) & 0x7ff) as i64 - 1023 - 60;
        m = f64::from_bits((b & 0x000f_ffff_ffff_ffff) | 0x3ff0_0000_0000_0000);
    }
    let z = (m - 1.0) / (m + 1.0); // 0 <= z < 1/3
    let z2 = z * z;
    let (mut term, mut sum) = (z, 0.0);
    let mut k = 1.0;
    while k < 60.0 {
        sum += term / k;
        term *= z2;
        k += 2.0;
    }
    e as f64 * core::f64::consts::LN_2 + 2.0 * sum
}

/// Marks rejected pixels: every disparity whose uncertainty exceeds `u_max` becomes
/// [`REJECTED`]. Returns the number of kept pixels.
pub fn reject(disparity: &mut [i16], uncertainty: &[i16], u_max: i16) -> usize {
    let mut kept = 0;
    for (d, u) in disparity.iter_mut().zip(uncertainty) {
        if *u > u_max {
            *d = REJECTED;
        } else {
            kept += 1;
        }
    }
    kept
}

/// Disparity value of a rejected pixel (`i16::MIN`, never produced by the network since
/// disparities are >= -1024 px only by saturation of an invalid state).
pub const REJECTED: i16 = i16::MIN;
