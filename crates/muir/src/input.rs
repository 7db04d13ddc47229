//! Input images as borrowed 8-bit buffers, and the checks every engine applies to them.
//!
//! Sides that are not multiples of [`Config::PAD_MULTIPLE`] are padded on the right and bottom by
//! edge replication (the network needs whole 1/16 cells); the output is cropped back to the input
//! size, so callers never see the padding.
#![deny(clippy::indexing_slicing)]

use core::fmt;

use crate::model::config::{Config, padded};

/// Pixel layout of an input image.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum PixelFormat {
    /// One byte per pixel; replicated to the three input channels.
    Gray8,
    /// Three bytes per pixel, R G B.
    Rgb8,
}

impl PixelFormat {
    /// Bytes per pixel.
    pub const fn channels(self) -> usize {
        match self {
            Self::Gray8 => 1,
            Self::Rgb8 => 3,
        }
    }
}

/// A row-major 8-bit image borrowed from the caller (camera buffer, decoded file).
#[derive(Clone, Copy, Debug)]
pub struct ImageView<'a> {
    /// Columns.
    pub width: usize,
    /// Rows.
    pub height: usize,
    /// Pixel layout.
    pub format: PixelFormat,
    /// `width * height * format.channels()` bytes.
    pub data: &'a [u8],
}

/// Why an input pair is rejected.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
#[cfg_attr(feature = "defmt", derive(defmt::Format))]
pub enum InputError {
    /// The buffer length does not match width x height x channels.
    DataLength {
        /// Bytes the size implies.
        expected: usize,
        /// Bytes given.
        found: usize,
    },
    /// Left and right images differ in size.
    SizeMismatch {
        /// Left (width, height).
        left: (usize, usize),
        /// Right (width, height).
        right: (usize, usize),
    },
    /// An image side is smaller than the network accepts.
    TooSmall {
        /// Image width.
        width: usize,
        /// Image height.
        height: usize,
        /// Smallest side accepted.
        min: usize,
    },
    /// An image side is larger than the engines accept ([`Config::MAX_IMAGE_WIDTH`],
    /// [`Config::MAX_IMAGE_HEIGHT`]).
    TooLarge {
        /// Image width.
        width: usize,
        /// Image height.
        height: usize,
        /// Largest width accepted.
        max_width: usize,
        /// Largest height accepted.
        max_height: usize,
    },
}

impl fmt::Display for InputError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match *self {
            Self::DataLength { expected, found } => {
                write!(f, "image buffer holds {found} bytes, its size implies {expected}")
            }
            Self::SizeMismatch { left, right } => write!(
                f,
                "left image is {}x{} but right image is {}x{}: a stereo pair must have one size",
                left.0, left.1, right.0, right.1
            ),
            Self::TooSmall { width, height, min } => {
                write!(f, "image {width}x{height} is too small: both sides must be at least {min} px")
            }
            Self::TooLarge { width, height, max_width, max_height } => write!(
                f,
                "image {width}x{height} is too large: at most {max_width}x{max_height} px"
            ),
        }
    }
}

#[cfg(feature = "std")]
impl std::error::Error for InputError {}

impl<'a> ImageView<'a> {
    /// Wraps a buffer, checking its length.
    pub fn new(width: usize, height: usize, format: PixelFormat, data: &'a [u8]) -> Result<Self, InputError> {
        check_size(width, height)?;
        let expected = width * height * format.channels();
        if data.len() != expected {
            return Err(InputError::DataLength { expected, found: data.len() });
        }
        Ok(Self { width, height, format, data })
    }

    /// Input-channel value (0..=255) of channel `c` at `(x, y)`, with edge replication outside
    /// the image (right/bottom padding).
    #[inline]
    pub fn at_clamped(&self, c: usize, x: usize, y: usize) -> u8 {
        let x = x.min(self.width - 1);
        let y = y.min(self.height - 1);
        let n = self.format.channels();
        let i = (y * self.width + x) * n + if n == 1 { 0 } else { c };
        // 0 past the end of a buffer shorter than its size says (`check_pair` refuses such a view).
        self.data.get(i).copied().unwrap_or(0)
    }
}

/// Rejects a size beyond [`Config::MAX_IMAGE_WIDTH`] x [`Config::MAX_IMAGE_HEIGHT`] (before any
/// size product is formed, so no product can overflow).
pub const fn check_size(width: usize, height: usize) -> Result<(), InputError> {
    if width > Config::MAX_IMAGE_WIDTH || height > Config::MAX_IMAGE_HEIGHT {
        return Err(InputError::TooLarge { width, height, max_width: Config::MAX_IMAGE_WIDTH, max_height: Config::MAX_IMAGE_HEIGHT });
    }
    Ok(())
}

/// Checks a stereo pair and returns the padded network input size `(width, height)`.
pub fn check_pair(left: &ImageView<'_>, right: &ImageView<'_>) -> Result<(usize, usize), InputError> {
    for im in [left, right] {
        // The fields are public: a view built without `new` is checked here too.
        check_size(im.width, im.height)?;
        let expected = im.width * im.height * im.format.channels();
        if im.data.len() != expected {
            return Err(InputError::DataLength { expected, found: im.data.len() });
        }
    }
    if (left.width, left.height) != (right.width, right.height) {
        return Err(InputError::SizeMismatch {
            left: (left.width, left.height),
            right: (right.width, right.height),
        });
    }
    if left.width < Config::MIN_SIDE || left.height < Config::MIN_SIDE {
        return Err(InputError::TooSmall { width: left.width, height: left.height, min: Config::MIN_SIDE });
    }
    Ok((padded(left.width), padded(left.height)))
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    use super::*;

    #[test]
    fn pair_checks() {
        let a = [0u8; 40 * 33 * 3];
        let b = [0u8; 40 * 33];
        let l = ImageView::new(40, 33, PixelFormat::Rgb8, &a).unwrap();
        let r = ImageView::new(40, 33, PixelFormat::Gray8, &b).unwrap();
        assert_eq!(check_pair(&l, &r), Ok((48, 48)));
        assert_eq!(
            ImageView::new(40, 33, PixelFormat::Rgb8, &b).unwrap_err(),
            InputError::DataLength { expected: 3960, found: 1320 }
        );
        let small = ImageView::new(40, 20, PixelFormat::Gray8, &b[..800]).unwrap();
        assert!(matches!(check_pair(&small, &small), Err(InputError::TooSmall { .. })));
        let other = ImageView::new(33, 40, PixelFormat::Gray8, &b).unwrap();
        assert!(matches!(check_pair(&r, &other), Err(InputError::SizeMismatch { .. })));
        // Too large: rejected before any size product (usize::MAX would wrap).
        assert!(matches!(ImageView::new(usize::MAX, usize::MAX, PixelFormat::Rgb8, &b), Err(InputError::TooLarge { .. })));
        assert!(matches!(ImageView::new(Config::MAX_IMAGE_WIDTH + 1, 1, PixelFormat::Gray8, &b), Err(InputError::TooLarge { .. })));
        let forged = ImageView { width: Config::MAX_IMAGE_WIDTH + 16, height: 40, format: PixelFormat::Gray8, data: &b };
        assert!(matches!(check_pair(&forged, &forged), Err(InputError::TooLarge { .. })));
        let widest = vec![0u8; Config::MAX_IMAGE_WIDTH * 32];
        let v = ImageView::new(Config::MAX_IMAGE_WIDTH, 32, PixelFormat::Gray8, &widest).unwrap();
        assert_eq!(check_pair(&v, &v), Ok((Config::MAX_IMAGE_WIDTH, 32)));
    }
}
