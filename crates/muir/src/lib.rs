#![doc = include_str!("../README.md")]
#![cfg_attr(not(feature = "std"), no_std)]
#![warn(missing_docs)]

pub mod arith;
pub mod engine;
pub mod format;
pub mod input;
/// The fixed-point kernels (row, pixel and plain whole-tensor forms). Internal: public only with
/// the `internals` feature, for the host tools' plain reference engine, tests and benches.
#[cfg(feature = "internals")]
pub mod kernels;
// Without `internals` the plain whole-tensor twins (the kernels' specification, run by the host
// reference engine and the tests) and a few of their helpers have no caller in this crate.
#[cfg(not(feature = "internals"))]
#[allow(dead_code)]
mod kernels;
pub mod model;

pub use input::{ImageView, InputError, PixelFormat};
pub use model::{Config, ConfigError, ConvId};
