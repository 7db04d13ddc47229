//! The resolution pyramid of a padded input: the sizes every stage of the network works at.
//! Part of the model description (MAC counts and the engine's memory plan both build on it).
#![deny(clippy::indexing_slicing)]

use super::config::padded;

/// Grid sizes of a padded input.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct Grid {
    /// Padded width, height.
    pub w: usize,
    /// Padded height.
    pub h: usize,
    /// 1/2 resolution.
    pub w2: usize,
    /// 1/2 resolution rows.
    pub h2: usize,
    /// 1/4 resolution.
    pub w4: usize,
    /// 1/4 resolution rows.
    pub h4: usize,
    /// 1/8 resolution.
    pub w8: usize,
    /// 1/8 resolution rows.
    pub h8: usize,
    /// 1/16 resolution.
    pub w16: usize,
    /// 1/16 resolution rows.
    pub h16: usize,
}

impl Grid {
    /// Grid of an input of `width x height` (before padding).
    pub const fn new(width: usize, height: usize) -> Self {
        let (w, h) = (padded(width), padded(height));
        // conv k3/k7 stride 2 with k/2 padding: ceil(n / 2).
        let (w2, h2) = (w.div_ceil(2), h.div_ceil(2));
        let (w4, h4) = (w2.div_ceil(2), h2.div_ceil(2));
        let (w8, h8) = (w4.div_ceil(2), h4.div_ceil(2));
        let (w16, h16) = (w8.div_ceil(2), h8.div_ceil(2));
        Self { w, h, w2, h2, w4, h4, w8, h8, w16, h16 }
    }
    /// Pixels of the 1/8 grid.
    pub const fn n8(&self) -> usize {
        self.w8 * self.h8
    }
    /// Pixels of the 1/16 grid.
    pub const fn n16(&self) -> usize {
        self.w16 * self.h16
    }
}
