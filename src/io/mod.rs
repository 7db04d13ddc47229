//! Host image I/O: PNG input views, PFM disparity maps and colourised previews.
//!
//! * [`read_png`] decodes 8- or 16-bit gray, gray+alpha, RGB, RGBA and palette PNGs into an
//!   [`OwnedImage`] ([`PixelFormat::Gray8`] or [`PixelFormat::Rgb8`]; alpha is dropped, 16-bit
//!   samples keep their high byte), whose [`OwnedImage::view`] is what the engines take.
//! * [`write_pfm`] / [`read_pfm`] handle float maps in the Middlebury convention (`Pf`/`PF`,
//!   negative scale = little endian, rows stored bottom-to-top); the API is always top-to-bottom.
//! * [`colourise_disparity`] / [`colourise_uncertainty`] turn float maps into RGB previews
//!   (turbo colormap, non-finite values black) for [`write_png`].
//!
//! Every failure is an [`IoError`] whose message names the file.

mod colour;
mod gt;
mod pfm;
mod png;

use std::fmt;
use std::path::{Path, PathBuf};

pub use colour::{INVALID_COLOUR, colourise_disparity, colourise_uncertainty, percentile, turbo};
pub use gt::{read_disparity_file, read_ground_truth};
pub use pfm::{FloatImage, read_pfm, write_pfm};
pub use png::{read_png, write_png};

use muir::input::{ImageView, PixelFormat};

/// An 8-bit image that owns its pixels (a decoded file, a colourised map).
#[derive(Clone, Debug, PartialEq, Eq)]
pub struct OwnedImage {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Pixel layout.
    pub format: PixelFormat,
    /// `width * height * format.channels()` bytes, row-major.
    pub data: Vec<u8>,
}

impl OwnedImage {
    /// Borrows the pixels as an engine input.
    pub fn view(&self) -> ImageView<'_> {
        ImageView { width: self.width, height: self.height, format: self.format, data: &self.data }
    }

    /// The `width x height` window whose top-left corner is `(x, y)`; `None` if it does not lie
    /// inside the image.
    pub fn crop(&self, x: usize, y: usize, width: usize, height: usize) -> Option<OwnedImage> {
        if x.checked_add(width)? > self.width || y.checked_add(height)? > self.height {
            return None;
        }
        let n = self.format.channels();
        let mut data = Vec::with_capacity(width * height * n);
        for row in y..y + height {
            let start = (row * self.width + x) * n;
            data.extend_from_slice(self.data.get(start..start + width * n)?);
        }
        Some(OwnedImage { width, height, format: self.format, data })
    }
}

/// Why reading or writing an image file failed.
#[derive(Clone, Debug, PartialEq, Eq)]
pub enum IoError {
    /// The file could not be opened, read or written.
    Io {
        /// The file.
        path: PathBuf,
        /// The operating system's message.
        message: String,
    },
    /// The file is not a PNG the decoder accepts (or the encoder failed).
    Png {
        /// The file.
        path: PathBuf,
        /// The codec's message.
        message: String,
    },
    /// The file is not a valid PFM (or the map to write is inconsistent).
    Pfm {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A valid file of a kind this module does not handle (e.g. an animated PNG frame layout).
    Unsupported {
        /// The file.
        path: PathBuf,
        /// What is not supported.
        what: String,
    },
}

impl IoError {
    /// The file the error is about.
    pub fn path(&self) -> &Path {
        match self {
            Self::Io { path, .. }
            | Self::Png { path, .. }
            | Self::Pfm { path, .. }
            | Self::Unsupported { path, .. } => path,
        }
    }

    pub(crate) fn io(path: &Path, e: &std::io::Error) -> Self {
        Self::Io { path: path.to_path_buf(), message: e.to_string() }
    }
}

impl fmt::Display for IoError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Io { path, message } => write!(f, "{}: {message}", path.display()),
            Self::Png { path, message } => write!(f, "{}: not a readable PNG: {message}", path.display()),
            Self::Pfm { path, reason } => write!(f, "{}: not a valid PFM: {reason}", path.display()),
            Self::Unsupported { path, what } => write!(f, "{}: unsupported: {what}", path.display()),
        }
    }
}

impl std::error::Error for IoError {}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    /// A fresh path in this process's scratch folder (each test uses its own names).
    pub(crate) fn temp_path(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("muir-io-tests-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn crop_and_view() {
        let data: Vec<u8> = (0..4 * 3 * 3).map(|v| v as u8).collect();
        let im = OwnedImage { width: 4, height: 3, format: PixelFormat::Rgb8, data };
        let c = im.crop(1, 1, 2, 2).unwrap();
        assert_eq!(c.data, vec![15, 16, 17, 18, 19, 20, 27, 28, 29, 30, 31, 32]);
        assert!(im.crop(3, 0, 2, 1).is_none());
        assert!(im.crop(0, 0, 4, 3).is_some());
        let v = c.view();
        assert_eq!((v.width, v.height, v.at_clamped(2, 1, 1)), (2, 2, 32));
    }

    #[test]
    fn messages_name_the_file() {
        let e = IoError::Pfm { path: "a/b.pfm".into(), reason: "bad header".into() };
        assert_eq!(e.to_string(), "a/b.pfm: not a valid PFM: bad header");
        assert_eq!(e.path(), Path::new("a/b.pfm"));
    }
}
