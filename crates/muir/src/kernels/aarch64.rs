//! The aarch64 SIMD level of the host kernels (Linux-class Cortex-A modules), chosen at run time:
//! NEON (Advanced SIMD, part of the aarch64 baseline: always there) and the dot-product extension
//! (`sdot`, FEAT_DotProd: Cortex-A55/A75 and later, checked once, then one relaxed atomic load per
//! call). Host only (feature `std`: the detection needs it).
//!
//! Today the convolution rows use it (`conv::neon`, same integers as the portable kernels);
//! everything else runs the portable loops.
//!
//! `MUIR_ARM_SIMD=0` in the environment (read once) keeps the portable loops, `MUIR_ARM_SIMD=neon`
//! the NEON kernels without `sdot` (what a Cortex-A53/A72 runs), anything else (`dotprod`, or
//! unset) what the CPU has, for comparisons.
#![deny(clippy::indexing_slicing)]

use core::sync::atomic::{AtomicU8, Ordering};

/// What the kernels may use.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord)]
pub enum Level {
    /// The portable loops.
    Portable = 1,
    /// NEON without the dot-product extension.
    Neon = 2,
    /// NEON and `sdot`.
    DotProd = 3,
}

const UNKNOWN: u8 = 0;

static LEVEL: AtomicU8 = AtomicU8::new(UNKNOWN);

/// The level the kernels take (detected on the first call, then cached).
#[inline(always)]
pub fn level() -> Level {
    match LEVEL.load(Ordering::Relaxed) {
        1 => Level::Portable,
        2 => Level::Neon,
        3 => Level::DotProd,
        _ => detect(),
    }
}

/// What this CPU has, whatever `MUIR_ARM_SIMD` says (the tests run every level it allows).
pub fn cpu_level() -> Level {
    if std::arch::is_aarch64_feature_detected!("dotprod") { Level::DotProd } else { Level::Neon }
}

#[cold]
#[inline(never)]
fn detect() -> Level {
    let var = std::env::var_os("MUIR_ARM_SIMD");
    let l = match var.as_ref().and_then(|v| v.to_str()) {
        Some("0") => Level::Portable,
        Some("neon") => Level::Neon,
        _ => cpu_level(),
    };
    LEVEL.store(l as u8, Ordering::Relaxed);
    l
}
