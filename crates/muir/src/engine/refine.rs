//! Streaming refinement: UFI initialisation, MGA keys and softmax statistics, the iterations
//! (MUD pass, MGA value pass, slow-fast ConvGRUs with the motion encoder, disparity head) and
//! the output (final MUD, upsampling mask, convex upsampling).
//!
//! Each pass walks the rows of its grid once; stage `i` of a pass computes row `s - lag_i` at step
//! `s`, reading rows of earlier stages from rings sized by the lag difference plus the kernel
//! reach. The hidden states are updated in place: with the gates at lag `L` and the candidate at
//! `L + 1`, the row being blended is never read again by a later gate row. No gate map, no
//! correlation volume and no attention matrix exists at full size.
//!
//! Buffers are carved from the plan-checked arena with the plan's sizes; rows are taken with the
//! `ring` helpers, which give an empty row instead of panicking where a buffer is shorter than
//! the plan says (which cannot happen for a plan-checked arena).
#![deny(clippy::indexing_slicing)]

use super::encoder::{conv, run_conv};
use super::layout::{Buf, FlowHeadLayout, GruLayout, MudLayout, UfiLayout, flow_head_stages, gru08_stages, gru16_stages, mga_value_stages, mud_stages, ufi_stages};
use crate::model::grid::Grid;
use super::ring::{Carver, Ring, chunk, chunk_mut, copy_row, first_n, first_n_mut, last_input_row};
use crate::arith::{lut, sat_i16};
use crate::format::QuantModel;
use crate::kernels::OutRow;
use crate::kernels::attention::{query_stats, rope_pixel};
use crate::kernels::conv::{ConvParams, MAX_K, PartRows};
use crate::kernels::corr::{LookupParams, LookupScratch, lookup_pixel, peaks_pixel};
use crate::kernels::eltwise::{blend_q15, mud_mask, mul_plane_q15, mul_q15, proposal_flow};
use crate::kernels::resample::pool2x_row;
#[cfg(not(feature = "std"))]
use crate::kernels::resample::interp_row;
use crate::kernels::upsample::upsample_pixel;
use crate::model::graph::Act;
use crate::model::layers::{ConvId::*, MASK_CHANNELS};

/// Frame tensors the refinement reads and updates.
pub struct Frame<'a> {
    /// Left features.
    pub f1: &'a [i8],
    /// Right features.
    pub f2: &'a [i8],
    /// 1/8 hidden state.
    pub net08: &'a mut [i16],
    /// 1/16 hidden state.
    pub net16: &'a mut [i16],
    /// 1/8 context (u8).
    pub inp08: &'a [u8],
    /// 1/16 context.
    pub inp16: &'a [u8],
}

/// Long-lived refinement buffers.
pub struct State<'a> {
    /// Disparity state (Q7.8 flow), `n8 x flow_channels`.
    pub flow: &'a mut [i16],
    /// Matchability mask (Q0.15), `n8`.
    pub mask: &'a mut [i16],
    /// Uncertainty (Q4.11), `n8`.
    pub u: &'a mut [i16],
    /// MGA keys, `n8 x qk`.
    pub keys: &'a mut [i16],
    /// MGA statistics, `2 x n8` (max, sum).
    pub stats: &'a mut [i64],
    /// MGA masked values, `n8 x hidden`.
    pub values: &'a mut [i16],
}

/// Per-pixel scratch.
pub struct Pixel<'a> {
    /// Conv patch.
    pub patch: &'a mut [u8],
    /// Lookup window.
    pub window: &'a mut [i32],
    /// Lookup prefix sums.
    pub prefix: &'a mut [i64],
    /// Correlation row for peaks.
    pub peaks_row: &'a mut [i32],
    /// Attention accumulators.
    pub acc: &'a mut [i64],
    /// One query.
    pub query: &'a mut [i16],
    /// Mask logits of one pixel.
    pub logits: &'a mut [i16],
    /// Mask-head features of one pixel.
    pub mask_px: &'a mut [i16],
}

/// Everything a refinement pass works with.
pub struct Ctx<'f, 'm, 'a> {
    /// The model.
    pub m: &'m QuantModel<'a>,
    /// Grid.
    pub g: Grid,
    /// Frame tensors.
    pub frame: Frame<'f>,
    /// Long-lived buffers.
    pub st: State<'f>,
    /// Per-pixel scratch.
    pub px: Pixel<'f>,
    /// Line-buffer region.
    pub rings: &'f mut [u8],
}

fn frac(m: &QuantModel<'_>, a: Act) -> i8 {
    m.format(a).frac
}

/// A single row as the input of a 1x1 conv.
fn one_row(t: &[i16], len: usize) -> PartRows<'_, i16> {
    full(first_n(t, len), 1, len, 0, 1)
}

fn full<'a>(t: &'a [i16], h: usize, row_len: usize, y: usize, k: usize) -> PartRows<'a, i16> {
    PartRows::of_tensor(t, h, row_len, y, k, 1)
}

/// Correlation row `y` at disparity state `flow` (Q8, channel 0 of `fc`).
#[allow(clippy::too_many_arguments)]
fn lookup_row(m: &QuantModel<'_>, f1: &[i8], f2: &[i8], flow: &[i16], fc: usize, g: &Grid, y: usize, win: &mut [i32], pre: &mut [i64], patch: &mut [u8], out: &mut [i16]) {
    let cfg = m.config();
    let mults = m.corr_mults();
    let p = LookupParams { levels: cfg.corr_levels, radius: cfg.corr_radius, post_pool: cfg.post_pool, mults: &mults };
    let (w, fd, cc) = (g.w8, cfg.fmap_dim, cfg.corr_channels());
    let f2row = chunk(f2, y, w * fd);
    #[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
    let _ = patch;
    #[cfg(feature = "std")]
    {
        // Host: the row's pixels as tasks on the kernel pool, scratch per thread.
        super::host_rows::lookup_row(&p, f1, f2row, flow, fc, w, y, fd, cc, (win.len(), pre.len()), out);
        return;
    }
    #[allow(unreachable_code)]
    let mut s = LookupScratch { window: win, prefix: pre };
    // Armv7E-M: the right row widened once into the idle patch scratch (the convolutions'), its
    // columns read by every pixel's window (`corr::window_wide`); where it does not fit, as below.
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    {
        // SAFETY: any bit pattern is a valid u32.
        let (_, words, _) = unsafe { patch.align_to_mut::<u32>() };
        let need = w * fd / 2;
        if fd.is_multiple_of(4)
            && f2row.len() == w * fd
            && let Some(wide) = words.get_mut(..need)
            && crate::kernels::dsp::widen_i8_quads(f2row, wide) == need / 2
        {
            let wide = &*wide;
            for x in 0..w {
                let px = y * w + x;
                let d = flow.get(px * fc).copied().unwrap_or(0);
                let f1 = chunk(f1, px, fd);
                crate::kernels::corr::lookup_with(&p, w, x, d, &mut s, chunk_mut(out, x, cc), |lo, win| {
                    crate::kernels::corr::window_wide(f1, f2row, wide, w, lo, win)
                });
            }
            return;
        }
    }
    for x in 0..w {
        let px = y * w + x;
        let d = flow.get(px * fc).copied().unwrap_or(0);
        lookup_pixel(&p, chunk(f1, px, fd), f2row, w, x, d, &mut s, chunk_mut(out, x, cc));
    }
}

/// u8 context row widened to i16.
fn widen_row(src: &[u8], dst: &mut [i16]) {
    for (d, s) in dst.iter_mut().zip(src) {
        *d = *s as i16;
    }
}

fn rows<'a>(r: &'a Ring<'_, i16>, y: usize, k: usize) -> PartRows<'a, i16> {
    r.part_rows(y, k, 1)
}

/// Produces rows of `ring` up to `upto` (clipped) with `f(row, dst)`.
fn fill(ring: &mut Ring<'_, i16>, upto: usize, mut f: impl FnMut(usize, &mut [i16])) {
    let upto = upto.min(ring.rows().saturating_sub(1));
    while ring.pending() && ring.produced() <= upto {
        let r = ring.produced();
        f(r, ring.push());
    }
}

pub(super) fn conv16(p: &ConvParams<'_>, parts: &[PartRows<'_, i16>], w: usize, out: &mut [i16], patch: &mut [u8]) {
    run_conv(p, parts, w, &mut OutRow::I16(out), patch);
}

/// [`conv16`] of a ConvGRU gate whose last input part is the context, the same in every
/// iteration for output row `row`: the host kernels compute that part's sums once per frame
/// (`with_constant_part`; a microcontroller has no RAM to keep them).
fn conv16_ctx(p: &ConvParams<'_>, parts: &[PartRows<'_, i16>], row: usize, w: usize, out: &mut [i16], patch: &mut [u8]) {
    #[cfg(all(feature = "std", target_arch = "x86_64"))]
    if let Some(last) = parts.len().checked_sub(1) {
        crate::kernels::conv::with_constant_part(last, row, || conv16(p, parts, w, out, patch));
        return;
    }
    #[allow(unreachable_code)]
    {
        let _ = row;
        conv16(p, parts, w, out, patch)
    }
}

/// [`conv16_ctx`] with `spare` arena bytes idle during the layer: on the DSP build the gathered
/// pixel pairs go there, the weights widened once for all of them
/// (`conv::conv_row_i16_w16_spare`), where it holds enough pairs; else as [`conv16_ctx`].
#[allow(clippy::too_many_arguments)]
fn conv16_spare(p: &ConvParams<'_>, parts: &[PartRows<'_, i16>], row: usize, w: usize, out: &mut [i16], patch: &mut [u8], spare: &mut [u8]) {
    #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
    if crate::kernels::conv::conv_row_i16_w16_spare(p, parts, w, &mut OutRow::I16(out), patch, spare) {
        return;
    }
    let _ = spare;
    conv16_ctx(p, parts, row, w, out, patch)
}

/// The convex upsampler's factor: every 1/8-grid pixel becomes an `UP x UP` block of the output
/// (the per-pixel block buffers of the output pass are this size).
const UP: usize = 8;
// The mask head predicts 9 convex weights for each pixel of the block.
const _: () = assert!(MASK_CHANNELS == 9 * UP * UP);

// ------------------------------------------------------------------------------------------------
// UFI
// ------------------------------------------------------------------------------------------------

/// UFI: three proposals, the gated initializer (in place on `net08`), then the candidate with the
/// lowest uncertainty per pixel into `flow`. `max_d8`: the largest proposal on the 1/8 grid
/// ([`crate::model::config::MaxDisparity::grid8`]).
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn ufi(c: &mut Ctx<'_, '_, '_>, max_d8: usize) {
    // Host: the proposals' feature rows kept whole from the initializer for the decoder (this
    // thread's memory), which the microcontroller computes again.
    #[cfg(feature = "std")]
    {
        let len = 3 * c.g.n8() * conv(c.m, UfiConv).cout;
        super::host_rows::with_ufi_features(len, |kept| ufi_with(c, max_d8, Some(kept)));
    }
    #[cfg(not(feature = "std"))]
    ufi_with(c, max_d8, None);
}

/// [`ufi`]; `kept`, where given, holds the three proposals' feature rows (`3 x n8 x` the
/// feature conv's channels) for the decoder, else the decoder computes them again.
fn ufi_with(c: &mut Ctx<'_, '_, '_>, max_d8: usize, mut kept: Option<&mut [i16]>) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, n8) = (g.w8, g.h8, g.n8());
    let (hd, fc, fd) = (cfg.hidden_dim, cfg.flow_channels, cfg.fmap_dim);
    let lay = UfiLayout::new(&cfg, &g);
    let mut cv = Carver::new(c.rings);
    let peaks = cv.i16(lay.peaks);
    let flow_k = cv.i16(lay.flow_k);
    let corr = cv.i16(lay.corr);
    let (b_c, b_f, b_feat, b_q, b_inp) = (cv.i16(lay.c.buf), cv.i16(lay.f.buf), cv.i16(lay.feat.buf), cv.i16(lay.q.buf), cv.i16(lay.inp.buf));
    let z = cv.i16(lay.z);
    let pend = cv.i16(lay.pending.buf);
    let b_h1 = cv.i16(lay.h1.buf);
    let h2 = cv.i16(lay.h2);
    // Proposals.
    for y in 0..h8 {
        let f2row = chunk(c.frame.f2, y, w * fd);
        for x in 0..w {
            let p = y * w + x;
            let (d1, d2) = peaks_pixel(chunk(c.frame.f1, p, fd), f2row, x, cfg.ufi_peak_separation, max_d8, c.px.peaks_row);
            if let [a, b] = chunk_mut(peaks, p, 2) {
                (*a, *b) = (d1 as i16, d2 as i16);
            }
        }
    }
    let set_flow = |k: usize, flow_k: &mut [i16]| {
        for p in 0..n8 {
            let d = if k == 0 { 0 } else { peaks.get(2 * p + k - 1).map_or(0, |&d| proposal_flow(d as u16)) };
            if let Some(f) = flow_k.get_mut(p * fc) {
                *f = d;
            }
        }
    };
    let (pc, pf, pconv, pq, pz, ph1, ph2) =
        (conv(m, UfiC), conv(m, UfiF), conv(m, UfiConv), conv(m, UfiQ), conv(m, UfiZ), conv(m, UfiHead1), conv(m, UfiHead2));
    let cc = cfg.corr_channels();
    let fl_row = w * fc;
    // Rows of the proposal features (lags 0 and 1) shared by the initializer and the decoder.
    macro_rules! feature_rows {
        ($s:expr, $rc:expr, $rf:expr, $rfeat:expr) => {{
            let s = $s;
            if ufi_stages::SCHEDULE.row(s, ufi_stages::LOOKUP, h8).is_some() {
                lookup_row(m, c.frame.f1, c.frame.f2, flow_k, fc, &g, s, c.px.window, c.px.prefix, c.px.patch, corr);
                conv16(&pc, &[full(corr, 1, w * cc, 0, 1)], w, $rc.push(), c.px.patch);
                conv16(&pf, &[full(flow_k, h8, fl_row, s, 3)], w, $rf.push(), c.px.patch);
            }
            // The feature row produced at this step, if any.
            let r = ufi_stages::SCHEDULE.row(s, ufi_stages::FEATURES, h8);
            if let Some(r) = r {
                conv16(&pconv, &[rows(&$rc, r, 3), rows(&$rf, r, 3)], w, $rfeat.push(), c.px.patch);
            }
            r
        }};
    }
    let frow = w * pconv.cout;
    for k in 0..3 {
        set_flow(k, flow_k);
        let mut rc = Ring::of(&mut b_c[..], lay.c, h8);
        let mut rf = Ring::of(&mut b_f[..], lay.f, h8);
        let mut rfeat = Ring::of(&mut b_feat[..], lay.feat, h8);
        let mut rq = Ring::of(&mut b_q[..], lay.q, h8);
        let mut rinp = Ring::of(&mut b_inp[..], lay.inp, h8);
        let mut rpend = Ring::of(&mut pend[..], lay.pending, h8);
        let row = w * hd;
        for s in 0..ufi_stages::SCHEDULE.steps(h8) {
            // lag 0 and 1: corr, disparity and proposal features (kept for the decoder on the
            // host)
            if let Some(r) = feature_rows!(s, rc, rf, rfeat)
                && let Some(kept) = kept.as_deref_mut()
                && let Some(d) = kept.get_mut((k * h8 + r) * frow..(k * h8 + r + 1) * frow)
            {
                d.copy_from_slice(rfeat.row(r));
            }
            // lag 2: candidate state q = tanh(convq([feat, flow_k, ctx]))
            if let Some(r) = ufi_stages::SCHEDULE.row(s, ufi_stages::CANDIDATE, h8) {
                fill(&mut rinp, last_input_row(r, 3, 1, h8), |y, d| widen_row(chunk(c.frame.inp08, y, w * cfg.context_dim), d));
                conv16(&pq, &[rows(&rfeat, r, 3), full(flow_k, h8, fl_row, r, 3), rows(&rinp, r, 3)], w, rq.push(), c.px.patch);
            }
            // lag 3: gate and blend (write-back one row later: the next gate row reads this one)
            if let Some(r) = ufi_stages::SCHEDULE.row(s, ufi_stages::GATE, h8) {
                conv16(&pz, &[full(c.frame.net08, h8, row, r, 3), rows(&rq, r, 3)], w, first_n_mut(z, row), c.px.patch);
                let dst = rpend.push();
                copy_row(dst, chunk(c.frame.net08, r, row));
                blend_q15(dst, first_n(z, row), rq.row(r));
                if r >= 1 {
                    copy_row(chunk_mut(c.frame.net08, r - 1, row), rpend.row(r - 1));
                }
            }
        }
        copy_row(chunk_mut(c.frame.net08, h8 - 1, row), rpend.row(h8 - 1));
    }
    // Decoder: per proposal a refined disparity and an uncertainty; keep the least uncertain.
    let table = m.u_table();
    for k in 0..3 {
        set_flow(k, flow_k);
        let mut rc = Ring::of(&mut b_c[..], lay.c, h8);
        let mut rf = Ring::of(&mut b_f[..], lay.f, h8);
        let mut rfeat = Ring::of(&mut b_feat[..], lay.feat, h8);
        let mut rh1 = Ring::of(&mut b_h1[..], lay.h1, h8);
        let kept_k = kept.as_deref().and_then(|f| f.get(k * h8 * frow..(k + 1) * h8 * frow));
        for s in 0..ufi_stages::SCHEDULE.steps(h8) {
            if kept_k.is_none() {
                feature_rows!(s, rc, rf, rfeat);
            }
            if let Some(r) = ufi_stages::SCHEDULE.row(s, ufi_stages::CANDIDATE, h8) {
                let feat = match kept_k {
                    Some(f) => full(f, h8, frow, r, 3),
                    None => rows(&rfeat, r, 3),
                };
                conv16(&ph1, &[full(c.frame.net08, h8, w * hd, r, 3), feat, full(flow_k, h8, fl_row, r, 3)], w, rh1.push(), c.px.patch);
            }
            if let Some(r) = ufi_stages::SCHEDULE.row(s, ufi_stages::GATE, h8) {
                let h2 = first_n_mut(h2, 2 * w);
                conv16(&ph2, &[rows(&rh1, r, 3)], w, h2, c.px.patch);
                for (x, (out, u)) in h2.chunks_exact(2).zip(chunk_mut(c.st.u, r, w)).enumerate() {
                    let p = r * w + x;
                    let (&[delta, logit], Some(&fk)) = (out, flow_k.get(p * fc)) else { continue };
                    let cand_flow = sat_i16(fk as i64 + delta as i64);
                    let cand_u = lut::table_q11(&table, logit);
                    // strictly smaller: ties keep the earlier proposal (argmin, first)
                    if k == 0 || cand_u < *u {
                        *u = cand_u;
                        if let Some(f) = c.st.flow.get_mut(p * fc) {
                            *f = cand_flow;
                        }
                    }
                }
            }
        }
    }
}

// ------------------------------------------------------------------------------------------------
// MGA setup
// ------------------------------------------------------------------------------------------------

/// Query (or key) of pixel `p` at (x, y): 1x1 conv of the context, then RoPE.
#[allow(clippy::too_many_arguments)]
fn qk_pixel(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, x: usize, y: usize, w: usize, phases: &[u32], patch: &mut [u8], out: &mut [i16]) {
    let i = y * w + x;
    let mut r = [None; MAX_K];
    r[0] = Some(chunk(inp08, i, ctx));
    run_conv(p, &[PartRows { rows: r }], 1, &mut OutRow::I16(out), patch);
    rope_pixel(out, x, y, phases);
}

/// Queries (or keys) of a run of pixels `x0 .. x0 + n` of row `y` into `out` (`n x cout` values):
/// one 1x1 conv call over the run's context values (so `run_conv` takes pixel pairs and, from
/// three pairs, the weights widened once), then RoPE per pixel. The same integers as
/// [`qk_pixel`] for each pixel: a 1x1 convolution reads no neighbours.
#[allow(clippy::too_many_arguments)]
fn qk_run(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, x0: usize, n: usize, y: usize, w: usize, phases: &[u32], patch: &mut [u8], out: &mut [i16]) {
    let i = y * w + x0;
    let mut r = [None; MAX_K];
    r[0] = Some(inp08.get(i * ctx..(i + n) * ctx).unwrap_or_default());
    let out = first_n_mut(out, n * p.cout);
    run_conv(p, &[PartRows { rows: r }], n, &mut OutRow::I16(out), patch);
    for (x, o) in out.chunks_exact_mut(p.cout.max(1)).enumerate() {
        rope_pixel(o, x0 + x, y, phases);
    }
}

/// Calls `f(x, query)` for every pixel of row `y` (`w` of them) with its query ([`qk_pixel`]'s
/// values): computed in runs of pixels as long as `buf` holds ([`qk_run`], runs of equal length),
/// or pixel by pixel into `query` where `buf` cannot hold one.
#[allow(clippy::too_many_arguments)]
fn row_queries(p: &ConvParams<'_>, inp08: &[u8], ctx: usize, y: usize, w: usize, phases: &[u32], patch: &mut [u8], buf: &mut [i16], query: &mut [i16], mut f: impl FnMut(usize, &[i16])) {
    let qk = p.cout;
    let per = buf.len().checked_div(qk).unwrap_or(0);
    if per == 0 {
        for x in 0..w {
            qk_pixel(p, inp08, ctx, x, y, w, phases, patch, query);
            f(x, query);
        }
        return;
    }
    let size = w.div_ceil(w.div_ceil(per).max(1)).max(1);
    let mut x0 = 0;
    while x0 < w {
        let n = size.min(w - x0);
        qk_run(p, inp08, ctx, x0, n, y, w, phases, patch, buf);
        for (x, q) in buf.chunks_exact(qk).take(n).enumerate() {
            f(x0 + x, q);
        }
        x0 += n;
    }
}

/// One RoPE phase step per query/key channel pair: `mga_qk_dim / 2` of them, and a config's widths
/// are at most `MAX_WIDTH` (checked when the config is validated).
fn rope_phases(m: &QuantModel<'_>) -> [u32; crate::model::config::MAX_WIDTH / 2] {
    let mut ph = [0u32; crate::model::config::MAX_WIDTH / 2];
    for (i, v) in ph.iter_mut().enumerate().take(m.config().mga_qk_dim / 2) {
        *v = m.rope_phase(i);
    }
    ph
}

/// Keys (after RoPE) and every query's softmax statistics; once per frame.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn mga_setup(c: &mut Ctx<'_, '_, '_>) {
    let m = c.m;
    let cfg = *m.config();
    let (w, h8, qk, ctx) = (c.g.w8, c.g.h8, cfg.mga_qk_dim, cfg.context_dim);
    let phases = rope_phases(m);
    let phases = first_n(&phases, qk / 2);
    let (pq, pk) = (conv(m, MgaQuery), conv(m, MgaKey));
    for y in 0..h8 {
        #[cfg(feature = "std")]
        {
            // Host: the row's keys by one conv call.
            super::host_rows::keys_row(&pk, c.frame.inp08, ctx, y, w, phases, chunk_mut(c.st.keys, y, w * qk));
            continue;
        }
        // The row's keys by one conv call.
        #[allow(unreachable_code)]
        qk_run(&pk, c.frame.inp08, ctx, 0, w, y, w, phases, c.px.patch, chunk_mut(c.st.keys, y, w * qk));
    }
    let am = m.att_mult();
    // Host: the keys are final.
    #[cfg(feature = "std")]
    super::host_rows::new_keys();
    for y in 0..h8 {
        #[cfg(feature = "std")]
        {
            // Host: the row's queries at once, its pixels on the kernel pool.
            super::host_rows::stats_row(&pq, c.frame.inp08, ctx, y, w, phases, c.st.keys, am, chunk_mut(c.st.stats, y, 2 * w));
            continue;
        }
        // The row's queries in runs of pixels (the mask logits' buffer, idle until the output
        // pass).
        #[allow(unreachable_code)]
        let (keys, stats) = (&*c.st.keys, &mut *c.st.stats);
        #[allow(unreachable_code)]
        row_queries(&pq, c.frame.inp08, ctx, y, w, phases, c.px.patch, c.px.logits, c.px.query, |x, q| {
            let (mx, sum) = query_stats(q, keys, am);
            if let [a, b] = chunk_mut(stats, y * w + x, 2) {
                (*a, *b) = (mx, sum);
            }
        });
    }
}

// ------------------------------------------------------------------------------------------------
// Iteration passes
// ------------------------------------------------------------------------------------------------

/// MUD pass: matchability mask into `mask`, uncertainty into `u`.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn mud_pass(c: &mut Ctx<'_, '_, '_>) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, hd, fc) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels);
    let lay = MudLayout::new(&cfg, &g);
    let mut cv = Carver::new(c.rings);
    let mut rcorr = cv.ring16(lay.corr, h8);
    let mut r1 = cv.ring16(lay.mud1, h8);
    let mut r2 = cv.ring16(lay.mud2, h8);
    let out = cv.i16(lay.mud3);
    let (p1, p2, p3) = (conv(m, Mud1), conv(m, Mud2), conv(m, Mud3));
    let table = m.u_table();
    for s in 0..mud_stages::SCHEDULE.steps(h8) {
        if mud_stages::SCHEDULE.row(s, mud_stages::LOOKUP, h8).is_some() {
            lookup_row(m, c.frame.f1, c.frame.f2, c.st.flow, fc, &g, s, c.px.window, c.px.prefix, c.px.patch, rcorr.push());
        }
        if let Some(r) = mud_stages::SCHEDULE.row(s, mud_stages::HIDDEN1, h8) {
            conv16(&p1, &[full(c.frame.net08, h8, w * hd, r, 3), rows(&rcorr, r, 3), full(c.st.flow, h8, w * fc, r, 3)], w, r1.push(), c.px.patch);
        }
        if let Some(r) = mud_stages::SCHEDULE.row(s, mud_stages::HIDDEN2, h8) {
            conv16(&p2, &[rows(&r1, r, 3)], w, r2.push(), c.px.patch);
        }
        if let Some(r) = mud_stages::SCHEDULE.row(s, mud_stages::OUT, h8) {
            let out = first_n_mut(out, 2 * w);
            conv16(&p3, &[rows(&r2, r, 3)], w, out, c.px.patch);
            let (mask, u) = (chunk_mut(c.st.mask, r, w), chunk_mut(c.st.u, r, w));
            for ((o, m), u) in out.chunks_exact(2).zip(mask).zip(u) {
                if let &[logit_m, logit_u] = o {
                    *m = mud_mask(logit_m);
                    *u = lut::table_q11(&table, logit_u);
                }
            }
        }
    }
}

/// MGA value pass: `values = value(net08) * sigmoid(mask conv([net08, corr, flow, m]))`.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn mga_values(c: &mut Ctx<'_, '_, '_>) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, hd, fc) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels);
    let lay = MudLayout::new(&cfg, &g);
    let mut cv = Carver::new(c.rings);
    let mut rcorr = cv.ring16(lay.corr, h8);
    let hm = cv.i16(lay.hm);
    let v = cv.i16(lay.v);
    let (pm, pv) = (conv(m, MgaMask), conv(m, MgaValue));
    for s in 0..mga_value_stages::SCHEDULE.steps(h8) {
        if mga_value_stages::SCHEDULE.row(s, mga_value_stages::LOOKUP, h8).is_some() {
            lookup_row(m, c.frame.f1, c.frame.f2, c.st.flow, fc, &g, s, c.px.window, c.px.prefix, c.px.patch, rcorr.push());
        }
        if let Some(r) = mga_value_stages::SCHEDULE.row(s, mga_value_stages::OUT, h8) {
            let parts = [
                full(c.frame.net08, h8, w * hd, r, 3),
                rows(&rcorr, r, 3),
                full(c.st.flow, h8, w * fc, r, 3),
                full(c.st.mask, h8, w, r, 3),
            ];
            let (hm, v) = (first_n_mut(hm, w), first_n_mut(v, w * hd));
            conv16(&pm, &parts, w, hm, c.px.patch);
            conv16(&pv, &[full(c.frame.net08, h8, w * hd, r, 1)], w, v, c.px.patch);
            // Armv7E-M: channel-major (`aggregate_query_cm` reads two keys of a channel a word).
            #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
            crate::kernels::eltwise::mul_plane_q15_cm(v, hm, hd, c.st.values, w * h8, r * w);
            #[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
            mul_plane_q15(v, hm, hd, chunk_mut(c.st.values, r, w * hd));
        }
    }
}

/// The 1/16 ConvGRU step: `net16 = gru16(net16, ctx16, pool2x(net08))`, in place.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn gru16(c: &mut Ctx<'_, '_, '_>) {
    let g = c.g;
    let hd = c.m.config().hidden_dim;
    let net08 = &*c.frame.net08;
    gru16_with(c.m, &g, c.frame.inp16, c.frame.net16, c.px.patch, c.rings, |s, out| pool2x_row(net08, g.h8, g.w8, hd, s, out));
}

/// Every row of `pool2x(net08)` (`h16 x w16 x hidden`) into `out`: the 1/16 steps' input from the
/// 1/8 state, for [`gru16_with`] on a thread that does not read `net08` itself (host).
#[cfg(feature = "std")]
pub fn pool2x_state(m: &QuantModel<'_>, g: &Grid, net08: &[i16], out: &mut [i16]) {
    let hd = m.config().hidden_dim;
    for y in 0..g.h16 {
        pool2x_row(net08, g.h8, g.w8, hd, y, chunk_mut(out, y, g.w16 * hd));
    }
}

/// The MGA output rows of an iteration (host: its values final, written by [`mga_values`]),
/// each computed on its own, in any order and on any thread: what every row reads.
#[cfg(feature = "std")]
pub struct GlbPass<'a> {
    pqy: ConvParams<'a>,
    phases: [u32; crate::model::config::MAX_WIDTH / 2],
    qk: usize,
    inp08: &'a [u8],
    keys: &'a [i16],
    stats: &'a [i64],
    values: &'a [i16],
    g: Grid,
    hd: usize,
    ctx: usize,
    am: crate::arith::Multiplier,
    shift: i8,
}

#[cfg(feature = "std")]
impl<'a> GlbPass<'a> {
    /// The pass of model `m` on grid `g`: the context `inp08`, the frame's keys and softmax
    /// statistics, the iteration's values.
    pub fn new(m: &'a QuantModel<'_>, g: &Grid, inp08: &'a [u8], keys: &'a [i16], stats: &'a [i64], values: &'a [i16]) -> Self {
        let cfg = *m.config();
        GlbPass {
            pqy: conv(m, MgaQuery),
            phases: rope_phases(m),
            qk: cfg.mga_qk_dim,
            inp08,
            keys,
            stats,
            values,
            g: *g,
            hd: cfg.hidden_dim,
            ctx: cfg.context_dim,
            am: m.att_mult(),
            shift: frac(m, Act::Glb) - frac(m, Act::MgaV),
        }
    }

    /// Lays out this pass's keys and values in `att`, for [`GlbPass::row`] with it.
    pub fn lay_out(&self, att: &mut super::host_rows::AttentionState) {
        att.lay_out_pass(self.keys, self.values, self.pqy.cout, self.hd);
    }

    /// Row `y` into `d` (`w8 x hidden`), with the attention state `att` (laid out for this
    /// pass) where given, else this thread's (the engine's `host_rows::new_values` called before
    /// the pass).
    pub fn row(&self, att: Option<&super::host_rows::AttentionState>, y: usize, d: &mut [i16]) {
        let w = self.g.w8;
        let stats = chunk(self.stats, y, 2 * w);
        let phases = first_n(&self.phases, self.qk / 2);
        super::host_rows::aggregate_row(att, &self.pqy, self.inp08, self.ctx, y, w, phases, self.keys, self.values, self.hd, stats, self.am, self.shift, d);
    }
}

/// The MGA output of every row of the iteration (host: its values final, written by
/// [`mga_values`]) into `out` (`h8` rows of `w8 x hidden`), with this thread's attention state.
#[cfg(feature = "std")]
pub fn glb_rows(m: &QuantModel<'_>, g: &Grid, inp08: &[u8], keys: &[i16], stats: &[i64], values: &[i16], out: &mut [i16]) {
    super::host_rows::new_values();
    let pass = GlbPass::new(m, g, inp08, keys, stats, values);
    for (y, d) in out.chunks_exact_mut((g.w8 * pass.hd).max(1)).take(g.h8).enumerate() {
        pass.row(None, y, d);
    }
}

/// [`gru16`] on explicit buffers: `pooled(y, row)` writes row `y` of `pool2x(net08)`; `patch`
/// and `rings` as the context's (the plan's sizes).
#[allow(clippy::too_many_arguments)]
pub fn gru16_with(m: &QuantModel<'_>, g: &Grid, inp16: &[u8], net16: &mut [i16], patch: &mut [u8], rings: &mut [u8], pooled: impl Fn(usize, &mut [i16])) {
    let cfg = *m.config();
    let (w, h, hd, ctx) = (g.w16, g.h16, cfg.hidden_dim, cfg.context_dim);
    let lay = GruLayout::new(&cfg, g);
    let mut cv = Carver::new(rings);
    let row = w * hd;
    let mut pool = Ring::of_len(cv.i16(lay.mo.buf), lay.mo, row, h);
    let mut inp = Ring::of_len(cv.i16(lay.inp.buf), lay.inp, w * ctx, h);
    let mut rz = Ring::of_len(cv.i16(lay.z.buf), lay.z, row, h);
    let mut rh = Ring::of_len(cv.i16(lay.rh.buf), lay.rh, row, h);
    let gate = cv.i16(lay.gate);
    let q = cv.i16(lay.q);
    // The 1/8 pass's buffers after `q`, idle here.
    let spare = cv.raw(Buf { at: lay.q.end(), len: lay.total.saturating_sub(lay.q.end()) });
    let (pz, pr, pq) = (conv(m, Gru16Z), conv(m, Gru16R), conv(m, Gru16Q));
    for s in 0..gru16_stages::SCHEDULE.steps(h) {
        if gru16_stages::SCHEDULE.row(s, gru16_stages::INPUTS, h).is_some() {
            pooled(s, pool.push());
            widen_row(chunk(inp16, s, w * ctx), inp.push());
        }
        if let Some(r) = gru16_stages::SCHEDULE.row(s, gru16_stages::GATES, h) {
            let parts = [full(net16, h, row, r, 3), rows(&pool, r, 3), rows(&inp, r, 3)];
            conv16_spare(&pz, &parts, r, w, rz.push(), patch, spare);
            let gate = first_n_mut(gate, row);
            conv16_spare(&pr, &parts, r, w, gate, patch, spare);
            mul_q15(gate, chunk(net16, r, row), rh.push());
        }
        if let Some(r) = gru16_stages::SCHEDULE.row(s, gru16_stages::CANDIDATE, h) {
            let q = first_n_mut(q, row);
            conv16_spare(&pq, &[rows(&rh, r, 3), rows(&pool, r, 3), rows(&inp, r, 3)], r, w, q, patch, spare);
            blend_q15(chunk_mut(net16, r, row), rz.row(r), q);
        }
    }
}

/// Motion encoder and the 1/8 ConvGRU: `net08 = gru08(net08, ctx08, [motion, interp(net16), glb])`,
/// in place; the correlation is looked up at the current disparity row by row.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn gru08(c: &mut Ctx<'_, '_, '_>) {
    gru08_with(c, None)
}

/// Host, one thread: [`gru08`] with the iteration's MGA output rows aggregated first, all of them,
/// into a buffer of this thread (`h8` rows of `w8 x hidden`), then read row by row. Aggregated
/// between the gate rows instead (the firmware's order, which has no RAM for the rows), each row
/// streams the kept softmax weights and the values through the caches and evicts the gates'
/// weights: `muir-slim`'s update and reset gates took 96 us a row against 76 us on Teddy. The
/// same integers: the rows read the final keys, statistics and values, as on the second thread
/// of `engine::side`.
#[cfg(feature = "std")]
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn gru08_after_glb(c: &mut Ctx<'_, '_, '_>) {
    std::thread_local! {
        /// The rows, kept for the next frames (no allocation once the first has run).
        static GLB: core::cell::RefCell<Vec<i16>> = const { core::cell::RefCell::new(Vec::new()) };
    }
    let m = c.m;
    let cfg = *m.config();
    if !cfg.mga {
        return gru08(c);
    }
    let g = c.g;
    let row = g.w8 * cfg.hidden_dim;
    GLB.with_borrow_mut(|glb| {
        let out = crate::kernels::pool::scratch(glb, g.h8 * row);
        glb_rows(m, &g, c.frame.inp08, c.st.keys, c.st.stats, c.st.values, out);
        let out = &*out;
        gru08_with(c, Some(&mut |y, d| copy_row(d, chunk(out, y, row))));
    });
}

/// [`gru08`], its MGA output rows from `glb(y, row)` where given (host: aggregated on another
/// thread, `engine::side`) instead of aggregated here.
#[allow(clippy::type_complexity)]
pub fn gru08_with(c: &mut Ctx<'_, '_, '_>, mut glb: Option<&mut dyn FnMut(usize, &mut [i16])>) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, hd, fc, cc, ctx) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels, cfg.corr_channels(), cfg.context_dim);
    let lay = GruLayout::new(&cfg, &g);
    // Host: this pass's MGA values are final (written by `mga_values`).
    #[cfg(feature = "std")]
    super::host_rows::new_values();
    // (Carved in the layout's order.)
    let mut cv = Carver::new(c.rings);
    let mut rmo = Ring::of_len(cv.i16(lay.mo.buf), lay.mo, w * (cfg.motion_dim - fc), h8);
    let mut rinp = cv.ring16(lay.inp, h8);
    let mut rz = cv.ring16(lay.z, h8);
    let mut rrh = cv.ring16(lay.rh, h8);
    let gate = cv.i16(lay.gate);
    let q = cv.i16(lay.q);
    let corr = cv.i16(lay.corr);
    let corr_m = cv.i16(lay.corr_m);
    let mut rc1 = cv.ring16(lay.c1, h8);
    let mut rc2 = cv.ring16(lay.c2, h8);
    let mut rf1 = cv.ring16(lay.f1, h8);
    let mut rf2 = cv.ring16(lay.f2, h8);
    let mut rup = cv.ring16(lay.up, h8);
    let mut rglb = cv.ring16(lay.glb, h8);
    let (pc1, pc2, pf1, pf2, pmo) = (conv(m, MotC1), conv(m, MotC2), conv(m, MotF1), conv(m, MotF2), conv(m, MotOut));
    let (pz, pr, pq) = (conv(m, Gru08Z), conv(m, Gru08R), conv(m, Gru08Q));
    let pquery = if cfg.mga { Some(conv(m, MgaQuery)) } else { None };
    let phases = rope_phases(m);
    let phases = first_n(&phases, cfg.mga_qk_dim / 2);
    let (am, glb_shift) = (m.att_mult(), frac(m, Act::Glb) - frac(m, Act::MgaV));
    let row = w * hd;
    for s in 0..gru08_stages::SCHEDULE.steps(h8) {
        if gru08_stages::SCHEDULE.row(s, gru08_stages::LOOKUP, h8).is_some() {
            lookup_row(m, c.frame.f1, c.frame.f2, c.st.flow, fc, &g, s, c.px.window, c.px.prefix, c.px.patch, first_n_mut(corr, w * cc));
            // corr features: cat[C, C * m, m] with MUD (three parts), C alone without
            if cfg.mud {
                let mrow = chunk(c.st.mask, s, w);
                mul_plane_q15(first_n(corr, w * cc), mrow, cc, first_n_mut(corr_m, w * cc));
                conv16(&pc1, &[one_row(corr, w * cc), one_row(corr_m, w * cc), one_row(mrow, w)], w, rc1.push(), c.px.patch);
            } else {
                conv16(&pc1, &[one_row(corr, w * cc)], w, rc1.push(), c.px.patch);
            }
            conv16(&pf1, &[full(c.st.flow, h8, w * fc, s, 7)], w, rf1.push(), c.px.patch);
        }
        if let Some(r) = gru08_stages::SCHEDULE.row(s, gru08_stages::MOTION2, h8) {
            conv16(&pc2, &[rows(&rc1, r, 3)], w, rc2.push(), c.px.patch);
            conv16(&pf2, &[rows(&rf1, r, 3)], w, rf2.push(), c.px.patch);
        }
        if let Some(r) = gru08_stages::SCHEDULE.row(s, gru08_stages::MOTION, h8) {
            conv16(&pmo, &[rows(&rc2, r, 3), rows(&rf2, r, 3)], w, rmo.push(), c.px.patch);
        }
        if let Some(r) = gru08_stages::SCHEDULE.row(s, gru08_stages::GATES, h8) {
            let upto = last_input_row(r, 3, 1, h8);
            let (net16, w16, h16) = (&*c.frame.net16, g.w16, g.h16);
            fill(&mut rup, upto, |y, d| {
                // Host: the row's pixels on the kernel pool.
                #[cfg(feature = "std")]
                super::host_rows::interp_row(net16, h16, w16, hd, h8, w, y, d);
                #[cfg(not(feature = "std"))]
                interp_row(net16, h16, w16, hd, h8, w, y, d);
            });
            fill(&mut rinp, upto, |y, d| widen_row(chunk(c.frame.inp08, y, w * ctx), d));
            if let (Some(f), true) = (glb.as_mut(), cfg.mga) {
                fill(&mut rglb, upto, |y, d| f(y, d));
            } else if let Some(pqy) = &pquery {
                let st = &c.st;
                let px = &mut c.px;
                fill(&mut rglb, upto, |y, d| {
                    #[cfg(feature = "std")]
                    {
                        // Host: the row's queries at once, its pixels on the kernel pool.
                        let stats = chunk(st.stats, y, 2 * w);
                        super::host_rows::aggregate_row(None, pqy, c.frame.inp08, ctx, y, w, phases, st.keys, st.values, hd, stats, am, glb_shift, d);
                        return;
                    }
                    // The row's queries in runs of pixels (the mask logits' buffer, idle
                    // until the output pass).
                    #[allow(unreachable_code)]
                    let acc = &mut *px.acc;
                    #[allow(unreachable_code)]
                    row_queries(pqy, c.frame.inp08, ctx, y, w, phases, px.patch, px.logits, px.query, |x, q| {
                        let stats = match *chunk(st.stats, y * w + x, 2) {
                            [mx, sum] => (mx, sum),
                            _ => (0, 0),
                        };
                        // Armv7E-M: the values channel-major (`mga_values`).
                        #[cfg(all(target_arch = "arm", feature = "dsp", not(feature = "mve")))]
                        crate::kernels::attention::aggregate_query_cm(q, st.keys, st.values, w * h8, hd, stats, am, glb_shift, acc, chunk_mut(d, x, hd));
                        #[cfg(not(all(target_arch = "arm", feature = "dsp", not(feature = "mve"))))]
                        crate::kernels::attention::aggregate_query(q, st.keys, st.values, hd, stats, am, glb_shift, acc, chunk_mut(d, x, hd));
                    });
                });
            }
            let net = full(c.frame.net08, h8, row, r, 3);
            let fl = full(c.st.flow, h8, w * fc, r, 3);
            let mut parts = [net, rows(&rmo, r, 3), fl, rows(&rup, r, 3), rows(&rinp, r, 3), rows(&rinp, r, 3)];
            let n = if cfg.mga {
                parts[4] = rows(&rglb, r, 3);
                6
            } else {
                5
            };
            let gate = first_n_mut(gate, row);
            conv16_ctx(&pz, first_n(&parts, n), r, w, rz.push(), c.px.patch);
            conv16_ctx(&pr, first_n(&parts, n), r, w, gate, c.px.patch);
            mul_q15(gate, chunk(c.frame.net08, r, row), rrh.push());
        }
        if let Some(r) = gru08_stages::SCHEDULE.row(s, gru08_stages::CANDIDATE, h8) {
            let fl = full(c.st.flow, h8, w * fc, r, 3);
            let mut parts = [rows(&rrh, r, 3), rows(&rmo, r, 3), fl, rows(&rup, r, 3), rows(&rinp, r, 3), rows(&rinp, r, 3)];
            let n = if cfg.mga {
                parts[4] = rows(&rglb, r, 3);
                6
            } else {
                5
            };
            let q = first_n_mut(q, row);
            conv16_ctx(&pq, first_n(&parts, n), r, w, q, c.px.patch);
            blend_q15(chunk_mut(c.frame.net08, r, row), rz.row(r), q);
        }
    }
}

/// Disparity head: `flow += conv2(relu(conv1(net08)))`, row by row: adds its update to the disparity state. Returns how many 1/8-grid pixels moved
/// by more than `settled` (Q7.8), the measure of [`super::EarlyStop`].
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn flow_head(c: &mut Ctx<'_, '_, '_>, settled: u16) -> usize {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, hd, fc) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels);
    let lay = FlowHeadLayout::new(&cfg, &g);
    let mut cv = Carver::new(c.rings);
    let mut rh = Ring::of_len(cv.i16(lay.head.buf), lay.head, w * cfg.flow_head_dim, h8);
    let out = cv.i16(lay.head_out);
    let (p1, p2) = (conv(m, Flow1), conv(m, Flow2));
    let mut moved = 0usize;
    for s in 0..flow_head_stages::SCHEDULE.steps(h8) {
        if flow_head_stages::SCHEDULE.row(s, flow_head_stages::HIDDEN, h8).is_some() {
            conv16(&p1, &[full(c.frame.net08, h8, w * hd, s, 3)], w, rh.push(), c.px.patch);
        }
        if let Some(r) = flow_head_stages::SCHEDULE.row(s, flow_head_stages::OUT, h8) {
            let out = first_n_mut(out, w * fc);
            conv16(&p2, &[rows(&rh, r, 3)], w, out, c.px.patch);
            moved += add_update(chunk_mut(c.st.flow, r, w * fc), out, w, fc, settled);
        }
    }
    moved
}

/// Adds a row of the disparity head's output (`out`, `w` pixels of `fc`; channel 0 is the
/// update) to the row's disparity state; returns how many pixels moved by more than `settled`.
pub fn add_update(flow: &mut [i16], out: &[i16], w: usize, fc: usize, settled: u16) -> usize {
    let mut moved = 0;
    for x in 0..w {
        let i = x * fc;
        let (Some(f), Some(&delta)) = (flow.get_mut(i), out.get(i)) else { break };
        let before = *f;
        *f = sat_i16(before as i64 + delta as i64);
        moved += ((*f as i64 - before as i64).unsigned_abs() > settled as u64) as usize;
    }
    moved
}

/// `put(at, row)` for each row of the `UP x UP` block of 1/8-grid pixel `(x, y)` that lies inside
/// the `width x height` output, cropped to it: `at` the index of its first value in the output,
/// `row` its values (`UP` or fewer at the right edge).
fn crop_block(x: usize, y: usize, width: usize, height: usize, blk: &[i16; UP * UP], mut put: impl FnMut(usize, &[i16])) {
    let cols = width.saturating_sub(UP * x).min(UP);
    for (dy, row) in blk.chunks_exact(UP).enumerate() {
        let oy = UP * y + dy;
        if oy >= height {
            break;
        }
        put(oy * width + UP * x, row.get(..cols).unwrap_or_default());
    }
}

/// Upsampling: mask head and convex upsampling of disparity (Q10.5 px) and uncertainty (Q4.11)
/// into the cropped `width x height` outputs.
#[inline(never)] // a phase: its stack frame must not add to the caller's (see `engine::STACK_BUDGET`)
pub fn upsample(c: &mut Ctx<'_, '_, '_>, width: usize, height: usize, disp: &mut [i16], mut unc: Option<&mut [i16]>) {
    let m = c.m;
    let cfg = *m.config();
    let g = c.g;
    let (w, h8, hd, fc, mh) = (g.w8, g.h8, cfg.hidden_dim, cfg.flow_channels, cfg.mask_head_dim);
    let lay = FlowHeadLayout::new(&cfg, &g);
    let rings_len = c.rings.len();
    let mut cv = Carver::new(c.rings);
    // (Host: each band's row of the mask head is its thread's, `host_rows::row_bands`.)
    #[cfg(not(feature = "std"))]
    let mid = first_n_mut(cv.i16(lay.head.buf), w * mh);
    let flow0 = cv.i16(lay.flow0);
    // The line buffers past this pass's (the iterations' are larger): the firmware's runs of
    // mask logits.
    #[cfg(not(feature = "std"))]
    let spare = cv.i16(Buf { at: lay.total, len: rings_len.saturating_sub(lay.total) / 8 * 8 });
    let _ = rings_len;
    let (p1, p2) = (conv(m, Mask1), conv(m, Mask2));
    let mask_frac = frac(m, Act::MaskLogit);
    // channel 0 of the disparity state (the only one with MUIR; RAFT's y is 0)
    for (d, f) in flow0.iter_mut().zip(c.st.flow.chunks_exact(fc.max(1))) {
        if let Some(&f) = f.first() {
            *d = f;
        }
    }
    let u_src: Option<&[i16]> = if cfg.mud { Some(&*c.st.u) } else { None };
    #[cfg(not(feature = "std"))]
    let (mut dblk, mut ublk) = ([0i16; UP * UP], [0i16; UP * UP]);
    let flow0 = first_n(flow0, g.n8());
    // Host: the rows in bands, a band a thread (`host_rows::row_bands`); each row's logits by
    // one conv call, its pixels' blocks on the kernel pool where it is free (each writes its own
    // columns of the output). Firmware: row by row, the logits by one conv call per run of
    // pixels (runs of equal length) in the idle line buffers, pixel by pixel where they cannot
    // hold one pixel's logits. A 1x1 convolution: the same integers either way.
    #[cfg(feature = "std")]
    {
        let (dp, dlen) = (crate::kernels::pool::Shared(disp.as_mut_ptr()), disp.len());
        let (up, ulen) = match unc.as_mut() {
            Some(u) => (crate::kernels::pool::Shared(u.as_mut_ptr()), u.len()),
            None => (crate::kernels::pool::Shared(core::ptr::null_mut()), 0),
        };
        let net08 = &*c.frame.net08;
        super::host_rows::row_bands(h8, w * mh, p1.patch_len(), &|y, mid, patch| {
            conv16(&p1, &[full(net08, h8, w * hd, y, 3)], w, mid, patch);
            super::host_rows::mask_logits_row(&p2, mid, w, mh, &|x, logits| {
                let (mut dblk, mut ublk) = ([0i16; UP * UP], [0i16; UP * UP]);
                upsample_pixel(logits, mask_frac, flow0, u_src, h8, w, y, x, &mut dblk, u_src.map(|_| &mut ublk[..]), UP);
                for (blk, (out, len)) in [(&dblk, (&dp, dlen)), (&ublk, (&up, ulen))] {
                    crop_block(x, y, width, height, blk, |at, row| {
                        if at + row.len() <= len {
                            // SAFETY: `at .. at + row.len()` lies inside the output (`len`
                            // values; 0 without uncertainty) and belongs to pixel `x`'s block
                            // of row `y`, which no other task writes.
                            unsafe { out.slice(at, row.len()) }.copy_from_slice(row);
                        }
                    });
                }
            });
        });
    }
    #[cfg(not(feature = "std"))]
    for y in 0..h8 {
        conv16(&p1, &[full(c.frame.net08, h8, w * hd, y, 3)], w, mid, c.px.patch);
        let mut pixel = |x: usize, logits: &mut [i16]| {
            upsample_pixel(logits, mask_frac, flow0, u_src, h8, w, y, x, &mut dblk, u_src.map(|_| &mut ublk[..]), UP);
            crop_block(x, y, width, height, &dblk, |at, row| {
                if let Some(d) = disp.get_mut(at..at + row.len()) {
                    d.copy_from_slice(row);
                }
            });
            if let Some(u) = unc.as_deref_mut() {
                crop_block(x, y, width, height, &ublk, |at, row| {
                    if let Some(d) = u.get_mut(at..at + row.len()) {
                        d.copy_from_slice(row);
                    }
                });
            }
        };
        {
            let per = spare.len() / MASK_CHANNELS;
            if per == 0 {
                for x in 0..w {
                    let mut r = [None; MAX_K];
                    r[0] = Some(chunk(mid, x, mh));
                    let logits = first_n_mut(c.px.logits, MASK_CHANNELS);
                    conv16(&p2, &[PartRows { rows: r }], 1, logits, c.px.patch);
                    pixel(x, logits);
                }
            } else {
                let size = w.div_ceil(w.div_ceil(per).max(1)).max(1);
                let mut x0 = 0;
                while x0 < w {
                    let n = size.min(w - x0);
                    let mut r = [None; MAX_K];
                    r[0] = Some(mid.get(x0 * mh..(x0 + n) * mh).unwrap_or_default());
                    let run = first_n_mut(spare, n * MASK_CHANNELS);
                    conv16(&p2, &[PartRows { rows: r }], n, run, c.px.patch);
                    for (i, logits) in run.chunks_exact_mut(MASK_CHANNELS).enumerate() {
                        pixel(x0 + i, logits);
                    }
                    x0 += n;
                }
            }
        }
    }
}
