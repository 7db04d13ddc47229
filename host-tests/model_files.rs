//! Float model files: the public RAFT-Stereo realtime checkpoint layout loads, and every kind of
//! mismatch is a typed error naming the tensor.
//!
//! `fixtures/raft-stereo-realtime-params.txt` is a copy of `shared/reference/`: every state_dict key
//! of the public `raftstereo-realtime.pth` with its shape and dtype.

mod support;

use muir::Config;
use muir_tools::float::seeded;
use muir_tools::float::weights::{FloatWeights, Param, ParamData, StateDict, WeightError, to_safetensors};

fn checkpoint_layout() -> Vec<(String, Vec<usize>, bool)> {
    let text = include_str!("fixtures/raft-stereo-realtime-params.txt");
    text.lines()
        .filter(|l| !l.starts_with('#') && !l.trim().is_empty())
        .map(|l| {
            let f: Vec<&str> = l.split_whitespace().collect();
            let shape = if f[1] == "scalar" { vec![] } else { f[1].split('x').map(|d| d.parse().unwrap()).collect() };
            (f[0].to_string(), shape, f[2] == "int64")
        })
        .collect()
}

/// A state dict with exactly the checkpoint's names and shapes, random (seeded) values.
fn checkpoint_state_dict(prefix: &str) -> StateDict {
    checkpoint_layout()
        .into_iter()
        .map(|(name, shape, int)| {
            let data = if int {
                ParamData::I64(vec![1234])
            } else {
                ParamData::F32(seeded::tensor(&name, &shape, 42))
            };
            (format!("{prefix}{name}"), Param { shape, data })
        })
        .collect()
}

fn bytes_without_config(sd: &StateDict) -> Vec<u8> {
    // to_safetensors always writes the config; strip it from the header.
    let with = to_safetensors(sd, &Config::RAFT_STEREO_REALTIME, &[]).unwrap();
    support::strip_safetensors_metadata(&with)
}

#[test]
fn realtime_checkpoint_layout_loads() {
    let layout = checkpoint_layout();
    assert_eq!(layout.iter().map(|(_, s, _)| s.iter().product::<usize>()).sum::<usize>(), 9_875_013);
    let rt = Config::RAFT_STEREO_REALTIME;
    // Without config metadata: the config is named by the caller (the CLI's --config).
    let bytes = bytes_without_config(&checkpoint_state_dict(""));
    assert_eq!(FloatWeights::from_safetensors(&bytes, None).unwrap_err(), WeightError::NoConfig);
    let w = FloatWeights::from_safetensors(&bytes, Some(&rt)).expect("checkpoint layout loads");
    assert_eq!(w.config, rt);
    // DataParallel's "module." prefix is accepted.
    let bytes = bytes_without_config(&checkpoint_state_dict("module."));
    FloatWeights::from_safetensors(&bytes, Some(&rt)).expect("module.-prefixed checkpoint loads");
    // The layout the loader expects is exactly the checkpoint's (names and shapes).
    let mut ours: Vec<_> = muir_tools::float::weights::expected_tensors(&rt).into_iter().map(|(n, s, _)| (n, s)).collect();
    let mut theirs: Vec<_> = layout.into_iter().map(|(n, s, _)| (n, s)).collect();
    ours.sort();
    theirs.sort();
    assert_eq!(ours, theirs);
}

fn load(sd: StateDict) -> Result<FloatWeights, WeightError> {
    FloatWeights::from_safetensors(&to_safetensors(&sd, &Config::RAFT_STEREO_REALTIME, &[]).unwrap(), None)
}

#[test]
fn missing_tensor_is_named() {
    let mut sd = checkpoint_state_dict("");
    sd.remove("update_block.gru08.convq.bias");
    assert_eq!(load(sd).unwrap_err(), WeightError::Missing { name: "update_block.gru08.convq.bias".into() });
}

#[test]
fn unexpected_tensor_is_named() {
    let mut sd = checkpoint_state_dict("");
    sd.insert("mud.conv1.weight".into(), Param { shape: vec![1], data: ParamData::F32(vec![0.0]) });
    assert_eq!(load(sd).unwrap_err(), WeightError::Unexpected { name: "mud.conv1.weight".into() });
}

#[test]
fn wrong_shape_is_named() {
    let mut sd = checkpoint_state_dict("");
    sd.insert("cnet.conv1.weight".into(), Param { shape: vec![64, 3, 5, 5], data: ParamData::F32(vec![0.1; 64 * 75]) });
    assert_eq!(
        load(sd).unwrap_err(),
        WeightError::Shape { name: "cnet.conv1.weight".into(), expected: vec![64, 3, 7, 7], found: vec![64, 3, 5, 5] }
    );
}

#[test]
fn nan_and_inf_are_named() {
    for bad in [f32::NAN, f32::INFINITY] {
        let mut sd = checkpoint_state_dict("");
        let p = sd.get_mut("update_block.flow_head.conv2.weight").unwrap();
        if let ParamData::F32(v) = &mut p.data {
            v[17] = bad;
        }
        assert_eq!(
            load(sd).unwrap_err(),
            WeightError::NonFinite { name: "update_block.flow_head.conv2.weight".into(), index: 17 }
        );
    }
}

#[test]
fn negative_variance_and_wrong_dtype_are_named() {
    let mut sd = checkpoint_state_dict("");
    if let ParamData::F32(v) = &mut sd.get_mut("cnet.norm1.running_var").unwrap().data {
        v[3] = -1.0;
    }
    assert_eq!(
        load(sd).unwrap_err(),
        WeightError::NegativeVariance { name: "cnet.norm1.running_var".into(), index: 3 }
    );
    let mut sd = checkpoint_state_dict("");
    sd.insert("cnet.conv1.bias".into(), Param { shape: vec![64], data: ParamData::I64(vec![0; 64]) });
    assert!(matches!(load(sd).unwrap_err(), WeightError::Dtype { name, .. } if name == "cnet.conv1.bias"));
}

#[test]
fn truncated_and_corrupted_files_are_format_errors() {
    let bytes = to_safetensors(&seeded::state_dict(&Config::MUIR_SLIM, 1), &Config::MUIR_SLIM, &[]).unwrap();
    FloatWeights::from_safetensors(&bytes, None).expect("slim round trip");
    for cut in [0, 7, 100, bytes.len() / 2, bytes.len() - 1] {
        assert!(
            matches!(FloatWeights::from_safetensors(&bytes[..cut], None), Err(WeightError::Format(_))),
            "cut at {cut}"
        );
    }
    let mut bad = bytes.clone();
    bad[9] = b'#';
    assert!(matches!(FloatWeights::from_safetensors(&bad, None), Err(WeightError::Format(_))));
}

#[test]
fn config_metadata_is_checked() {
    let sd = seeded::state_dict(&Config::MUIR_SLIM, 1);
    // A slim file read as realtime: the file's own config wins, and it loads.
    let bytes = to_safetensors(&sd, &Config::MUIR_SLIM, &[]).unwrap();
    assert_eq!(FloatWeights::from_safetensors(&bytes, Some(&Config::RAFT_STEREO_REALTIME)).unwrap().config, Config::MUIR_SLIM);
    // Slim weights declared as muir-fast: first mismatch is a shape error naming the tensor.
    let bytes = to_safetensors(&sd, &Config::MUIR_FAST, &[]).unwrap();
    assert!(matches!(FloatWeights::from_safetensors(&bytes, None), Err(WeightError::Shape { .. })));
    // Invalid config JSON.
    assert!(matches!(
        muir_tools::float::weights::config_from_json(r#"{"config_version": 1, "name": "x"}"#),
        Err(WeightError::Config(_))
    ));
    let mut json: serde_json::Value = serde_json::from_str(&muir_tools::float::weights::config_to_json(&Config::MUIR_SLIM)).unwrap();
    json["mga_qk_dim"] = 30.into();
    assert!(matches!(muir_tools::float::weights::config_from_json(&json.to_string()), Err(WeightError::Config(_))));
    json["mga_qk_dim"] = 32.into();
    json["config_version"] = 9.into();
    assert!(matches!(muir_tools::float::weights::config_from_json(&json.to_string()), Err(WeightError::Config(_))));
}

#[test]
fn python_presets_parse() {
    // Written by python/muir/config.py (Config.to_json) for each preset.
    let text = include_str!("fixtures/python-presets.json");
    let all: serde_json::Value = serde_json::from_str(text).unwrap();
    for c in Config::PRESETS {
        let j = all[c.name.as_str()].to_string();
        assert_eq!(muir_tools::float::weights::config_from_json(&j).unwrap(), c, "{}", c.name);
    }
}
