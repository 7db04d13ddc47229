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

/// Threads for the float engine's matrix products (1 ..= 4; `matrixmultiply` splits the output
/// into blocks, each summed by one thread in the same order, so the results are the same bits for
/// any count). Takes effect only before the first matrix product of the process, which reads it
/// once; later calls return `false`. Without the crate feature `threads` there is one thread.
pub fn set_threads(n: usize) -> bool {
    use std::sync::atomic::{AtomicBool, Ordering};
    static SET: AtomicBool = AtomicBool::new(false);
    if SET.swap(true, Ordering::SeqCst) {
        return false;
    }
    // SAFETY: `set_var` must not race with other threads reading the environment. It runs once,
    // before this process's first matrix product; the CLI calls it first thing in `run`, while it
    // has one thread.
    unsafe { std::env::set_var("MATMUL_NUM_THREADS", n.clamp(1, 4).to_string()) };
    true
}
