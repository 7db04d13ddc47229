//! The five real 320x240 crops (with ground truth) on which the fixed engine is compared with the
//! float reference: `host-tests/fixed_vs_float.rs` and `examples/quant_drift.rs`. The list lives in
//! `host-tests/fixtures/crops.txt`, which `python/muir/qat.py` reads too.

use std::path::Path;

use muir_tools::io::{OwnedImage, read_ground_truth, read_png};
use muir_tools::reference::disparity_px;

/// The shared data sets, beside the repository as in CI.
pub const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data");
/// Crop width (the `size` line of `crops.txt`; checked when the list is read).
pub const W: usize = 320;
/// Crop height.
pub const H: usize = 240;

/// The crop list: `size W H`, then one `scene x y` line per crop (textured windows of five scenes of
/// different datasets); `#` starts a comment.
const LIST: &str = include_str!("../fixtures/crops.txt");

/// (scene, crop x, crop y) from [`LIST`]; panics on a malformed list (a test fixture, not user input).
pub fn scenes() -> Vec<(&'static str, usize, usize)> {
    let mut out = Vec::new();
    for line in LIST.lines().map(|l| l.split('#').next().unwrap_or("").trim()).filter(|l| !l.is_empty()) {
        let f: Vec<&str> = line.split_whitespace().collect();
        let num = |s: &str| s.parse::<usize>().unwrap_or_else(|_| panic!("crops.txt: bad number in {line:?}"));
        match f.as_slice() {
            ["size", w, h] => assert_eq!((num(w), num(h)), (W, H), "crops.txt: size must be {W} {H}"),
            [scene, x, y] => out.push((*scene, num(x), num(y))),
            _ => panic!("crops.txt: bad line {line:?}"),
        }
    }
    out
}

/// One cropped pair and its ground-truth disparity (row-major, `W x H`, non-finite = unknown).
pub struct Pair {
    pub name: &'static str,
    pub left: OwnedImage,
    pub right: OwnedImage,
    pub gt: Vec<f32>,
}

/// The five pairs; `None` when `../shared/data` is absent and `MUIR_SKIP_DATA=1` (a failure
/// without it, see [`data_missing`]).
pub fn pairs() -> Option<Vec<Pair>> {
    if !Path::new(DATA).exists() && data_missing(DATA) {
        return None;
    }
    Some(
        scenes()
            .into_iter()
            .map(|(name, x, y)| {
                let dir = Path::new(DATA).join(name);
                let l = read_png(dir.join("left.png")).unwrap();
                let r = read_png(dir.join("right.png")).unwrap();
                let g = read_ground_truth(&dir).unwrap();
                let gt = (y..y + H).flat_map(|yy| g.data[yy * g.width + x..yy * g.width + x + W].to_vec()).collect();
                Pair { name, left: l.crop(x, y, W, H).unwrap(), right: r.crop(x, y, W, H).unwrap(), gt }
            })
            .collect(),
    )
}

/// Sum of |d_float - d_fixed| (pixels) and the count within 1 px, `fixed` in the engine's
/// disparity format ([`disparity_px`]).
pub fn disparity_gap(float: &[f32], fixed: &[i16]) -> (f64, usize) {
    float.iter().zip(fixed).fold((0.0, 0), |(s, w), (a, b)| {
        let d = (a - disparity_px(*b)).abs();
        (s + d as f64, w + (d <= 1.0) as usize)
    })
}

/// Tests that need `../shared/data` fail without it (a silent pass would claim a check that did
/// not run), unless `MUIR_SKIP_DATA=1` asks to skip them (then the test passes with a note).
pub fn data_missing(what: &str) -> bool {
    if std::env::var_os("MUIR_SKIP_DATA").is_some_and(|v| v == "1") {
        eprintln!("skipped (MUIR_SKIP_DATA=1): {what} is absent");
        return true;
    }
    panic!("{what} is absent: check out ../shared beside the repository, or set MUIR_SKIP_DATA=1 to skip the tests that need it");
}
