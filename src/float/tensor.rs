//! Dense f32 tensor, channel-major (C x H x W), batch of one.

use std::ops::{Index, IndexMut};

/// A `c x h x w` f32 tensor stored channel-major: element `(c, y, x)` at `(c * h + y) * w + x`.
#[derive(Clone, Debug, PartialEq)]
pub struct Tensor {
    /// Channels.
    pub c: usize,
    /// Rows.
    pub h: usize,
    /// Columns.
    pub w: usize,
    /// Values, `c * h * w` of them.
    pub data: Vec<f32>,
}

impl Tensor {
    /// All zeros.
    pub fn zeros(c: usize, h: usize, w: usize) -> Self {
        Self { c, h, w, data: vec![0.0; c * h * w] }
    }

    /// Wraps `data` (length must be `c * h * w`).
    pub fn from_vec(c: usize, h: usize, w: usize, data: Vec<f32>) -> Self {
        assert_eq!(data.len(), c * h * w, "tensor data length");
        Self { c, h, w, data }
    }

    /// Pixels per channel.
    pub fn plane(&self) -> usize {
        self.h * self.w
    }

    /// Channel `i` as a slice of `h * w` values.
    pub fn channel(&self, i: usize) -> &[f32] {
        let p = self.plane();
        &self.data[i * p..(i + 1) * p]
    }

    /// Channel `i`, mutable.
    pub fn channel_mut(&mut self, i: usize) -> &mut [f32] {
        let p = self.plane();
        &mut self.data[i * p..(i + 1) * p]
    }

    /// Channels `[from, from + n)` as a new tensor.
    pub fn channels(&self, from: usize, n: usize) -> Tensor {
        let p = self.plane();
        Tensor::from_vec(n, self.h, self.w, self.data[from * p..(from + n) * p].to_vec())
    }

    /// Concatenation along channels (all parts share h x w).
    pub fn cat(parts: &[&Tensor]) -> Tensor {
        let (h, w) = (parts[0].h, parts[0].w);
        let mut data = Vec::with_capacity(parts.iter().map(|t| t.data.len()).sum());
        let mut c = 0;
        for t in parts {
            assert!(t.h == h && t.w == w, "cat of tensors with different sizes");
            data.extend_from_slice(&t.data);
            c += t.c;
        }
        Tensor::from_vec(c, h, w, data)
    }

    /// Applies `f` to every element (on the float engine's threads when large, `super::par`).
    pub fn map(mut self, f: impl Fn(f32) -> f32 + Sync) -> Tensor {
        super::par::chunks(&mut self.data, 1, &|_, ch| ch.iter_mut().for_each(|v| *v = f(*v)));
        self
    }

    /// Element-wise combination with a tensor of the same shape.
    pub fn zip(mut self, other: &Tensor, f: impl Fn(f32, f32) -> f32 + Sync) -> Tensor {
        assert_eq!(self.data.len(), other.data.len(), "zip of different shapes");
        super::par::chunks(&mut self.data, 1, &|i, ch| ch.iter_mut().zip(&other.data[i..]).for_each(|(a, b)| *a = f(*a, *b)));
        self
    }

    /// Multiplies every channel by the single-channel tensor `m`.
    pub fn mul_plane(mut self, m: &Tensor) -> Tensor {
        assert!(m.c == 1 && m.h == self.h && m.w == self.w);
        let p = self.plane();
        for ch in self.data.chunks_mut(p) {
            ch.iter_mut().zip(&m.data).for_each(|(a, b)| *a *= b);
        }
        self
    }

    /// Largest absolute value (0 for an empty tensor).
    pub fn max_abs(&self) -> f32 {
        self.data.iter().fold(0.0f32, |m, v| m.max(v.abs()))
    }
}

impl Index<(usize, usize, usize)> for Tensor {
    type Output = f32;
    fn index(&self, (c, y, x): (usize, usize, usize)) -> &f32 {
        &self.data[(c * self.h + y) * self.w + x]
    }
}

impl IndexMut<(usize, usize, usize)> for Tensor {
    fn index_mut(&mut self, (c, y, x): (usize, usize, usize)) -> &mut f32 {
        &mut self.data[(c * self.h + y) * self.w + x]
    }
}
