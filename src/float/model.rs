//! The float reference network: MUIR (MUD, UFI, MGA, post-pooling lookup) and the RAFT-Stereo
//! realtime baseline, step for step as the PyTorch twin (`python/muir/model.py`).
//!
//! Every intermediate tensor can be observed through a [`Trace`] under the twin's trace names; the
//! golden parity tests compare them all.

use std::collections::BTreeMap;

use super::corr::{lookup, peaks};
use super::gemm::{Epilogue, Lhs, Packed};
use super::ops::{
    Weights, aggregate, attention_matrix, conv_with, convex_upsample, instance_norm, interp, pool2x, relu, rope_2d, sigmoid,
};
use super::par;
use super::tensor::Tensor;
use super::weights::{FloatConv, FloatWeights};
use super::winograd;
use muir::input::{ImageView, InputError, check_pair};
use muir::model::config::{Config, MaxDisparity};
use muir::model::layers::ConvId::{self, *};
use muir::model::layers::ConvShape;

/// Receives intermediate tensors by name.
pub trait Trace {
    /// Called with each intermediate tensor.
    fn record(&mut self, name: &str, t: &Tensor);
    /// False when records are discarded (lets the caller skip building them).
    fn active(&self) -> bool {
        true
    }
}

/// Discards everything.
pub struct NoTrace;

impl Trace for NoTrace {
    fn record(&mut self, _: &str, _: &Tensor) {}
    fn active(&self) -> bool {
        false
    }
}

impl Trace for BTreeMap<String, Tensor> {
    fn record(&mut self, name: &str, t: &Tensor) {
        self.insert(name.to_string(), t.clone());
    }
}

/// Network output at the padded input resolution.
#[derive(Clone, Debug)]
pub struct FloatOutput {
    /// Left-view disparity in pixels (1 x H x W).
    pub disparity: Tensor,
    /// Uncertainty `u = log(beta^2)` (predicted error `exp(u/2)` px), 1 x H x W; `None` without MUD.
    pub uncertainty: Option<Tensor>,
    /// Matchability mask of the final state at 1/8 resolution; `None` without MUD.
    pub matchability: Option<Tensor>,
}

/// Prediction for an image pair, cropped to the input size.
#[derive(Clone, Debug)]
pub struct Prediction {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Disparity in pixels, row-major.
    pub disparity: Vec<f32>,
    /// Uncertainty `u` per pixel (predicted error `exp(u/2)`); `None` without MUD.
    pub uncertainty: Option<Vec<f32>>,
    /// Matchability at 1/8 resolution (`(w8, h8, values)`); `None` without MUD.
    pub matchability: Option<(usize, usize, Vec<f32>)>,
}

impl Prediction {
    /// The full-resolution refinement ([`muir::kernels::fullres`]) on this prediction, as the
    /// fixed engine runs it on its output: disparity rounded to Q10.5 and `u` to Q4.11, the integer
    /// stage, and the changed pixels' values written back (the others keep their float value).
    /// Returns the number of pixels the matching decided.
    pub fn refine_full_res(&mut self, left: &ImageView<'_>, right: &ImageView<'_>) -> usize {
        use muir::arith::{DISP_FRAC, LOG_FRAC, sat_i16};
        let q = |v: f32, frac: u8| sat_i16((v as f64 * (1u32 << frac) as f64).round() as i64);
        let mut d: Vec<i16> = self.disparity.iter().map(|v| if v.is_finite() { q(*v, DISP_FRAC) } else { 0 }).collect();
        let before = d.clone();
        let u: Option<Vec<i16>> = self.uncertainty.as_ref().map(|u| u.iter().map(|v| q(*v, LOG_FRAC)).collect());
        let mut scratch = muir::kernels::fullres::ScratchVec::new(self.width);
        let n = muir::kernels::fullres::refine_image(left, right, &mut d, u.as_deref(), scratch.view());
        // A pixel whose result equals its rounded input keeps its float value (the
        // PyTorch twin's evaluation, python/muir/fullres.py, does the same).
        let scale = 1.0 / (1u32 << DISP_FRAC) as f32;
        for ((out, new), old) in self.disparity.iter_mut().zip(&d).zip(&before) {
            if new != old {
                *out = *new as f32 * scale;
            }
        }
        n
    }
}

/// Float reference model: validated weights plus the forward pass.
#[derive(Clone, Debug)]
pub struct FloatModel {
    weights: FloatWeights,
    max_disparity: MaxDisparity,
    /// Every computed layer's weights packed for the matrix product, by [`ConvId::index`].
    packed: Vec<Option<Packed>>,
    /// The 3x3 stride-1 layers' Winograd weights ([`winograd_fits`]), by [`ConvId::index`].
    wino: Vec<Option<winograd::Weights>>,
    /// Each GRU's z and r convolutions stacked into one (the same input): 1/8, then 1/16.
    zr: [Option<Stacked>; 2],
}

/// Whether a layer runs as Winograd F(2x2, 3x3) ([`winograd`]): 3x3, stride 1, and enough
/// channels for the transforms to cost less than the multiply-adds they save (measured: with 16
/// and more, muir-slim's 32- and 48-channel backbone layers were slower than direct; with 64 and
/// more, both Teddy muir-slim and raft-stereo-realtime gain).
fn winograd_fits(s: &ConvShape) -> bool {
    s.k == 3 && s.stride == 1 && s.cin >= 64 && s.cout >= 64
}

/// Two layers of one input as one convolution: their weights packed one above the other.
#[derive(Clone, Debug)]
struct Stacked {
    shape: ConvShape,
    packed: Packed,
    wino: Option<winograd::Weights>,
    bias: Vec<f32>,
}

impl Stacked {
    /// `a` and `b` stacked, if they have the same shape and no batch norm.
    fn new(a: Option<&FloatConv>, b: Option<&FloatConv>) -> Option<Self> {
        let (a, b) = (a?, b?);
        if a.shape != b.shape || a.bn.is_some() || b.bn.is_some() {
            return None;
        }
        let kk = a.shape.cin * a.shape.k * a.shape.k;
        let weight = [&a.weight[..], &b.weight[..]].concat();
        let packed = Packed::new(Lhs { data: &weight, row: kk, col: 1 }, 2 * a.shape.cout, kk);
        let bias = [&a.bias[..], &b.bias[..]].concat();
        let shape = ConvShape { cout: 2 * a.shape.cout, ..a.shape };
        let wino = winograd_fits(&shape).then(|| winograd::Weights::new(&weight, shape.cout, shape.cin));
        Some(Self { shape, packed, wino, bias })
    }
}

struct Context {
    f1: Tensor,
    f2: Tensor,
    net08: Tensor,
    net16: Tensor,
    inp08: Tensor,
    ctx08: [Tensor; 3],
    ctx16: [Tensor; 3],
}

impl FloatModel {
    /// Wraps validated weights.
    pub fn new(weights: FloatWeights) -> Self {
        let mut packed = vec![None; ConvId::COUNT];
        let mut wino = vec![None; ConvId::COUNT];
        for id in ConvId::ALL {
            if let Some(c) = weights.get(*id) {
                let kk = c.shape.cin * c.shape.k * c.shape.k;
                packed[id.index()] = Some(Packed::new(Lhs { data: &c.weight, row: kk, col: 1 }, c.shape.cout, kk));
                if winograd_fits(&c.shape) {
                    wino[id.index()] = Some(winograd::Weights::new(&c.weight, c.shape.cout, c.shape.cin));
                }
            }
        }
        let zr = [
            Stacked::new(weights.get(Gru08Z), weights.get(Gru08R)),
            Stacked::new(weights.get(Gru16Z), weights.get(Gru16R)),
        ];
        Self { weights, max_disparity: MaxDisparity::DEFAULT, packed, wino, zr }
    }

    /// Sets the largest disparity of UFI's proposal search ([`MaxDisparity`], default 256 px).
    pub fn set_max_disparity(&mut self, max: MaxDisparity) {
        self.max_disparity = max;
    }

    /// The largest disparity of UFI's proposal search.
    pub fn max_disparity(&self) -> MaxDisparity {
        self.max_disparity
    }

    /// The model config.
    pub fn config(&self) -> &Config {
        &self.weights.config
    }

    /// The weights.
    pub fn weights(&self) -> &FloatWeights {
        &self.weights
    }

    fn layer(&self, id: ConvId) -> &FloatConv {
        // FloatWeights::from_state_dict fills every layer the config computes, and the forward pass
        // only asks for those: a miss is a bug in this file, not bad data.
        self.weights.get(id).unwrap_or_else(|| panic!("layer {} not loaded", id.name()))
    }

    fn conv(&self, id: ConvId, x: &Tensor) -> Tensor {
        self.conv_cat(id, &[x], false)
    }

    /// `relu(conv(x))`.
    fn conv_relu(&self, id: ConvId, x: &Tensor) -> Tensor {
        self.conv_cat(id, &[x], true)
    }

    /// The layer on the channel concatenation of `parts`, then ReLU if `relu`.
    fn conv_cat(&self, id: ConvId, parts: &[&Tensor], relu: bool) -> Tensor {
        let l = self.layer(id);
        let epi = Epilogue { bias: Some(&l.bias), bn: l.bn.as_ref(), scale: None, relu };
        if let Some(w) = &self.wino[id.index()] {
            return winograd::conv(parts, w, &epi);
        }
        // Packed in `new` for every layer the weights hold.
        let p = self.packed[id.index()].as_ref().unwrap_or_else(|| panic!("layer {} not packed", id.name()));
        conv_with(parts, &l.shape, Weights::Packed(p), &epi)
    }

    /// Residual block; records its mid and output activations as `q.<names[0]>`, `q.<names[1]>`
    /// (calibration statistics of the quantised engine's slots).
    fn res_block(&self, x: &Tensor, ids: [ConvId; 2], ds: Option<ConvId>, names: [&str; 2], tr: &mut dyn Trace) -> Tensor {
        let y = self.conv_relu(ids[0], x);
        tr.record(names[0], &y);
        let y = self.conv_relu(ids[1], &y);
        let ds = ds.map(|d| self.conv(d, x));
        // relu(skip + y)
        let out = y.zip(ds.as_ref().unwrap_or(x), |a, b| (b + a).max(0.0));
        tr.record(names[1], &out);
        out
    }

    /// The matching-feature block (InstanceNorm residual block + conv).
    fn fmap_branch(&self, x: &Tensor, tr: &mut dyn Trace) -> Tensor {
        let raw1 = self.conv(FmapC1, x);
        tr.record("q.fmap_raw1", &raw1);
        let mid = relu(instance_norm(raw1));
        tr.record("q.fmap_mid", &mid);
        let raw2 = self.conv(FmapC2, &mid);
        tr.record("q.fmap_raw2", &raw2);
        let y = relu(instance_norm(raw2));
        let blk = y.zip(x, |a, b| (b + a).max(0.0));
        tr.record("q.fmap_blk", &blk);
        let f = self.conv(FmapOut, &blk);
        tr.record("q.fmap", &f);
        f
    }

    fn trunk(&self, img: &Tensor, tr: &mut dyn Trace) -> [Tensor; 4] {
        let c1 = self.conv_relu(Conv1, img);
        tr.record("q.c1", &c1);
        let x = self.res_block(&c1, [L1b0c1, L1b0c2], None, ["q.l1b0m", "q.l1b0o"], tr);
        let l1 = self.res_block(&x, [L1b1c1, L1b1c2], None, ["q.l1b1m", "q.l1b1o"], tr);
        let x = self.res_block(&l1, [L2b0c1, L2b0c2], Some(L2b0ds), ["q.l2b0m", "q.l2b0o"], tr);
        let l2 = self.res_block(&x, [L2b1c1, L2b1c2], None, ["q.l2b1m", "q.l2b1o"], tr);
        let x = self.res_block(&l2, [L3b0c1, L3b0c2], Some(L3b0ds), ["q.l3b0m", "q.l3b0o"], tr);
        let l3 = self.res_block(&x, [L3b1c1, L3b1c2], None, ["q.l3b1m", "q.l3b1o"], tr);
        [c1, l1, l2, l3]
    }

    fn head(&self, x: &Tensor, ids: [ConvId; 3], names: [&str; 2], tr: &mut dyn Trace) -> Tensor {
        let y = self.res_block(x, [ids[0], ids[1]], None, names, tr);
        self.conv(ids[2], &y)
    }

    fn split3(t: Tensor, h: usize) -> [Tensor; 3] {
        [t.channels(0, h), t.channels(h, h), t.channels(2 * h, h)]
    }

    fn encode(&self, left: &Tensor, right: &Tensor, tr: &mut dyn Trace) -> Context {
        let cfg = self.config();
        let [lc1, ll1, ll2, xl] = self.trunk(left, tr);
        let [rc1, rl1, rl2, xr] = self.trunk(right, tr);
        if tr.active() {
            tr.record("backbone.conv1", &Tensor::cat(&[&lc1, &rc1]));
            tr.record("backbone.layer1", &Tensor::cat(&[&ll1, &rl1]));
            tr.record("backbone.layer2", &Tensor::cat(&[&ll2, &rl2]));
            tr.record("backbone.layer3", &Tensor::cat(&[&xl, &xr]));
        }
        let (f1, f2) = (self.fmap_branch(&xl, tr), self.fmap_branch(&xr, tr));
        tr.record("fmap1", &f1);
        tr.record("fmap2", &f2);
        let n08 = self.head(&xl, [H08nC1, H08nC2, H08nOut], ["q.h08nm", "q.h08no"], tr);
        let c08 = self.head(&xl, [H08cC1, H08cC2, H08cOut], ["q.h08cm", "q.h08co"], tr);
        let x = self.res_block(&xl, [L4b0c1, L4b0c2], Some(L4b0ds), ["q.l4b0m", "q.l4b0o"], tr);
        let y = self.res_block(&x, [L4b1c1, L4b1c2], None, ["q.l4b1m", "q.l4b1o"], tr);
        let n16 = self.head(&y, [H16nC1, H16nC2, H16nOut], ["q.h16nm", "q.h16no"], tr);
        let c16 = self.head(&y, [H16cC1, H16cC2, H16cOut], ["q.h16cm", "q.h16co"], tr);
        let (net08, net16) = (n08.map(f32::tanh), n16.map(f32::tanh));
        let (inp08, inp16) = (relu(c08), relu(c16));
        tr.record("net08.init", &net08);
        tr.record("net16.init", &net16);
        tr.record("inp08", &inp08);
        tr.record("inp16", &inp16);
        tr.record("q.inp08", &inp08);
        tr.record("q.inp16", &inp16);
        let z08 = self.conv(Czqr08, &inp08);
        let z16 = self.conv(Czqr16, &inp16);
        tr.record("czqr08", &z08);
        tr.record("czqr16", &z16);
        let h = cfg.hidden_dim;
        Context { f1, f2, net08, net16, inp08, ctx08: Self::split3(z08, h), ctx16: Self::split3(z16, h) }
    }

    fn gru(&self, ids: [ConvId; 3], h: &Tensor, ctx: &[Tensor; 3], xs: &[&Tensor]) -> Tensor {
        let mut parts = vec![h];
        parts.extend_from_slice(xs);
        let n = h.data.len();
        // z and r from one product where they are stacked, else one each.
        let stacked = self.zr[if ids[0] == Gru08Z { 0 } else { 1 }].as_ref();
        let zr = match stacked {
            Some(st) => {
                let epi = Epilogue { bias: Some(&st.bias), ..Default::default() };
                match &st.wino {
                    Some(w) => winograd::conv(&parts, w, &epi),
                    None => conv_with(&parts, &st.shape, Weights::Packed(&st.packed), &epi),
                }
            }
            None => Tensor::cat(&[&self.conv_cat(ids[0], &parts, false), &self.conv_cat(ids[1], &parts, false)]),
        };
        let (zs, rs) = zr.data.split_at(n);
        let mut z = vec![0.0f32; n];
        par::chunks(&mut z, 1, &|i, ch| {
            ch.iter_mut().zip(&zs[i..]).zip(&ctx[0].data[i..]).for_each(|((v, a), b)| *v = sigmoid(a + b));
        });
        // r * h
        let mut rh = vec![0.0f32; n];
        par::chunks(&mut rh, 1, &|i, ch| {
            ch.iter_mut().zip(&rs[i..]).zip(&ctx[1].data[i..]).zip(&h.data[i..]).for_each(|(((v, a), b), h)| *v = sigmoid(a + b) * h);
        });
        let rh = Tensor::from_vec(h.c, h.h, h.w, rh);
        parts[0] = &rh;
        let q = self.conv_cat(ids[2], &parts, false);
        // (1 - z) * h + z * tanh(q + ctx)
        let mut out = q.data;
        par::chunks(&mut out, 1, &|i, ch| {
            for (((q, c), z), h) in ch.iter_mut().zip(&ctx[2].data[i..]).zip(&z[i..]).zip(&h.data[i..]) {
                *q = (1.0 - z) * h + z * (*q + c).tanh();
            }
        });
        Tensor::from_vec(h.c, h.h, h.w, out)
    }

    /// `u = log(eps_min^2 + (eps_max^2 - eps_min^2) * sigmoid(v))`.
    fn uncertainty(&self, v: Tensor) -> Tensor {
        let cfg = self.config();
        let (lo, hi) = (cfg.eps_min * cfg.eps_min, cfg.eps_max * cfg.eps_max);
        v.map(|x| (lo + (hi - lo) * sigmoid(x)).ln())
    }

    fn mud(&self, net08: &Tensor, corr: &Tensor, flow: &Tensor, tr: &mut dyn Trace) -> (Tensor, Tensor) {
        let x = self.conv_cat(Mud1, &[net08, corr, &flow.channels(0, 1)], true);
        tr.record("q.mud1", &x);
        let x = self.conv_relu(Mud2, &x);
        tr.record("q.mud2", &x);
        let ab = self.conv(Mud3, &x);
        (ab.channels(0, 1).map(sigmoid), self.uncertainty(ab.channels(1, 1)))
    }

    fn flow_tensor(&self, x: Tensor) -> Tensor {
        if self.config().flow_channels == 2 { Tensor::cat(&[&x, &Tensor::zeros(1, x.h, x.w)]) } else { x }
    }

    fn ufi(&self, c: &Context, tr: &mut dyn Trace) -> (Tensor, Tensor) {
        let cfg = self.config();
        let pk = peaks(&c.f1, &c.f2, cfg.ufi_peak_separation, self.max_disparity.grid8());
        tr.record("ufi.peaks", &pk);
        let (h8, w8) = (c.net08.h, c.net08.w);
        let props = [Tensor::zeros(1, h8, w8), pk.channels(0, 1), pk.channels(1, 1)];
        let mut hid = c.net08.clone();
        let mut feats = Vec::with_capacity(3);
        for (k, prop) in props.iter().enumerate() {
            let flow_k = self.flow_tensor(prop.clone().map(|v| -v));
            let corr_k = lookup(&c.f1, &c.f2, &flow_k, cfg);
            tr.record(&format!("ufi.corr{k}"), &corr_k);
            tr.record("q.corr", &corr_k);
            let cc = self.conv_relu(UfiC, &corr_k);
            let ff = self.conv_relu(UfiF, &flow_k);
            tr.record("q.ufi_c", &cc);
            tr.record("q.ufi_f", &ff);
            let feat = self.conv_cat(UfiConv, &[&cc, &ff], true);
            tr.record("q.ufi_feat", &feat);
            let fk = Tensor::cat(&[&feat, &flow_k]);
            let q = self.conv_cat(UfiQ, &[&fk, &c.inp08], false).map(f32::tanh);
            let z = self.conv_cat(UfiZ, &[&hid, &q], false).map(sigmoid);
            // hid + (q - hid) * z
            let step = q.zip(&hid, |a, b| a - b).zip(&z, |a, b| a * b);
            hid = hid.zip(&step, |a, b| a + b);
            tr.record(&format!("ufi.hidden{k}"), &hid);
            feats.push(fk);
        }
        let mut cand_flow = Vec::with_capacity(3);
        let mut cand_u = Vec::with_capacity(3);
        for (k, fk) in feats.iter().enumerate() {
            let mid = self.conv_cat(UfiHead1, &[&hid, fk], true);
            tr.record("q.ufi_head", &mid);
            let out = self.conv(UfiHead2, &mid);
            cand_flow.push(props[k].clone().map(|v| -v).zip(&out.channels(0, 1), |a, b| a + b));
            cand_u.push(self.uncertainty(out.channels(1, 1)));
        }
        let cf = Tensor::cat(&[&cand_flow[0], &cand_flow[1], &cand_flow[2]]);
        let cu = Tensor::cat(&[&cand_u[0], &cand_u[1], &cand_u[2]]);
        tr.record("ufi.cand_flow", &cf);
        tr.record("ufi.cand_u", &cu);
        let mut flow0 = Tensor::zeros(1, h8, w8);
        let mut u0 = Tensor::zeros(1, h8, w8);
        let mut choice = Tensor::zeros(1, h8, w8);
        for i in 0..h8 * w8 {
            // argmin over the three candidates, first on ties (torch.argmin)
            let mut best = 0;
            for k in 1..3 {
                if cand_u[k].data[i] < cand_u[best].data[i] {
                    best = k;
                }
            }
            flow0.data[i] = cand_flow[best].data[i];
            u0.data[i] = cand_u[best].data[i];
            choice.data[i] = best as f32;
        }
        tr.record("ufi.choice", &choice);
        (flow0, hid)
    }

    /// Runs the network on padded input tensors (3 x H x W, values 0..255, sides multiples of 16).
    pub fn forward(&self, left: &Tensor, right: &Tensor, tr: &mut dyn Trace) -> FloatOutput {
        self.forward_iters(left, right, self.config().iters, tr)
    }

    /// [`FloatModel::forward`] with `iters` refinement iterations instead of the config's.
    pub fn forward_iters(&self, left: &Tensor, right: &Tensor, iters: usize, tr: &mut dyn Trace) -> FloatOutput {
        let cfg = *self.config();
        let norm = |t: &Tensor| t.clone().map(|v| 2.0 * (v / 255.0) - 1.0);
        let mut c = self.encode(&norm(left), &norm(right), tr);
        let (h8, w8) = (c.net08.h, c.net08.w);
        let mut flow = if cfg.ufi {
            let (flow0, hid) = self.ufi(&c, tr);
            c.net08 = hid;
            self.flow_tensor(flow0)
        } else {
            Tensor::zeros(cfg.flow_channels, h8, w8)
        };
        tr.record("init.flow", &flow.channels(0, 1));
        tr.record("init.net08", &c.net08);
        let attn = if cfg.mga {
            let (q0, k0) = (self.conv(MgaQuery, &c.inp08), self.conv(MgaKey, &c.inp08));
            tr.record("q.mga_q", &q0);
            tr.record("q.mga_k", &k0);
            let q = rope_2d(q0, cfg.mga_rope_base);
            let k = rope_2d(k0, cfg.mga_rope_base);
            tr.record("q.mga_q", &q);
            tr.record("q.mga_k", &k);
            tr.record("mga.query", &q);
            tr.record("mga.key", &k);
            Some(attention_matrix(&q, &k))
        } else {
            None
        };
        let (mut net08, mut net16) = (c.net08.clone(), c.net16.clone());
        for itr in 0..iters {
            let corr = lookup(&c.f1, &c.f2, &flow, &cfg);
            tr.record(&format!("iter{itr}.corr"), &corr);
            tr.record("q.corr", &corr);
            let mut m = None;
            // The motion encoder's input: corr, or (with MUD) corr, corr * m, m.
            let mut masked = None;
            if cfg.mud {
                let (mm, u) = self.mud(&net08, &corr, &flow, tr);
                tr.record(&format!("iter{itr}.mud_m"), &mm);
                tr.record(&format!("iter{itr}.mud_u"), &u);
                masked = Some(corr.clone().mul_plane(&mm));
                m = Some(mm);
            }
            let corr_in: Vec<&Tensor> = match (&masked, &m) {
                (Some(cm), Some(mm)) => vec![&corr, cm, mm],
                _ => vec![&corr],
            };
            let glb = match (&attn, &m) {
                (Some(a), Some(m)) => {
                    let hm = self.conv_cat(MgaMask, &[&net08, &corr, &flow.channels(0, 1), m], false).map(sigmoid);
                    let v0 = self.conv(MgaValue, &net08);
                    tr.record("q.mga_v", &v0);
                    let v = v0.mul_plane(&hm);
                    let g = aggregate(a, &v);
                    tr.record("q.glb", &g);
                    tr.record(&format!("iter{itr}.mga_mask"), &hm);
                    tr.record(&format!("iter{itr}.mga"), &g);
                    Some(g)
                }
                _ => None,
            };
            let g16 = [Gru16Z, Gru16R, Gru16Q];
            let pooled = pool2x(&net08);
            net16 = self.gru(g16, &net16, &c.ctx16, &[&pooled]);
            net16 = self.gru(g16, &net16, &c.ctx16, &[&pooled]);
            let c1 = self.conv_cat(MotC1, &corr_in, true);
            let cor = self.conv_relu(MotC2, &c1);
            let f1 = self.conv_relu(MotF1, &flow);
            let flo = self.conv_relu(MotF2, &f1);
            let out = self.conv_cat(MotOut, &[&cor, &flo], true);
            tr.record("q.mot_c1", &c1);
            tr.record("q.mot_c2", &cor);
            tr.record("q.mot_f1", &f1);
            tr.record("q.mot_f2", &flo);
            tr.record("q.mot_out", &out);
            if tr.active() {
                tr.record(&format!("iter{itr}.motion"), &Tensor::cat(&[&out, &flow]));
            }
            let up16 = interp(&net16, h8, w8);
            // The GRU's input after the hidden state: motion (out, flow), up16, the MGA context.
            let mut xs = vec![&out, &flow, &up16];
            if let Some(g) = &glb {
                xs.push(g);
            }
            net08 = self.gru([Gru08Z, Gru08R, Gru08Q], &net08, &c.ctx08, &xs);
            let fmid = self.conv_relu(Flow1, &net08);
            tr.record("q.flow_mid", &fmid);
            let delta = self.conv(Flow2, &fmid);
            let mut new_flow = flow.clone();
            for (o, d) in new_flow.channel_mut(0).iter_mut().zip(delta.channel(0)) {
                *o += d;
            }
            flow = new_flow; // channel 1 (RAFT's y) stays zero
            tr.record(&format!("iter{itr}.net16"), &net16);
            tr.record(&format!("iter{itr}.net08"), &net08);
            tr.record(&format!("iter{itr}.flow"), &flow.channels(0, 1));
        }
        let (mut u_final, mut m_final) = (None, None);
        if cfg.mud {
            let corr = lookup(&c.f1, &c.f2, &flow, &cfg);
            tr.record("q.corr", &corr);
            let (m, u) = self.mud(&net08, &corr, &flow, tr);
            tr.record("final.corr", &corr);
            tr.record("final.mud_m", &m);
            tr.record("final.mud_u", &u);
            u_final = Some(u);
            m_final = Some(m);
        }
        let mmid = self.conv_relu(Mask1, &net08);
        tr.record("q.mask_mid", &mmid);
        let mask = self.conv(Mask2, &mmid).map(|v| 0.25 * v);
        tr.record("q.mask_logit", &mask);
        tr.record("up_mask", &mask);
        let disparity = convex_upsample(&flow.channels(0, 1).map(|v| 8.0 * v), &mask).map(|v| -v);
        tr.record("up.disp", &disparity);
        let uncertainty = u_final.map(|u| convex_upsample(&u, &mask));
        if let Some(u) = &uncertainty {
            tr.record("up.u", u);
        }
        FloatOutput { disparity, uncertainty, matchability: m_final }
    }

    /// Pads a pair to the network size and runs it with `iters` iterations, recording into `tr`.
    pub fn trace_pair(
        &self,
        left: &ImageView<'_>,
        right: &ImageView<'_>,
        iters: usize,
        tr: &mut dyn Trace,
    ) -> Result<FloatOutput, InputError> {
        let (pw, ph) = check_pair(left, right)?;
        let to_tensor = |im: &ImageView<'_>| {
            let mut t = Tensor::zeros(3, ph, pw);
            for c in 0..3 {
                for y in 0..ph {
                    for x in 0..pw {
                        t[(c, y, x)] = im.at_clamped(c, x, y) as f32;
                    }
                }
            }
            t
        };
        Ok(self.forward_iters(&to_tensor(left), &to_tensor(right), iters, tr))
    }

    /// Runs the network on an image pair of any size (padded internally, output cropped back);
    /// `iters` overrides the config's iteration count.
    pub fn predict(
        &self,
        left: &ImageView<'_>,
        right: &ImageView<'_>,
        iters: Option<usize>,
    ) -> Result<Prediction, InputError> {
        let iters = iters.unwrap_or(self.config().iters);
        let out = self.trace_pair(left, right, iters, &mut NoTrace);
        // The convolutions' scratch is kept for one frame, not beyond it.
        super::ops::release_scratch();
        let out = out?;
        let crop = |t: &Tensor| {
            let mut v = Vec::with_capacity(left.width * left.height);
            for y in 0..left.height {
                v.extend_from_slice(&t.data[y * t.w..y * t.w + left.width]);
            }
            v
        };
        Ok(Prediction {
            width: left.width,
            height: left.height,
            disparity: crop(&out.disparity),
            uncertainty: out.uncertainty.as_ref().map(crop),
            matchability: out.matchability.map(|m| (m.w, m.h, m.data)),
        })
    }
}
