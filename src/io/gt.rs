//! Ground-truth disparity of the scenes in `shared/data` (encodings per its MANIFEST.md).

use std::fs::File;
use std::io::BufReader;
use std::path::Path;

use ::png::{BitDepth, ColorType, Decoder, Transformations};

use super::{FloatImage, IoError, read_pfm};

/// Reads a scene folder's left-view ground truth in pixels; invalid pixels are NaN.
///
/// | file | disparity |
/// |---|---|
/// | `truedisp.pgm` (tsukuba) | v / 16 |
/// | `disp2.pgm` (Middlebury 2001) | v / 8 |
/// | `disp2.png` (Middlebury 2003, quarter size) | v / 4 |
/// | `disp1.png` (Middlebury 2005/2006: third size v / 3, `*_half` folders v / 2) | |
/// | `disp0.pfm` (ETH3D) | value (+inf invalid) |
/// | `gt_disparity.png` (KITTI, 16-bit) | v / 256 |
///
/// Zero encodes "unknown" in the integer formats.
pub fn read_ground_truth(scene: impl AsRef<Path>) -> Result<FloatImage, IoError> {
    let dir = scene.as_ref();
    let dataset = dir.parent().and_then(|p| p.file_name()).and_then(|n| n.to_str()).unwrap_or("");
    let scaled = |img: (usize, usize, Vec<u32>), div: f32| {
        let (width, height, v) = img;
        let data = v.iter().map(|&x| if x == 0 { f32::NAN } else { x as f32 / div }).collect();
        FloatImage { width, height, data }
    };
    let candidates: [(&str, f32); 5] = [
        ("truedisp.pgm", 16.0),
        ("disp2.pgm", 8.0),
        ("disp2.png", 4.0),
        ("disp1.png", if dataset.ends_with("_half") { 2.0 } else { 3.0 }),
        ("gt_disparity.png", 256.0),
    ];
    for (name, div) in candidates {
        let p = dir.join(name);
        if p.exists() {
            let raw = if name.ends_with(".pgm") { read_pgm(&p)? } else { read_png_raw(&p)? };
            return Ok(scaled(raw, div));
        }
    }
    let p = dir.join("disp0.pfm");
    if p.exists() {
        let mut f = read_pfm(&p)?;
        f.data.iter_mut().for_each(|v| {
            if !v.is_finite() {
                *v = f32::NAN
            }
        });
        return Ok(f);
    }
    Err(IoError::Unsupported { path: dir.to_path_buf(), what: "no known ground-truth file".into() })
}

/// Largest disparity a ground-truth file may state (px); larger values are sentinels.
const MAX_PLAUSIBLE: f32 = 10_000.0;

/// Reads one disparity file in pixels; invalid pixels are NaN.
///
/// PFM values in 0 ..= 10,000 px are taken as they are (others = invalid); 8/16-bit PNG and 8-bit PGM values are
/// divided by `scale` (e.g. 4 for Middlebury 2003 quarter size, 256 for KITTI), 0 = invalid.
pub fn read_disparity_file(path: impl AsRef<Path>, scale: f32) -> Result<FloatImage, IoError> {
    let path = path.as_ref();
    let ext = path.extension().and_then(|e| e.to_str()).unwrap_or("").to_ascii_lowercase();
    let raw = match ext.as_str() {
        "pfm" => {
            let mut f = read_pfm(path)?;
            // Only a plausible disparity is a measurement: non-finite, negative and huge values
            // (-1e30 / 1e30 sentinels) are unknown.
            f.data.iter_mut().filter(|v| !(v.is_finite() && **v >= 0.0 && **v <= MAX_PLAUSIBLE)).for_each(|v| *v = f32::NAN);
            return Ok(f);
        }
        "pgm" => read_pgm(path)?,
        "png" => read_png_raw(path)?,
        _ => return Err(IoError::Unsupported { path: path.to_path_buf(), what: "disparity file is not .pfm, .png or .pgm".into() }),
    };
    let (width, height, v) = raw;
    let data = v.iter().map(|&x| if x == 0 { f32::NAN } else { x as f32 / scale }).collect();
    Ok(FloatImage { width, height, data })
}

/// 8-bit binary PGM (P5).
fn read_pgm(path: &Path) -> Result<(usize, usize, Vec<u32>), IoError> {
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, &e))?;
    let bad = |what: &str| IoError::Unsupported { path: path.to_path_buf(), what: what.into() };
    let mut fields = Vec::new();
    let mut pos = 0;
    while fields.len() < 4 {
        while pos < bytes.len() && bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if pos < bytes.len() && bytes[pos] == b'#' {
            while pos < bytes.len() && bytes[pos] != b'\n' {
                pos += 1;
            }
            continue;
        }
        let start = pos;
        while pos < bytes.len() && !bytes[pos].is_ascii_whitespace() {
            pos += 1;
        }
        if start == pos {
            return Err(bad("PGM header ends early"));
        }
        fields.push(String::from_utf8_lossy(&bytes[start..pos]).to_string());
    }
    pos += 1;
    let num = |s: &str| s.parse::<usize>().map_err(|_| bad("PGM header is not numeric"));
    if fields[0] != "P5" || num(&fields[3])? > 255 {
        return Err(bad("only 8-bit binary PGM (P5) is supported"));
    }
    let (w, h) = (num(&fields[1])?, num(&fields[2])?);
    let data = bytes.get(pos..pos + w * h).ok_or_else(|| bad("PGM data ends early"))?;
    Ok((w, h, data.iter().map(|v| *v as u32).collect()))
}

/// Gray PNG with its full bit depth (8 or 16).
fn read_png_raw(path: &Path) -> Result<(usize, usize, Vec<u32>), IoError> {
    let file = File::open(path).map_err(|e| IoError::io(path, &e))?;
    let err = |m: String| IoError::Png { path: path.to_path_buf(), message: m };
    let mut d = Decoder::new(BufReader::new(file));
    d.set_transformations(Transformations::EXPAND);
    let mut r = d.read_info().map_err(|e| err(e.to_string()))?;
    let mut buf = vec![0u8; r.output_buffer_size().ok_or_else(|| err("too large".into()))?];
    let info = r.next_frame(&mut buf).map_err(|e| err(e.to_string()))?;
    let (w, h) = (info.width as usize, info.height as usize);
    let chans = match info.color_type {
        ColorType::Grayscale => 1,
        ColorType::GrayscaleAlpha => 2,
        ColorType::Rgb => 3,
        ColorType::Rgba => 4,
        other => return Err(err(format!("colour type {other:?}"))),
    };
    let mut out = Vec::with_capacity(w * h);
    for y in 0..h {
        let row = &buf[y * info.line_size..];
        for x in 0..w {
            out.push(match info.bit_depth {
                BitDepth::Sixteen => u16::from_be_bytes([row[2 * x * chans], row[2 * x * chans + 1]]) as u32,
                _ => row[x * chans] as u32,
            });
        }
    }
    Ok((w, h, out))
}

#[cfg(test)]
mod tests {
    use super::*;

    const DATA: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data");

    #[test]
    fn decodes_each_dataset() {
        if !Path::new(DATA).exists() {
            println!("skipped: ../shared/data absent");
            return;
        }
        // (scene, size, max disparity from MANIFEST.md)
        for (scene, w, h, dmax) in [
            ("middlebury2001/tsukuba", 384, 288, 14.0),
            ("middlebury2001/venus", 434, 383, 19.8),
            ("middlebury2003/teddy", 450, 375, 52.8),
            ("middlebury2006/Aloe", 427, 370, 70.3),
            ("middlebury2005_half/Reindeer", 671, 555, 100.5),
            ("eth3d_twoview/playground", 941, 490, 20.0),
            ("kitti2015/000005_10", 1242, 375, 101.2),
        ] {
            let g = read_ground_truth(Path::new(DATA).join(scene)).unwrap();
            assert_eq!((g.width, g.height), (w, h), "{scene}");
            let m = g.data.iter().filter(|v| v.is_finite()).fold(0f32, |a, b| a.max(*b));
            assert!((m - dmax).abs() < 0.2, "{scene}: max {m}, manifest {dmax}");
        }
    }
}
