//! Streaming encoder: image rows -> layer3 (1/8) through line buffers, then the 1/8 and 1/16
//! heads (hidden state, context, layer4) and the matching features, each a row pipeline.
//!
//! Stages pull their input rows on demand ([`Source::ensure`]); every ring holds only the rows
//! its consumer still needs (3, or 4 in front of a stride-2 block).
//!
//! Buffers are carved from the plan-checked arena with the plan's sizes; rows are taken with the
//! `ring` helpers, which give an empty row instead of panicking where a buffer is shorter than
//! the plan says (which cannot happen for a plan-checked arena).
#![deny(clippy::indexing_slicing)]

use super::layout::{Buf, FeatureHeadLayout, TRUNK_OUT_CAP, TrunkLayout};
use crate::model::grid::Grid;
use super::ring::{Carver, Ring, chunk, chunk_mut, copy_row, first_n_mut, last_input_row};
use crate::arith::sat_u8;
use crate::format::QuantModel;
use crate::input::ImageView;
use crate::kernels::conv::{ConvParams, PartRows, conv_row};
use crate::kernels::eltwise::{Skip, residual_relu};
use crate::kernels::norm::{ChannelNorm, normalize, stats_from_sums};
use crate::kernels::{Elem, OutRow};
use crate::model::graph::{Act, QLayer};
use crate::model::layers::ConvId::{self, *};

/// Shared per-row scratch.
pub struct Scratch<'a> {
    /// Patch gather buffer (bytes; viewed as i8 or i16).
    pub patch: &'a mut [u8],
    /// A conv2 output row (i16).
    pub c2: &'a mut [i16],
    /// A downsample output row (i16).
    pub ds: &'a mut [i16],
}

/// Conv params of a layer the model is known to hold. `QuantModel::parse` checked that every
/// layer the config computes is present, and the engine asks only for those; a missing one would
/// be a layer without outputs ([`ConvParams::EMPTY`]: its rows stay as they are).
pub fn conv<'m>(m: &'m QuantModel<'_>, id: ConvId) -> ConvParams<'m> {
    m.conv(id).unwrap_or(ConvParams::EMPTY)
}

/// Runs `conv_row` with the scratch patch typed as `T`.
pub fn run_conv<T: Elem + bytemuck::Pod>(p: &ConvParams<'_>, inputs: &[PartRows<'_, T>], w_in: usize, out: &mut OutRow<'_>, patch: &mut [u8]) {
    // Two patches when the scratch holds them (conv_row then works on pixel pairs), else one.
    if T::conv_row_wide(p, inputs, w_in, out, patch) {
        return;
    }
    let one = p.patch_len() * core::mem::size_of::<T>();
    let n = if patch.len() >= 2 * one { 2 * one } else { one };
    let patch: &mut [T] = bytemuck::cast_slice_mut(first_n_mut(patch, n));
    conv_row(p, inputs, w_in, out, patch);
}

/// A row producer.
pub trait Source {
    /// Element type of the rows.
    type T: Copy;
    /// Makes rows up to `row` available (no-op for whole tensors).
    fn ensure(&mut self, row: usize, m: &QuantModel<'_>, s: &mut Scratch<'_>);
    /// Input rows of output row `y` of a `k`/`stride` conv.
    fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, Self::T>;
    /// Row `r` (must be available).
    fn row(&self, r: usize) -> &[Self::T];
    /// Rows of the tensor.
    fn rows(&self) -> usize;
    /// Columns of the tensor.
    fn width(&self) -> usize;
}

/// A whole tensor as a source.
pub struct Full<'a, T> {
    /// HWC data.
    pub data: &'a [T],
    /// Rows.
    pub h: usize,
    /// Columns.
    pub w: usize,
    /// Channels.
    pub c: usize,
}

impl<T: Copy> Source for Full<'_, T> {
    type T = T;
    fn ensure(&mut self, _: usize, _: &QuantModel<'_>, _: &mut Scratch<'_>) {}
    fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, T> {
        PartRows::of_tensor(self.data, self.h, self.w * self.c, y, k, stride)
    }
    fn row(&self, r: usize) -> &[T] {
        chunk(self.data, r, self.w * self.c)
    }
    fn rows(&self) -> usize {
        self.h
    }
    fn width(&self) -> usize {
        self.w
    }
}

/// Image rows as `2 * pixel - 255` (i16, 3 channels), right/bottom edge replication.
pub struct ImageRows<'a, 'i> {
    img: &'a ImageView<'i>,
    ring: Ring<'a, i16>,
    w: usize,
}

impl Source for ImageRows<'_, '_> {
    type T = i16;
    fn ensure(&mut self, row: usize, _: &QuantModel<'_>, _: &mut Scratch<'_>) {
        while self.ring.produced() <= row {
            let y = self.ring.produced();
            let (img, w) = (self.img, self.w);
            let dst = self.ring.push();
            for (x, px) in dst.chunks_exact_mut(3).take(w).enumerate() {
                for (c, v) in px.iter_mut().enumerate() {
                    *v = 2 * img.at_clamped(c, x, y) as i16 - 255;
                }
            }
        }
    }
    fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, i16> {
        self.ring.part_rows(y, k, stride)
    }
    fn row(&self, r: usize) -> &[i16] {
        self.ring.row(r)
    }
    fn rows(&self) -> usize {
        self.ring.rows()
    }
    fn width(&self) -> usize {
        self.w
    }
}

/// A single conv as a stage, output rows of `O` (`u8`, or `i16` in a wide trunk).
pub struct ConvStage<'a, S: Source, O> {
    src: S,
    id: ConvId,
    out: Ring<'a, O>,
    w: usize,
}

impl<'a, S: Source, O: Elem> Source for ConvStage<'a, S, O>
where
    S::T: Elem + bytemuck::Pod,
{
    type T = O;
    fn ensure(&mut self, row: usize, m: &QuantModel<'_>, s: &mut Scratch<'_>) {
        let p = conv(m, self.id);
        while self.out.produced() <= row.min(self.out.rows() - 1) {
            let y = self.out.produced();
            self.src.ensure(last_input_row(y, p.k, p.stride, self.src.rows()), m, s);
            let rows = self.src.part_rows(y, p.k, p.stride);
            let w_in = self.src.width();
            run_conv(&p, &[rows], w_in, &mut O::as_out(self.out.push()), s.patch);
        }
    }
    fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, O> {
        self.out.part_rows(y, k, stride)
    }
    fn row(&self, r: usize) -> &[O] {
        self.out.row(r)
    }
    fn rows(&self) -> usize {
        self.out.rows()
    }
    fn width(&self) -> usize {
        self.w
    }
}

/// A residual block (BatchNorm folded): `out = relu(skip + relu(c2(relu(c1(x)))))`, skip = x or a
/// 1x1 downsample conv. Input rows `S::T`, mid and output rows `O` (`u8`, or `i16` in a wide
/// trunk; a block without downsample has `S::T == O`).
pub struct Block<'a, S: Source, O> {
    src: S,
    ids: [ConvId; 2],
    ds: Option<ConvId>,
    stride: usize,
    skip_frac: i8,
    out_frac: i8,
    mid: Ring<'a, O>,
    out: Ring<'a, O>,
    w: usize,
}

impl<'a, S: Source, O: Elem + bytemuck::Pod> Source for Block<'a, S, O>
where
    S::T: Elem + bytemuck::Pod,
{
    type T = O;
    fn ensure(&mut self, row: usize, m: &QuantModel<'_>, s: &mut Scratch<'_>) {
        let (p1, p2) = (conv(m, self.ids[0]), conv(m, self.ids[1]));
        let w_in = self.src.width();
        while self.out.produced() <= row.min(self.out.rows() - 1) {
            let y = self.out.produced();
            let need_mid = (y + 1).min(self.mid.rows() - 1);
            while self.mid.produced() <= need_mid {
                let r = self.mid.produced();
                self.src.ensure(last_input_row(r, 3, self.stride, self.src.rows()), m, s);
                let rows = self.src.part_rows(r, 3, self.stride);
                run_conv(&p1, &[rows], w_in, &mut O::as_out(self.mid.push()), s.patch);
            }
            let n = self.w * p2.cout;
            let c2 = first_n_mut(s.c2, n);
            run_conv(&p2, &[self.mid.part_rows(y, 3, 1)], self.w, &mut OutRow::I16(c2), s.patch);
            let skip = match self.ds {
                Some(d) => {
                    let pd = conv(m, d);
                    let ds = first_n_mut(s.ds, n);
                    run_conv(&pd, &[self.src.part_rows(y, 1, self.stride)], w_in, &mut OutRow::I16(ds), s.patch);
                    Skip::Projected(ds)
                }
                None => Skip::Input { x: self.src.row(y), frac: self.skip_frac },
            };
            residual_relu(c2, skip, self.out_frac, self.out.push());
        }
    }
    fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, O> {
        self.out.part_rows(y, k, stride)
    }
    fn row(&self, r: usize) -> &[O] {
        self.out.row(r)
    }
    fn rows(&self) -> usize {
        self.out.rows()
    }
    fn width(&self) -> usize {
        self.w
    }
}

fn frac(m: &QuantModel<'_>, a: Act) -> i8 {
    m.format(a).frac
}

fn in_frac(m: &QuantModel<'_>, id: ConvId) -> i8 {
    QLayer::of(id, m.config()).and_then(|l| l.parts[0]).map_or(0, |p| frac(m, p.act))
}

#[allow(clippy::too_many_arguments)]
fn block<'a, S: Source, O: Elem>(
    src: S,
    m: &QuantModel<'_>,
    ids: [ConvId; 2],
    ds: Option<ConvId>,
    out_act: Act,
    c: usize,
    bufs: (&'a mut [O], &'a mut [O]),
    out_cap: usize,
) -> Block<'a, S, O> {
    let stride = if ds.is_some() && ids[0].shape(m.config()).is_some_and(|s| s.stride == 2) { 2 } else { 1 };
    let rows = if stride == 2 { src.rows().div_ceil(2) } else { src.rows() };
    let w = if stride == 2 { src.width().div_ceil(2) } else { src.width() };
    Block {
        stride,
        skip_frac: in_frac(m, ids[0]),
        out_frac: frac(m, out_act),
        mid: Ring::new(bufs.0, 3, w * c, rows),
        out: Ring::new(bufs.1, out_cap, w * c, rows),
        w,
        src,
        ids,
        ds,
    }
}

/// Streams one image through conv1 .. layer3 into `l3` (HWC u8, `h8 x w8 x d3`).
pub fn trunk(m: &QuantModel<'_>, img: &ImageView<'_>, g: &Grid, rings: &mut [u8], patch: &mut [u8], l3: &mut [u8]) {
    if m.config().wide_trunk {
        trunk_as::<i16>(m, img, g, rings, patch, l3)
    } else {
        trunk_as::<u8>(m, img, g, rings, patch, l3)
    }
}

/// [`trunk`] with conv1, layer1 and layer2 stored as `T`.
fn trunk_as<T: Elem + bytemuck::Pod>(
    m: &QuantModel<'_>,
    img: &ImageView<'_>,
    g: &Grid,
    rings: &mut [u8],
    patch: &mut [u8],
    l3: &mut [u8],
) {
    let cfg = *m.config();
    let [d1, d2, d3] = cfg.backbone_dims;
    let lay = TrunkLayout::new(&cfg, g);
    let mut cv = Carver::new(rings);
    let image = ImageRows { img, ring: Ring::new(cv.i16(lay.image), 7, g.w * 3, g.h), w: g.w };
    let c1 = ConvStage { src: image, id: Conv1, out: Ring::<T>::new(cv.typed(lay.c1), 3, g.w2 * d1, g.h2), w: g.w2 };
    let [k0, k1, k2, k3, (a4, b4), (a5, b5)] = lay.blocks;
    let mut take = |(a, b): (Buf, Buf)| -> (&mut [T], &mut [T]) { (cv.typed(a), cv.typed(b)) };
    let b0 = take(k0);
    let b1 = take(k1);
    let b2 = take(k2);
    let b3 = take(k3);
    let b4 = (cv.u8(a4), cv.u8(b4));
    let b5 = (cv.u8(a5), cv.u8(b5));
    let c2 = cv.i16(lay.c2);
    let ds = cv.i16(lay.ds);
    use Act as A;
    let x = block(c1, m, [L1b0c1, L1b0c2], None, A::L1b0o, d1, b0, TRUNK_OUT_CAP[0]);
    let x = block(x, m, [L1b1c1, L1b1c2], None, A::L1b1o, d1, b1, TRUNK_OUT_CAP[1]);
    let x = block(x, m, [L2b0c1, L2b0c2], Some(L2b0ds), A::L2b0o, d2, b2, TRUNK_OUT_CAP[2]);
    let x = block(x, m, [L2b1c1, L2b1c2], None, A::L2b1o, d2, b3, TRUNK_OUT_CAP[3]);
    let x = block(x, m, [L3b0c1, L3b0c2], Some(L3b0ds), A::L3b0o, d3, b4, TRUNK_OUT_CAP[4]);
    let mut x = block(x, m, [L3b1c1, L3b1c2], None, A::L3b1o, d3, b5, TRUNK_OUT_CAP[5]);
    let mut s = Scratch { patch, c2, ds };
    let row = g.w8 * d3;
    for y in 0..g.h8 {
        x.ensure(y, m, &mut s);
        copy_row(chunk_mut(l3, y, row), x.row(y));
    }
}

/// Context heads on the 1/8 (or 1/16) features: block + 3x3 conv; the output rows go to `out`
/// (HWC, `i16` for the hidden state, `u8` for the context).
#[allow(clippy::too_many_arguments)]
fn head(m: &QuantModel<'_>, x: &[u8], h: usize, w: usize, ids: [ConvId; 3], out_act: Act, lay: &FeatureHeadLayout, rings: &mut [u8], patch: &mut [u8], out: OutRow<'_>) {
    let d3 = m.config().backbone_dims[2];
    let mut cv = Carver::new(rings);
    let bufs = (cv.u8(lay.blocks[0].0), cv.u8(lay.blocks[0].1));
    let c2 = cv.i16(lay.c2);
    let ds = cv.i16(lay.ds);
    let mut b = block(Full { data: x, h, w, c: d3 }, m, [ids[0], ids[1]], None, out_act, d3, bufs, 3);
    let mut s = Scratch { patch, c2, ds };
    let p = conv(m, ids[2]);
    let n = w * p.cout;
    let mut out = out;
    for y in 0..h {
        b.ensure(last_input_row(y, 3, 1, h), m, &mut s);
        let rows = b.part_rows(y, 3, 1);
        match &mut out {
            OutRow::I8(o) => run_conv(&p, &[rows], w, &mut OutRow::I8(chunk_mut(o, y, n)), s.patch),
            OutRow::U8(o) => run_conv(&p, &[rows], w, &mut OutRow::U8(chunk_mut(o, y, n)), s.patch),
            OutRow::I16(o) => run_conv(&p, &[rows], w, &mut OutRow::I16(chunk_mut(o, y, n)), s.patch),
        }
    }
}

/// layer4 (two blocks, the first with stride 2) from `l3` into `l4`.
fn layer4(m: &QuantModel<'_>, l3: &[u8], g: &Grid, lay: &FeatureHeadLayout, rings: &mut [u8], patch: &mut [u8], l4: &mut [u8]) {
    let d3 = m.config().backbone_dims[2];
    let mut cv = Carver::new(rings);
    let b0 = (cv.u8(lay.blocks[0].0), cv.u8(lay.blocks[0].1));
    let b1 = (cv.u8(lay.blocks[1].0), cv.u8(lay.blocks[1].1));
    let c2 = cv.i16(lay.c2);
    let ds = cv.i16(lay.ds);
    let x = block(Full { data: l3, h: g.h8, w: g.w8, c: d3 }, m, [L4b0c1, L4b0c2], Some(L4b0ds), Act::L4b0o, d3, b0, 3);
    let mut x = block(x, m, [L4b1c1, L4b1c2], None, Act::L4b1o, d3, b1, 1);
    let mut s = Scratch { patch, c2, ds };
    let row = g.w16 * d3;
    for y in 0..g.h16 {
        x.ensure(y, m, &mut s);
        copy_row(chunk_mut(l4, y, row), x.row(y));
    }
}

/// Matching features: InstanceNorm residual block + conv, from `l3` into `f` (HWC i8). The
/// InstanceNorm statistics need whole maps, so the rows are computed three times: conv1 for its
/// statistics, conv1 + norm + conv2 for the second statistics, then everything for the output.
#[allow(clippy::too_many_arguments)]
fn features(m: &QuantModel<'_>, l3: &[u8], g: &Grid, lay: &FeatureHeadLayout, rings: &mut [u8], patch: &mut [u8], norms: &mut [i64], f: &mut [i8]) {
    if m.config().backbone_dims[2] == 0 {
        return; // no feature channels (a parsed config has them): nothing to compute
    }
    #[cfg(feature = "std")]
    {
        let _ = (lay, rings);
        features_kept(m, l3, g, patch, norms, f);
    }
    #[cfg(not(feature = "std"))]
    features_streamed(m, l3, g, lay, rings, patch, norms, f);
}

/// [`features`] in the plan's line buffers: conv1's rows computed again for each of the three
/// passes that read them and conv2's for both (a microcontroller's RAM holds a few rows, not
/// the tensors).
#[cfg(not(feature = "std"))]
#[allow(clippy::too_many_arguments)]
fn features_streamed(m: &QuantModel<'_>, l3: &[u8], g: &Grid, lay: &FeatureHeadLayout, rings: &mut [u8], patch: &mut [u8], norms: &mut [i64], f: &mut [i8]) {
    let d3 = m.config().backbone_dims[2];
    let (h, w) = (g.h8, g.w8);
    let n = (h * w) as i64;
    let src = Full { data: l3, h, w, c: d3 };
    let (p1, p2, p3) = (conv(m, FmapC1), conv(m, FmapC2), conv(m, FmapOut));
    let (f_raw1, f_mid, f_raw2, f_blk, f_l3) =
        (frac(m, Act::FmapRaw1), frac(m, Act::FmapMid), frac(m, Act::FmapRaw2), frac(m, Act::FmapBlk), frac(m, Act::L3b1o));
    let mut cv = Carver::new(rings);
    let raw = cv.i16(lay.raw);
    let mid_buf = cv.u8(lay.mid);
    let blk_buf = cv.u8(lay.blk);
    let row = w * d3;
    let ybuf = first_n_mut(cv.i16(lay.y), row);
    // The plan's statistics buffer holds both passes' (2 x d3 each).
    let Some((st1, st2)) = norms.split_at_mut_checked(2 * d3) else { return };
    // Pass 1: statistics of conv1.
    accumulate_stats(st1, d3, |r, out| run_conv(&p1, &[src.part_rows(r, 3, 1)], w, &mut OutRow::I16(out), patch), h, raw, row);
    let stats1 = finish_stats(st1, d3, n, f_raw1);
    // mid row r = relu(norm(conv1 row r)) as u8 (the saturation is the ReLU)
    let mid_row = |r: usize, raw: &mut [i16], patch: &mut [u8], dst: &mut [u8]| {
        let raw = first_n_mut(raw, row);
        run_conv(&p1, &[src.part_rows(r, 3, 1)], w, &mut OutRow::I16(raw), patch);
        normalize_u8(raw, stats1, d3, f_mid, dst);
    };
    // Pass 2: statistics of conv2 over the normalised conv1 rows.
    st2.fill(0);
    {
        let mut mid = Ring::new(&mut mid_buf[..], 3, row, h);
        for y in 0..h {
            while mid.produced() <= last_input_row(y, 3, 1, h) {
                let r = mid.produced();
                mid_row(r, raw, patch, mid.push());
            }
            run_conv(&p2, &[mid.part_rows(y, 3, 1)], w, &mut OutRow::I16(ybuf), patch);
            add_sums(st2, d3, ybuf);
        }
    }
    let stats2 = finish_stats(st2, d3, n, f_raw2);
    // Pass 3: output rows.
    let mut mid = Ring::new(&mut mid_buf[..], 3, row, h);
    let mut blk = Ring::new(&mut blk_buf[..], 3, row, h);
    let fo = w * p3.cout;
    for y in 0..h {
        while blk.produced() <= last_input_row(y, 3, 1, h) {
            let r = blk.produced();
            while mid.produced() <= last_input_row(r, 3, 1, h) {
                let q = mid.produced();
                mid_row(q, raw, patch, mid.push());
            }
            run_conv(&p2, &[mid.part_rows(r, 3, 1)], w, &mut OutRow::I16(ybuf), patch);
            normalize_relu_i16(ybuf, stats2, d3, f_blk);
            residual_relu(ybuf, Skip::Input { x: chunk(l3, r, row), frac: f_l3 }, f_blk, blk.push());
        }
        run_conv(&p3, &[blk.part_rows(y, 3, 1)], w, &mut OutRow::I8(chunk_mut(f, y, fo)), patch);
    }
}

/// [`features_kept`]'s tensors: conv1's raw rows, their normalised form, conv2's raw rows and
/// the residual block's output.
#[cfg(feature = "std")]
type FeatureTensors = (Vec<i16>, Vec<u8>, Vec<i16>, Vec<u8>);

#[cfg(feature = "std")]
std::thread_local! {
    /// [`FeatureTensors`] on the thread that encodes.
    static FEATURES: core::cell::RefCell<FeatureTensors> = const { core::cell::RefCell::new((Vec::new(), Vec::new(), Vec::new(), Vec::new())) };
}

/// [`features`] on the host: each pass's rows kept whole for the next (in this thread's memory,
/// not the plan's line buffers), so conv1 runs once instead of three times and conv2 once
/// instead of twice (a microcontroller recomputes them rather than hold `h8 x w8 x 64` values
/// each). The same convolutions of the same rows, the same statistics: the same integers.
#[cfg(feature = "std")]
fn features_kept(m: &QuantModel<'_>, l3: &[u8], g: &Grid, patch: &mut [u8], norms: &mut [i64], f: &mut [i8]) {
    use crate::kernels::pool::scratch;
    let d3 = m.config().backbone_dims[2];
    let (h, w) = (g.h8, g.w8);
    let n = (h * w) as i64;
    let row = w * d3;
    let src = Full { data: l3, h, w, c: d3 };
    let (p1, p2, p3) = (conv(m, FmapC1), conv(m, FmapC2), conv(m, FmapOut));
    let (f_raw1, f_mid, f_raw2, f_blk, f_l3) =
        (frac(m, Act::FmapRaw1), frac(m, Act::FmapMid), frac(m, Act::FmapRaw2), frac(m, Act::FmapBlk), frac(m, Act::L3b1o));
    let Some((st1, st2)) = norms.split_at_mut_checked(2 * d3) else { return };
    FEATURES.with_borrow_mut(|(raw1, mid, raw2, blk)| {
        let (raw1, mid, raw2, blk) = (scratch(raw1, h * row), scratch(mid, h * row), scratch(raw2, h * row), scratch(blk, h * row));
        // Pass 1: conv1, its statistics.
        st1.fill(0);
        for (y, r) in raw1.chunks_exact_mut(row.max(1)).enumerate() {
            run_conv(&p1, &[src.part_rows(y, 3, 1)], w, &mut OutRow::I16(r), patch);
            add_sums(st1, d3, r);
        }
        let stats1 = finish_stats(st1, d3, n, f_raw1);
        // Pass 2: relu(norm(conv1)) as u8 (the saturation is the ReLU), conv2 of it, its statistics.
        normalize_u8(raw1, stats1, d3, f_mid, mid);
        st2.fill(0);
        for (y, r) in raw2.chunks_exact_mut(row.max(1)).enumerate() {
            run_conv(&p2, &[PartRows::of_tensor(mid, h, row, y, 3, 1)], w, &mut OutRow::I16(r), patch);
            add_sums(st2, d3, r);
        }
        let stats2 = finish_stats(st2, d3, n, f_raw2);
        // Pass 3: the residual block's rows, then the output conv.
        normalize_relu_i16(raw2, stats2, d3, f_blk);
        for (y, (r, b)) in raw2.chunks_exact(row.max(1)).zip(blk.chunks_exact_mut(row.max(1))).enumerate() {
            residual_relu(r, Skip::Input { x: chunk(l3, y, row), frac: f_l3 }, f_blk, b);
        }
        let fo = w * p3.cout;
        for y in 0..h {
            run_conv(&p3, &[PartRows::of_tensor(blk, h, row, y, 3, 1)], w, &mut OutRow::I8(chunk_mut(f, y, fo)), patch);
        }
    });
}

#[cfg(not(feature = "std"))]
fn accumulate_stats(st: &mut [i64], c: usize, mut conv_row_fn: impl FnMut(usize, &mut [i16]), h: usize, raw: &mut [i16], row: usize) {
    st.fill(0);
    let raw = first_n_mut(raw, row);
    for y in 0..h {
        conv_row_fn(y, raw);
        add_sums(st, c, raw);
    }
}

fn add_sums(st: &mut [i64], c: usize, row: &[i16]) {
    if c == 0 {
        return; // no channels
    }
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if crate::kernels::norm::avx512::add_moments(st, c, row) {
        return;
    }
    // Pixel by pixel, channel `i` of a pixel to pair `i` of `st` (no division per value).
    for px in row.chunks_exact(c) {
        for (v, pair) in px.iter().zip(st.chunks_exact_mut(2)) {
            if let [sum, squares] = pair {
                *sum += *v as i64;
                *squares += *v as i64 * *v as i64;
            }
        }
    }
}

/// `dst[i] = sat_u8(normalize(src[i], stat(channel of i), f_out))` (the saturation is the
/// ReLU) for `[pixel][channel]` values: on 512-bit vectors where the host has them
/// ([`crate::kernels::norm::avx512`]), else by [`normalize_row`].
fn normalize_u8(src: &[i16], st: &[i64], c: usize, f_out: i8, dst: &mut [u8]) {
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if crate::kernels::norm::avx512::normalize_u8(src, st, c, f_out, dst) {
        return;
    }
    normalize_row(src, st, c, dst, |v, s| sat_u8(normalize(v, s, f_out)));
}

/// `row[i] = sat_i16(max(normalize(row[i], stat(channel of i), f_out), 0))` in place, as
/// [`normalize_u8`] (vectors where the host has them, else [`normalize_in_place`]).
fn normalize_relu_i16(row: &mut [i16], st: &[i64], c: usize, f_out: i8) {
    #[cfg(all(target_arch = "x86_64", feature = "std"))]
    if crate::kernels::norm::avx512::normalize_relu_i16(row, st, c, f_out) {
        return;
    }
    normalize_in_place(row, st, c, |v, s| crate::arith::sat_i16(normalize(v, s, f_out).max(0)));
}

/// `dst[i] = f(src[i], stat(channel of i))` for rows of `c`-channel pixels (`st` the statistics
/// pairs of [`finish_stats`]), pixel by pixel without a division per value.
fn normalize_row<T>(src: &[i16], st: &[i64], c: usize, dst: &mut [T], f: impl Fn(i16, ChannelNorm) -> T) {
    if c == 0 {
        return; // no channels
    }
    for (dp, sp) in dst.chunks_exact_mut(c).zip(src.chunks_exact(c)) {
        for ((d, v), pair) in dp.iter_mut().zip(sp).zip(st.chunks_exact(2)) {
            if let &[mean, recip] = pair {
                *d = f(*v, ChannelNorm { mean, recip });
            }
        }
    }
}

/// [`normalize_row`] of a row onto itself.
fn normalize_in_place(row: &mut [i16], st: &[i64], c: usize, f: impl Fn(i16, ChannelNorm) -> i16) {
    if c == 0 {
        return; // no channels
    }
    for px in row.chunks_exact_mut(c) {
        for (v, pair) in px.iter_mut().zip(st.chunks_exact(2)) {
            if let &[mean, recip] = pair {
                *v = f(*v, ChannelNorm { mean, recip });
            }
        }
    }
}

/// Turns per-channel (sum, sum of squares) into statistics, in place: (mean, recip).
fn finish_stats(st: &mut [i64], c: usize, n: i64, f_in: i8) -> &[i64] {
    for pair in st.chunks_exact_mut(2).take(c) {
        if let [a, b] = pair {
            let s = stats_from_sums(*a, *b, n, f_in);
            (*a, *b) = (s.mean, s.recip);
        }
    }
    st
}

/// Frame-zone outputs of the encoder.
pub struct EncoderOut<'a> {
    /// Matching features of this image.
    pub features: &'a mut [i8],
    /// Left image only: hidden states and context.
    pub context: Option<ContextOut<'a>>,
}

/// Context outputs (left image).
pub struct ContextOut<'a> {
    /// 1/8 hidden state (Q0.15).
    pub net08: &'a mut [i16],
    /// 1/16 hidden state.
    pub net16: &'a mut [i16],
    /// 1/8 context (u8).
    pub inp08: &'a mut [u8],
    /// 1/16 context.
    pub inp16: &'a mut [u8],
}

/// Encoder scratch for one image.
pub struct EncoderScratch<'a> {
    /// layer3 (whole).
    pub l3: &'a mut [u8],
    /// layer4 (whole).
    pub l4: &'a mut [u8],
    /// InstanceNorm statistics.
    pub norms: &'a mut [i64],
    /// Line buffers.
    pub rings: &'a mut [u8],
    /// Patch scratch.
    pub patch: &'a mut [u8],
}

/// Encodes one image: features, and for the left image the context.
pub fn encode(m: &QuantModel<'_>, img: &ImageView<'_>, g: &Grid, s: EncoderScratch<'_>, out: EncoderOut<'_>) {
    trunk(m, img, g, s.rings, s.patch, s.l3);
    image_features(m, s.l3, g, s.rings, s.patch, s.norms, out.features);
    if let Some(ctx) = out.context {
        hidden08(m, s.l3, g, s.rings, s.patch, ctx.net08);
        context_rest(m, s.l3, g, s.rings, s.patch, s.l4, ctx.inp08, ctx.net16, ctx.inp16);
    }
}

/// The matching features from the image's layer3 `l3` into `f`.
pub(super) fn image_features(m: &QuantModel<'_>, l3: &[u8], g: &Grid, rings: &mut [u8], patch: &mut [u8], norms: &mut [i64], f: &mut [i8]) {
    let lay = FeatureHeadLayout::new(m.config(), g);
    features(m, l3, g, &lay, rings, patch, norms, f);
}

/// The left image's context, first part: the 1/8 hidden state's head. (The context is computed
/// in two parts so that two threads can share it, this one about a third of the work.)
pub(super) fn hidden08(m: &QuantModel<'_>, l3: &[u8], g: &Grid, rings: &mut [u8], patch: &mut [u8], net08: &mut [i16]) {
    let lay = FeatureHeadLayout::new(m.config(), g);
    head(m, l3, g.h8, g.w8, [H08nC1, H08nC2, H08nOut], Act::H08no, &lay, rings, patch, OutRow::I16(net08));
}

/// The left image's context, second part: the 1/8 context head, layer4 (into `l4`) and the two
/// 1/16 heads. It reads only `l3` and writes outputs of its own, so it may run beside
/// [`hidden08`] and the features.
#[allow(clippy::too_many_arguments)]
pub(super) fn context_rest(m: &QuantModel<'_>, l3: &[u8], g: &Grid, rings: &mut [u8], patch: &mut [u8], l4: &mut [u8], inp08: &mut [u8], net16: &mut [i16], inp16: &mut [u8]) {
    use Act as A;
    let lay = FeatureHeadLayout::new(m.config(), g);
    head(m, l3, g.h8, g.w8, [H08cC1, H08cC2, H08cOut], A::H08co, &lay, rings, patch, OutRow::U8(inp08));
    layer4(m, l3, g, &lay, rings, patch, l4);
    head(m, l4, g.h16, g.w16, [H16nC1, H16nC2, H16nOut], A::H16no, &lay, rings, patch, OutRow::I16(net16));
    head(m, l4, g.h16, g.w16, [H16cC1, H16cC2, H16cOut], A::H16co, &lay, rings, patch, OutRow::U8(inp16));
}
