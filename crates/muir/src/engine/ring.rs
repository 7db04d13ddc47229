//! Line buffers and arena carving, and the slice helpers of the engine's phases.
//!
//! The phases carve their buffers from an arena whose length the engine checked against the plan,
//! with the sizes the plan gives: every row they take lies inside its buffer. The helpers below
//! still return an empty (or shorter) slice where a buffer is shorter than that, so no input can
//! reach an index panic; for a plan-checked arena this cannot happen.
#![deny(clippy::indexing_slicing)]

use core::num::NonZeroUsize;

use super::layout::{Buf, RingDecl};
use crate::kernels::conv::{MAX_K, PartRows};

/// Splits typed, disjoint buffers off an arena, in increasing offset order.
pub struct Carver<'a> {
    rest: &'a mut [u8],
    pos: usize,
}

impl<'a> Carver<'a> {
    /// Carves from `arena` (8-byte aligned, checked by the engine).
    pub fn new(arena: &'a mut [u8]) -> Self {
        Self { rest: arena, pos: 0 }
    }

    /// Restarts carving at absolute offset `at` (>= the current position) of a region that begins
    /// at `base` within the original arena. Used for nested layouts.
    fn bytes(&mut self, b: Buf) -> &'a mut [u8] {
        // Plans lay buffers out in increasing order without overlap; a violation is a bug in the
        // plan code (caught by the engine tests: the buffer comes back empty and the bits differ).
        if b.at < self.pos {
            debug_assert!(false, "buffers carved out of order");
            return &mut [];
        }
        let rest = core::mem::take(&mut self.rest);
        // Past the end of the arena (shorter than the plan: the engine refuses that before it
        // carves), the buffer is empty and so is every later one.
        let Some((_, tail)) = rest.split_at_mut_checked(b.at - self.pos) else { return &mut [] };
        let Some((buf, tail)) = tail.split_at_mut_checked(b.len) else { return &mut [] };
        self.rest = tail;
        self.pos = b.end();
        buf
    }

    /// A byte buffer viewed as `i8`.
    pub fn i8(&mut self, b: Buf) -> &'a mut [i8] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// A byte buffer viewed as `u64`.
    pub fn u64(&mut self, b: Buf) -> &'a mut [u64] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// A byte buffer as `u8` values.
    pub fn u8(&mut self, b: Buf) -> &'a mut [u8] {
        self.bytes(b)
    }
    /// A byte buffer viewed as `u16`.
    pub fn u16(&mut self, b: Buf) -> &'a mut [u16] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// A byte buffer viewed as `i16`.
    pub fn i16(&mut self, b: Buf) -> &'a mut [i16] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// The i16 ring a layout declares ([`Ring::of`]), carved here.
    pub fn ring16(&mut self, d: RingDecl, rows: usize) -> Ring<'a, i16> {
        Ring::of(self.i16(d.buf), d, rows)
    }
    /// A byte buffer viewed as `T` (`u8` or `i16`: the trunk's storage).
    pub fn typed<T: bytemuck::Pod>(&mut self, b: Buf) -> &'a mut [T] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// A byte buffer viewed as `i32`.
    pub fn i32(&mut self, b: Buf) -> &'a mut [i32] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// A byte buffer viewed as `i64`.
    pub fn i64(&mut self, b: Buf) -> &'a mut [i64] {
        bytemuck::cast_slice_mut(self.bytes(b))
    }
    /// Raw bytes.
    pub fn raw(&mut self, b: Buf) -> &'a mut [u8] {
        self.bytes(b)
    }
}

/// A ring of `cap` rows of `len` elements over a tensor of `rows` rows: row `r` lives in slot
/// `r % cap` from the moment it is pushed until `cap` newer rows are.
pub struct Ring<'a, T> {
    buf: &'a mut [T],
    // Non-zero, so the slot arithmetic has no division-by-zero path.
    cap: NonZeroUsize,
    len: usize,
    rows: usize,
    next: usize,
}

impl<'a, T: Copy> Ring<'a, T> {
    /// A ring over `buf` (at least `cap * len` elements; a shorter buffer, which a plan-checked
    /// arena never gives, yields empty rows past its end, and `cap = 0` counts as 1).
    pub fn new(buf: &'a mut [T], cap: usize, len: usize, rows: usize) -> Self {
        debug_assert!(buf.len() >= cap * len, "ring buffer too small");
        Self { buf, cap: NonZeroUsize::new(cap).unwrap_or(NonZeroUsize::MIN), len, rows, next: 0 }
    }

    /// The ring a stage's layout declares ([`RingDecl`]: depth and row length), over the buffer
    /// carved from that declaration, for a tensor of `rows` rows.
    pub fn of(buf: &'a mut [T], d: RingDecl, rows: usize) -> Self {
        Self::new(buf, d.cap, d.len, rows)
    }

    /// [`Ring::of`] with rows of `len <= d.len` elements: a pass that reuses a declared ring for a
    /// narrower tensor (the 1/16 ConvGRU in the 1/8 one's rings, the disparity head in the ring
    /// sized for the larger of the two heads). A longer `len` is cut to the declaration's.
    pub fn of_len(buf: &'a mut [T], d: RingDecl, len: usize, rows: usize) -> Self {
        debug_assert!(len <= d.len, "ring row {len} longer than declared {}", d.len);
        Self::new(buf, d.cap, len.min(d.len), rows)
    }

    /// Rows pushed so far (the next row to produce).
    pub fn produced(&self) -> usize {
        self.next
    }

    /// Total rows of the tensor.
    pub fn rows(&self) -> usize {
        self.rows
    }

    /// True while rows remain to be produced.
    pub fn pending(&self) -> bool {
        self.next < self.rows
    }

    /// Row `r`, which must still be held (a row that is not, a scheduling bug the engine tests
    /// would catch by its bits, reads as empty).
    pub fn row(&self, r: usize) -> &[T] {
        if !(r < self.next && r + self.cap.get() >= self.next) {
            debug_assert!(false, "ring row {r} not held (next {}, cap {})", self.next, self.cap);
            return &[];
        }
        chunk(self.buf, r % self.cap, self.len)
    }

    /// The slot of the next row; it counts as produced once this returns.
    pub fn push(&mut self) -> &mut [T] {
        let s = self.next % self.cap;
        self.next += 1;
        chunk_mut(self.buf, s, self.len)
    }

    /// The `k` input rows output row `y` of a `k`-kernel, stride-`stride` conv reads (`None` in
    /// the zero padding).
    pub fn part_rows(&self, y: usize, k: usize, stride: usize) -> PartRows<'_, T> {
        let mut rows = [None; MAX_K];
        for (ky, r) in rows.iter_mut().enumerate().take(k) {
            let iy = (y * stride + ky) as isize - (k / 2) as isize;
            if iy >= 0 && (iy as usize) < self.rows {
                *r = Some(self.row(iy as usize));
            }
        }
        PartRows { rows }
    }
}

/// Highest input row output row `y` of a `k`/`stride` conv reads, clipped to the tensor.
pub const fn last_input_row(y: usize, k: usize, stride: usize, rows: usize) -> usize {
    let r = y * stride + k / 2;
    if r >= rows { rows.saturating_sub(1) } else { r }
}

/// Element range `i * len .. (i + 1) * len` of `t` (row `i` of a tensor with rows of `len`
/// values, or pixel `i` with `len` channels); empty when `t` is shorter, which a buffer carved from
/// a plan-checked arena never is.
#[inline(always)]
pub fn chunk<T>(t: &[T], i: usize, len: usize) -> &[T] {
    t.get(i * len..(i + 1) * len).unwrap_or(&[])
}

/// [`chunk`] of a mutable slice.
#[inline(always)]
pub fn chunk_mut<T>(t: &mut [T], i: usize, len: usize) -> &mut [T] {
    t.get_mut(i * len..(i + 1) * len).unwrap_or_default()
}

/// The first `n` values of `t` (all of them when it is shorter).
#[inline(always)]
pub fn first_n<T>(t: &[T], n: usize) -> &[T] {
    t.get(..n).unwrap_or(t)
}

/// [`first_n`] of a mutable slice.
#[inline(always)]
pub fn first_n_mut<T>(t: &mut [T], n: usize) -> &mut [T] {
    let n = n.min(t.len());
    t.get_mut(..n).unwrap_or_default()
}

/// `dst.copy_from_slice(src)`, skipped when the lengths differ (rows of plan-checked buffers
/// never do).
#[inline(always)]
pub fn copy_row<T: Copy>(dst: &mut [T], src: &[T]) {
    if dst.len() == src.len() {
        dst.copy_from_slice(src);
    }
}
