//! Float (f32) reference of the network, host only.
//!
//! It is checked against the PyTorch twin tensor by tensor (`host-tests/float_parity.rs`), and the
//! fixed-point engine is checked against it.

pub mod corr;
pub mod model;
pub mod ops;
pub mod seeded;
pub mod tensor;
pub mod weights;

pub use model::{FloatModel, FloatOutput, NoTrace, Prediction, Trace};
pub use tensor::Tensor;
pub use weights::{FloatWeights, WeightError};
