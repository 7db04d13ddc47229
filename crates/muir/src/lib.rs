#![doc = include_str!("../README.md")]
#![cfg_attr(not(feature = "std"), no_std)]
#![warn(missing_docs)]
// No panic a caller's input can reach: no unwrap/expect/panic! and no indexing or slicing that can
// panic outside tests (each remaining `allow` says why it cannot fire; every module also denies
// indexing itself). Checked by `cargo clippy -p muir` in scripts/test.sh; what the compiler still
// emits is counted by boards/qemu-mps2/panic-sites.py, which fails on any branch into a panic path
// from muir's code in the firmware.
#![cfg_attr(not(test), deny(clippy::unwrap_used, clippy::expect_used, clippy::panic, clippy::indexing_slicing))]

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
