//! Host side of MUIR: everything a vision engineer runs on a workstation around the `no_std`
//! engine of the [`muir`] crate.
//!
//! - [`float`]: the float reference (the PyTorch twin's numbers, every tensor), safetensors I/O;
//! - [`reference`]: the plain fixed-point reference engine over whole tensors;
//! - [`calib`]: calibration (activation formats, per-channel weight scales, GPTQ experiments);
//! - [`writer`]: the `.muirq` blob writer (the reader is `muir::format`);
//! - [`io`]: PNG, PFM and ground-truth readers and writers, colour maps;
//! - the `muir` command-line tool (`src/bin/muir.rs`).
#![warn(missing_docs)]
// Everything here needs std (feature `std`, on by default); without it the package is empty.
#![cfg_attr(not(feature = "std"), no_std)]

pub use muir;

#[cfg(feature = "std")]
pub mod calib;
#[cfg(feature = "std")]
pub mod float;
#[cfg(feature = "std")]
pub mod io;
#[cfg(feature = "std")]
pub mod reference;
#[cfg(feature = "std")]
pub mod writer;

/// The repository README's examples, compiled by `cargo test --doc` (its firmware example
/// embeds `models/muir-slim.muirq` from this package's directory).
#[cfg(doctest)]
#[doc = include_str!("../README.md")]
pub struct ReadmeDoctests;
