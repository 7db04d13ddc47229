//! Float weights: safetensors files (config JSON in the metadata), checked against the layer table.
//!
//! Loading is strict, like PyTorch's `load_state_dict(strict=True)`: every expected tensor must be
//! there with its exact shape and finite values, and no other tensor may be. Each failure is a
//! [`WeightError`] that names the tensor.

use std::collections::BTreeMap;
use std::fmt;

use safetensors::tensor::{Dtype, SafeTensors, TensorView};

use muir::model::config::{CONFIG_VERSION, Config, ConfigError};
use muir::model::layers::{ConvId, ConvShape, Norm};

/// Safetensors metadata key holding the config JSON.
pub const CONFIG_KEY: &str = "muir_config";

/// BatchNorm epsilon (PyTorch default).
pub const BN_EPS: f32 = 1e-5;

/// Why a float model file was rejected.
#[derive(Clone, Debug, PartialEq)]
pub enum WeightError {
    /// Not a readable safetensors file (truncated, bad header, ...).
    Format(String),
    /// The file has no config metadata and none was named.
    NoConfig,
    /// The config metadata is not valid.
    Config(String),
    /// An expected tensor is absent.
    Missing {
        /// Tensor name.
        name: String,
    },
    /// The file holds a tensor the config does not have.
    Unexpected {
        /// Tensor name.
        name: String,
    },
    /// A tensor has the wrong shape.
    Shape {
        /// Tensor name.
        name: String,
        /// Shape the config implies.
        expected: Vec<usize>,
        /// Shape in the file.
        found: Vec<usize>,
    },
    /// A tensor has an unsupported element type.
    Dtype {
        /// Tensor name.
        name: String,
        /// Element type in the file.
        found: String,
    },
    /// A tensor holds NaN or infinity.
    NonFinite {
        /// Tensor name.
        name: String,
        /// Flat index of the first bad value.
        index: usize,
    },
    /// A BatchNorm variance is negative.
    NegativeVariance {
        /// Tensor name.
        name: String,
        /// Flat index of the first bad value.
        index: usize,
    },
}

impl fmt::Display for WeightError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::Format(m) => write!(f, "not a valid safetensors model file: {m}"),
            Self::NoConfig => write!(f, "the model file carries no config metadata ('{CONFIG_KEY}'): name one with --config"),
            Self::Config(m) => write!(f, "invalid model config: {m}"),
            Self::Missing { name } => write!(f, "tensor '{name}' is missing"),
            Self::Unexpected { name } => write!(f, "unexpected tensor '{name}' (not part of this config)"),
            Self::Shape { name, expected, found } => {
                write!(f, "tensor '{name}' has shape {found:?}, expected {expected:?}")
            }
            Self::Dtype { name, found } => write!(f, "tensor '{name}' has element type {found}, expected F32"),
            Self::NonFinite { name, index } => write!(f, "tensor '{name}' holds NaN or infinity at index {index}"),
            Self::NegativeVariance { name, index } => write!(f, "tensor '{name}' holds a negative variance at index {index}"),
        }
    }
}

impl std::error::Error for WeightError {}

impl From<ConfigError> for WeightError {
    fn from(e: ConfigError) -> Self {
        WeightError::Config(e.to_string())
    }
}

/// Values of one named tensor.
#[derive(Clone, Debug, PartialEq)]
pub enum ParamData {
    /// Float weights.
    F32(Vec<f32>),
    /// Integer buffers (`num_batches_tracked`).
    I64(Vec<i64>),
}

/// One named tensor of a state dict.
#[derive(Clone, Debug, PartialEq)]
pub struct Param {
    /// Shape (empty for a scalar).
    pub shape: Vec<usize>,
    /// Values.
    pub data: ParamData,
}

/// Named tensors, as in a PyTorch state_dict.
pub type StateDict = BTreeMap<String, Param>;

/// A model file's content: tensors and the config found in its metadata, if any.
#[derive(Clone, Debug)]
pub struct ModelFile {
    /// Tensors by name.
    pub tensors: StateDict,
    /// Config from the metadata.
    pub config: Option<Config>,
    /// All metadata entries.
    pub metadata: BTreeMap<String, String>,
}

/// Parses safetensors bytes.
pub fn parse_safetensors(bytes: &[u8]) -> Result<ModelFile, WeightError> {
    let (_, meta) = SafeTensors::read_metadata(bytes).map_err(|e| WeightError::Format(e.to_string()))?;
    let st = SafeTensors::deserialize(bytes).map_err(|e| WeightError::Format(e.to_string()))?;
    let metadata: BTreeMap<String, String> = meta.metadata().clone().unwrap_or_default().into_iter().collect();
    let config = match metadata.get(CONFIG_KEY) {
        Some(json) => Some(config_from_json(json)?),
        None => None,
    };
    let mut tensors = StateDict::new();
    for (name, view) in st.tensors() {
        let shape = view.shape().to_vec();
        let raw = view.data();
        let data = match view.dtype() {
            Dtype::F32 => ParamData::F32(raw.chunks_exact(4).map(|b| f32::from_le_bytes([b[0], b[1], b[2], b[3]])).collect()),
            Dtype::I64 => ParamData::I64(
                raw.chunks_exact(8).map(|b| i64::from_le_bytes([b[0], b[1], b[2], b[3], b[4], b[5], b[6], b[7]])).collect(),
            ),
            other => return Err(WeightError::Dtype { name, found: format!("{other:?}") }),
        };
        tensors.insert(name, Param { shape, data });
    }
    Ok(ModelFile { tensors, config, metadata })
}

/// Serialises tensors and a config into safetensors bytes (the format the twin writes).
pub fn to_safetensors(tensors: &StateDict, config: &Config, extra: &[(&str, String)]) -> Result<Vec<u8>, WeightError> {
    let bytes: Vec<(String, Vec<u8>, Dtype, Vec<usize>)> = tensors
        .iter()
        .map(|(k, p)| match &p.data {
            ParamData::F32(v) => (k.clone(), v.iter().flat_map(|x| x.to_le_bytes()).collect(), Dtype::F32, p.shape.clone()),
            ParamData::I64(v) => (k.clone(), v.iter().flat_map(|x| x.to_le_bytes()).collect(), Dtype::I64, p.shape.clone()),
        })
        .collect();
    let views = bytes
        .iter()
        .map(|(k, b, dt, shape)| {
            TensorView::new(*dt, shape.clone(), b).map(|v| (k.clone(), v)).map_err(|e| WeightError::Format(e.to_string()))
        })
        .collect::<Result<Vec<_>, _>>()?;
    let mut meta: std::collections::HashMap<String, String> = extra.iter().map(|(k, v)| (k.to_string(), v.clone())).collect();
    meta.insert(CONFIG_KEY.into(), config_to_json(config));
    safetensors::serialize(views, Some(meta)).map_err(|e| WeightError::Format(e.to_string()))
}

// ------------------------------------------------------------------------------------------------
// Config JSON (same fields as python/muir/config.py)
// ------------------------------------------------------------------------------------------------
#[derive(serde::Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct ConfigJson {
    config_version: u32,
    name: String,
    backbone_dims: [usize; 3],
    hidden_dim: usize,
    context_dim: usize,
    fmap_dim: usize,
    corr_levels: usize,
    corr_radius: usize,
    motion_corr_dims: [usize; 2],
    motion_flow_dims: [usize; 2],
    motion_dim: usize,
    flow_head_dim: usize,
    mask_head_dim: usize,
    flow_channels: usize,
    iters: usize,
    post_pool: bool,
    mud: bool,
    mud_dim: usize,
    ufi: bool,
    ufi_corr_dim: usize,
    ufi_flow_dim: usize,
    ufi_dim: usize,
    ufi_head_dim: usize,
    ufi_peak_separation: usize,
    mga: bool,
    mga_qk_dim: usize,
    mga_rope_base: f32,
    eps_min: f32,
    eps_max: f32,
    checkpoint_extras: bool,
}

/// Parses and validates a config JSON object.
pub fn config_from_json(json: &str) -> Result<Config, WeightError> {
    let j: ConfigJson = serde_json::from_str(json).map_err(|e| WeightError::Config(e.to_string()))?;
    if j.config_version != CONFIG_VERSION {
        return Err(ConfigError::Version.into());
    }
    let name = muir::model::config::Name::new(&j.name)
        .ok_or_else(|| WeightError::Config(format!("name '{}' is longer than 32 bytes", j.name)))?;
    let c = Config {
        name,
        backbone_dims: j.backbone_dims,
        hidden_dim: j.hidden_dim,
        context_dim: j.context_dim,
        fmap_dim: j.fmap_dim,
        corr_levels: j.corr_levels,
        corr_radius: j.corr_radius,
        motion_corr_dims: j.motion_corr_dims,
        motion_flow_dims: j.motion_flow_dims,
        motion_dim: j.motion_dim,
        flow_head_dim: j.flow_head_dim,
        mask_head_dim: j.mask_head_dim,
        flow_channels: j.flow_channels,
        iters: j.iters,
        post_pool: j.post_pool,
        mud: j.mud,
        mud_dim: j.mud_dim,
        ufi: j.ufi,
        ufi_corr_dim: j.ufi_corr_dim,
        ufi_flow_dim: j.ufi_flow_dim,
        ufi_dim: j.ufi_dim,
        ufi_head_dim: j.ufi_head_dim,
        ufi_peak_separation: j.ufi_peak_separation,
        mga: j.mga,
        mga_qk_dim: j.mga_qk_dim,
        mga_rope_base: j.mga_rope_base,
        eps_min: j.eps_min,
        eps_max: j.eps_max,
        checkpoint_extras: j.checkpoint_extras,
        wide_trunk: false,
    };
    c.validate()?;
    Ok(c)
}

/// The config as JSON (the twin's `Config.to_json` format).
pub fn config_to_json(c: &Config) -> String {
    let j = ConfigJson {
        config_version: CONFIG_VERSION,
        name: c.name.as_str().to_string(),
        backbone_dims: c.backbone_dims,
        hidden_dim: c.hidden_dim,
        context_dim: c.context_dim,
        fmap_dim: c.fmap_dim,
        corr_levels: c.corr_levels,
        corr_radius: c.corr_radius,
        motion_corr_dims: c.motion_corr_dims,
        motion_flow_dims: c.motion_flow_dims,
        motion_dim: c.motion_dim,
        flow_head_dim: c.flow_head_dim,
        mask_head_dim: c.mask_head_dim,
        flow_channels: c.flow_channels,
        iters: c.iters,
        post_pool: c.post_pool,
        mud: c.mud,
        mud_dim: c.mud_dim,
        ufi: c.ufi,
        ufi_corr_dim: c.ufi_corr_dim,
        ufi_flow_dim: c.ufi_flow_dim,
        ufi_dim: c.ufi_dim,
        ufi_head_dim: c.ufi_head_dim,
        ufi_peak_separation: c.ufi_peak_separation,
        mga: c.mga,
        mga_qk_dim: c.mga_qk_dim,
        mga_rope_base: c.mga_rope_base,
        eps_min: c.eps_min,
        eps_max: c.eps_max,
        checkpoint_extras: c.checkpoint_extras,
    };
    serde_json::to_string(&j).unwrap_or_default()
}

// ------------------------------------------------------------------------------------------------
// Typed weights
// ------------------------------------------------------------------------------------------------
/// BatchNorm with stored statistics: `(x - mean) * inv_std * weight + bias`.
#[derive(Clone, Debug, PartialEq)]
pub struct BatchNorm {
    /// Scale (gamma).
    pub weight: Vec<f32>,
    /// Shift (beta).
    pub bias: Vec<f32>,
    /// Running mean.
    pub mean: Vec<f32>,
    /// Running variance.
    pub var: Vec<f32>,
    /// `1 / sqrt(var + eps)`.
    pub inv_std: Vec<f32>,
}

/// One convolution's float weights (`cout x cin x k x k`, row-major) and its BatchNorm.
#[derive(Clone, Debug, PartialEq)]
pub struct FloatConv {
    /// Layer shape.
    pub shape: ConvShape,
    /// Weights, `cout x (cin * k * k)`.
    pub weight: Vec<f32>,
    /// Bias, `cout`.
    pub bias: Vec<f32>,
    /// BatchNorm after the conv.
    pub bn: Option<BatchNorm>,
}

/// All computed layers of a config, by [`ConvId`].
#[derive(Clone, Debug)]
pub struct FloatWeights {
    /// The config the weights were checked against.
    pub config: Config,
    convs: Vec<Option<FloatConv>>,
}

impl FloatWeights {
    /// The layer `id`; `None` if the config does not compute it.
    pub fn get(&self, id: ConvId) -> Option<&FloatConv> {
        self.convs[id.index()].as_ref()
    }

    /// Mutable access to a layer (calibration folds and rescales).
    pub fn get_mut(&mut self, id: ConvId) -> Option<&mut FloatConv> {
        self.convs[id.index()].as_mut()
    }

    /// Reads a safetensors model file. `fallback` names the config if the file has none.
    pub fn from_safetensors(bytes: &[u8], fallback: Option<&Config>) -> Result<Self, WeightError> {
        let file = parse_safetensors(bytes)?;
        let config = file.config.or(fallback.copied()).ok_or(WeightError::NoConfig)?;
        Self::from_state_dict(file.tensors, &config)
    }

    /// Checks a state dict against `config` and keeps the computed layers. A `module.` prefix on
    /// every key (checkpoints saved from `torch.nn.DataParallel`) is stripped.
    pub fn from_state_dict(mut sd: StateDict, config: &Config) -> Result<Self, WeightError> {
        config.validate()?;
        if !sd.is_empty() && sd.keys().all(|k| k.starts_with("module.")) {
            sd = sd.into_iter().map(|(k, v)| (k["module.".len()..].to_string(), v)).collect();
        }
        let mut convs = vec![None; ConvId::COUNT];
        for &id in ConvId::ALL {
            let Some(shape) = id.shape(config) else { continue };
            let name = id.name();
            let weight = take_f32(&mut sd, &format!("{name}.weight"), &[shape.cout, shape.cin, shape.k, shape.k])?;
            let bias = take_f32(&mut sd, &format!("{name}.bias"), &[shape.cout])?;
            let bn = match shape.norm {
                Norm::Batch(prefix) => {
                    let bn = take_bn(&mut sd, prefix, shape.cout)?;
                    if let Some(alias) = id.bn_alias() {
                        take_bn(&mut sd, alias, shape.cout)?;
                    }
                    Some(bn)
                }
                _ => None,
            };
            if !id.checkpoint_only() {
                convs[id.index()] = Some(FloatConv { shape, weight, bias, bn });
            }
        }
        if let Some(name) = sd.keys().next() {
            return Err(WeightError::Unexpected { name: name.clone() });
        }
        Ok(Self { config: *config, convs })
    }
}

fn take_f32(sd: &mut StateDict, name: &str, shape: &[usize]) -> Result<Vec<f32>, WeightError> {
    let p = sd.remove(name).ok_or_else(|| WeightError::Missing { name: name.into() })?;
    if p.shape != shape {
        return Err(WeightError::Shape { name: name.into(), expected: shape.to_vec(), found: p.shape });
    }
    match p.data {
        ParamData::F32(v) => match v.iter().position(|x| !x.is_finite()) {
            Some(index) => Err(WeightError::NonFinite { name: name.into(), index }),
            None => Ok(v),
        },
        ParamData::I64(_) => Err(WeightError::Dtype { name: name.into(), found: "I64".into() }),
    }
}

fn take_bn(sd: &mut StateDict, prefix: &str, c: usize) -> Result<BatchNorm, WeightError> {
    let weight = take_f32(sd, &format!("{prefix}.weight"), &[c])?;
    let bias = take_f32(sd, &format!("{prefix}.bias"), &[c])?;
    let mean = take_f32(sd, &format!("{prefix}.running_mean"), &[c])?;
    let var_name = format!("{prefix}.running_var");
    let var = take_f32(sd, &var_name, &[c])?;
    if let Some(index) = var.iter().position(|v| *v < 0.0) {
        return Err(WeightError::NegativeVariance { name: var_name, index });
    }
    // A counter PyTorch keeps beside the statistics; optional, carries nothing for inference.
    let nbt = format!("{prefix}.num_batches_tracked");
    if let Some(p) = sd.remove(&nbt) {
        if !p.shape.is_empty() && p.shape != [1] {
            return Err(WeightError::Shape { name: nbt, expected: vec![], found: p.shape });
        }
    }
    let inv_std = var.iter().map(|v| 1.0 / (v + BN_EPS).sqrt()).collect();
    Ok(BatchNorm { weight, bias, mean, var, inv_std })
}

/// Shapes of every tensor a model file of `config` holds (what the twin's state_dict holds).
pub fn expected_tensors(config: &Config) -> Vec<(String, Vec<usize>, bool)> {
    let mut out = Vec::new();
    for &id in ConvId::ALL {
        let Some(s) = id.shape(config) else { continue };
        out.push((format!("{}.weight", id.name()), vec![s.cout, s.cin, s.k, s.k], false));
        out.push((format!("{}.bias", id.name()), vec![s.cout], false));
        if let Norm::Batch(prefix) = s.norm {
            for p in core::iter::once(prefix).chain(id.bn_alias()) {
                for field in ["weight", "bias", "running_mean", "running_var"] {
                    out.push((format!("{p}.{field}"), vec![s.cout], false));
                }
                out.push((format!("{p}.num_batches_tracked"), vec![], true));
            }
        }
    }
    out
}
