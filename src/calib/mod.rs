//! Calibration: float weights + calibration pairs -> quantised model (`.muirq`), with a report.
//!
//! 1. The float reference runs on the calibration pairs; a [`CalibTrace`] collects, for every
//!    calibrated activation slot ([`Act`] without a fixed format), the largest magnitude and a
//!    histogram of magnitudes (32 bins per octave).
//! 2. Each slot gets the finest power-of-two format that holds its range: the maximum
//!    ([`RangeMethod::MinMax`]) or a percentile of the magnitudes ([`RangeMethod::Percentile`]);
//!    or the format with the least expected squared error, clipping plus rounding, over the
//!    histogram ([`RangeMethod::Mse`]).
//! 3. [`quantize`] folds BatchNorm, the image normalisation, part scales, merged context convs and
//!    output factors into effective weights, quantises them per output channel (int8 symmetric),
//!    biases into accumulator units (i64) and derives the requantisation multipliers. Weights are
//!    rounded to nearest, or ([`Rounding::Gptq`], the backbone's convs) with error compensation
//!    from the second moments of each layer's input patches ([`gptq`]).

pub mod gptq;

use std::collections::BTreeMap;
use std::fmt::{self, Write as _};

use muir::arith::{GATE_FRAC, LOG_FRAC, Multiplier, QFormat};
use crate::float::weights::FloatWeights;
use muir::kernels::conv::EXTRA_BITS;
use crate::float::{FloatModel, Tensor, Trace};
use crate::writer::{QuantLayer, QuantModelData};
use muir::format::{MAX_LEVELS, U_TABLE_LEN};
use muir::input::ImageView;
use muir::model::config::Config;
use muir::model::graph::{Act, PostOp, QLayer};
use muir::model::layers::ConvId;
use gptq::{InputMoments, Rounder};

const BINS_PER_OCTAVE: f64 = 32.0;
const MIN_EXP: f64 = -24.0;
const BINS: usize = 48 * 32;

/// Magnitude statistics of one activation slot.
#[derive(Clone, Debug)]
pub struct RangeStats {
    /// Largest magnitude seen.
    pub max_abs: f32,
    /// Values seen.
    pub count: u64,
    /// Magnitudes below the first bin (including zeros).
    pub small: u64,
    hist: Vec<u64>,
}

impl Default for RangeStats {
    fn default() -> Self {
        Self { max_abs: 0.0, count: 0, small: 0, hist: vec![0; BINS] }
    }
}

impl RangeStats {
    /// Adds values.
    pub fn add(&mut self, values: &[f32]) {
        for v in values {
            let a = v.abs();
            if !a.is_finite() {
                continue;
            }
            self.count += 1;
            self.max_abs = self.max_abs.max(a);
            let b = ((a as f64).log2() - MIN_EXP) * BINS_PER_OCTAVE;
            if b < 0.0 || a == 0.0 {
                self.small += 1;
            } else {
                self.hist[(b as usize).min(BINS - 1)] += 1;
            }
        }
    }

    /// Magnitude below which a fraction `p` of the values lie (upper edge of the bin).
    pub fn percentile(&self, p: f64) -> f32 {
        let target = (p * self.count as f64).ceil() as u64;
        let mut seen = self.small;
        if seen >= target {
            return 2f64.powf(MIN_EXP) as f32;
        }
        for (i, n) in self.hist.iter().enumerate() {
            seen += n;
            if seen >= target {
                let edge = 2f64.powf(MIN_EXP + (i + 1) as f64 / BINS_PER_OCTAVE);
                return (edge as f32).min(self.max_abs);
            }
        }
        self.max_abs
    }

    /// Expected squared error per value of storing the values in format `f`: clipping above the
    /// largest code, rounding below (`a^2` for magnitudes that round to 0, else `step^2 / 12`).
    /// Each bin counts at its geometric centre.
    pub fn quant_mse(&self, f: QFormat) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let step = 2f64.powi(-(f.frac as i32));
        let lim = f.qmax() as f64 * step;
        let mut err = 0.0;
        for (i, n) in self.hist.iter().enumerate().filter(|(_, n)| **n > 0) {
            let a = 2f64.powf(MIN_EXP + (i as f64 + 0.5) / BINS_PER_OCTAVE).min(self.max_abs as f64);
            let e = if a > lim {
                (a - lim).powi(2)
            } else if a < step / 2.0 {
                a * a
            } else {
                step * step / 12.0
            };
            err += *n as f64 * e;
        }
        err / self.count as f64
    }

    /// Fraction of the values whose magnitude exceeds `limit`.
    pub fn fraction_above(&self, limit: f32) -> f64 {
        if self.count == 0 {
            return 0.0;
        }
        let b = (((limit as f64).log2() - MIN_EXP) * BINS_PER_OCTAVE).max(0.0) as usize;
        let above: u64 = self.hist.iter().skip(b + 1).sum();
        above as f64 / self.count as f64
    }
}

/// Collects [`RangeStats`] from the float reference's `q.<slot>` records, and for
/// [`Rounding::Gptq`] the second moments of the backbone convs' input patches.
#[derive(Clone, Debug, Default)]
pub struct CalibTrace {
    /// Statistics by slot name.
    pub stats: BTreeMap<String, RangeStats>,
    /// Input-patch moments by layer.
    pub moments: BTreeMap<ConvId, InputMoments>,
    /// Layers whose moments are collected, by input slot name: (layer, k, stride).
    consumers: BTreeMap<&'static str, Vec<(ConvId, usize, usize)>>,
}

/// Input patches sampled per recorded tensor and layer for the moments.
const MOMENT_PATCHES: usize = 1024;

impl CalibTrace {
    /// A trace for `cfg`; with `rounding == Gptq` it also collects the input moments of every
    /// conv that reads a single u8 slot (the backbone, its heads and the feature head).
    pub fn new(cfg: &Config, rounding: Rounding) -> Self {
        let mut consumers: BTreeMap<&'static str, Vec<(ConvId, usize, usize)>> = BTreeMap::new();
        if rounding == Rounding::Gptq {
            for &id in ConvId::ALL {
                let (Some(ql), Some(s)) = (QLayer::of(id, cfg), id.shape(cfg)) else { continue };
                if let [Some(p), None, None, None, None, None] = ql.parts {
                    if p.act.storage_in(cfg).unsigned && ql.merged.is_none() {
                        consumers.entry(p.act.name()).or_default().push((id, s.k, s.stride));
                    }
                }
            }
        }
        Self { consumers, ..Self::default() }
    }
}

impl Trace for CalibTrace {
    fn record(&mut self, name: &str, t: &Tensor) {
        if let Some(slot) = name.strip_prefix("q.") {
            self.stats.entry(slot.to_string()).or_default().add(&t.data);
            for &(id, k, stride) in self.consumers.get(slot).into_iter().flatten() {
                self.moments.entry(id).or_insert_with(|| InputMoments::new(k * k * t.c)).add_patches(t, k, stride, MOMENT_PATCHES);
            }
        }
    }
}

/// How an 8-bit slot's range is chosen from its statistics (16-bit slots always hold the largest
/// magnitude seen, see [`choose_formats`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub enum RangeMethod {
    /// The largest magnitude seen.
    MinMax,
    /// The given quantile of the magnitudes (e.g. 0.9999).
    Percentile(f64),
    /// The least expected squared error ([`RangeStats::quant_mse`]) among the formats from the
    /// one that holds the maximum to 6 bits finer.
    Mse,
}

impl fmt::Display for RangeMethod {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::MinMax => write!(f, "minmax"),
            Self::Percentile(p) => write!(f, "percentile {:.4}% for 8-bit slots, maximum for 16-bit ones", p * 100.0),
            Self::Mse => write!(f, "least squared error for 8-bit slots, maximum for 16-bit ones"),
        }
    }
}

/// Why calibration failed.
#[derive(Clone, Debug, PartialEq)]
pub enum CalibError {
    /// No calibration pair was given.
    NoPairs,
    /// An input pair was rejected.
    Input(muir::input::InputError),
    /// A calibrated slot was never observed (the float model did not record it).
    Unobserved {
        /// Slot name.
        act: &'static str,
    },
    /// A multiplier is out of the representable range.
    Multiplier {
        /// Layer name.
        layer: &'static str,
        /// Real value.
        value: f64,
    },
}

impl fmt::Display for CalibError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::NoPairs => write!(f, "no calibration pairs"),
            Self::Input(e) => write!(f, "calibration pair rejected: {e}"),
            Self::Unobserved { act } => write!(f, "activation '{act}' was not observed during calibration"),
            Self::Multiplier { layer, value } => write!(f, "layer '{layer}': requantisation multiplier {value:e} out of range"),
        }
    }
}

impl std::error::Error for CalibError {}

/// The slot's format: fixed by the spec, or from its statistics (8-bit slots by `method`, 16-bit
/// slots by their largest magnitude).
pub fn choose_formats(cfg: &Config, stats: &BTreeMap<String, RangeStats>, method: RangeMethod) -> Result<[QFormat; Act::COUNT], CalibError> {
    let mut out = [QFormat::i8(0); Act::COUNT];
    for &act in Act::ALL {
        out[act.index()] = match act.fixed_format() {
            Some(f) => f,
            None => match stats.get(act.name()) {
                // 16-bit slots hold every observed value whatever the method: their resolution is
                // never the bottleneck (>= 11 bits below the maximum), while a clipped value can
                // be: the disparity-driven slots (ufi_f, mot_f1, ...) see their largest values at
                // large disparities and far UFI proposals, exactly the rare pixels a percentile
                // clips (issue #19: the engine invented disparities on wide images).
                Some(s) if s.count > 0 && act.storage_in(cfg).bits == 16 => act.storage_in(cfg).for_range(s.max_abs.max(1e-6)),
                Some(s) if s.count > 0 => {
                    match method {
                        RangeMethod::MinMax => act.storage_in(cfg).for_range(s.max_abs.max(1e-6)),
                        RangeMethod::Percentile(p) => act.storage_in(cfg).for_range(s.percentile(p).max(1e-6)),
                        RangeMethod::Mse => {
                            let widest = act.storage_in(cfg).for_range(s.max_abs.max(1e-6));
                            (0..=6)
                                .map(|d| QFormat { frac: widest.frac.saturating_add(d), ..widest })
                                .min_by(|a, b| s.quant_mse(*a).total_cmp(&s.quant_mse(*b)))
                                .unwrap_or(widest)
                        }
                    }
                }
                _ if !slot_used(act, cfg) => act.storage_in(cfg),
                _ => return Err(CalibError::Unobserved { act: act.name() }),
            },
        };
    }
    Ok(out)
}

/// True when some computed layer of `cfg` reads or writes `act`.
pub fn slot_used(act: Act, cfg: &Config) -> bool {
    ConvId::ALL.iter().filter_map(|id| QLayer::of(*id, cfg)).any(|l| {
        l.out[0] == act || (l.split < usize::MAX && l.out[1] == act) || l.parts.iter().flatten().any(|p| p.act == act)
    }) || (act == Act::Glb && cfg.mga)
        || (act == Act::Corr)
}

/// Real scale of one part's integers (the image is `2 * pixel - 255` with scale 1/255).
fn part_scale(act: Act, formats: &[QFormat; Act::COUNT]) -> f64 {
    if act == Act::Image { 1.0 / 255.0 } else { 2f64.powi(-(formats[act.index()].frac as i32)) }
}

/// Quantises float weights with the given activation formats, rounding weights to nearest.
pub fn quantize(w: &FloatWeights, formats: &[QFormat; Act::COUNT]) -> Result<QuantModelData, CalibError> {
    quantize_with(w, formats, &BTreeMap::new())
}

/// Where one effective weight comes from: the layer's own weight (index into
/// [`FloatConv::weight`](crate::float::weights::FloatConv)) or the merged context conv's.
#[derive(Clone, Copy, Debug)]
enum Source {
    Own(usize),
    Merged(ConvId, usize),
}

/// One output channel of a blob layer in effective units: BatchNorm, the input parts' scales and the
/// output factor folded in, parts in the blob's order (`ky, kx, ci` within a part). Each part
/// `ranges[p]` gets its own int8 scale.
struct EffectiveChannel {
    eff: Vec<f64>,
    src: Vec<Source>,
    ranges: Vec<(usize, usize)>,
    bias: f64,
}

/// The effective weights of output channel `c` of layer `id`; `part_scale(act)` is the real value
/// of one step of the part's input slot.
fn effective_channel(w: &FloatWeights, id: ConvId, ql: &QLayer, c: usize, part_scale: &dyn Fn(Act) -> f64) -> Option<EffectiveChannel> {
    let cfg = w.config;
    let fc = w.get(id)?;
    let s = fc.shape;
    let kk = s.k * s.k;
    // BatchNorm folded into the weights and bias.
    let (bn_k, mut bias) = match &fc.bn {
        Some(bn) => {
            let k = bn.weight[c] as f64 / (bn.var[c] as f64 + crate::float::weights::BN_EPS as f64).sqrt();
            (k, (fc.bias[c] as f64 - bn.mean[c] as f64) * k + bn.bias[c] as f64)
        }
        None => (1.0, fc.bias[c] as f64),
    };
    // Merged context conv: extra input part with that conv's weights for this gate's chunk.
    let merged = ql.merged.and_then(|(mid, chunk)| w.get(mid).map(|m| (mid, m, chunk)));
    let parts: Vec<_> = ql.parts.iter().flatten().copied().collect();
    let np = parts.len();
    let factor = ql.out_factor as f64;
    let mut ch = EffectiveChannel { eff: Vec::new(), src: Vec::new(), ranges: Vec::new(), bias: 0.0 };
    let mut cin0 = 0;
    for (pi, part) in parts.iter().enumerate() {
        let scale = part_scale(part.act) * factor;
        let is_ctx = merged.is_some() && pi == np - 1;
        let start = ch.eff.len();
        for ky in 0..s.k {
            for kx in 0..s.k {
                for ci in 0..part.channels {
                    let (v, src) = match (is_ctx, merged) {
                        (true, Some((mid, m, chunk))) => {
                            let row = chunk * cfg.hidden_dim + c;
                            let i = (row * m.shape.cin + ci) * kk + ky * s.k + kx;
                            (m.weight[i] as f64, Source::Merged(mid, i))
                        }
                        _ => {
                            let i = (c * s.cin + cin0 + ci) * kk + ky * s.k + kx;
                            (fc.weight[i] as f64 * bn_k, Source::Own(i))
                        }
                    };
                    ch.eff.push(v * scale);
                    ch.src.push(src);
                }
            }
        }
        ch.ranges.push((start, ch.eff.len()));
        if !is_ctx {
            cin0 += part.channels;
        }
    }
    if let Some((_, m, chunk)) = merged {
        bias += m.bias[chunk * cfg.hidden_dim + c] as f64;
    }
    ch.bias = bias * factor;
    Some(ch)
}

/// The int8 step of one part: its largest magnitude maps to 127 (symmetric, per output channel).
fn weight_step(eff: &[f64]) -> f64 {
    let max = eff.iter().fold(0f64, |m, v| m.max(v.abs()));
    if max > 0.0 { max / 127.0 } else { 1.0 }
}

/// [`quantize`], with GPTQ rounding for the layers that have input moments.
pub fn quantize_with(w: &FloatWeights, formats: &[QFormat; Act::COUNT], moments: &BTreeMap<ConvId, InputMoments>) -> Result<QuantModelData, CalibError> {
    let cfg = w.config;
    let scale = |act: Act| part_scale(act, formats);
    let mut layers = Vec::new();
    for &id in ConvId::ALL {
        let Some(ql) = QLayer::of(id, &cfg) else { continue };
        let Some(fc) = w.get(id) else { continue };
        let s = fc.shape;
        let parts: Vec<_> = ql.parts.iter().flatten().copied().collect();
        let patch = s.k * s.k * parts.iter().map(|p| p.channels).sum::<usize>();
        let np = parts.len();
        let mut q = QuantLayer {
            id,
            k: s.k,
            stride: s.stride,
            post: ql.post,
            parts: parts.iter().map(|p| p.channels).collect(),
            cout: s.cout,
            weights: vec![0; s.cout * patch],
            bias: vec![0; s.cout],
            mult: vec![Multiplier::ZERO; s.cout * np],
        };
        let rounder = moments.get(&id).filter(|m| np == 1 && ql.merged.is_none() && m.d == patch).and_then(Rounder::new);
        for c in 0..s.cout {
            let Some(ch) = effective_channel(w, id, &ql, c, &scale) else { continue };
            let out_frac = match ql.post {
                PostOp::Sigmoid | PostOp::Tanh => GATE_FRAC as i32,
                _ => formats[ql.out_act(c).index()].frac as i32,
            } + EXTRA_BITS as i32;
            // One int8 scale per (channel, part): parts of very different ranges keep full precision.
            for (pi, &(a, b)) in ch.ranges.iter().enumerate() {
                let sw = weight_step(&ch.eff[a..b]);
                let dst = &mut q.weights[c * patch + a..c * patch + b];
                match &rounder {
                    Some(r) => dst.copy_from_slice(&r.round(&ch.eff[a..b], sw)),
                    None => {
                        for (dst, v) in dst.iter_mut().zip(&ch.eff[a..b]) {
                            *dst = (v / sw).round().clamp(-127.0, 127.0) as i8;
                        }
                    }
                }
                let r = sw * 2f64.powi(out_frac);
                q.mult[c * np + pi] = Multiplier::from_f64(r).ok_or(CalibError::Multiplier { layer: id.name(), value: r })?;
            }
            q.bias[c] = (ch.bias * 2f64.powi(out_frac)).round().clamp(-(2f64.powi(62)), 2f64.powi(62)) as i64;
        }
        layers.push(q);
    }
    Ok(QuantModelData {
        config: cfg,
        formats: *formats,
        corr_mults: corr_multipliers(&cfg, formats)?,
        att_mult: attention_multiplier(&cfg, formats)?,
        rope_phases: rope_phases(&cfg),
        u_table: uncertainty_table(&cfg),
        layers,
    })
}

/// Moves every weight the blob quantises onto its int8 grid: each (output channel, input part)
/// group of effective weights becomes `q * step` with `q` the integer [`quantize`] rounds it to
/// (BatchNorm stays separate: a weight is scaled so that its folded value lands on the grid).
/// Quantising the result reproduces the same integers exactly, so the float reference of the
/// snapped model runs the weights the integer engine runs and the two differ by activation
/// rounding only. Returns the snapped weights and the RMS relative change of the moved weights.
pub fn snap_to_grid(w: &FloatWeights) -> (FloatWeights, f64) {
    let cfg = w.config;
    let mut out = w.clone();
    let (mut num, mut den) = (0f64, 0f64);
    // Part scales are powers of two (or the image's) times a per-layer factor: a constant per
    // group, which the grid does not depend on, so unit scales will do.
    let unit = |_: Act| 1.0;
    for &id in ConvId::ALL {
        let Some(ql) = QLayer::of(id, &cfg) else { continue };
        let Some(cout) = w.get(id).map(|fc| fc.shape.cout) else { continue };
        for c in 0..cout {
            let Some(ch) = effective_channel(w, id, &ql, c, &unit) else { continue };
            for &(a, b) in &ch.ranges {
                let sw = weight_step(&ch.eff[a..b]);
                for (v, src) in ch.eff[a..b].iter().zip(&ch.src[a..b]) {
                    if *v == 0.0 {
                        continue;
                    }
                    let ratio = (v / sw).round().clamp(-127.0, 127.0) * sw / v;
                    let (conv, i) = match *src {
                        Source::Own(i) => (id, i),
                        Source::Merged(mid, i) => (mid, i),
                    };
                    if let Some(fc) = out.get_mut(conv) {
                        let old = fc.weight[i] as f64;
                        fc.weight[i] = (old * ratio) as f32;
                        num += (old * (ratio - 1.0)).powi(2);
                        den += old * old;
                    }
                }
            }
        }
    }
    (out, if den > 0.0 { (num / den).sqrt() } else { 0.0 })
}

fn corr_multipliers(cfg: &Config, f: &[QFormat; Act::COUNT]) -> Result<Vec<Multiplier>, CalibError> {
    let ff = f[Act::Fmap.index()].frac as i32;
    let fcorr = f[Act::Corr.index()].frac as i32;
    (0..cfg.corr_levels.min(MAX_LEVELS))
        .map(|l| {
            let units = if cfg.post_pool { 8 + l as i32 } else { 8 + 2 * l as i32 };
            let r = 2f64.powi(fcorr - 2 * ff - units) / (cfg.fmap_dim as f64).sqrt();
            Multiplier::from_f64(r).ok_or(CalibError::Multiplier { layer: "corr lookup", value: r })
        })
        .collect()
}

fn attention_multiplier(cfg: &Config, f: &[QFormat; Act::COUNT]) -> Result<Multiplier, CalibError> {
    if !cfg.mga {
        return Ok(Multiplier::ZERO);
    }
    let (fq, fk) = (f[Act::MgaQ.index()].frac as i32, f[Act::MgaK.index()].frac as i32);
    let r = 2f64.powi(LOG_FRAC as i32 - fq - fk) / (cfg.mga_qk_dim as f64).sqrt();
    Multiplier::from_f64(r).ok_or(CalibError::Multiplier { layer: "attention", value: r })
}

/// RoPE phase steps (2^32 per turn) of each channel pair: pair `i` of a half turns by
/// `base^(-i/n)` radians per pixel.
pub fn rope_phases(cfg: &Config) -> Vec<u32> {
    if !cfg.mga {
        return Vec::new();
    }
    let pairs = cfg.mga_qk_dim / 2;
    let n = pairs / 2;
    (0..pairs)
        .map(|p| {
            let i = p % n;
            let freq = (cfg.mga_rope_base as f64).powf(-(i as f64) / n as f64);
            let turns = freq / std::f64::consts::TAU;
            ((turns * 4294967296.0).round() as u64 & 0xFFFF_FFFF) as u32
        })
        .collect()
}

/// `u = ln(eps_min^2 + (eps_max^2 - eps_min^2) sigmoid(b))` in Q4.11 at `b = -16 + i/32`.
pub fn uncertainty_table(cfg: &Config) -> Vec<i16> {
    let (lo, hi) = ((cfg.eps_min as f64).powi(2), (cfg.eps_max as f64).powi(2));
    (0..U_TABLE_LEN)
        .map(|i| {
            let b = -16.0 + i as f64 / 32.0;
            let u = (lo + (hi - lo) / (1.0 + (-b).exp())).ln();
            (u * 2f64.powi(LOG_FRAC as i32)).round().clamp(-32768.0, 32767.0) as i16
        })
        .collect()
}

/// How weights are rounded to their int8 steps.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Default)]
pub enum Rounding {
    /// Each weight to the nearest step.
    #[default]
    Nearest,
    /// Backbone convs with GPTQ error compensation ([`gptq`]), the others to nearest.
    Gptq,
}

impl fmt::Display for Rounding {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            Self::Nearest => "round to nearest",
            Self::Gptq => "GPTQ rounding of the backbone",
        })
    }
}

/// Calibration settings.
#[derive(Clone, Copy, Debug)]
pub struct CalibOptions {
    /// Range rule.
    pub method: RangeMethod,
    /// Refinement iterations run on each pair.
    pub iters: usize,
    /// Weight rounding.
    pub rounding: Rounding,
    /// Store conv1, layer1 and layer2 activations in i16 ([`Config::wide_trunk`]).
    pub wide_trunk: bool,
}

/// Result of [`calibrate`].
#[derive(Clone, Debug)]
pub struct Calibration {
    /// The quantised model.
    pub data: QuantModelData,
    /// Statistics by slot.
    pub stats: BTreeMap<String, RangeStats>,
    /// Range rule used.
    pub method: RangeMethod,
    /// Weight rounding used.
    pub rounding: Rounding,
}

/// Runs the float model on `pairs`, chooses formats and quantises. `progress(done, total)` is
/// called after each pair.
pub fn calibrate(model: &FloatModel, pairs: &[(ImageView<'_>, ImageView<'_>)], opts: CalibOptions, progress: &mut dyn FnMut(usize, usize)) -> Result<Calibration, CalibError> {
    if pairs.is_empty() {
        return Err(CalibError::NoPairs);
    }
    let mut trace = CalibTrace::new(model.config(), opts.rounding);
    for (i, (l, r)) in pairs.iter().enumerate() {
        model.trace_pair(l, r, opts.iters, &mut trace).map_err(CalibError::Input)?;
        progress(i + 1, pairs.len());
    }
    let cfg = Config { wide_trunk: opts.wide_trunk, ..*model.config() };
    let formats = choose_formats(&cfg, &trace.stats, opts.method)?;
    let mut data = quantize_with(model.weights(), &formats, &trace.moments)?;
    data.config.wide_trunk = opts.wide_trunk;
    Ok(Calibration { data, stats: trace.stats, method: opts.method, rounding: opts.rounding })
}

impl Calibration {
    /// Per-slot and per-layer report (Markdown).
    pub fn report(&self) -> String {
        let mut s = String::new();
        let cfg = &self.data.config;
        let trunk = if cfg.wide_trunk { ", wide trunk: conv1 .. layer2 in i16" } else { "" };
        let _ = writeln!(s, "# Calibration of {} ({}, {}{trunk})\n", cfg.name, self.method, self.rounding);
        let _ = writeln!(s, "| slot | bits | frac | range (max) | representable | clipped |");
        let _ = writeln!(s, "|---|---|---|---|---|---|");
        for &act in Act::ALL {
            let f = self.data.formats[act.index()];
            let (max, clipped) = match self.stats.get(act.name()) {
                Some(st) => {
                    let lim = f.qmax() as f32 * 2f32.powi(-(f.frac as i32));
                    (format!("{:.4}", st.max_abs), format!("{:.4}%", 100.0 * st.fraction_above(lim)))
                }
                None => ("-".into(), "-".into()),
            };
            let rep = f.qmax() as f64 * 2f64.powi(-(f.frac as i32));
            let kind = if act.fixed_format().is_some() { " (fixed)" } else { "" };
            let _ = writeln!(s, "| {}{} | {} | {} | {} | {:.4} | {} |", act.name(), kind, f.bits, f.frac, max, rep, clipped);
        }
        let _ = writeln!(s, "\n| layer | k | cin | cout | post | parts | multiplier (min..max) |");
        let _ = writeln!(s, "|---|---|---|---|---|---|---|");
        for l in &self.data.layers {
            let (lo, hi) = l.mult.iter().map(|m| m.to_f64()).fold((f64::MAX, 0f64), |(a, b), v| (a.min(v), b.max(v)));
            let _ = writeln!(
                s,
                "| {} | {} | {} | {} | {:?} | {} | {:.3e}..{:.3e} |",
                l.id.name(),
                l.k,
                l.parts.iter().sum::<usize>(),
                l.cout,
                l.post,
                l.parts.len(),
                lo,
                hi
            );
        }
        s
    }
}

/// Every record of a run, in order (for comparing two runs tensor by tensor).
#[derive(Clone, Debug, Default)]
pub struct Records(pub Vec<(String, Tensor)>);

impl Trace for Records {
    fn record(&mut self, name: &str, t: &Tensor) {
        self.0.push((name.to_string(), t.clone()));
    }
}

/// Signal-to-quantisation-noise ratio of one traced tensor (accumulated over its occurrences).
#[derive(Clone, Debug, PartialEq)]
pub struct Sqnr {
    /// Trace name (`q.<slot>` for activation slots).
    pub name: String,
    /// `10 log10(sum f^2 / sum (f - q)^2)`.
    pub db: f64,
    /// Occurrences compared (e.g. one per iteration).
    pub count: usize,
}

/// The records of two runs side by side: the n-th record of each name in `float` with the n-th of
/// the same name in `fixed`, where both have the same shape; in `float`'s order.
pub fn paired<'r>(float: &'r Records, fixed: &'r Records) -> Vec<(&'r str, &'r Tensor, &'r Tensor)> {
    let mut by_name: BTreeMap<&str, Vec<&Tensor>> = BTreeMap::new();
    for (n, t) in &fixed.0 {
        by_name.entry(n.as_str()).or_default().push(t);
    }
    let mut seen: BTreeMap<&str, usize> = BTreeMap::new();
    let mut out = Vec::new();
    for (n, f) in &float.0 {
        let idx = seen.entry(n.as_str()).or_default();
        if let Some(q) = by_name.get(n.as_str()).and_then(|v| v.get(*idx)).filter(|q| q.c == f.c && q.data.len() == f.data.len()) {
            out.push((n.as_str(), f, *q));
        }
        *idx += 1;
    }
    out
}

/// SQNR of the fixed-point run `fixed` against the float run `float`, over the [`paired`] records.
/// Errors accumulate through the network, so later layers show the end-to-end effect of all
/// earlier quantisation.
pub fn sqnr(float: &Records, fixed: &Records) -> Vec<Sqnr> {
    let mut acc: BTreeMap<&str, (f64, f64, usize)> = BTreeMap::new();
    for (n, f, q) in paired(float, fixed) {
        let e = acc.entry(n).or_default();
        for (a, b) in f.data.iter().zip(&q.data) {
            e.0 += (*a as f64).powi(2);
            e.1 += (*a as f64 - *b as f64).powi(2);
        }
        e.2 += 1;
    }
    acc.into_iter()
        .map(|(name, (s, e, count))| Sqnr { name: name.to_string(), db: 10.0 * (s.max(1e-30) / e.max(1e-30)).log10(), count })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn stats(values: &[f32]) -> RangeStats {
        let mut s = RangeStats::default();
        s.add(values);
        s
    }

    #[test]
    fn percentile_and_clipping() {
        let v: Vec<f32> = (1..=1000).map(|i| i as f32 / 100.0).collect(); // 0.01 .. 10
        let s = stats(&v);
        assert_eq!(s.count, 1000);
        assert_eq!(s.max_abs, 10.0);
        let p = s.percentile(0.5);
        assert!((4.9..5.2).contains(&p), "{p}");
        assert!((s.fraction_above(5.0) - 0.5).abs() < 0.02);
    }

    /// 16-bit slots hold every observed value (a disparity-driven slot's largest values are its
    /// rarest), 8-bit ones clip at the percentile.
    #[test]
    fn sixteen_bit_slots_are_never_clipped() {
        let cfg = Config::MUIR_SLIM;
        let mut v: Vec<f32> = (0..100_000).map(|i| (i % 1000) as f32 * 0.01).collect(); // 0 .. 9.99
        v.push(140.0);
        let mut map = BTreeMap::new();
        for act in Act::ALL.iter().filter(|a| a.fixed_format().is_none()) {
            map.insert(act.name().to_string(), stats(&v));
        }
        let f = choose_formats(&cfg, &map, RangeMethod::Percentile(0.9999)).unwrap();
        let ufi_f = f[Act::UfiF.index()];
        assert_eq!(ufi_f.bits, 16);
        assert!(ufi_f.to_f32(ufi_f.qmax()) >= 140.0, "{ufi_f:?}");
        assert!(ufi_f.to_f32(ufi_f.qmax()) < 280.0, "one bit of range, no more: {ufi_f:?}");
        let c1 = f[Act::C1.index()];
        assert_eq!(c1.bits, 8);
        assert!(c1.to_f32(c1.qmax()) < 140.0, "8-bit slots clip the outlier: {c1:?}");
        assert!(c1.to_f32(c1.qmax()) >= 9.0, "{c1:?}");
    }

    #[test]
    fn mse_trades_clipping_against_rounding() {
        let best = |s: &RangeStats| {
            let widest = QFormat::u8(0).for_range(s.max_abs);
            (0..=6).map(|d| QFormat { frac: widest.frac + d, ..widest }).min_by(|a, b| s.quant_mse(*a).total_cmp(&s.quant_mse(*b)))
        };
        let mut v: Vec<f32> = (0..100_000).map(|i| (i % 1000) as f32 * 0.0009).collect(); // 0 .. 0.8991
        // No outlier: clipping costs more than the step saves; the format that holds the maximum.
        let s = stats(&v);
        assert_eq!(QFormat::u8(0).for_range(s.max_abs), QFormat::u8(8));
        assert_eq!(best(&s), Some(QFormat::u8(8)));
        // One mild outlier: halving the step for 100,000 values beats clipping one.
        v.push(1.3);
        let s = stats(&v);
        assert_eq!(QFormat::u8(0).for_range(s.max_abs), QFormat::u8(7));
        assert!(s.quant_mse(QFormat::u8(8)) < s.quant_mse(QFormat::u8(7)));
        assert_eq!(best(&s), Some(QFormat::u8(8)));
        // A far outlier pulls the range most of the way: clipping it to ~1 would cost more than
        // the rounding noise of all the others at a coarse step.
        v.push(100.0);
        let s = stats(&v);
        assert_eq!(QFormat::u8(0).for_range(s.max_abs), QFormat::u8(1));
        assert_eq!(best(&s), Some(QFormat::u8(2)));
    }
}

#[cfg(test)]
mod snap_tests {
    use super::*;
    use crate::float::seeded;

    /// Integers of every (layer, channel, part) group, and each group's largest distance of
    /// `eff / step` from an integer.
    fn grid(w: &FloatWeights) -> (Vec<i64>, f64) {
        let (mut ints, mut off) = (Vec::new(), 0f64);
        for &id in ConvId::ALL {
            let Some(ql) = QLayer::of(id, &w.config) else { continue };
            let Some(cout) = w.get(id).map(|fc| fc.shape.cout) else { continue };
            for c in 0..cout {
                let Some(ch) = effective_channel(w, id, &ql, c, &|_| 1.0) else { continue };
                for &(a, b) in &ch.ranges {
                    let sw = weight_step(&ch.eff[a..b]);
                    for v in &ch.eff[a..b] {
                        let x = v / sw;
                        ints.push(x.round() as i64);
                        off = off.max((x - x.round()).abs());
                    }
                }
            }
        }
        (ints, off)
    }

    #[test]
    fn snapped_weights_sit_on_the_grid_they_round_to() {
        for cfg in Config::PRESETS {
            let w = FloatWeights::from_state_dict(seeded::state_dict(&cfg, 11), &cfg).unwrap();
            let (ints, off) = grid(&w);
            assert!(off > 0.4, "{}: seeded weights are off the grid", cfg.name);
            let (s, rms) = snap_to_grid(&w);
            // Rounding to 255 levels moves a weight by at most half a step: a small relative change.
            assert!(rms > 1e-4 && rms < 0.02, "{}: {rms}", cfg.name);
            let (snapped_ints, snapped_off) = grid(&s);
            assert_eq!(snapped_ints, ints, "{}: snapping changed an integer", cfg.name);
            assert!(snapped_off < 1e-4, "{}: {snapped_off}", cfg.name);
            // Idempotent: a second snap moves nothing beyond f32 rounding.
            let (_, again) = snap_to_grid(&s);
            assert!(again < 1e-6, "{}: {again}", cfg.name);
            // Layers the blob does not quantise are untouched, biases and BatchNorm too.
            for &id in ConvId::ALL {
                if let (Some(a), Some(b)) = (w.get(id), s.get(id)) {
                    assert_eq!(a.bias, b.bias);
                    assert_eq!(a.bn, b.bn);
                    if QLayer::of(id, &cfg).is_none() && !ConvId::ALL.iter().any(|m| QLayer::of(*m, &cfg).is_some_and(|q| q.merged.is_some_and(|(mid, _)| mid == id))) {
                        assert_eq!(a.weight, b.weight, "{}", id.name());
                    }
                }
            }
        }
    }
}
