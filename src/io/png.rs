//! PNG decoding to [`OwnedImage`] and encoding from it (the `png` crate).

use std::fs::File;
use std::io::{BufReader, BufWriter, ErrorKind};
use std::path::Path;

use ::png::{BitDepth, ColorType, Decoder, DecodingError, Encoder, EncodingError, Transformations};

use super::{IoError, OwnedImage};
use muir::input::PixelFormat;

/// Reads a PNG as 8-bit gray or RGB.
///
/// Gray and gray+alpha give [`PixelFormat::Gray8`]; RGB, RGBA and palette images (expanded through
/// the palette) give [`PixelFormat::Rgb8`]. Alpha is dropped and 16-bit samples keep their high
/// byte. Interlaced files are accepted; for animated PNGs the first frame is read. Files larger
/// than the engines accept (`Config::MAX_IMAGE_WIDTH` x `MAX_IMAGE_HEIGHT`) are rejected from
/// their header, before their pixels are allocated.
pub fn read_png(path: impl AsRef<Path>) -> Result<OwnedImage, IoError> {
    let path = path.as_ref();
    let file = File::open(path).map_err(|e| IoError::io(path, &e))?;
    let png_err = |e: DecodingError| match e {
        DecodingError::IoError(io) if io.kind() == ErrorKind::UnexpectedEof => {
            IoError::Png { path: path.to_path_buf(), message: "the file ends early (truncated)".into() }
        }
        DecodingError::IoError(io) => IoError::io(path, &io),
        other => IoError::Png { path: path.to_path_buf(), message: other.to_string() },
    };
    let mut decoder = Decoder::new(BufReader::new(file));
    decoder.set_transformations(Transformations::EXPAND | Transformations::STRIP_16);
    let mut reader = decoder.read_info().map_err(png_err)?;
    // The header's size is checked before anything is allocated: a small file may claim any size.
    let (hw, hh) = (reader.info().width as usize, reader.info().height as usize);
    if let Err(e) = muir::input::check_size(hw, hh) {
        return Err(IoError::Unsupported { path: path.to_path_buf(), what: e.to_string() });
    }
    let size = reader.output_buffer_size().ok_or_else(|| IoError::Unsupported {
        path: path.to_path_buf(),
        what: "the image is too large to hold in memory".into(),
    })?;
    let mut buf = vec![0u8; size];
    let info = reader.next_frame(&mut buf).map_err(png_err)?;
    let unsupported = |what: String| IoError::Unsupported { path: path.to_path_buf(), what };
    if info.bit_depth != BitDepth::Eight {
        return Err(unsupported(format!("decoded bit depth {:?} (expected 8)", info.bit_depth)));
    }
    let (width, height) = (info.width as usize, info.height as usize);
    let (format, keep, stride) = match info.color_type {
        ColorType::Grayscale => (PixelFormat::Gray8, 1, 1),
        ColorType::GrayscaleAlpha => (PixelFormat::Gray8, 1, 2),
        ColorType::Rgb => (PixelFormat::Rgb8, 3, 3),
        ColorType::Rgba => (PixelFormat::Rgb8, 3, 4),
        other => return Err(unsupported(format!("decoded colour type {other:?}"))),
    };
    let row_bytes = width * stride;
    if info.line_size < row_bytes || buf.len() < info.line_size * height.saturating_sub(1) + row_bytes {
        return Err(unsupported("decoded frame is smaller than its header says".into()));
    }
    let mut data = Vec::with_capacity(width * height * keep);
    for y in 0..height {
        let row = &buf[y * info.line_size..y * info.line_size + row_bytes];
        if keep == stride {
            data.extend_from_slice(row);
        } else {
            for px in row.chunks_exact(stride) {
                data.extend_from_slice(&px[..keep]);
            }
        }
    }
    Ok(OwnedImage { width, height, format, data })
}

/// Writes an 8-bit gray or RGB PNG.
pub fn write_png(path: impl AsRef<Path>, image: &OwnedImage) -> Result<(), IoError> {
    let path = path.as_ref();
    let expected = image.width * image.height * image.format.channels();
    if image.data.len() != expected {
        return Err(IoError::Png {
            path: path.to_path_buf(),
            message: format!("image buffer holds {} bytes, its size implies {expected}", image.data.len()),
        });
    }
    let (Ok(w), Ok(h)) = (u32::try_from(image.width), u32::try_from(image.height)) else {
        return Err(IoError::Unsupported { path: path.to_path_buf(), what: "image side exceeds u32".into() });
    };
    let png_err = |e: EncodingError| match e {
        EncodingError::IoError(io) => IoError::io(path, &io),
        other => IoError::Png { path: path.to_path_buf(), message: other.to_string() },
    };
    let file = File::create(path).map_err(|e| IoError::io(path, &e))?;
    let mut encoder = Encoder::new(BufWriter::new(file), w, h);
    encoder.set_color(match image.format {
        PixelFormat::Gray8 => ColorType::Grayscale,
        PixelFormat::Rgb8 => ColorType::Rgb,
    });
    encoder.set_depth(BitDepth::Eight);
    // fdeflate's PNG-tuned DEFLATE: the default (`Balanced`, zlib-like) took a tenth of a
    // `muir run` on Teddy (the three previews); these files are a few percent larger.
    encoder.set_compression(png::Compression::Fast);
    let mut writer = encoder.write_header().map_err(png_err)?;
    writer.write_image_data(&image.data).map_err(png_err)?;
    writer.finish().map_err(png_err)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::tests::temp_path;

    fn write_raw(path: &Path, w: u32, h: u32, color: ColorType, depth: BitDepth, palette: Option<&[u8]>, data: &[u8]) {
        let mut e = Encoder::new(BufWriter::new(File::create(path).unwrap()), w, h);
        e.set_color(color);
        e.set_depth(depth);
        if let Some(p) = palette {
            e.set_palette(p.to_vec());
        }
        let mut wr = e.write_header().unwrap();
        wr.write_image_data(data).unwrap();
        wr.finish().unwrap();
    }

    #[test]
    fn colour_types() {
        let p = temp_path("colour_types.png");
        // 3x2 gray.
        write_raw(&p, 3, 2, ColorType::Grayscale, BitDepth::Eight, None, &[1, 2, 3, 4, 5, 6]);
        let im = read_png(&p).unwrap();
        assert_eq!((im.width, im.height, im.format), (3, 2, PixelFormat::Gray8));
        assert_eq!(im.data, [1, 2, 3, 4, 5, 6]);
        // Gray + alpha: alpha dropped.
        write_raw(&p, 2, 1, ColorType::GrayscaleAlpha, BitDepth::Eight, None, &[7, 255, 8, 0]);
        assert_eq!(read_png(&p).unwrap().data, [7, 8]);
        // RGBA: alpha dropped.
        write_raw(&p, 2, 1, ColorType::Rgba, BitDepth::Eight, None, &[1, 2, 3, 9, 4, 5, 6, 9]);
        let im = read_png(&p).unwrap();
        assert_eq!((im.format, im.data.as_slice()), (PixelFormat::Rgb8, &[1u8, 2, 3, 4, 5, 6][..]));
        // 16-bit gray and RGB: high byte.
        write_raw(&p, 2, 1, ColorType::Grayscale, BitDepth::Sixteen, None, &[0x12, 0x34, 0xAB, 0xCD]);
        assert_eq!(read_png(&p).unwrap().data, [0x12, 0xAB]);
        write_raw(&p, 1, 1, ColorType::Rgb, BitDepth::Sixteen, None, &[1, 0, 2, 0xFF, 3, 7]);
        assert_eq!(read_png(&p).unwrap().data, [1, 2, 3]);
        // Palette: expanded to RGB.
        let pal = [10, 20, 30, 40, 50, 60];
        write_raw(&p, 3, 1, ColorType::Indexed, BitDepth::Eight, Some(&pal), &[1, 0, 1]);
        let im = read_png(&p).unwrap();
        assert_eq!((im.format, im.data.as_slice()), (PixelFormat::Rgb8, &[40u8, 50, 60, 10, 20, 30, 40, 50, 60][..]));
        std::fs::remove_file(&p).ok();
    }

    #[test]
    fn round_trip_and_errors() {
        let p = temp_path("round_trip.png");
        let im = OwnedImage { width: 5, height: 3, format: PixelFormat::Rgb8, data: (0..45).collect() };
        write_png(&p, &im).unwrap();
        assert_eq!(read_png(&p).unwrap(), im);
        let g = OwnedImage { width: 2, height: 2, format: PixelFormat::Gray8, data: vec![0, 64, 128, 255] };
        write_png(&p, &g).unwrap();
        assert_eq!(read_png(&p).unwrap(), g);

        // Truncated file.
        let bytes = std::fs::read(&p).unwrap();
        std::fs::write(&p, &bytes[..bytes.len() / 2]).unwrap();
        let e = read_png(&p).unwrap_err();
        assert!(matches!(e, IoError::Png { .. }), "{e:?}");
        assert!(e.to_string().contains("round_trip.png"), "{e}");
        // Not a PNG.
        std::fs::write(&p, b"P5\n2 2\n255\n0000").unwrap();
        assert!(matches!(read_png(&p).unwrap_err(), IoError::Png { .. }));
        // Missing file.
        std::fs::remove_file(&p).unwrap();
        let e = read_png(&p).unwrap_err();
        assert!(matches!(e, IoError::Io { .. }) && e.to_string().contains("round_trip.png"), "{e}");
        // Inconsistent buffer.
        let bad = OwnedImage { width: 2, height: 2, format: PixelFormat::Rgb8, data: vec![0; 4] };
        assert!(matches!(write_png(&p, &bad), Err(IoError::Png { .. })));
    }
}
