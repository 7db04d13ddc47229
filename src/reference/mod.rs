//! Plain fixed-point engine (host): the quantised network over whole tensors, with the plain
//! kernel twins. It defines what the streaming engine (`muir::engine`) must compute bit for bit,
//! and exposes every intermediate tensor (dequantised) for per-layer SQNR against the float
//! reference.

use muir::arith::{FLOW_FRAC, LOG_FRAC, UNIT_FRAC, lut, sat_i16};
use crate::float::{Tensor, Trace};
use muir::format::QuantModel;
use muir::input::{ImageView, InputError, check_pair};
use muir::kernels::attention::{attention_plain, rope_pixel};
use muir::kernels::conv::conv_plain;
use muir::kernels::corr::{LookupParams, lookup_pixel_plain, peaks_pixel_plain};
use muir::kernels::eltwise::{Skip, blend_q15, mud_mask, mul_plane_q15, mul_q15, proposal_flow, residual_relu};
use muir::kernels::norm::{channel_stats, normalize};
use muir::kernels::resample::{interp_row, pool2x_row};
use muir::kernels::upsample::upsample_pixel;
use muir::kernels::Elem;
use muir::model::config::Config;
use muir::model::graph::Act;
use muir::model::layers::ConvId::{self, *};

/// A whole HWC tensor.
#[derive(Clone, Debug, PartialEq)]
pub struct QT<T> {
    /// Rows.
    pub h: usize,
    /// Columns.
    pub w: usize,
    /// Channels.
    pub c: usize,
    /// `h * w * c` values.
    pub d: Vec<T>,
}

impl<T: Elem> QT<T> {
    fn zeros(h: usize, w: usize, c: usize) -> Self {
        Self { h, w, c, d: vec![T::default(); h * w * c] }
    }
    /// Channels `[from, from + n)`.
    fn channels(&self, from: usize, n: usize) -> Self {
        let mut d = Vec::with_capacity(self.h * self.w * n);
        for px in self.d.chunks(self.c) {
            d.extend_from_slice(&px[from..from + n]);
        }
        Self { h: self.h, w: self.w, c: n, d }
    }
    /// Dequantised CHW float tensor (for traces).
    pub fn to_tensor(&self, frac: i8) -> Tensor {
        let s = 2f32.powi(-(frac as i32));
        let mut t = Tensor::zeros(self.c, self.h, self.w);
        for (p, px) in self.d.chunks(self.c).enumerate() {
            for (ch, v) in px.iter().enumerate() {
                t.data[ch * self.h * self.w + p] = v.to_i32() as f32 * s;
            }
        }
        t
    }
}

/// Output of the fixed-point network at the padded input size.
#[derive(Clone, Debug, PartialEq)]
pub struct FixedOutput {
    /// Columns (padded).
    pub width: usize,
    /// Rows (padded).
    pub height: usize,
    /// Disparity, Q10.5 pixels ([`muir::arith::DISP_FRAC`]).
    pub disparity: Vec<i16>,
    /// Uncertainty `u`, Q4.11; `None` without MUD.
    pub uncertainty: Option<Vec<i16>>,
}

/// The plain fixed-point engine.
pub struct Reference<'m, 'a> {
    m: &'m QuantModel<'a>,
    inject: Option<&'m crate::calib::Records>,
    max_disparity: muir::model::config::MaxDisparity,
}

/// Encoder outputs.
pub struct Ctx {
    /// Left features.
    pub f1: QT<i8>,
    /// Right features.
    pub f2: QT<i8>,
    /// 1/8 hidden state.
    pub net08: QT<i16>,
    /// 1/16 hidden state.
    pub net16: QT<i16>,
    /// 1/8 context (stored u8, widened once here since only i16 convs read it).
    pub inp08: QT<i16>,
    /// 1/16 context.
    pub inp16: QT<i16>,
}

impl<'m, 'a> Reference<'m, 'a> {
    /// Wraps a parsed model.
    pub fn new(m: &'m QuantModel<'a>) -> Self {
        Self { m, inject: None, max_disparity: Default::default() }
    }

    /// The same with another largest disparity of UFI's proposal search (default 256 px).
    pub fn with_max_disparity(self, max: muir::model::config::MaxDisparity) -> Self {
        Self { max_disparity: max, ..self }
    }

    /// Diagnostic: replaces the tensors named `backbone.conv1`, `backbone.layer1`, `backbone.layer2`,
    /// `backbone.layer3`, `fmap1`, `fmap2`, `inp08`, `inp16`, `ufi.peaks`, `init.flow` and
    /// `init.net08` (after UFI) by the given float records, quantised to their slots, so that the
    /// effect of quantising one part of the network can be measured on its own
    /// (`examples/quant_drift.rs`).
    #[doc(hidden)]
    pub fn with_injected(m: &'m QuantModel<'a>, float_records: &'m crate::calib::Records) -> Self {
        Self { m, inject: Some(float_records), max_disparity: Default::default() }
    }

    fn injected(&self, name: &str) -> Option<&Tensor> {
        self.inject?.0.iter().find(|(n, _)| n == name).map(|(_, t)| t)
    }

    /// `t` (CHW float) quantised into an HWC tensor of format `frac`.
    fn quantize_like<T: Elem>(&self, t: &Tensor, frac: i8) -> QT<T> {
        let f = muir::arith::QFormat { frac, ..T::STORAGE };
        let mut q = QT::<T>::zeros(t.h, t.w, t.c);
        for ch in 0..t.c {
            for p in 0..t.h * t.w {
                q.d[p * t.c + ch] = T::from_i64_sat(f.quantize(t.data[ch * t.h * t.w + p]));
            }
        }
        q
    }

    fn cfg(&self) -> &Config {
        self.m.config()
    }

    fn frac(&self, a: Act) -> i8 {
        self.m.format(a).frac
    }

    fn conv<T: Elem, O: Elem>(&self, id: ConvId, inputs: &[&QT<T>]) -> QT<O> {
        // Layers asked for here exist: QuantModel::parse checked every computed layer.
        let p = self.m.conv(id).unwrap_or_else(|| panic!("layer {} missing", id.name()));
        let (h, w) = (inputs[0].h, inputs[0].w);
        let ho = (h + 2 * (p.k / 2) - p.k) / p.stride + 1;
        let wo = p.out_width(w);
        let mut out = QT::<O>::zeros(ho, wo, p.cout);
        let ins: Vec<&[T]> = inputs.iter().map(|t| t.d.as_slice()).collect();
        let mut row = O::as_out(&mut out.d);
        conv_plain(&p, &ins, h, w, &mut row);
        out
    }

    fn record<T: Elem>(&self, tr: &mut dyn Trace, name: &str, t: &QT<T>, frac: i8) {
        if tr.active() {
            tr.record(name, &t.to_tensor(frac));
        }
    }

    /// A residual block on input `X`, mid and output `O` (`u8`, or `i16` in a wide trunk).
    fn block<X: Elem, O: Elem>(
        &self,
        x: &QT<X>,
        ids: [ConvId; 2],
        ds: Option<ConvId>,
        acts: [Act; 2],
        tr: &mut dyn Trace,
    ) -> QT<O> {
        let mid: QT<O> = self.conv(ids[0], &[x]);
        self.record(tr, &format!("q.{}", acts[0].name()), &mid, self.frac(acts[0]));
        let y: QT<i16> = self.conv(ids[1], &[&mid]);
        let f_out = self.frac(acts[1]);
        let mut out = QT::<O>::zeros(y.h, y.w, y.c);
        match ds {
            Some(d) => {
                let p: QT<i16> = self.conv(d, &[x]);
                residual_relu(&y.d, Skip::<X>::Projected(&p.d), f_out, &mut out.d);
            }
            None => {
                let f_in = self.in_frac(ids[0]);
                residual_relu(&y.d, Skip::Input { x: &x.d, frac: f_in }, f_out, &mut out.d)
            }
        }
        self.record(tr, &format!("q.{}", acts[1].name()), &out, f_out);
        out
    }

    fn in_frac(&self, id: ConvId) -> i8 {
        let ql = muir::model::graph::QLayer::of(id, self.cfg());
        ql.and_then(|l| l.parts[0]).map_or(0, |p| self.frac(p.act))
    }

    /// Padded integer image (`2 * pixel - 255`).
    pub fn image(&self, im: &ImageView<'_>, pw: usize, ph: usize) -> QT<i16> {
        let mut t = QT::<i16>::zeros(ph, pw, 3);
        for y in 0..ph {
            for x in 0..pw {
                for c in 0..3 {
                    t.d[(y * pw + x) * 3 + c] = 2 * im.at_clamped(c, x, y) as i16 - 255;
                }
            }
        }
        t
    }

    /// Float trunk tensor `name` of one image (`side` 0 left, 1 right; the float trace holds both
    /// concatenated along channels) quantised to `act`'s slot, or `x` when nothing is injected.
    fn inject_side<T: Elem>(&self, name: &str, side: usize, act: Act, x: QT<T>) -> QT<T> {
        match self.injected(name) {
            Some(t) => self.quantize_like(&t.channels(side * t.c / 2, t.c / 2), self.frac(act)),
            None => x,
        }
    }

    fn trunk(&self, img: &QT<i16>, side: usize, tr: &mut dyn Trace) -> QT<u8> {
        if self.cfg().wide_trunk { self.trunk_as::<i16>(img, side, tr) } else { self.trunk_as::<u8>(img, side, tr) }
    }

    /// [`Self::trunk`] with conv1, layer1 and layer2 stored as `T`.
    fn trunk_as<T: Elem>(&self, img: &QT<i16>, side: usize, tr: &mut dyn Trace) -> QT<u8> {
        let c1: QT<T> = self.conv(Conv1, &[img]);
        let c1 = self.inject_side("backbone.conv1", side, Act::C1, c1);
        self.record(tr, "q.c1", &c1, self.frac(Act::C1));
        use Act as A;
        let x: QT<T> = self.block(&c1, [L1b0c1, L1b0c2], None, [A::L1b0m, A::L1b0o], tr);
        let x: QT<T> = self.block(&x, [L1b1c1, L1b1c2], None, [A::L1b1m, A::L1b1o], tr);
        let x = self.inject_side("backbone.layer1", side, A::L1b1o, x);
        let x: QT<T> = self.block(&x, [L2b0c1, L2b0c2], Some(L2b0ds), [A::L2b0m, A::L2b0o], tr);
        let x: QT<T> = self.block(&x, [L2b1c1, L2b1c2], None, [A::L2b1m, A::L2b1o], tr);
        let x = self.inject_side("backbone.layer2", side, A::L2b1o, x);
        let x: QT<u8> = self.block(&x, [L3b0c1, L3b0c2], Some(L3b0ds), [A::L3b0m, A::L3b0o], tr);
        self.block(&x, [L3b1c1, L3b1c2], None, [A::L3b1m, A::L3b1o], tr)
    }

    fn instance_norm_relu(&self, raw: &QT<i16>, f_in: i8, f_out: i8) -> QT<i16> {
        let mut out = QT::<i16>::zeros(raw.h, raw.w, raw.c);
        for ch in 0..raw.c {
            let s = channel_stats(&raw.d, raw.c, ch, f_in);
            for p in 0..raw.h * raw.w {
                let i = p * raw.c + ch;
                out.d[i] = sat_i16(normalize(raw.d[i], s, f_out).max(0));
            }
        }
        out
    }

    fn fmap(&self, l3: &QT<u8>, tr: &mut dyn Trace) -> QT<i8> {
        let raw1: QT<i16> = self.conv(FmapC1, &[l3]);
        self.record(tr, "q.fmap_raw1", &raw1, self.frac(Act::FmapRaw1));
        let mid16 = self.instance_norm_relu(&raw1, self.frac(Act::FmapRaw1), self.frac(Act::FmapMid));
        let mid = QT { h: mid16.h, w: mid16.w, c: mid16.c, d: mid16.d.iter().map(|v| u8::from_i64_sat(*v as i64)).collect() };
        self.record(tr, "q.fmap_mid", &mid, self.frac(Act::FmapMid));
        let raw2: QT<i16> = self.conv(FmapC2, &[&mid]);
        self.record(tr, "q.fmap_raw2", &raw2, self.frac(Act::FmapRaw2));
        let f_blk = self.frac(Act::FmapBlk);
        let y = self.instance_norm_relu(&raw2, self.frac(Act::FmapRaw2), f_blk);
        let mut blk = QT::<u8>::zeros(y.h, y.w, y.c);
        residual_relu(&y.d, Skip::Input { x: &l3.d, frac: self.frac(Act::L3b1o) }, f_blk, &mut blk.d);
        self.record(tr, "q.fmap_blk", &blk, f_blk);
        let f: QT<i8> = self.conv(FmapOut, &[&blk]);
        self.record(tr, "q.fmap", &f, self.frac(Act::Fmap));
        f
    }

    /// The encoder on padded integer images.
    pub fn encode(&self, left: &QT<i16>, right: &QT<i16>, tr: &mut dyn Trace) -> Ctx {
        use Act as A;
        let (mut xl, mut xr) = (self.trunk(left, 0, tr), self.trunk(right, 1, tr));
        if let Some(t) = self.injected("backbone.layer3") {
            // The float trace holds left and right concatenated along channels.
            let c = t.c / 2;
            xl = self.quantize_like(&t.channels(0, c), self.frac(A::L3b1o));
            xr = self.quantize_like(&t.channels(c, c), self.frac(A::L3b1o));
        }
        let f1 = self.fmap(&xl, tr);
        let f2 = self.fmap(&xr, tr);
        self.record(tr, "fmap1", &f1, self.frac(A::Fmap));
        self.record(tr, "fmap2", &f2, self.frac(A::Fmap));
        let head = |x: &QT<u8>, ids: [ConvId; 3], acts: [Act; 2], tr: &mut dyn Trace| -> QT<i16> {
            let b: QT<u8> = self.block(x, [ids[0], ids[1]], None, acts, tr);
            self.conv(ids[2], &[&b])
        };
        let head8 = |x: &QT<u8>, ids: [ConvId; 3], acts: [Act; 2], tr: &mut dyn Trace| -> QT<i16> {
            let b: QT<u8> = self.block(x, [ids[0], ids[1]], None, acts, tr);
            widen(&self.conv::<u8, u8>(ids[2], &[&b]))
        };
        let net08 = head(&xl, [H08nC1, H08nC2, H08nOut], [A::H08nm, A::H08no], tr);
        let inp08 = head8(&xl, [H08cC1, H08cC2, H08cOut], [A::H08cm, A::H08co], tr);
        let x: QT<u8> = self.block(&xl, [L4b0c1, L4b0c2], Some(L4b0ds), [A::L4b0m, A::L4b0o], tr);
        let y: QT<u8> = self.block(&x, [L4b1c1, L4b1c2], None, [A::L4b1m, A::L4b1o], tr);
        let net16 = head(&y, [H16nC1, H16nC2, H16nOut], [A::H16nm, A::H16no], tr);
        let inp16 = head8(&y, [H16cC1, H16cC2, H16cOut], [A::H16cm, A::H16co], tr);
        self.record(tr, "net08.init", &net08, UNIT_FRAC as i8);
        self.record(tr, "net16.init", &net16, UNIT_FRAC as i8);
        self.record(tr, "q.inp08", &inp08, self.frac(A::Inp08));
        self.record(tr, "q.inp16", &inp16, self.frac(A::Inp16));
        Ctx { f1, f2, net08, net16, inp08, inp16 }
    }

    fn lookup(&self, c: &Ctx, flow: &QT<i16>) -> QT<i16> {
        let cfg = self.cfg();
        let mults = self.m.corr_mults();
        let p = LookupParams { levels: cfg.corr_levels, radius: cfg.corr_radius, post_pool: cfg.post_pool, mults: &mults };
        let (h, w, fc) = (c.f1.h, c.f1.w, c.f1.c);
        let cc = cfg.corr_channels();
        let mut out = QT::<i16>::zeros(h, w, cc);
        for y in 0..h {
            let f2 = &c.f2.d[y * w * fc..(y + 1) * w * fc];
            for x in 0..w {
                let px = y * w + x;
                let f1 = &c.f1.d[px * fc..(px + 1) * fc];
                lookup_pixel_plain(&p, f1, f2, w, x, flow.d[px * flow.c], &mut out.d[px * cc..(px + 1) * cc]);
            }
        }
        out
    }

    /// MUD: `(m` Q0.15, `u` Q4.11`)`.
    fn mud(&self, net08: &QT<i16>, corr: &QT<i16>, flow: &QT<i16>, tr: &mut dyn Trace) -> (QT<i16>, QT<i16>) {
        let f0 = flow.channels(0, 1);
        let a: QT<i16> = self.conv(Mud1, &[net08, corr, &f0]);
        self.record(tr, "q.mud1", &a, self.frac(Act::Mud1));
        let b: QT<i16> = self.conv(Mud2, &[&a]);
        self.record(tr, "q.mud2", &b, self.frac(Act::Mud2));
        let mu: QT<i16> = self.conv(Mud3, &[&b]);
        let table = self.m.u_table();
        let n = mu.h * mu.w;
        let mut m = QT::<i16>::zeros(mu.h, mu.w, 1);
        let mut u = QT::<i16>::zeros(mu.h, mu.w, 1);
        for p in 0..n {
            m.d[p] = mud_mask(mu.d[2 * p]);
            u.d[p] = lut::table_q11(&table, mu.d[2 * p + 1]);
        }
        (m, u)
    }

    fn flow_tensor(&self, x: &QT<i16>) -> QT<i16> {
        if self.cfg().flow_channels == 1 {
            return x.clone();
        }
        let mut t = QT::<i16>::zeros(x.h, x.w, 2);
        for (p, v) in x.d.iter().enumerate() {
            t.d[2 * p] = *v;
        }
        t
    }

    /// UFI: returns the initial disparity state, updates `c.net08`.
    pub fn ufi(&self, c: &mut Ctx, tr: &mut dyn Trace) -> QT<i16> {
        let cfg = *self.cfg();
        let (h, w, fc) = (c.f1.h, c.f1.w, c.f1.c);
        let mut props = [QT::<i16>::zeros(h, w, 1), QT::<i16>::zeros(h, w, 1), QT::<i16>::zeros(h, w, 1)];
        for y in 0..h {
            let f2 = &c.f2.d[y * w * fc..(y + 1) * w * fc];
            for x in 0..w {
                let px = y * w + x;
                let (d1, d2) = peaks_pixel_plain(&c.f1.d[px * fc..(px + 1) * fc], f2, x, cfg.ufi_peak_separation, self.max_disparity.grid8());
                props[1].d[px] = proposal_flow(d1);
                props[2].d[px] = proposal_flow(d2);
            }
        }
        if let Some(t) = self.injected("ufi.peaks") {
            for p in 0..h * w {
                props[1].d[p] = proposal_flow(t.data[p] as u16);
                props[2].d[p] = proposal_flow(t.data[h * w + p] as u16);
            }
        }
        let mut hid = c.net08.clone();
        let mut feats = Vec::with_capacity(3);
        for (k, prop) in props.iter().enumerate() {
            let flow_k = self.flow_tensor(prop);
            let corr = self.lookup(c, &flow_k);
            self.record(tr, &format!("ufi.corr{k}"), &corr, self.frac(Act::Corr));
            self.record(tr, "q.corr", &corr, self.frac(Act::Corr));
            let uc: QT<i16> = self.conv(UfiC, &[&corr]);
            let uf: QT<i16> = self.conv(UfiF, &[&flow_k]);
            self.record(tr, "q.ufi_c", &uc, self.frac(Act::UfiC));
            self.record(tr, "q.ufi_f", &uf, self.frac(Act::UfiF));
            let feat: QT<i16> = self.conv(UfiConv, &[&uc, &uf]);
            self.record(tr, "q.ufi_feat", &feat, self.frac(Act::UfiFeat));
            let q: QT<i16> = self.conv(UfiQ, &[&feat, &flow_k, &c.inp08]);
            let z: QT<i16> = self.conv(UfiZ, &[&hid, &q]);
            blend_q15(&mut hid.d, &z.d, &q.d);
            self.record(tr, &format!("ufi.hidden{k}"), &hid, UNIT_FRAC as i8);
            feats.push((feat, flow_k));
        }
        let table = self.m.u_table();
        let mut cand_flow = [QT::<i16>::zeros(h, w, 1), QT::<i16>::zeros(h, w, 1), QT::<i16>::zeros(h, w, 1)];
        let mut cand_u = cand_flow.clone();
        for (k, (feat, flow_k)) in feats.iter().enumerate() {
            let mid: QT<i16> = self.conv(UfiHead1, &[&hid, feat, flow_k]);
            self.record(tr, "q.ufi_head", &mid, self.frac(Act::UfiHead));
            let out: QT<i16> = self.conv(UfiHead2, &[&mid]);
            for p in 0..h * w {
                cand_flow[k].d[p] = sat_i16(props[k].d[p] as i64 + out.d[2 * p] as i64);
                cand_u[k].d[p] = lut::table_q11(&table, out.d[2 * p + 1]);
            }
        }
        let mut flow0 = QT::<i16>::zeros(h, w, 1);
        for p in 0..h * w {
            let best = ufi_choice([cand_u[0].d[p], cand_u[1].d[p], cand_u[2].d[p]]);
            flow0.d[p] = cand_flow[best].d[p];
        }
        c.net08 = hid;
        flow0
    }

    fn attention_qk(&self, c: &Ctx) -> (QT<i16>, QT<i16>) {
        let mut q: QT<i16> = self.conv(MgaQuery, &[&c.inp08]);
        let mut k: QT<i16> = self.conv(MgaKey, &[&c.inp08]);
        let pairs = self.cfg().mga_qk_dim / 2;
        let phases: Vec<u32> = (0..pairs).map(|i| self.m.rope_phase(i)).collect();
        for t in [&mut q, &mut k] {
            let (w, ch) = (t.w, t.c);
            for (p, px) in t.d.chunks_mut(ch).enumerate() {
                rope_pixel(px, p % w, p / w, &phases);
            }
        }
        (q, k)
    }

    /// Runs the network on padded integer images (`h x w x 3`, `2 * pixel - 255`).
    pub fn forward(&self, left: &QT<i16>, right: &QT<i16>, iters: usize, tr: &mut dyn Trace) -> FixedOutput {
        use Act as A;
        let cfg = *self.cfg();
        let mut c = self.encode(left, right, tr);
        if let (Some(a), Some(b)) = (self.injected("inp08"), self.injected("inp16")) {
            c.inp08 = widen(&self.quantize_like::<u8>(a, self.frac(A::Inp08)));
            c.inp16 = widen(&self.quantize_like::<u8>(b, self.frac(A::Inp16)));
        }
        if let (Some(a), Some(b)) = (self.injected("fmap1"), self.injected("fmap2")) {
            c.f1 = self.quantize_like(a, self.frac(A::Fmap));
            c.f2 = self.quantize_like(b, self.frac(A::Fmap));
        }
        let (h, w) = (c.net08.h, c.net08.w);
        let mut flow = if cfg.ufi { self.flow_tensor(&self.ufi(&mut c, tr)) } else { QT::<i16>::zeros(h, w, cfg.flow_channels) };
        if let Some(t) = self.injected("init.flow") {
            flow = self.flow_tensor(&self.quantize_like(t, FLOW_FRAC as i8));
        }
        if let Some(t) = self.injected("init.net08") {
            c.net08 = self.quantize_like(t, UNIT_FRAC as i8);
        }
        self.record(tr, "init.flow", &flow.channels(0, 1), FLOW_FRAC as i8);
        let qk = if cfg.mga { Some(self.attention_qk(&c)) } else { None };
        let glb_shift = self.frac(A::Glb) - self.frac(A::MgaV);
        let (mut net08, mut net16) = (c.net08.clone(), c.net16.clone());
        for itr in 0..iters {
            let corr = self.lookup(&c, &flow);
            self.record(tr, &format!("iter{itr}.corr"), &corr, self.frac(A::Corr));
            self.record(tr, "q.corr", &corr, self.frac(A::Corr));
            let mut m = None;
            if cfg.mud {
                let (mm, u) = self.mud(&net08, &corr, &flow, tr);
                self.record(tr, &format!("iter{itr}.mud_m"), &mm, UNIT_FRAC as i8);
                self.record(tr, &format!("iter{itr}.mud_u"), &u, LOG_FRAC as i8);
                m = Some(mm);
            }
            let glb = match (&qk, &m) {
                (Some((q, k)), Some(m)) => {
                    let f0 = flow.channels(0, 1);
                    let hm: QT<i16> = self.conv(MgaMask, &[&net08, &corr, &f0, m]);
                    let v0: QT<i16> = self.conv(MgaValue, &[&net08]);
                    self.record(tr, "q.mga_v", &v0, self.frac(A::MgaV));
                    let mut v = v0.clone();
                    mul_plane_q15(&v0.d, &hm.d, v0.c, &mut v.d);
                    let g = attention_plain(&q.d, &k.d, &v.d, q.c, v.c, self.m.att_mult(), glb_shift);
                    let g = QT { h, w, c: v.c, d: g };
                    self.record(tr, "q.glb", &g, self.frac(A::Glb));
                    Some(g)
                }
                _ => None,
            };
            // Coarse GRU, twice (slow-fast).
            for _ in 0..2 {
                let pooled = pool2x(&net08);
                net16 = self.gru([Gru16Z, Gru16R, Gru16Q], &net16, &[&pooled, &c.inp16]);
            }
            // Motion features.
            let corr_in: Vec<QT<i16>> = match &m {
                Some(m) => {
                    let mut cm = corr.clone();
                    mul_plane_q15(&corr.d, &m.d, corr.c, &mut cm.d);
                    vec![corr.clone(), cm, m.clone()]
                }
                None => vec![corr.clone()],
            };
            let refs: Vec<&QT<i16>> = corr_in.iter().collect();
            let c1: QT<i16> = self.conv(MotC1, &refs);
            let c2: QT<i16> = self.conv(MotC2, &[&c1]);
            let f1: QT<i16> = self.conv(MotF1, &[&flow]);
            let f2: QT<i16> = self.conv(MotF2, &[&f1]);
            let mo: QT<i16> = self.conv(MotOut, &[&c2, &f2]);
            self.record(tr, "q.mot_c1", &c1, self.frac(A::MotC1));
            self.record(tr, "q.mot_c2", &c2, self.frac(A::MotC2));
            self.record(tr, "q.mot_f1", &f1, self.frac(A::MotF1));
            self.record(tr, "q.mot_f2", &f2, self.frac(A::MotF2));
            self.record(tr, "q.mot_out", &mo, self.frac(A::MotOut));
            let up16 = interp(&net16, h, w);
            let mut xs: Vec<&QT<i16>> = vec![&mo, &flow, &up16];
            if let Some(g) = &glb {
                xs.push(g);
            }
            xs.push(&c.inp08);
            net08 = self.gru([Gru08Z, Gru08R, Gru08Q], &net08, &xs);
            let fm: QT<i16> = self.conv(Flow1, &[&net08]);
            self.record(tr, "q.flow_mid", &fm, self.frac(A::FlowMid));
            let delta: QT<i16> = self.conv(Flow2, &[&fm]);
            for p in 0..h * w {
                let i = p * flow.c;
                flow.d[i] = sat_i16(flow.d[i] as i64 + delta.d[p * delta.c] as i64);
            }
            self.record(tr, &format!("iter{itr}.net16"), &net16, UNIT_FRAC as i8);
            self.record(tr, &format!("iter{itr}.net08"), &net08, UNIT_FRAC as i8);
            self.record(tr, &format!("iter{itr}.flow"), &flow.channels(0, 1), FLOW_FRAC as i8);
        }
        let mut u_final = None;
        if cfg.mud {
            let corr = self.lookup(&c, &flow);
            self.record(tr, "q.corr", &corr, self.frac(A::Corr));
            let (m, u) = self.mud(&net08, &corr, &flow, tr);
            self.record(tr, "final.mud_m", &m, UNIT_FRAC as i8);
            self.record(tr, "final.mud_u", &u, LOG_FRAC as i8);
            u_final = Some(u);
        }
        let mm: QT<i16> = self.conv(Mask1, &[&net08]);
        self.record(tr, "q.mask_mid", &mm, self.frac(A::MaskMid));
        let logits: QT<i16> = self.conv(Mask2, &[&mm]);
        self.record(tr, "q.mask_logit", &logits, self.frac(A::MaskLogit));
        let f0 = flow.channels(0, 1);
        let (hh, ww) = (8 * h, 8 * w);
        let mut disp = vec![0i16; hh * ww];
        let mut uo = u_final.as_ref().map(|_| vec![0i16; hh * ww]);
        for y in 0..h {
            for x in 0..w {
                let o = 8 * y * ww + 8 * x;
                let lg = &logits.d[(y * w + x) * 576..(y * w + x + 1) * 576];
                upsample_pixel(
                    lg,
                    self.frac(A::MaskLogit),
                    &f0.d,
                    u_final.as_ref().map(|u| u.d.as_slice()),
                    h,
                    w,
                    y,
                    x,
                    &mut disp[o..],
                    uo.as_mut().map(|u| &mut u[o..]),
                    ww,
                );
            }
        }
        if tr.active() {
            let dq = QT { h: hh, w: ww, c: 1, d: disp.clone() };
            self.record(tr, "up.disp", &dq, muir::arith::DISP_FRAC as i8);
            if let Some(u) = &uo {
                self.record(tr, "up.u", &QT { h: hh, w: ww, c: 1, d: u.clone() }, LOG_FRAC as i8);
            }
        }
        FixedOutput { width: ww, height: hh, disparity: disp, uncertainty: uo }
    }

    fn gru(&self, ids: [ConvId; 3], h: &QT<i16>, xs: &[&QT<i16>]) -> QT<i16> {
        let mut parts: Vec<&QT<i16>> = vec![h];
        parts.extend_from_slice(xs);
        let z: QT<i16> = self.conv(ids[0], &parts);
        let r: QT<i16> = self.conv(ids[1], &parts);
        let mut rh = h.clone();
        mul_q15(&r.d, &h.d, &mut rh.d);
        parts[0] = &rh;
        let q: QT<i16> = self.conv(ids[2], &parts);
        let mut out = h.clone();
        blend_q15(&mut out.d, &z.d, &q.d);
        out
    }

    /// Runs on an image pair of any size; outputs cropped back to the input size.
    pub fn predict(&self, left: &ImageView<'_>, right: &ImageView<'_>, iters: Option<usize>, tr: &mut dyn Trace) -> Result<FixedOutput, InputError> {
        let (pw, ph) = check_pair(left, right)?;
        let out = self.forward(&self.image(left, pw, ph), &self.image(right, pw, ph), iters.unwrap_or(self.cfg().iters), tr);
        let crop = |v: &[i16]| -> Vec<i16> { (0..left.height).flat_map(|y| v[y * pw..y * pw + left.width].iter().copied()).collect() };
        Ok(FixedOutput {
            width: left.width,
            height: left.height,
            disparity: crop(&out.disparity),
            uncertainty: out.uncertainty.as_deref().map(crop),
        })
    }
}

/// u8 tensor as i16 (same values).
pub fn widen(x: &QT<u8>) -> QT<i16> {
    QT { h: x.h, w: x.w, c: x.c, d: x.d.iter().map(|v| *v as i16).collect() }
}

/// `pool2x` of a whole tensor.
pub fn pool2x(x: &QT<i16>) -> QT<i16> {
    let (ho, wo) = (x.h.div_ceil(2), x.w.div_ceil(2));
    let mut out = QT::<i16>::zeros(ho, wo, x.c);
    for y in 0..ho {
        pool2x_row(&x.d, x.h, x.w, x.c, y, &mut out.d[y * wo * x.c..(y + 1) * wo * x.c]);
    }
    out
}

/// Bilinear align-corners resize of a whole tensor.
pub fn interp(x: &QT<i16>, h: usize, w: usize) -> QT<i16> {
    let mut out = QT::<i16>::zeros(h, w, x.c);
    for y in 0..h {
        interp_row(&x.d, x.h, x.w, x.c, h, w, y, &mut out.d[y * w * x.c..(y + 1) * w * x.c]);
    }
    out
}

/// Index of the smallest of three uncertainties (first on ties).
#[inline]
pub fn ufi_choice(u: [i16; 3]) -> usize {
    let mut best = 0;
    for k in 1..3 {
        if u[k] < u[best] {
            best = k;
        }
    }
    best
}

/// Converts a fixed-point uncertainty threshold: pixels with `exp(u/2) > tau` have
/// `u > 2 ln(tau)`; returns that bound in Q4.11.
pub fn u_threshold(tau_px: f32) -> i16 {
    let v = 2.0 * (tau_px.max(1e-6) as f64).ln() * (1 << LOG_FRAC) as f64;
    v.round().clamp(-32768.0, 32767.0) as i16
}

/// Dequantised disparity in pixels.
pub fn disparity_px(q: i16) -> f32 {
    q as f32 / (1 << muir::arith::DISP_FRAC) as f32
}

