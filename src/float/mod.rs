//! Float (f32) reference of the network, host only.
//!
//! It is checked against the PyTorch twin tensor by tensor (`host-tests/float_parity.rs`), and the
//! fixed-point engine is checked against it.

pub mod corr;
pub mod gemm;
pub mod model;
pub mod ops;
pub mod par;
pub mod seeded;
pub mod tensor;
pub mod weights;
pub mod winograd;

pub use model::{FloatModel, FloatOutput, NoTrace, Prediction, Trace};
pub use tensor::Tensor;
pub use weights::{FloatWeights, WeightError};

/// Threads for the float engine's matrix products (1 ..= 4, the caller included): the kernel
/// pool of the fixed-point engine (`muir::kernels::pool`), shared by both engines. Each output
/// tile is summed by one thread in the same order, so the results are the same bits for any count.
/// Without the crate feature `threads` this does nothing: the pool keeps the count it has (1
/// unless the fixed-point engine's `Engine::set_threads` changed it).
pub fn set_threads(n: usize) {
    #[cfg(feature = "threads")]
    muir::kernels::pool::set_threads(n.clamp(1, 4));
    #[cfg(not(feature = "threads"))]
    let _ = n;
}
