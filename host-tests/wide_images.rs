//! Fixed-point engine vs float reference at the sizes cameras deliver (issue #19): real pairs as
//! strips from 320 px to the largest accepted width (`Config::MAX_IMAGE_WIDTH`, 1920 px), on the
//! largest disparities of `../shared/data`, for both shipped blobs. It compares the network's
//! outputs (the full-resolution refinement, a per-pixel post-process without size-dependent state,
//! is off in both engines here and measured by `fixed_vs_float.rs`).
//!
//! Before the fix the engine agreed with the float model below 512 px and broke beyond (a 671 px
//! Middlebury pair: mean |d_fixed - d_float| 2.40 px, a 941 px ETH3D pair 5.68 px, KITTI's 1242 px
//! frame garbage): the 16-bit slots fed by the disparity (ufi_f, mot_f1, ...) were calibrated on
//! 320x240 crops and saturated at the disparities and far UFI proposals of wide frames. Each strip
//! is held near the figures measured after the fix ([`within_bounds`]), so a size-dependent defect
//! (a cliff) fails the test whatever the width at which it starts.
//!
//! Strips (rows x columns of the stored image; `up` = bilinear upscaling of the strip's source
//! rows, disparities scale with it):
//! * KITTI 2015 000005_10 (1242x375, disparities to ~100 px on the strip): left-aligned strips 320,
//!   640, 1024 px, the full 1242 px, and the full width upscaled to 1920 px (disparities to ~155 px);
//! * Middlebury 2005 Reindeer at half size (671x555, disparities to 100 px): right-aligned strips
//!   512 and 520 px (either side of the old cliff) and the full 671 px;
//! * ETH3D playground (941x490): the full width.

#[path = "support/crops.rs"]
#[allow(dead_code)]
mod crops;

use std::path::Path;

use muir::engine::{Engine, Output, Plan};
use muir_tools::float::{FloatModel, FloatWeights};
use muir::format::QuantModel;
use muir::input::PixelFormat;
use muir_tools::io::{OwnedImage, read_png};
use muir::model::config::Config;

use crops::{DATA, disparity_gap};

const ROOT: &str = env!("CARGO_MANIFEST_DIR");

/// One strip: scene, first row, rows, first column, columns, upscaled width (0 = none), and the
/// figures measured on it (mean |d_fixed - d_float| px, share within 1 px) for the u8-trunk blob
/// and the wide-trunk blob, 2026-12-04, shipped model (phase 8; phase 7 in git history), calibration of
/// `scripts/quantize-shipped.sh`, proposal search up to the default `MaxDisparity` (256 px).
struct Strip {
    scene: &'static str,
    y: usize,
    h: usize,
    x: usize,
    w: usize,
    up: usize,
    measured: [(f64, f64); 2],
}

#[allow(clippy::too_many_arguments)]
const fn s(scene: &'static str, y: usize, h: usize, x: usize, w: usize, up: usize, u8_trunk: (f64, f64), wide: (f64, f64)) -> Strip {
    Strip { scene, y, h, x, w, up, measured: [u8_trunk, wide] }
}

const KITTI: &str = "kitti2015/000005_10";
const REINDEER: &str = "middlebury2005_half/Reindeer";
const STRIPS: [Strip; 9] = [
    s(KITTI, 230, 96, 0, 320, 0, (0.1160, 1.0000), (0.0806, 0.9999)),
    s(KITTI, 230, 96, 0, 640, 0, (0.1221, 1.0000), (0.1008, 0.9919)),
    s(KITTI, 230, 96, 0, 1024, 0, (0.1439, 0.9877), (0.0977, 0.9896)),
    s(KITTI, 230, 96, 0, 1242, 0, (0.2602, 0.9607), (0.1428, 0.9750)),
    s(KITTI, 250, 62, 0, 1242, 1920, (0.4157, 0.8936), (0.2987, 0.9169)),
    s(REINDEER, 200, 128, 671 - 512, 512, 0, (0.1967, 0.9770), (0.1354, 0.9783)),
    s(REINDEER, 200, 128, 671 - 520, 520, 0, (0.1845, 0.9823), (0.1102, 0.9933)),
    s(REINDEER, 200, 128, 0, 671, 0, (0.1668, 0.9734), (0.1812, 0.9502)),
    s("eth3d_twoview/playground", 250, 96, 0, 941, 0, (0.0857, 0.9930), (0.0393, 0.9997)),
];

/// The blobs, in the order of `Strip::measured`.
const BLOBS: [&str; 2] = ["muir-slim.muirq", "muir-slim-wide.muirq"];

/// A strip fails when it is clearly worse than measured: the mean difference grows by more than
/// 30 % + 0.03 px, or the pixels off by more than 1 px by more than 30 % + 1 point. Issue #19's
/// target (mean <= 0.1 px, >= 99 % within 1 px) is printed met / not met per strip. Most of what
/// remained on the large-disparity strips after the saturation fix was UFI's proposal search over
/// the whole row: a far, spurious correlation peak won on near-ties and the engines' features
/// picked different ones (KITTI 1242 px strip, u8 trunk: 0.674 px / 86.9 % within 1 px); with the
/// search bounded by `MaxDisparity` (default 256 px) it is 0.260 px / 96.1 %. What is left there
/// is the 8-bit trunk's noise flipping near-tied proposals where the float model is itself
/// ambiguous (README "Accuracy"), not a size limit.
fn within_bounds((mean, within): (f64, f64), (m0, w0): (f64, f64)) -> bool {
    mean <= 1.3 * m0 + 0.03 && (1.0 - within) <= 1.3 * (1.0 - w0) + 0.01
}

/// Bilinear resize of an RGB or gray image to `w x h` (pixel centres aligned).
fn resize(im: &OwnedImage, w: usize, h: usize) -> OwnedImage {
    let n = im.format.channels();
    let (sx, sy) = (im.width as f32 / w as f32, im.height as f32 / h as f32);
    let mut data = vec![0u8; w * h * n];
    for y in 0..h {
        let fy = ((y as f32 + 0.5) * sy - 0.5).clamp(0.0, (im.height - 1) as f32);
        let (y0, ty) = (fy.floor() as usize, fy - fy.floor());
        let y1 = (y0 + 1).min(im.height - 1);
        for x in 0..w {
            let fx = ((x as f32 + 0.5) * sx - 0.5).clamp(0.0, (im.width - 1) as f32);
            let (x0, tx) = (fx.floor() as usize, fx - fx.floor());
            let x1 = (x0 + 1).min(im.width - 1);
            for c in 0..n {
                let p = |xx: usize, yy: usize| im.data[(yy * im.width + xx) * n + c] as f32;
                let v = (1.0 - ty) * ((1.0 - tx) * p(x0, y0) + tx * p(x1, y0)) + ty * ((1.0 - tx) * p(x0, y1) + tx * p(x1, y1));
                data[(y * w + x) * n + c] = (v + 0.5).clamp(0.0, 255.0) as u8;
            }
        }
    }
    OwnedImage { width: w, height: h, format: im.format, data }
}

fn strip_pair(st: &Strip) -> (OwnedImage, OwnedImage) {
    let dir = Path::new(DATA).join(st.scene);
    let cut = |v: &str| {
        let im = read_png(dir.join(v)).unwrap().crop(st.x, st.y, st.w, st.h).unwrap();
        if st.up > 0 { resize(&im, st.up, (st.h * st.up).div_ceil(st.w)) } else { im }
    };
    (cut("left.png"), cut("right.png"))
}

#[test]
fn fixed_engine_agrees_with_float_at_every_width() {
    if !Path::new(DATA).exists() && crops::data_missing(DATA) {
        return;
    }
    let float_bytes = std::fs::read(Path::new(ROOT).join("models/muir-slim.safetensors")).unwrap();
    let float = FloatModel::new(FloatWeights::from_safetensors(&float_bytes, None).unwrap());
    let pairs: Vec<_> = STRIPS.iter().map(strip_pair).collect();
    assert!(pairs.iter().any(|(l, _)| l.width == Config::MAX_IMAGE_WIDTH), "a strip at the largest width");
    // The network's outputs (the full-resolution refinement off in both engines): the refinement
    // is a per-pixel function of the images and the network's disparity with no size-dependent
    // state, and as an argmin it turns the engines' small differences on ambiguous pixels into
    // whole-pixel ones (README "Accuracy"); fixed_vs_float.rs measures the refined outputs.
    let floats: Vec<Vec<f32>> = pairs.iter().map(|(l, r)| float.predict(&l.view(), &r.view(), None).unwrap().disparity).collect();
    let mut failures = Vec::new();
    for (b, blob_name) in BLOBS.iter().enumerate() {
        let blob = std::fs::read(Path::new(ROOT).join("models").join(blob_name)).unwrap();
        let q = QuantModel::parse(&blob).unwrap();
        println!("\n{blob_name}:");
        println!("| strip | size | float max disparity | mean abs diff (px) | within 1 px | issue #19 target (0.1 px, 99 %) |");
        println!("|---|---|---:|---:|---:|---|");
        for ((st, (l, r)), fd) in STRIPS.iter().zip(&pairs).zip(&floats) {
            let (w, h) = (l.width, l.height);
            let plan = Plan::new(q.config(), w, h);
            let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
            let mut engine = Engine::new(&q, bytemuck::cast_slice_mut(&mut arena)).unwrap();
            engine.set_full_res_refinement(false);
            let mut d = vec![0i16; w * h];
            engine.run(&l.view(), &r.view(), &mut Output { disparity: &mut d, uncertainty: None }).unwrap();
            let (sd, wi) = disparity_gap(fd, &d);
            let (mean, within) = (sd / (w * h) as f64, wi as f64 / (w * h) as f64);
            let dmax = fd.iter().cloned().fold(0f32, f32::max);
            let met = mean <= 0.1 && within >= 0.99;
            println!(
                "| {} x{} y{}{} | {w}x{h} | {dmax:.1} | {mean:.4} | {:.2}% | {} |",
                st.scene,
                st.x,
                st.y,
                if st.up > 0 { " (upscaled)" } else { "" },
                100.0 * within,
                if met { "met" } else { "not met" }
            );
            if !within_bounds((mean, within), st.measured[b]) {
                failures.push(format!(
                    "{blob_name} on {} at {w}x{h}: {mean:.4} px, {:.2}% within 1 px (measured {:?})",
                    st.scene,
                    100.0 * within,
                    st.measured[b]
                ));
            }
        }
    }
    assert!(failures.is_empty(), "strips beyond the bounds: {failures:#?}");
}

/// Sizes beyond the limit are rejected with a typed error by both engines, not run into garbage.
#[test]
fn sizes_beyond_the_limit_are_rejected() {
    let (w, h) = (Config::MAX_IMAGE_WIDTH + 16, 32);
    let px = vec![0u8; w * h];
    assert!(matches!(
        muir::input::ImageView::new(w, h, PixelFormat::Gray8, &px),
        Err(muir::input::InputError::TooLarge { max_width: Config::MAX_IMAGE_WIDTH, .. })
    ));
    let forged = muir::input::ImageView { width: w, height: h, format: PixelFormat::Gray8, data: &px };
    let blob = std::fs::read(Path::new(ROOT).join("models/muir-slim.muirq")).unwrap();
    let q = QuantModel::parse(&blob).unwrap();
    let mut arena = vec![0u64; 1024];
    let mut engine = Engine::new(&q, bytemuck::cast_slice_mut(&mut arena)).unwrap();
    let mut d = vec![0i16; w * h];
    let e = engine.run(&forged, &forged, &mut Output { disparity: &mut d, uncertainty: None }).unwrap_err();
    assert!(e.to_string().contains("too large"), "{e}");
    let float_bytes = std::fs::read(Path::new(ROOT).join("models/muir-slim.safetensors")).unwrap();
    let float = FloatModel::new(FloatWeights::from_safetensors(&float_bytes, None).unwrap());
    assert!(float.predict(&forged, &forged, None).is_err());
}
