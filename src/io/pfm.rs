//! PFM float maps, Middlebury/Scharstein convention.
//!
//! Header: `Pf` (one channel) or `PF` (three), then width and height, then a scale whose sign gives
//! the byte order (negative = little endian), each followed by whitespace; then `f32` samples with
//! rows stored bottom-to-top. This module always hands rows top-to-bottom.

use std::path::Path;

use super::IoError;

/// A single-channel float map, rows top-to-bottom.
#[derive(Clone, Debug, PartialEq)]
pub struct FloatImage {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// `width * height` values, row-major.
    pub data: Vec<f32>,
}

/// Writes `values` (`width * height`, rows top-to-bottom) as a single-channel `Pf` file, scale
/// -1 (little endian). Values are stored as given: no clamping, infinities and NaN allowed.
pub fn write_pfm(path: impl AsRef<Path>, width: usize, height: usize, values: &[f32]) -> Result<(), IoError> {
    let path = path.as_ref();
    let bytes = encode(width, height, values).map_err(|reason| IoError::Pfm { path: path.to_path_buf(), reason })?;
    std::fs::write(path, bytes).map_err(|e| IoError::io(path, &e))
}

/// Reads a `Pf` or `PF` file (channel 0 of `PF`), either byte order.
pub fn read_pfm(path: impl AsRef<Path>) -> Result<FloatImage, IoError> {
    let path = path.as_ref();
    let bytes = std::fs::read(path).map_err(|e| IoError::io(path, &e))?;
    decode(&bytes).map_err(|reason| IoError::Pfm { path: path.to_path_buf(), reason })
}

fn encode(width: usize, height: usize, values: &[f32]) -> Result<Vec<u8>, String> {
    let n = width.checked_mul(height).ok_or("image size overflows")?;
    if values.len() != n {
        return Err(format!("{} values given for a {width}x{height} map", values.len()));
    }
    if n == 0 {
        return Err(format!("empty map ({width}x{height})"));
    }
    let header = format!("Pf\n{width} {height}\n-1.0\n");
    let mut out = Vec::with_capacity(header.len() + 4 * n);
    out.extend_from_slice(header.as_bytes());
    for row in values.chunks_exact(width).rev() {
        for v in row {
            out.extend_from_slice(&v.to_le_bytes());
        }
    }
    Ok(out)
}

/// Splits the next whitespace-delimited ASCII token off `bytes[*pos..]`, then consumes the single
/// whitespace byte that ends it.
fn token<'a>(bytes: &'a [u8], pos: &mut usize, what: &str) -> Result<&'a str, String> {
    while *pos < bytes.len() && bytes[*pos].is_ascii_whitespace() {
        *pos += 1;
    }
    let start = *pos;
    while *pos < bytes.len() && !bytes[*pos].is_ascii_whitespace() && *pos - start < 64 {
        *pos += 1;
    }
    if *pos >= bytes.len() || !bytes[*pos].is_ascii_whitespace() {
        return Err(format!("header ends or is malformed before its {what}"));
    }
    let tok = std::str::from_utf8(&bytes[start..*pos]).map_err(|_| format!("header {what} is not text"))?;
    *pos += 1;
    Ok(tok)
}

fn decode(bytes: &[u8]) -> Result<FloatImage, String> {
    let mut pos = 0;
    let magic = token(bytes, &mut pos, "'Pf'/'PF' tag").map_err(|_| "no 'Pf'/'PF' tag".to_string())?;
    let channels = match magic {
        "Pf" => 1,
        "PF" => 3,
        other => return Err(format!("tag '{}' is not 'Pf' or 'PF'", other.escape_debug())),
    };
    let dim = |s: &str, what: &str| -> Result<usize, String> {
        match s.parse::<usize>() {
            Ok(v) if v > 0 => Ok(v),
            _ => Err(format!("{what} '{}' is not a positive integer", s.escape_debug())),
        }
    };
    let width = dim(token(bytes, &mut pos, "width")?, "width")?;
    let height = dim(token(bytes, &mut pos, "height")?, "height")?;
    let scale_tok = token(bytes, &mut pos, "scale")?;
    let scale: f32 = scale_tok
        .parse()
        .ok()
        .filter(|s: &f32| s.is_finite() && *s != 0.0)
        .ok_or_else(|| format!("scale '{}' is not a non-zero number", scale_tok.escape_debug()))?;
    let little = scale < 0.0;
    let n = width
        .checked_mul(height)
        .and_then(|n| n.checked_mul(channels * 4))
        .ok_or_else(|| format!("size {width}x{height} overflows"))?;
    let body = &bytes[pos..];
    if body.len() != n {
        return Err(format!(
            "{width}x{height}x{channels} floats need {n} data bytes, the file holds {}{}",
            body.len(),
            if body.len() < n { " (truncated)" } else { "" }
        ));
    }
    let mut data = Vec::with_capacity(width * height);
    for row in body.chunks_exact(width * channels * 4).rev() {
        for px in row.chunks_exact(channels * 4) {
            let b = [px[0], px[1], px[2], px[3]];
            data.push(if little { f32::from_le_bytes(b) } else { f32::from_be_bytes(b) });
        }
    }
    Ok(FloatImage { width, height, data })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::tests::temp_path;

    #[test]
    fn round_trip_non_square_with_inf() {
        let p = temp_path("round_trip.pfm");
        let (w, h) = (5, 3);
        let mut v: Vec<f32> = (0..w * h).map(|i| i as f32 * 0.5 - 2.0).collect();
        v[1] = f32::INFINITY;
        v[7] = -1e30;
        write_pfm(&p, w, h, &v).unwrap();
        let bytes = std::fs::read(&p).unwrap();
        assert!(bytes.starts_with(b"Pf\n5 3\n-1.0\n"));
        // Bottom row first in the file.
        let first = f32::from_le_bytes(bytes[12..16].try_into().unwrap());
        assert_eq!(first, v[10]);
        let r = read_pfm(&p).unwrap();
        assert_eq!((r.width, r.height), (w, h));
        assert_eq!(r.data.len(), v.len());
        for (a, b) in r.data.iter().zip(&v) {
            assert_eq!(a.to_bits(), b.to_bits());
        }
        std::fs::remove_file(&p).ok();
    }

    #[test]
    fn big_endian_and_three_channels() {
        // 2x2 PF, big endian, scale 1. The first stored row is the bottom one, so channel 0 reads
        // 1 2 (top) / 3 4 (bottom).
        let mut bytes = b"PF\n2 2\n1.0\n".to_vec();
        for v in [3.0f32, 30.0, 300.0, 4.0, 40.0, 400.0, 1.0, 10.0, 100.0, 2.0, 20.0, 200.0] {
            bytes.extend_from_slice(&v.to_be_bytes());
        }
        let r = decode(&bytes).unwrap();
        assert_eq!(r, FloatImage { width: 2, height: 2, data: vec![1.0, 2.0, 3.0, 4.0] });
        // Extra whitespace in the header is fine.
        let mut bytes = b"Pf  1\n\n1 -1\n".to_vec();
        bytes.extend_from_slice(&7.5f32.to_le_bytes());
        assert_eq!(decode(&bytes).unwrap().data, vec![7.5]);
    }

    #[test]
    fn bad_files() {
        let e = |b: &[u8]| decode(b).unwrap_err();
        assert!(e(b"P6\n1 1\n255\n").contains("not 'Pf'"));
        assert!(e(b"Pf\n0 1\n-1\n\0\0\0\0").contains("width"));
        assert!(e(b"Pf\n1 x\n-1\n\0\0\0\0").contains("height"));
        assert!(e(b"Pf\n1 1\n0\n\0\0\0\0").contains("scale"));
        assert!(e(b"Pf\n2 1\n-1\n\0\0\0\0").contains("truncated"));
        assert!(e(b"Pf\n2 1").contains("header ends or is malformed"));
        assert!(e(b"").contains("tag"));
        assert!(encode(2, 2, &[0.0; 3]).is_err());
        let p = temp_path("missing.pfm");
        let err = read_pfm(&p).unwrap_err();
        assert!(matches!(err, IoError::Io { .. }) && err.to_string().contains("missing.pfm"), "{err}");
        std::fs::write(&p, b"Pf\n2 1\n-1\n\0\0\0\0").unwrap();
        let err = read_pfm(&p).unwrap_err();
        assert!(matches!(err, IoError::Pfm { .. }) && err.to_string().contains("missing.pfm"), "{err}");
        std::fs::remove_file(&p).ok();
    }

    #[test]
    fn eth3d_ground_truth() {
        let path = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/eth3d_twoview/playground/disp0.pfm");
        if !Path::new(path).exists() {
            println!("skipped: {path} is absent (../shared not checked out)");
            return;
        }
        let r = read_pfm(path).unwrap();
        assert_eq!((r.width, r.height), (941, 490));
        let finite: Vec<f32> = r.data.iter().copied().filter(|v| v.is_finite()).collect();
        let invalid = r.data.iter().filter(|v| **v == f32::INFINITY).count();
        assert_eq!(finite.len() + invalid, r.data.len(), "only finite values and +inf");
        let valid = finite.len() as f64 / r.data.len() as f64;
        assert!((valid - 0.496).abs() < 0.01, "valid fraction {valid}");
        let (lo, hi) = finite.iter().fold((f32::MAX, f32::MIN), |(a, b), v| (a.min(*v), b.max(*v)));
        assert!((2.0..2.2).contains(&lo) && (19.9..20.1).contains(&hi), "range {lo}..{hi}");
        // Re-encoding gives the same bytes (our writer uses the same convention and header).
        let bytes = std::fs::read(path).unwrap();
        let body = encode(r.width, r.height, &r.data).unwrap();
        let header_len = bytes.len() - r.width * r.height * 4;
        assert_eq!(&bytes[header_len..], &body[body.len() - r.width * r.height * 4..]);
    }
}
