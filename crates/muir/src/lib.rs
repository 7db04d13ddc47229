#![doc = include_str!("../README.md")]
#![cfg_attr(not(feature = "std"), no_std)]
#![warn(missing_docs)]

pub mod arith;
pub mod engine;
pub mod format;
pub mod input;
pub mod kernels;
pub mod model;

pub use input::{ImageView, InputError, PixelFormat};
pub use model::{Config, ConfigError, ConvId};
