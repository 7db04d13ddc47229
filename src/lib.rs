#![doc = include_str!("../README.md")]
#![cfg_attr(not(feature = "std"), no_std)]
#![warn(missing_docs)]

pub mod arith;
pub mod engine;
pub mod format;
pub mod input;
pub mod kernels;
pub mod model;

#[cfg(feature = "std")]
pub mod calib;
#[cfg(feature = "std")]
pub mod float;
#[cfg(feature = "std")]
pub mod reference;
#[cfg(feature = "std")]
pub mod io;

pub use input::{ImageView, InputError, PixelFormat};
pub use model::{Config, ConfigError, ConvId};
