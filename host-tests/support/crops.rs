//! The five real 320x240 crops (with ground truth) on which the fixed engine is compared with the
//! float reference: `host-tests/fixed_vs_float.rs` and `examples/quant_drift.rs`.

use std::path::Path;

use muir::io::{OwnedImage, read_ground_truth, read_png};

/// The shared data sets, beside the repository as in CI.
pub const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data");
/// Crop width.
pub const W: usize = 320;
/// Crop height.
pub const H: usize = 240;

/// (scene, crop x, crop y): textured windows of five scenes of different datasets.
pub const SCENES: [(&str, usize, usize); 5] = [
    ("middlebury2001/tsukuba", 32, 24),
    ("middlebury2003/teddy", 100, 80),
    ("middlebury2005/Art", 120, 100),
    ("middlebury2006/Aloe", 90, 90),
    ("eth3d_twoview/playground", 400, 150),
];

/// One cropped pair and its ground-truth disparity (row-major, `W x H`, non-finite = unknown).
pub struct Pair {
    pub name: &'static str,
    pub left: OwnedImage,
    pub right: OwnedImage,
    pub gt: Vec<f32>,
}

/// The five pairs; `None` (with a note) when `../shared/data` is absent.
pub fn pairs() -> Option<Vec<Pair>> {
    if !Path::new(DATA).exists() {
        println!("skipped: {DATA} is absent (../shared not checked out)");
        return None;
    }
    Some(
        SCENES
            .iter()
            .map(|&(name, x, y)| {
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
