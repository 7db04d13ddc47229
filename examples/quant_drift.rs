//! Where the fixed engine's disparity leaves the float reference's, on the fixed_vs_float test's
//! five 320x240 crops:
//! 1. mean |d_fixed - d_float| and the share within 1 px after 0, 1, 2, 4 and 7 iterations;
//! 2. the same after 7 iterations when float tensors replace the fixed ones at one point
//!    (`Reference::with_injected`): the backbone's conv1, layer1, layer2 or trunk (layer3) output,
//!    the matching features, the context, the UFI peaks, or the whole initial state (disparity +
//!    hidden state). Each injected tensor is quantised to its slot, so what an injection removes is
//!    the noise accumulated upstream of it.
//! 3. the float network with only its weights rounded (per output channel, symmetric, to +-127 as
//!    in the blob, or to finer steps) and float activations: how much of the difference the int8
//!    weights of the encoder (layers reading u8 slots) and of the update block cause on their own
//!    (the blob scales each input part of a multi-part layer separately, so the update block's
//!    figure here is an upper bound).
//!
//! `cargo run --release --example quant_drift [-- MODEL_STEM [SCENE:Y:H:X:W]]` (default
//! `models/muir-slim` on the five crops; a strip `SCENE:Y:H:X:W` of a `../shared/data` scene, e.g.
//! `kitti2015/000005_10:230:96:0:1242`, replaces the crops by that one strip).

// The test's crops; the ground truth it also loads is not needed here.
#[path = "../host-tests/support/crops.rs"]
#[allow(dead_code)]
mod crops;

use muir_tools::calib::Records;
use muir_tools::float::{FloatModel, FloatWeights, NoTrace};
use muir::format::QuantModel;
use muir::model::graph::{Act, QLayer};
use muir::model::layers::ConvId;
use muir_tools::reference::Reference;

use crops::disparity_gap;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let stem = std::env::args().nth(1).unwrap_or_else(|| "models/muir-slim".into());
    let weights = FloatWeights::from_safetensors(&std::fs::read(format!("{stem}.safetensors"))?, None)?;
    let float = FloatModel::new(weights.clone());
    let blob = std::fs::read(format!("{stem}.muirq"))?;
    let q = QuantModel::parse(&blob)?;
    let pairs: Vec<_> = match std::env::args().nth(2) {
        Some(strip) => {
            let f: Vec<&str> = strip.split(':').collect();
            let [scene, y, h, x, w] = f[..] else { return Err("strip: SCENE:Y:H:X:W".into()) };
            let (y, h, x, w) = (y.parse()?, h.parse()?, x.parse()?, w.parse()?);
            let dir = std::path::Path::new(crops::DATA).join(scene);
            let cut = |v: &str| -> Result<_, Box<dyn std::error::Error>> { muir_tools::io::read_png(dir.join(v))?.crop(x, y, w, h).ok_or_else(|| "strip outside the image".into()) };
            vec![(cut("left.png")?, cut("right.png")?)]
        }
        None => crops::pairs().ok_or("needs ../shared/data")?.into_iter().map(|p| (p.left, p.right)).collect(),
    };
    let n = pairs.iter().map(|(l, _)| l.width * l.height).sum::<usize>() as f64;

    println!("| iterations | mean abs diff (px) | within 1 px |\n|---|---|---|");
    for iters in [0usize, 1, 2, 4, 7] {
        let (mut sd, mut wi) = (0.0, 0);
        for (l, r) in &pairs {
            let f = float.predict(&l.view(), &r.view(), Some(iters))?;
            let d = Reference::new(&q).predict(&l.view(), &r.view(), Some(iters), &mut NoTrace)?;
            let (s, w) = disparity_gap(&f.disparity, &d.disparity);
            sd += s;
            wi += w;
        }
        println!("| {iters} | {:.4} | {:.2}% |", sd / n, 100.0 * wi as f64 / n);
    }

    let iters = float.config().iters;
    let points: [(&str, &[&str]); 11] = [
        ("nothing", &[]),
        ("backbone conv1 output (1/2)", &["backbone.conv1"]),
        ("backbone layer1 output (1/2)", &["backbone.layer1"]),
        ("backbone layer2 output (1/4)", &["backbone.layer2"]),
        ("backbone trunk output (1/8, layer3)", &["backbone.layer3"]),
        ("matching features (fmap1/2)", &["fmap1", "fmap2"]),
        ("context (inp08/16)", &["inp08", "inp16"]),
        ("features + context (fmap1/2, inp08/16)", &["fmap1", "fmap2", "inp08", "inp16"]),
        ("UFI peaks", &["ufi.peaks"]),
        ("features + context + UFI peaks", &["fmap1", "fmap2", "inp08", "inp16", "ufi.peaks"]),
        ("initial state (init.flow, init.net08)", &["init.flow", "init.net08"]),
    ];
    println!("\n| float tensors injected | mean abs diff (px) | within 1 px |\n|---|---|---|");
    for (what, names) in points {
        let (mut sd, mut wi) = (0.0, 0);
        for (l, r) in &pairs {
            let mut rec = Records::default();
            let f = float.trace_pair(&l.view(), &r.view(), iters, &mut rec)?;
            rec.0.retain(|(name, _)| names.contains(&name.as_str()));
            let d = Reference::with_injected(&q, &rec).predict(&l.view(), &r.view(), None, &mut NoTrace)?;
            let (w, h) = (l.width, l.height);
            let fd: Vec<f32> = (0..h).flat_map(|y| f.disparity.data[y * f.disparity.w..y * f.disparity.w + w].to_vec()).collect();
            let (s, w) = disparity_gap(&fd, &d.disparity);
            sd += s;
            wi += w;
        }
        println!("| {what} | {:.4} | {:.2}% |", sd / n, 100.0 * wi as f64 / n);
    }

    println!("\n| weights rounded (float activations) | steps | mean abs diff (px) | within 1 px |\n|---|---|---|---|");
    let reference: Vec<Vec<f32>> =
        pairs.iter().map(|(l, r)| float.predict(&l.view(), &r.view(), None).map(|p| p.disparity)).collect::<Result<_, _>>()?;
    for encoder in [true, false] {
        for levels in [127.0f64, 511.0, 2047.0] {
            let mut w = weights.clone();
            let cfg = w.config;
            for &id in ConvId::ALL {
                let Some(ql) = QLayer::of(id, &cfg) else { continue };
                let reads_u8 = ql.parts.iter().flatten().all(|p| p.act.unsigned() || p.act == Act::Image);
                let Some(c) = w.get_mut(id).filter(|_| reads_u8 == encoder) else { continue };
                let per = c.weight.len() / c.shape.cout;
                for row in c.weight.chunks_mut(per) {
                    let step = row.iter().fold(0f32, |m, v| m.max(v.abs())) as f64 / levels;
                    if step > 0.0 {
                        row.iter_mut().for_each(|v| *v = ((*v as f64 / step).round() * step) as f32);
                    }
                }
            }
            let rounded = FloatModel::new(w);
            let (mut sd, mut wi) = (0.0, 0);
            for ((l, r), d0) in pairs.iter().zip(&reference) {
                let d = rounded.predict(&l.view(), &r.view(), None)?.disparity;
                for (a, b) in d.iter().zip(d0) {
                    sd += (a - b).abs() as f64;
                    wi += ((a - b).abs() <= 1.0) as usize;
                }
            }
            let what = if encoder { "encoder (layers reading u8 slots)" } else { "update block (all other layers)" };
            println!("| {what} | +-{levels} | {:.4} | {:.2}% |", sd / n, 100.0 * wi as f64 / n);
        }
    }
    Ok(())
}
