//! PyTorch twin -> Rust float reference: every intermediate tensor of the golden fixtures.
//!
//! Fixtures: `host-tests/fixtures/golden/<config>.safetensors`, written by `python -m muir.golden`
//! (the twin with seeded weights on a crop of Middlebury 2003 "cones"). The weights are rebuilt here
//! from the seed (`muir_tools::float::seeded`, bit-identical to `python/muir/seeded.py`). Tolerance: for
//! each tensor, max |rust - twin| <= 1e-4 * max |twin|.

use std::collections::BTreeMap;

use muir_tools::float::weights::{FloatWeights, ParamData, parse_safetensors};
use muir_tools::float::{FloatModel, Tensor, seeded};

const TOLERANCE: f32 = 1e-4;

fn fixture(name: &str) -> Vec<u8> {
    let path = format!("{}/host-tests/fixtures/golden/{name}.safetensors", env!("CARGO_MANIFEST_DIR"));
    std::fs::read(&path).unwrap_or_else(|e| panic!("{path}: {e} (regenerate with `python -m muir.golden`)"))
}

fn group(name: &str) -> String {
    match name.strip_prefix("iter") {
        Some(rest) => match rest.split_once('.') {
            Some((_, tail)) => format!("iter*.{tail}"),
            None => name.to_string(),
        },
        None => name.trim_end_matches(char::is_numeric).to_string(),
    }
}

fn check(config_name: &str) {
    let file = parse_safetensors(&fixture(config_name)).expect("fixture parses");
    let config = file.config.expect("fixture carries its config");
    assert_eq!(config.name.as_str(), config_name);
    let seed: u64 = file.metadata["seed"].parse().expect("seed");
    let weights = FloatWeights::from_state_dict(seeded::state_dict(&config, seed), &config).expect("seeded weights load");
    let model = FloatModel::new(weights);

    let get = |name: &str| -> (Vec<usize>, Vec<f32>) {
        let p = &file.tensors[name];
        match &p.data {
            ParamData::F32(v) => (p.shape.clone(), v.clone()),
            ParamData::I64(_) => panic!("{name}: not f32"),
        }
    };
    let input = |name: &str| {
        let (s, v) = get(name);
        Tensor::from_vec(s[0], s[1], s[2], v)
    };
    let mut trace: BTreeMap<String, Tensor> = BTreeMap::new();
    model.forward(&input("input.left"), &input("input.right"), &mut trace);

    let mut groups: BTreeMap<String, f32> = BTreeMap::new();
    let mut failures = Vec::new();
    let mut compared = 0;
    for name in file.tensors.keys().filter(|k| !k.starts_with("input.")) {
        let (shape, want) = get(name);
        let Some(got) = trace.get(name) else {
            failures.push(format!("{name}: not produced by the Rust reference"));
            continue;
        };
        if got.data.len() != want.len() {
            failures.push(format!("{name}: {} values, twin has {} (shape {shape:?})", got.data.len(), want.len()));
            continue;
        }
        let scale = want.iter().fold(0.0f32, |m, v| m.max(v.abs())).max(f32::MIN_POSITIVE);
        let err = got.data.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0.0f32, f32::max) / scale;
        let g = groups.entry(group(name)).or_insert(0.0);
        *g = g.max(err);
        if err.is_nan() || err > TOLERANCE {
            failures.push(format!("{name}: max rel error {err:.3e} > {TOLERANCE:e}"));
        }
        compared += 1;
    }
    eprintln!("{config_name}: {compared} tensors compared; max |delta| / max |twin| per group:");
    for (g, e) in &groups {
        eprintln!("  {g:<22} {e:.2e}");
    }
    assert!(compared > 40, "too few tensors compared ({compared})");
    assert!(failures.is_empty(), "{config_name} parity failures:\n{}", failures.join("\n"));
}

#[test]
fn muir_fast_matches_twin() {
    check("muir-fast");
}

#[test]
fn muir_slim_matches_twin() {
    check("muir-slim");
}

#[test]
fn raft_stereo_realtime_matches_twin() {
    check("raft-stereo-realtime");
}

/// The shipped model (trained): the Rust float reference reproduces the twin's full-resolution
/// disparity on a real crop (fixture written by `python -m muir.golden --shipped
/// models/muir-slim.safetensors`) within 0.01 px.
#[test]
fn shipped_model_matches_twin_on_a_real_pair() {
    let file = parse_safetensors(&fixture("shipped-muir-slim")).expect("fixture parses");
    let model_path = format!("{}/models/muir-slim.safetensors", env!("CARGO_MANIFEST_DIR"));
    let bytes = std::fs::read(&model_path).unwrap_or_else(|e| panic!("{model_path}: {e}"));
    let model = FloatModel::new(FloatWeights::from_safetensors(&bytes, None).expect("shipped model loads"));
    assert_eq!(Some(*model.config()), file.config, "fixture made with another model config");
    let get = |name: &str| match &file.tensors[name].data {
        ParamData::F32(v) => (file.tensors[name].shape.clone(), v.clone()),
        ParamData::I64(_) => panic!("{name}: not f32"),
    };
    let input = |name: &str| {
        let (s, v) = get(name);
        Tensor::from_vec(s[0], s[1], s[2], v)
    };
    let out = model.forward(&input("input.left"), &input("input.right"), &mut muir_tools::float::NoTrace);
    let (_, want) = get("up.disp");
    let worst = out.disparity.data.iter().zip(&want).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
    let range = want.iter().fold(0f32, |m, v| m.max(v.abs()));
    eprintln!("shipped model: max |disparity rust - twin| = {worst:.2e} px (disparities up to {range:.1} px)");
    assert!(worst <= 0.01, "max |delta| {worst} px > 0.01 px");
    if let (Some(u), Some((_, wu))) = (&out.uncertainty, file.tensors.contains_key("up.u").then(|| get("up.u"))) {
        let worst_u = u.data.iter().zip(&wu).map(|(a, b)| (a - b).abs()).fold(0f32, f32::max);
        eprintln!("shipped model: max |u rust - twin| = {worst_u:.2e}");
        assert!(worst_u <= 1e-3, "uncertainty differs by {worst_u}");
    }
}

/// The full-resolution refinement: the Rust integer stage (`kernels::fullres`, what both engines
/// and the firmware run) gives the same integers as the twin's evaluation (`python/muir/fullres.py`)
/// on a real crop, with the twin network's disparity and uncertainty as input (fixture written by
/// `python -m muir.golden --fullres models/muir-slim.safetensors`).
#[test]
fn full_res_refinement_matches_twin_bit_for_bit() {
    use muir::kernels::fullres::{ScratchVec, refine_image};
    let file = parse_safetensors(&fixture("fullres-teddy")).expect("fixture parses");
    let get = |name: &str| match &file.tensors[name].data {
        ParamData::F32(v) => (file.tensors[name].shape.clone(), v.iter().map(|x| *x as i16).collect::<Vec<i16>>()),
        ParamData::I64(_) => panic!("{name}: not f32"),
    };
    let (shape, d0) = get("fullres.d0");
    let (_, u) = get("fullres.u");
    let (_, want) = get("fullres.out");
    let (h, w) = (shape[0], shape[1]);
    // The crop of python/muir/golden.py FULLRES_CROP.
    let (y0, x0) = (150, 180);
    let root = env!("CARGO_MANIFEST_DIR");
    let crop = |v: &str| muir_tools::io::read_png(format!("{root}/assets/teddy/{v}.png")).unwrap().crop(x0, y0, w, h).unwrap();
    let (l, r) = (crop("left"), crop("right"));
    let mut d = d0.clone();
    let mut scratch = ScratchVec::new(w);
    let n = refine_image(&l.view(), &r.view(), &mut d, Some(&u), scratch.view());
    let differ = d.iter().zip(&want).filter(|(a, b)| a != b).count();
    eprintln!("full-resolution refinement: {n} of {} pixels refined, {differ} differ from the twin", w * h);
    assert!(n > w * h / 2, "most pixels of a textured crop are refined");
    assert_eq!(differ, 0, "Rust and twin refinement differ on {differ} pixels");
    assert!(d.iter().zip(&d0).any(|(a, b)| a != b));
}

/// The float engine on 1, 2 and 4 threads (`float::set_threads`): every traced tensor the same
/// bits (each sum is made by one thread, in one order, whatever the thread count).
#[test]
fn same_bits_for_any_thread_count() {
    for config_name in ["muir-fast", "raft-stereo-realtime"] {
        let file = parse_safetensors(&fixture(config_name)).expect("fixture parses");
        let config = file.config.expect("fixture carries its config");
        let seed: u64 = file.metadata["seed"].parse().expect("seed");
        let weights = FloatWeights::from_state_dict(seeded::state_dict(&config, seed), &config).expect("seeded weights load");
        let model = FloatModel::new(weights);
        let input = |name: &str| {
            let p = &file.tensors[name];
            match &p.data {
                ParamData::F32(v) => Tensor::from_vec(p.shape[0], p.shape[1], p.shape[2], v.clone()),
                ParamData::I64(_) => panic!("{name}: not f32"),
            }
        };
        let (left, right) = (input("input.left"), input("input.right"));
        let mut first: Option<BTreeMap<String, Tensor>> = None;
        for threads in [1, 2, 4] {
            muir_tools::float::set_threads(threads);
            let mut trace: BTreeMap<String, Tensor> = BTreeMap::new();
            model.forward(&left, &right, &mut trace);
            match &first {
                None => first = Some(trace),
                Some(f) => {
                    assert_eq!(f.len(), trace.len());
                    for (name, t) in f {
                        let same = t.data.iter().zip(&trace[name].data).all(|(a, b)| a.to_bits() == b.to_bits());
                        assert!(same, "{config_name}: {name} differs between 1 and {threads} threads");
                    }
                }
            }
        }
        muir_tools::float::set_threads(1);
    }
}
