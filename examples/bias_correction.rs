//! Empirical bias correction, measured (docs/experiments/bias-correction): does shifting conv
//! biases by the fixed engine's mean error close the engine's gap to the float reference?
//!
//! 1. Signed mean error `mean(q - f)` of every activation slot on the first fixed_vs_float crop
//!    (first occurrence), against its RMS: a ratio near 0 is unbiased noise.
//! 2. Jacobi passes on the four calibration pairs of the shipped blob (models/README.md): each pass
//!    runs the engine's reference kernels, takes per output channel the mean error of the layer's
//!    output slot where the float value exceeds `THRESHOLD` steps of the slot (so the mean is the
//!    pre-ReLU error), and subtracts `DAMPING` times it from the int32 bias. Layers ending in a
//!    sigmoid/tanh, split outputs and the 1x1 downsample convs (their block's conv2 carries the
//!    shared output) are left alone. After each pass: the gap on the five crops (held out).
//!
//! `cargo run --release --example bias_correction -- [PASSES [DAMPING [THRESHOLD [trunk|all]]]]`
//! (defaults 2, 0.5, 4, trunk: only layers reading u8 slots or the image). About 4 CPU min a pass.

#[path = "../host-tests/support/crops.rs"]
#[allow(dead_code)]
mod crops;

use std::collections::BTreeMap;

use muir_tools::calib::{CalibOptions, RangeMethod, Records, Rounding, calibrate, paired};
use muir_tools::float::{FloatModel, FloatWeights, NoTrace};
use muir::format::QuantModel;
use muir_tools::writer::{QuantModelData, write};
use muir_tools::io::{OwnedImage, read_png};
use muir::kernels::conv::EXTRA_BITS;
use muir::model::graph::{Act, PostOp, QLayer};
use muir_tools::reference::Reference;

/// The shipped blob's calibration pairs (models/README.md), cropped to 320x240 like `--max-size`.
const CALIB: [&str; 4] = ["oakd_desk", "oakd_living_room", "kitti2015_000051_11", "oakd_stairs"];

type Error = Box<dyn std::error::Error>;

/// Mean |d_fixed - d_float| and the share within 1 px over the crops.
fn gap(data: &QuantModelData, pairs: &[crops::Pair], float: &[Vec<f32>]) -> Result<(f64, f64), Error> {
    let blob = write(data);
    let q = QuantModel::parse(&blob)?;
    let (mut sum, mut within, mut n) = (0.0, 0usize, 0usize);
    for (p, f) in pairs.iter().zip(float) {
        let d = Reference::new(&q).predict(&p.left.view(), &p.right.view(), None, &mut NoTrace)?;
        let (s, w) = crops::disparity_gap(f, &d.disparity);
        sum += s;
        within += w;
        n += f.len();
    }
    Ok((sum / n as f64, 100.0 * within as f64 / n as f64))
}

fn main() -> Result<(), Error> {
    let arg = |i: usize| std::env::args().nth(i);
    let passes: usize = arg(1).map_or(Ok(2), |s| s.parse())?;
    let damping: f64 = arg(2).map_or(Ok(0.5), |s| s.parse())?;
    let threshold: f32 = arg(3).map_or(Ok(4.0), |s| s.parse())?;
    let trunk_only = arg(4).is_none_or(|s| s != "all");

    let model = FloatModel::new(FloatWeights::from_safetensors(&std::fs::read("models/muir-slim.safetensors")?, None)?);
    let cfg = *model.config();
    let pairs = crops::pairs().ok_or("needs ../shared/data")?;
    let float: Vec<Vec<f32>> = pairs.iter().map(|p| model.predict(&p.left.view(), &p.right.view(), None).map(|o| o.disparity)).collect::<Result<_, _>>()?;

    // 1. Bias of each slot on the first crop.
    let shipped = std::fs::read("models/muir-slim.muirq")?;
    let q = QuantModel::parse(&shipped)?;
    let (p, mut fr, mut qr) = (&pairs[0], Records::default(), Records::default());
    model.trace_pair(&p.left.view(), &p.right.view(), cfg.iters, &mut fr)?;
    Reference::new(&q).predict(&p.left.view(), &p.right.view(), None, &mut qr)?;
    println!("slot bias on {} (first occurrence)\n| slot | mean(q - f) | rms(q - f) | mean / rms |\n|---|---|---|---|", p.name);
    let mut shown = Vec::new();
    for (name, f, q) in paired(&fr, &qr).into_iter().filter(|(n, ..)| n.starts_with("q.")) {
        if shown.contains(&name) {
            continue;
        }
        shown.push(name);
        let (s, s2) = f.data.iter().zip(&q.data).fold((0f64, 0f64), |(s, s2), (a, b)| {
            let d = (*b - *a) as f64;
            (s + d, s2 + d * d)
        });
        let m = f.data.len() as f64;
        let rms = (s2 / m).sqrt();
        println!("| {} | {:.5} | {:.5} | {:.3} |", &name[2..], s / m, rms, s / m / rms.max(1e-12));
    }

    // 2. Correction passes.
    let mut images: Vec<(OwnedImage, OwnedImage)> = Vec::new();
    for d in CALIB {
        let dir = std::path::Path::new(crops::DATA).join("nogt").join(d);
        let (l, r) = (read_png(dir.join("left.png"))?, read_png(dir.join("right.png"))?);
        let (w, h) = (l.width.min(320), l.height.min(240));
        images.push((l.crop(0, 0, w, h).ok_or("crop")?, r.crop(0, 0, w, h).ok_or("crop")?));
    }
    let views: Vec<_> = images.iter().map(|(l, r)| (l.view(), r.view())).collect();
    let opts =
        CalibOptions { method: RangeMethod::Percentile(0.9999), iters: cfg.iters, rounding: Rounding::Nearest, wide_trunk: false };
    let mut data = calibrate(&model, &views, opts, &mut |_, _| {})?.data;
    if write(&data) != shipped {
        return Err("the calibration does not reproduce models/muir-slim.muirq".into());
    }
    let float_records: Vec<Records> = views
        .iter()
        .map(|(l, r)| {
            let mut rec = Records::default();
            model.trace_pair(l, r, cfg.iters, &mut rec).map(|_| rec)
        })
        .collect::<Result<_, _>>()?;
    let g = gap(&data, &pairs, &float)?;
    println!("\n{} layers, damping {damping}, threshold {threshold} steps", if trunk_only { "trunk" } else { "all" });
    println!("| pass | channels corrected | mean abs diff (px) | within 1 px |\n|---|---|---|---|\n| 0 | 0 | {:.4} | {:.2}% |", g.0, g.1);
    for pass in 1..=passes {
        let blob = write(&data);
        let q = QuantModel::parse(&blob)?;
        let mut err: BTreeMap<&str, Vec<(f64, usize)>> = BTreeMap::new();
        for ((l, r), fr) in views.iter().zip(&float_records) {
            let mut qr = Records::default();
            Reference::new(&q).predict(l, r, None, &mut qr)?;
            for (name, f, t) in paired(fr, &qr) {
                let Some(act) = name.strip_prefix("q.").and_then(|s| Act::ALL.iter().find(|a| a.name() == s)) else { continue };
                let step = 2f32.powi(-(data.formats[act.index()].frac as i32));
                let e = err.entry(act.name()).or_insert_with(|| vec![(0.0, 0); f.c]);
                for (c, e) in e.iter_mut().enumerate() {
                    for (a, b) in f.channel(c).iter().zip(t.channel(c)).filter(|(a, _)| **a > threshold * step) {
                        e.0 += (*b - *a) as f64;
                        e.1 += 1;
                    }
                }
            }
        }
        let mut changed = 0;
        for l in &mut data.layers {
            let Some(ql) = QLayer::of(l.id, &cfg) else { continue };
            let encoder = ql.parts.iter().flatten().all(|p| p.act.unsigned() || p.act == Act::Image);
            if ql.split != usize::MAX || !matches!(ql.post, PostOp::Relu | PostOp::None) || l.id.name().contains("downsample") || (trunk_only && !encoder) {
                continue;
            }
            let Some(e) = err.get(ql.out[0].name()).filter(|e| e.len() == l.cout) else { continue };
            let frac = data.formats[ql.out[0].index()].frac as i32 + EXTRA_BITS as i32;
            for (b, &(s, n)) in l.bias.iter_mut().zip(e).filter(|(_, (_, n))| *n >= 100) {
                *b -= (damping * s / n as f64 * 2f64.powi(frac)).round() as i64;
                changed += 1;
            }
        }
        let g = gap(&data, &pairs, &float)?;
        println!("| {pass} | {changed} | {:.4} | {:.2}% |", g.0, g.1);
    }
    Ok(())
}
