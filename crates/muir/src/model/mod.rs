//! Model description: configuration presets and the table of layers.
#![deny(clippy::indexing_slicing)]

pub mod config;
pub mod graph;
pub mod grid;
pub mod layers;
pub mod macs;

pub use config::{Config, ConfigError};
pub use layers::{ConvId, ConvShape, Norm};
