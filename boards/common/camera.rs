//! The camera side shared by the real-board firmware (`boards/stm32h743`, `boards/rp2350`): the
//! [`Camera`] trait a driver implements, and [`TestPattern`], the synthetic pair that stands in for
//! one. Each board's `src/bin/stereo.rs` includes this file (`#[path]`) and defines `W` and `H`.

use super::{H, W};

/// A rectified stereo camera delivering 8-bit grey frames of `W` x `H` pixels (row-major, no row
/// padding). A real driver (e.g. two sensors on the DCMI, or one side-by-side sensor) implements
/// this: `capture` returns once both frames are in the buffers.
pub trait Camera {
    type Error: defmt::Format;
    /// Fills `left` and `right` (each `W * H` bytes) with the next pair.
    fn capture(&mut self, left: &mut [u8], right: &mut [u8]) -> Result<(), Self::Error>;
}

/// A synthetic pair: a random 2x2-block texture, the right view shifted by [`TestPattern::BG_PX`]
/// pixels of disparity in the background and [`TestPattern::FG_PX`] in a centred rectangle. The
/// texture changes every frame.
pub struct TestPattern {
    frame: u32,
}

impl Default for TestPattern {
    fn default() -> Self {
        Self::new()
    }
}

#[derive(defmt::Format)]
pub enum PatternError {
    /// A buffer is not `W * H` bytes.
    WrongSize,
}

impl TestPattern {
    pub const BG_PX: i32 = 4;

    /// The pattern's first frame.
    pub const fn new() -> Self {
        Self { frame: 0 }
    }
    pub const FG_PX: i32 = 12;

    fn hash(x: u32, y: u32, seed: u32) -> u32 {
        let mut h = x.wrapping_mul(0x9E37_79B1) ^ y.wrapping_mul(0x85EB_CA77) ^ seed.wrapping_mul(0xC2B2_AE3D);
        h ^= h >> 15;
        h = h.wrapping_mul(0x2C1B_3C6D);
        h ^= h >> 12;
        h = h.wrapping_mul(0x297A_2D39);
        h ^ (h >> 15)
    }

    /// The scene's texture at column `u` (may be outside the frame), row `y`.
    fn texture(u: i32, y: i32, seed: u32) -> u8 {
        (32 + (Self::hash((u >> 1) as u32, (y >> 1) as u32, seed) >> 25)) as u8 * 3 / 2
    }

    /// Disparity of the scene at (x, y), in pixels.
    fn disparity(x: usize, y: usize) -> i32 {
        if (W / 4..3 * W / 4).contains(&x) && (H / 4..3 * H / 4).contains(&y) { Self::FG_PX } else { Self::BG_PX }
    }
}

impl Camera for TestPattern {
    type Error = PatternError;

    fn capture(&mut self, left: &mut [u8], right: &mut [u8]) -> Result<(), PatternError> {
        if left.len() != W * H || right.len() != W * H {
            return Err(PatternError::WrongSize);
        }
        let seed = self.frame;
        self.frame = self.frame.wrapping_add(1);
        for y in 0..H {
            for x in 0..W {
                // left(x) = scene(x); right(x) = left(x + d): a left pixel x matches right x - d.
                left[y * W + x] = Self::texture(x as i32, y as i32, seed);
                right[y * W + x] = Self::texture(x as i32 + Self::disparity(x, y), y as i32, seed);
            }
        }
        Ok(())
    }
}
