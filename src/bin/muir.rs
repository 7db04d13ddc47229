//! `muir`: run the MUIR stereo network on image pairs and inspect model files.
//!
//! Runtime failures (unreadable files, bad model files, mismatched images) print
//! `error: <message>` to stderr and exit with status 1; usage errors are clap's (status 2).

use std::io::IsTerminal;
use std::path::{Path, PathBuf};
use std::process::ExitCode;
use std::time::{Duration, Instant};

use clap::{Args, Parser, Subcommand, ValueEnum};
use indicatif::{ProgressBar, ProgressStyle};

use muir_tools::calib::{CalibOptions, RangeMethod, Rounding, calibrate};
use muir::engine::{Disparity, LogVariance, Output, REJECTED, reject, u_threshold};
use muir_tools::float::weights::{ParamData, config_to_json, parse_safetensors};
use muir_tools::float::{FloatModel, FloatWeights};
use muir::format::QuantModel;
use muir::input::{ImageView, check_pair};
use muir_tools::io::{colourise_disparity, colourise_uncertainty, read_disparity_file, read_png, write_pfm, write_png};
use muir::model::config::{Config, MaxDisparity};

/// `println!` that ends the program quietly when stdout is a closed pipe (`muir plan | head`), as
/// command-line tools do, instead of panicking.
macro_rules! out {
    ($($t:tt)*) => {{
        use std::io::Write as _;
        if let Err(e) = writeln!(std::io::stdout(), $($t)*) {
            if e.kind() == std::io::ErrorKind::BrokenPipe {
                std::process::exit(0);
            }
            panic!("failed printing to stdout: {e}");
        }
    }};
}

/// MUIR stereo matching: disparity and predicted error from a rectified image pair.
#[derive(Parser, Debug)]
#[command(name = "muir", version, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand, Debug)]
enum Command {
    /// Computes the left-view disparity (and predicted error) of a rectified stereo pair.
    Run(RunArgs),
    /// Prints a model file's config and tensor counts, and checks its tensors against the config.
    Info(InfoArgs),
    /// Quantises a float model with calibration pairs into a fixed-point model (.muirq).
    Quantize(QuantizeArgs),
    /// Moves a float model's weights onto the int8 grid the quantiser uses (quantisation-aware
    /// export): the float engine then runs the integer engine's weights.
    Snap(SnapArgs),
    /// Prints the static working memory (RAM) of the fixed-point engine per config and size.
    Plan(PlanArgs),
    /// Prints multiply-accumulates per frame by stage (Markdown table), per config and size.
    Macs(MacsArgs),
}

/// The model file and its config.
#[derive(Args, Debug)]
struct ModelArgs {
    /// Model file: safetensors (float engine, as written by the PyTorch twin) or .muirq (fixed
    /// engine). Default: the shipped models/muir-slim.safetensors or models/muir-slim.muirq.
    #[arg(long, value_name = "M.safetensors")]
    model: Option<PathBuf>,
    /// Config preset (raft-stereo-realtime, muir-fast, muir-slim) for files without config
    /// metadata; if the file has one, the two must agree.
    #[arg(long, value_name = "NAME", value_parser = parse_preset)]
    config: Option<Config>,
}

/// A file shipped in the repository, found from any working directory (the crate's folder at
/// build time).
fn shipped(rel: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join(rel)
}

impl ModelArgs {
    /// The model file named on the command line, else the shipped muir-slim model for `engine`.
    fn path(&self, engine: Engine) -> PathBuf {
        self.model.clone().unwrap_or_else(|| {
            shipped(match engine {
                Engine::Float => "models/muir-slim.safetensors",
                Engine::Fixed => "models/muir-slim.muirq",
            })
        })
    }

    /// The engine asked for, else the one the model file is for (`.muirq`: fixed, any other
    /// file: float), else (no model file) the fixed-point engine: the device's integers, and on a
    /// host with AVX-512 VNNI the faster of the two (docs/performance.md).
    fn engine(&self, asked: Option<Engine>) -> Engine {
        asked.unwrap_or(match &self.model {
            Some(p) if p.extension().is_some_and(|e| e == "muirq") => Engine::Fixed,
            Some(_) => Engine::Float,
            None => Engine::Fixed,
        })
    }
}

/// Which implementation computes the network.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Engine {
    /// The f32 host reference (model: .safetensors).
    Float,
    /// The fixed-point engine, as on the device (model: .muirq).
    Fixed,
}

#[derive(Args, Debug)]
struct RunArgs {
    #[command(flatten)]
    model: ModelArgs,
    /// Left (reference) image, PNG (8/16-bit gray, RGB, RGBA or palette). Without --left and
    /// --right: the shipped demo pair (Middlebury 2003 Teddy, scored against its ground truth).
    #[arg(long, value_name = "L.png", requires = "right")]
    left: Option<PathBuf>,
    /// Right image, PNG, same size as the left one.
    #[arg(long, value_name = "R.png", requires = "left")]
    right: Option<PathBuf>,
    /// Update iterations (default: the config's).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(1..=1000))]
    iters: Option<u32>,
    /// Engine computing the network (default: from the model file, fixed for .muirq, float for
    /// .safetensors; fixed without a model file).
    #[arg(long, value_enum)]
    engine: Option<Engine>,
    /// Skips the full-resolution refinement (integer semi-global matching in a band around the
    /// network's disparity, on by default in both engines): the network's upsampled disparity as
    /// it is.
    #[arg(long)]
    no_refine: bool,
    /// Largest disparity (px) of the network's initial proposals (UFI): like a classical matcher's
    /// disparity range, it stops far, spurious correlation peaks from being proposed. 8 to 1016;
    /// the refinement iterations may still move a pixel beyond it. Same in both engines.
    #[arg(long, value_name = "PX", default_value_t = MaxDisparity::DEFAULT, value_parser = parse_max_disparity)]
    max_disparity: MaxDisparity,
    /// Threads (1 to 4; the results are the same bits for any count): the float engine's matrix
    /// products; the fixed-point engine's kernels (convolution rows, attention, correlation
    /// lookup split over a worker pool) and its two image encoders side by side; in both engines
    /// the full-resolution refinement's rows.
    #[arg(long, value_name = "N", default_value_t = 1, value_parser = clap::value_parser!(u8).range(1..=4))]
    threads: u8,
    /// Fixed engine: print the wall time of each phase of the frame (encoders, UFI, MGA, MUD, the
    /// ConvGRUs, the heads, the full-resolution refinement) after the summary.
    #[arg(long)]
    timings: bool,
    /// After the first frame, runs the same pair N more times on the same engine and buffers,
    /// as a camera pipeline runs frame after frame, and prints their times (minimum and median):
    /// the steady-state frame time, without the first frame's one-time costs (memory the OS
    /// maps and zeroes on first touch, the host kernels' weights re-laid). Every frame must give
    /// the first one's bits (checked: an error otherwise); the outputs are the last frame's.
    #[arg(long, value_name = "N", default_value_t = 0, value_parser = clap::value_parser!(u16).range(0..=1000))]
    repeat: u16,
    /// Fixed engine: adaptive iterations with the recommended criterion (stop once at most 100
    /// per mille of the 1/8-grid pixels still move by more than 1 px per iteration, after 2;
    /// chosen on training scenes: docs/experiments/adaptive-iterations); --iters stays the maximum.
    #[arg(long, conflicts_with = "early_stop")]
    adaptive: bool,
    /// Fixed engine: adaptive iterations, stop once at most P per mille of the 1/8-grid pixels
    /// still move by more than --settled px (full resolution) per iteration; --iters stays the
    /// maximum.
    #[arg(long, value_name = "P")]
    early_stop: Option<u16>,
    /// With --early-stop: the largest update (px at full resolution, rounded to 1/32 px) of a
    /// settled pixel.
    #[arg(long, value_name = "PX", default_value_t = 0.25, requires = "early_stop", value_parser = parse_tau)]
    settled: f32,
    /// With --early-stop: iterations always run.
    #[arg(long, value_name = "N", default_value_t = 2, requires = "early_stop")]
    min_iters: usize,
    /// Output: left-view disparity in pixels, full resolution, PFM. Without it the outputs go to
    /// --out-dir: disparity.pfm, disparity.png and, with MUD, error.pfm and error.png.
    #[arg(long, value_name = "OUT.pfm")]
    disparity: Option<PathBuf>,
    /// Folder for the default outputs when --disparity is not given (created if missing).
    #[arg(long, value_name = "DIR", default_value = "muir-out")]
    out_dir: PathBuf,
    /// Output: predicted error exp(u/2) in pixels, PFM (models with MUD only).
    #[arg(long, value_name = "OUT.pfm")]
    uncertainty: Option<PathBuf>,
    /// Output: colourised disparity preview (turbo, far blue to near red), PNG.
    #[arg(long, value_name = "OUT.png")]
    png: Option<PathBuf>,
    /// Output: colourised predicted-error preview (log scale), PNG (models with MUD only).
    #[arg(long, value_name = "OUT.png")]
    uncertainty_png: Option<PathBuf>,
    /// Rejects pixels whose predicted error exp(u/2) exceeds TAU pixels: +inf in the disparity
    /// PFM, black in the PNG (models with MUD only). Without it nothing is rejected.
    #[arg(long, value_name = "TAU", value_parser = parse_tau)]
    reject_above: Option<f32>,
    /// Ground-truth left-view disparity (PFM, or 8/16-bit PNG / PGM with 0 = unknown) to score the
    /// result against: EPE and bad-2.0 over known pixels (and over kept pixels with --reject-above).
    #[arg(long, value_name = "GT.png")]
    gt: Option<PathBuf>,
    /// Divisor of integer ground-truth values (4 for Middlebury 2003 quarter size, 256 for KITTI).
    #[arg(long, value_name = "S", default_value_t = 1.0, requires = "gt", value_parser = parse_tau)]
    gt_scale: f32,
}

#[derive(Args, Debug)]
struct QuantizeArgs {
    /// Float model (safetensors).
    #[arg(long, value_name = "M.safetensors")]
    model: PathBuf,
    /// Config preset for files without config metadata.
    #[arg(long, value_name = "NAME", value_parser = parse_preset)]
    config: Option<Config>,
    /// Calibration pair folders, each holding left.png and right.png (repeatable).
    #[arg(long = "calib", value_name = "DIR", required = true)]
    calib: Vec<PathBuf>,
    /// Crop each calibration pair to at most W x H (top-left corner), e.g. 320x240.
    #[arg(long, value_name = "WxH", value_parser = parse_size)]
    max_size: Option<(usize, usize)>,
    /// Range rule: percentile (of the magnitudes), minmax, or mse (least expected squared error).
    #[arg(long, value_enum, default_value_t = Method::Percentile)]
    method: Method,
    /// Percentile for --method percentile.
    #[arg(long, default_value_t = 99.99)]
    percentile: f64,
    /// Weight rounding: nearest, or gptq (backbone convs: each rounding error compensated on the
    /// weights not rounded yet, from the calibration inputs' second moments).
    #[arg(long, value_enum, default_value_t = RoundingArg::Nearest)]
    rounding: RoundingArg,
    /// Store conv1, layer1 and layer2 activations in i16 instead of u8: closer to the float
    /// model, wider line buffers (`muir plan` lists both RAM figures).
    #[arg(long)]
    wide_trunk: bool,
    /// Output: quantised model.
    #[arg(long, value_name = "OUT.muirq")]
    out: PathBuf,
    /// Output: per-slot and per-layer calibration report (Markdown).
    #[arg(long, value_name = "REPORT.md")]
    report: Option<PathBuf>,
}

#[derive(Args, Debug)]
struct SnapArgs {
    /// Float model (safetensors).
    #[arg(long, value_name = "M.safetensors")]
    model: PathBuf,
    /// Config preset for files without config metadata.
    #[arg(long, value_name = "NAME", value_parser = parse_preset)]
    config: Option<Config>,
    /// Output: the snapped float model (safetensors; other tensors and metadata kept).
    #[arg(long, value_name = "OUT.safetensors")]
    out: PathBuf,
}

/// Weight rounding of calibration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum RoundingArg {
    /// Every weight to the nearest int8 step.
    Nearest,
    /// GPTQ: each weight's rounding error compensated on the weights not yet rounded.
    Gptq,
}

/// Range rule of calibration.
#[derive(Clone, Copy, Debug, PartialEq, Eq, ValueEnum)]
enum Method {
    /// A percentile of the observed magnitudes.
    Percentile,
    /// The largest observed magnitude.
    Minmax,
    /// The format with the least expected squared error (clipping + rounding) over the histogram.
    Mse,
}

#[derive(Args, Debug)]
struct PlanArgs {
    /// Configs (default: all presets).
    #[arg(long = "config", value_name = "NAME", value_parser = parse_preset)]
    configs: Vec<Config>,
    /// Input sizes (default: 160x120 320x240 640x480 1242x375 1280x720 and the largest, 1920x1088).
    #[arg(long = "size", value_name = "WxH", value_parser = parse_size)]
    sizes: Vec<(usize, usize)>,
}

#[derive(Args, Debug)]
struct MacsArgs {
    /// Configs (default: all presets).
    #[arg(long = "config", value_name = "NAME", value_parser = parse_preset)]
    configs: Vec<Config>,
    /// Input sizes (default: 320x240).
    #[arg(long = "size", value_name = "WxH", value_parser = parse_size)]
    sizes: Vec<(usize, usize)>,
    /// Update iterations (default: the config's).
    #[arg(long, value_name = "N", value_parser = clap::value_parser!(u32).range(0..=1000))]
    iters: Option<u32>,
}

#[derive(Args, Debug)]
struct InfoArgs {
    #[command(flatten)]
    model: ModelArgs,
    /// Print one JSON object (config; for a .muirq also every activation slot's storage and
    /// fraction bits, the table `python -m muir.train --qat` reads) instead of text
    #[arg(long)]
    json: bool,
}

fn parse_preset(name: &str) -> Result<Config, String> {
    Config::preset(name).map_err(|e| e.to_string())
}

fn parse_max_disparity(s: &str) -> Result<MaxDisparity, String> {
    match s.parse::<usize>().map(MaxDisparity::new) {
        Ok(Ok(m)) => Ok(m),
        _ => Err(format!("'{s}' is not a disparity of {} to {} px", MaxDisparity::MIN, MaxDisparity::MAX)),
    }
}

fn parse_tau(s: &str) -> Result<f32, String> {
    match s.parse::<f32>() {
        Ok(v) if v.is_finite() && v > 0.0 => Ok(v),
        _ => Err(format!("'{s}' is not a positive number of pixels")),
    }
}

fn parse_size(s: &str) -> Result<(usize, usize), String> {
    let (w, h) = s.split_once(['x', 'X']).ok_or_else(|| format!("'{s}' is not WxH"))?;
    match (w.parse::<usize>(), h.parse::<usize>()) {
        (Ok(w), Ok(h)) if w >= Config::MIN_SIDE && h >= Config::MIN_SIDE && muir::input::check_size(w, h).is_ok() => Ok((w, h)),
        _ => Err(format!(
            "'{s}' is not WxH with sides from {} to {}x{}",
            Config::MIN_SIDE,
            Config::MAX_IMAGE_WIDTH,
            Config::MAX_IMAGE_HEIGHT
        )),
    }
}


fn main() -> ExitCode {
    let cli = Cli::parse();
    let result = match cli.command {
        Command::Run(args) => run(&args),
        Command::Info(args) => info(&args),
        Command::Quantize(args) => quantize(&args),
        Command::Snap(args) => snap(&args),
        Command::Plan(args) => plan(&args),
        Command::Macs(args) => macs(&args),
    };
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(message) => {
            eprintln!("error: {message}");
            ExitCode::FAILURE
        }
    }
}

/// A model file's tensors and the config they are checked against.
struct LoadedModel {
    weights: FloatWeights,
    tensors: usize,
    values: usize,
    bytes: usize,
}

fn load_model(args: &ModelArgs) -> Result<LoadedModel, String> {
    let path = &args.path(Engine::Float);
    let at = |e: &dyn std::fmt::Display| format!("{}: {e}", path.display());
    let bytes = std::fs::read(path).map_err(|e| at(&e))?;
    let file = parse_safetensors(&bytes).map_err(|e| at(&e))?;
    let config = model_config(path, file.config, args.config)?;
    let tensors = file.tensors.len();
    let values = file
        .tensors
        .values()
        .map(|p| match &p.data {
            ParamData::F32(v) => v.len(),
            ParamData::I64(v) => v.len(),
        })
        .sum();
    let weights = FloatWeights::from_state_dict(file.tensors, &config).map_err(|e| at(&e))?;
    Ok(LoadedModel { weights, tensors, values, bytes: bytes.len() })
}

/// The config of the model file at `path`: the one in its metadata (`found`) or the one named on
/// the command line; both must agree when both are there.
fn model_config(path: &Path, found: Option<Config>, named: Option<Config>) -> Result<Config, String> {
    match (found, named) {
        (Some(found), Some(named)) if found != named => {
            let how = if found.name == named.name { " (same name, different fields)" } else { "" };
            Err(format!("{}: the file's config '{}' differs from --config {}{how}", path.display(), found.name, named.name))
        }
        (Some(c), _) | (None, Some(c)) => Ok(c),
        (None, None) => Err(format!("{}: {}", path.display(), muir_tools::float::WeightError::NoConfig)),
    }
}

/// A prediction in real units, whichever engine made it.
struct Prediction {
    width: usize,
    height: usize,
    /// Disparity in pixels.
    disparity: Vec<f32>,
    /// Predicted error exp(u/2) in pixels, if the model has MUD.
    error_px: Option<Vec<f32>>,
    /// Disparity in pixels before rejection.
    raw_disparity: Vec<f32>,
    /// Pixels rejected by --reject-above.
    rejected: Option<usize>,
    /// Refinement iterations run.
    iters_used: usize,
    /// The fixed engine's phase times.
    phases: Option<muir::engine::PhaseTimes>,
    /// The first frame's time (`--repeat` runs more after it).
    first_frame: Duration,
    /// `--repeat`: the repeated frames' times.
    repeated: Vec<Duration>,
    /// `--repeat`, fixed engine: the last repeated frame's phase times.
    repeated_phases: Option<muir::engine::PhaseTimes>,
}

fn run(args: &RunArgs) -> Result<(), String> {
    muir_tools::float::set_threads(args.threads as usize);
    let engine_kind = args.model.engine(args.engine);
    // Without --left/--right: the shipped demo pair, scored against its ground truth.
    let demo = args.left.is_none();
    let (left_path, right_path) = match (&args.left, &args.right) {
        (Some(l), Some(r)) => (l.clone(), r.clone()),
        _ => (shipped("assets/teddy/left.png"), shipped("assets/teddy/right.png")),
    };
    let (gt_path, gt_scale) = match &args.gt {
        Some(g) => (Some(g.clone()), args.gt_scale),
        None if demo => (Some(shipped("assets/teddy/disp2.png")), 4.0),
        None => (None, args.gt_scale),
    };
    // Without --disparity: every output into --out-dir.
    let default_out = args.disparity.is_none();
    let in_dir = |name: &str| default_out.then(|| args.out_dir.join(name));
    let disparity = args.disparity.clone().unwrap_or_else(|| args.out_dir.join("disparity.pfm"));
    let png = args.png.clone().or_else(|| in_dir("disparity.png"));
    let uncertainty = args.uncertainty.clone().or_else(|| in_dir("error.pfm"));
    let uncertainty_png = args.uncertainty_png.clone().or_else(|| in_dir("error.png"));
    if default_out {
        std::fs::create_dir_all(&args.out_dir).map_err(|e| format!("{}: {e}", args.out_dir.display()))?;
    }
    let inputs: Vec<PathBuf> = [Some(left_path.clone()), Some(right_path.clone()), gt_path.clone(), Some(args.model.path(engine_kind))]
        .into_iter()
        .flatten()
        .collect();
    let outputs = [Some(&disparity), uncertainty.as_ref(), png.as_ref(), uncertainty_png.as_ref()];
    for path in outputs.into_iter().flatten() {
        check_output(path)?;
        if let Some(clash) = inputs.iter().find(|i| same_file(i, path)) {
            return Err(format!("{}: the output would overwrite the input {}", path.display(), clash.display()));
        }
    }
    let max_disparity = args.max_disparity;
    let path = &args.model.path(engine_kind);
    // The fixed-point model is parsed (and its CRC checked) here, once, as the float model is
    // loaded here: the frame's time below is the engine's alone for both.
    let bytes = match engine_kind {
        Engine::Fixed => std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?,
        Engine::Float => Vec::new(),
    };
    let (config, engine) = match engine_kind {
        Engine::Float => {
            let loaded = load_model(&args.model)?;
            let mut model = FloatModel::new(loaded.weights);
            model.set_max_disparity(max_disparity);
            (*model.config(), Loaded::Float(Box::new(model)))
        }
        Engine::Fixed => {
            let model = QuantModel::parse(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
            let config = *model.config();
            if let Some(named) = args.model.config {
                if named != config {
                    return Err(format!("{}: the model's config '{}' differs from --config {}", path.display(), config.name, named.name));
                }
            }
            (config, Loaded::Fixed(model))
        }
    };
    // Only what was asked for explicitly needs MUD; the default outputs skip the error maps.
    let wants_uncertainty = args.uncertainty.is_some() || args.uncertainty_png.is_some() || args.reject_above.is_some();
    let (uncertainty, uncertainty_png) = if config.mud { (uncertainty, uncertainty_png) } else { (None, None) };
    if wants_uncertainty && !config.mud {
        return Err(format!(
            "{}: model '{}' has no MUD head, so it predicts no uncertainty (drop --uncertainty/--uncertainty-png/--reject-above)",
            path.display(),
            config.name
        ));
    }
    let left = read_png(&left_path).map_err(|e| e.to_string())?;
    let right = read_png(&right_path).map_err(|e| e.to_string())?;
    let gt = match &gt_path {
        Some(path) => {
            let gt = read_disparity_file(path, gt_scale).map_err(|e| e.to_string())?;
            if (gt.width, gt.height) != (left.width, left.height) {
                return Err(format!(
                    "{}: ground truth is {}x{}, the images {}x{}",
                    path.display(),
                    gt.width,
                    gt.height,
                    left.width,
                    left.height
                ));
            }
            Some(gt.data)
        }
        None => None,
    };
    let pair_err = |e: &dyn std::fmt::Display| format!("{} / {}: {e}", left_path.display(), right_path.display());
    check_pair(&left.view(), &right.view()).map_err(|e| pair_err(&e))?;

    let iters = args.iters.map_or(config.iters, |n| n as usize);
    let label = match engine_kind {
        Engine::Float => "float",
        Engine::Fixed => "fixed",
    };
    let spinner = spinner(&format!("{} {}x{}, {iters} iterations, {label} engine", config.name, left.width, left.height));
    if (args.early_stop.is_some() || args.adaptive) && engine_kind != Engine::Fixed {
        return Err("--early-stop and --adaptive need the fixed engine (--engine fixed or a .muirq model)".into());
    }
    if args.timings && engine_kind != Engine::Fixed {
        return Err("--timings needs the fixed engine (--engine fixed or a .muirq model)".into());
    }
    let early = if args.adaptive {
        Some(muir::engine::EarlyStop::RECOMMENDED)
    } else {
        args.early_stop.map(|p| muir::engine::EarlyStop {
            min_iters: args.min_iters,
            // full-resolution px -> Q7.8 at 1/8: x 256 / 8 = x 32
            settled: (args.settled * 32.0).round().clamp(0.0, u16::MAX as f32) as u16,
            max_moving_per_mille: p.min(1000),
        })
    };
    let pred = engine.predict(&left.view(), &right.view(), iters, args.reject_above, !args.no_refine, early, max_disparity, args.threads as usize, args.repeat as usize);
    spinner.finish_and_clear();
    let pred = pred.map_err(|e| pair_err(&e))?;
    // The first frame's (`--repeat` frames are timed apart).
    let network = pred.first_frame;
    let (w, h) = (pred.width, pred.height);

    write_pfm(&disparity, w, h, &pred.disparity).map_err(|e| e.to_string())?;
    if let Some(path) = &png {
        write_png(path, &colourise_disparity(&pred.disparity, w, h, None)).map_err(|e| e.to_string())?;
    }
    if let Some(err_px) = &pred.error_px {
        if let Some(path) = &uncertainty {
            write_pfm(path, w, h, err_px).map_err(|e| e.to_string())?;
        }
        if let Some(path) = &uncertainty_png {
            write_png(path, &colourise_uncertainty(err_px, w, h, None)).map_err(|e| e.to_string())?;
        }
    }
    eprintln!("{}", summary(&config, label, w, h, iters, network, &pred));
    if let (true, Some(t)) = (args.timings, &pred.phases) {
        eprint!("{}", phase_table(t));
    }
    if !pred.repeated.is_empty() {
        let mut s: Vec<f64> = pred.repeated.iter().map(Duration::as_secs_f64).collect();
        s.sort_unstable_by(f64::total_cmp);
        // (An even count's median is the mean of its two middle values.)
        let mid = |i: usize| s.get(i).copied().unwrap_or(0.0);
        let (min, median) = (mid(0), (mid((s.len() - 1) / 2) + mid(s.len() / 2)) / 2.0);
        eprintln!("muir: {} repeated frame(s), the same bits as the first: min {min:.3} s, median {median:.3} s", s.len());
        if let (true, Some(t)) = (args.timings, &pred.repeated_phases) {
            eprintln!("muir: the last repeated frame's phases:");
            eprint!("{}", phase_table(t));
        }
    }
    if let Some(gt) = &gt {
        eprintln!("{}", score(gt, &pred));
    }
    Ok(())
}

/// EPE and bad-2.0 against ground truth, over all known pixels and (with rejection) the kept ones.
fn score(gt: &[f32], pred: &Prediction) -> String {
    let (mut n, mut sum, mut bad) = (0usize, 0f64, 0usize);
    let (mut nk, mut sumk, mut badk) = (0usize, 0f64, 0usize);
    // Rejected pixels are +inf in `disparity`; all pixels are scored on `raw_disparity`.
    for (i, g) in gt.iter().enumerate() {
        if !g.is_finite() {
            continue;
        }
        let d = pred.raw_disparity[i];
        let err = (d - g).abs() as f64;
        n += 1;
        sum += err;
        bad += (err > 2.0) as usize;
        if pred.disparity[i].is_finite() {
            nk += 1;
            sumk += err;
            badk += (err > 2.0) as usize;
        }
    }
    if n == 0 {
        return "muir: the ground truth has no known pixel".to_string();
    }
    let mut line = format!("muir: vs ground truth ({n} known pixels): EPE {:.3} px, bad 2.0 {:.2}%", sum / n as f64, 100.0 * bad as f64 / n as f64);
    if pred.rejected.is_some() {
        line += &match nk {
            0 => "; every known pixel rejected".to_string(),
            _ => format!(
                "; kept {:.1}% of them: EPE {:.3} px, bad 2.0 {:.2}%",
                100.0 * nk as f64 / n as f64,
                sumk / nk as f64,
                100.0 * badk as f64 / nk as f64
            ),
        };
    }
    line
}

/// A loaded model of either engine.
enum Loaded<'a> {
    Float(Box<FloatModel>),
    Fixed(QuantModel<'a>),
}

impl Loaded<'_> {
    #[allow(clippy::too_many_arguments)]
    fn predict(
        &self,
        left: &ImageView<'_>,
        right: &ImageView<'_>,
        iters: usize,
        tau: Option<f32>,
        refine: bool,
        early: Option<muir::engine::EarlyStop>,
        max_disparity: MaxDisparity,
        threads: usize,
        repeat: usize,
    ) -> Result<Prediction, String> {
        let start = Instant::now();
        let differs = |k: usize| format!("frame {} of --repeat gave other bits than the first frame (state left over from a frame to the next: a bug, please report it)", k + 2);
        match self {
            Loaded::Float(model) => {
                let frame = || {
                    model.predict(left, right, Some(iters)).map(|mut p| {
                        if refine {
                            p.refine_full_res(left, right);
                        }
                        p
                    })
                };
                let mut p = frame().map_err(|e| e.to_string())?;
                let first_frame = start.elapsed();
                // The same bits (NaN equal to itself, -0 not equal to 0).
                let same = |a: &[f32], b: &[f32]| a.len() == b.len() && a.iter().zip(b).all(|(x, y)| x.to_bits() == y.to_bits());
                let mut repeated = Vec::with_capacity(repeat);
                for k in 0..repeat {
                    let t = Instant::now();
                    let again = frame().map_err(|e| e.to_string())?;
                    repeated.push(t.elapsed());
                    let same_u = match (&p.uncertainty, &again.uncertainty) {
                        (Some(a), Some(b)) => same(a, b),
                        (None, None) => true,
                        _ => false,
                    };
                    if !same(&p.disparity, &again.disparity) || !same_u {
                        return Err(differs(k));
                    }
                    p = again;
                }
                let error_px: Option<Vec<f32>> = p.uncertainty.as_ref().map(|u| u.iter().map(|u| (0.5 * u).exp()).collect());
                let raw_disparity = p.disparity.clone();
                let mut disparity = p.disparity;
                let rejected = match (tau, &error_px) {
                    (Some(t), Some(e)) => Some(reject_float(&mut disparity, e, t)),
                    _ => None,
                };
                Ok(Prediction { width: p.width, height: p.height, disparity, error_px, raw_disparity, rejected, iters_used: iters, phases: None, repeated, first_frame, repeated_phases: None })
            }
            Loaded::Fixed(model) => {
                let (w, h) = (left.width, left.height);
                let plan = muir::engine::Plan::new(model.config(), w, h);
                let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
                let mut engine = muir::engine::Engine::new(model, bytemuck::cast_slice_mut(&mut arena)).map_err(|e| e.to_string())?;
                engine.set_full_res_refinement(refine);
                engine.set_early_stop(early);
                engine.set_max_disparity(max_disparity);
                engine.set_threads(threads);
                let mut d = vec![0i16; w * h];
                let mut u = vec![0i16; w * h];
                let unc = if model.config().mud { Some(&mut u[..]) } else { None };
                engine.run_iters(left, right, iters, &mut Output { disparity: &mut d, uncertainty: unc }).map_err(|e| e.to_string())?;
                let (used, phases, first_frame) = (engine.last_iterations(), engine.last_phase_times(), start.elapsed());
                let mut repeated = Vec::with_capacity(repeat);
                if repeat > 0 {
                    let (d0, u0) = (d.clone(), u.clone());
                    for k in 0..repeat {
                        let t = Instant::now();
                        let unc = if model.config().mud { Some(&mut u[..]) } else { None };
                        engine.run_iters(left, right, iters, &mut Output { disparity: &mut d, uncertainty: unc }).map_err(|e| e.to_string())?;
                        repeated.push(t.elapsed());
                        if d != d0 || u != u0 || engine.last_iterations() != used {
                            return Err(differs(k));
                        }
                    }
                }
                // The engine's integers as numbers, their fraction bits in the types (exact in f32).
                let px = |v: i16| Disparity::from_bits(v).to_num::<f32>();
                let raw_disparity = d.iter().map(|v| px(*v)).collect();
                let rejected = match tau {
                    Some(t) if model.config().mud => Some(d.len() - reject(&mut d, &u, u_threshold(t))),
                    _ => None,
                };
                let disparity = d.iter().map(|v| if *v == REJECTED { f32::INFINITY } else { px(*v) }).collect();
                let error_px = model.config().mud.then(|| u.iter().map(|v| (0.5 * LogVariance::from_bits(*v).to_num::<f32>()).exp()).collect());
                Ok(Prediction { width: w, height: h, disparity, error_px, raw_disparity, rejected, iters_used: used, phases: Some(phases), repeated_phases: (repeat > 0).then(|| engine.last_phase_times()), repeated, first_frame })
            }
        }
    }
}

/// Sets rejected pixels (predicted error above `tau`) to +inf; returns how many.
fn reject_float(disparity: &mut [f32], error_px: &[f32], tau: f32) -> usize {
    let mut n = 0;
    for (d, e) in disparity.iter_mut().zip(error_px) {
        if *e > tau {
            *d = f32::INFINITY;
            n += 1;
        }
    }
    n
}


/// One line: model, size, network time, disparity statistics.
fn summary(config: &Config, engine: &str, w: usize, h: usize, iters: usize, network: Duration, pred: &Prediction) -> String {
    let disparity = &pred.disparity;
    let mut finite: Vec<f32> = disparity.iter().copied().filter(|v| v.is_finite()).collect();
    finite.sort_unstable_by(f32::total_cmp);
    let stats = match (finite.first(), finite.get(finite.len() / 2), finite.last()) {
        (Some(lo), Some(med), Some(hi)) => format!("{lo:.2}/{med:.2}/{hi:.2} px"),
        _ => "n/a".to_string(),
    };
    let bad = match pred.rejected {
        Some(r) => format!("; rejected {r} of {} pixels ({:.1}% kept)", disparity.len(), 100.0 * (1.0 - r as f64 / disparity.len() as f64)),
        None if disparity.len() > finite.len() => format!(" ({} non-finite)", disparity.len() - finite.len()),
        None => String::new(),
    };
    format!(
        "muir: {} {w}x{h}, {} iters, {engine} engine: {:.3} s; disparity min/median/max {stats}{bad}",
        config.name,
        if pred.iters_used == iters { format!("{iters}") } else { format!("{} of {iters}", pred.iters_used) },
        network.as_secs_f64()
    )
}

/// `--timings`: one line per phase of the frame, milliseconds and share.
fn phase_table(t: &muir::engine::PhaseTimes) -> String {
    let total = t.total().as_secs_f64().max(1e-9);
    let mut s = String::new();
    for (p, d) in t.iter() {
        s += &format!("muir:   {:<22} {:>9.1} ms {:>5.1} %\n", p.name(), d.as_secs_f64() * 1e3, 100.0 * d.as_secs_f64() / total);
    }
    s + &format!("muir:   {:<22} {:>9.1} ms\n", "frame", total * 1e3)
}

fn spinner(message: &str) -> ProgressBar {
    if !std::io::stderr().is_terminal() {
        return ProgressBar::hidden();
    }
    let bar = ProgressBar::new_spinner();
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} {elapsed}") {
        bar.set_style(style);
    }
    bar.set_message(message.to_string());
    bar.enable_steady_tick(Duration::from_millis(100));
    bar
}

fn info(args: &InfoArgs) -> Result<(), String> {
    // A quantised blob is recognised by its magic, whatever its name.
    let path = args.model.path(args.model.engine(None));
    let head = std::fs::File::open(&path).and_then(|mut f| {
        let mut m = [0u8; 4];
        std::io::Read::read(&mut f, &mut m).map(|n| (n, m))
    });
    if let Ok((4, m)) = head {
        if m == muir::format::MAGIC {
            return info_blob(&path, args.json);
        }
    }
    let loaded = load_model(&args.model)?;
    let c = &loaded.weights.config;
    if args.json {
        let j = serde_json::json!({
            "model": path.display().to_string(),
            "kind": "safetensors",
            "bytes": loaded.bytes,
            "config": json_value(&config_to_json(c))?,
            "tensors": loaded.tensors,
            "values": loaded.values,
        });
        out!("{j:#}");
        return Ok(());
    }
    out!("model: {} ({} bytes)", path.display(), loaded.bytes);
    out!("config: {}", config_to_json(c));
    out!("tensors: {} ({} values)", loaded.tensors, loaded.values);
    out!("{}", features_line(c));
    Ok(())
}

fn features_line(c: &Config) -> String {
    format!("features: mud {}, ufi {}, mga {}, post-pool lookup {}, {} iterations", c.mud, c.ufi, c.mga, c.post_pool, c.iters)
}

fn json_value(text: &str) -> Result<serde_json::Value, String> {
    serde_json::from_str(text).map_err(|e| format!("internal: config JSON: {e}"))
}

/// `muir info` on a .muirq: its header, config and activation formats.
fn info_blob(path: &Path, json: bool) -> Result<(), String> {
    use muir::model::graph::Act;
    let bytes = std::fs::read(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let q = QuantModel::parse(&bytes).map_err(|e| format!("{}: {e}", path.display()))?;
    let c = q.config();
    let slots: Vec<_> = Act::ALL
        .iter()
        .map(|a| {
            let f = q.format(*a);
            (a.name(), f.bits, f.unsigned, f.frac, a.fixed_format().is_none())
        })
        .collect();
    if json {
        let j = serde_json::json!({
            "model": path.display().to_string(),
            "kind": "muirq",
            "format_version": muir::format::VERSION,
            "bytes": bytes.len(),
            "config": json_value(&config_to_json(c))?,
            "wide_trunk": c.wide_trunk,
            "slots": slots.iter().map(|(name, bits, unsigned, frac, calibrated)| serde_json::json!({
                "name": name, "bits": bits, "unsigned": unsigned, "frac": frac, "calibrated": calibrated,
            })).collect::<Vec<_>>(),
        });
        out!("{j:#}");
        return Ok(());
    }
    out!("model: {} ({} bytes, quantised, format version {})", path.display(), bytes.len(), muir::format::VERSION);
    out!("config: {}", config_to_json(c));
    out!("trunk: {}", if c.wide_trunk { "i16 (wide)" } else { "u8" });
    out!("{}", features_line(c));
    out!("\n| slot | storage | frac | |\n|---|---|---:|---|");
    for (name, bits, unsigned, frac, calibrated) in &slots {
        let storage = match (bits, unsigned) {
            (8, true) => "u8",
            (8, false) => "i8",
            _ => "i16",
        };
        out!("| {name} | {storage} | {frac} | {} |", if *calibrated { "calibrated" } else { "fixed by the spec" });
    }
    Ok(())
}

fn quantize(args: &QuantizeArgs) -> Result<(), String> {
    check_output(&args.out)?;
    if let Some(r) = &args.report {
        check_output(r)?;
    }
    let loaded = load_model(&ModelArgs { model: Some(args.model.clone()), config: args.config })?;
    let model = FloatModel::new(loaded.weights);
    let mut images = Vec::new();
    for dir in &args.calib {
        let l = read_png(dir.join("left.png")).map_err(|e| e.to_string())?;
        let r = read_png(dir.join("right.png")).map_err(|e| e.to_string())?;
        let (l, r) = match args.max_size {
            Some((mw, mh)) => {
                let (w, h) = (l.width.min(mw), l.height.min(mh));
                let crop = |im: &muir_tools::io::OwnedImage| im.crop(0, 0, w, h);
                (crop(&l).unwrap_or(l.clone()), crop(&r).unwrap_or(r.clone()))
            }
            None => (l, r),
        };
        check_pair(&l.view(), &r.view()).map_err(|e| format!("{}: {e}", dir.display()))?;
        images.push((l, r));
    }
    let pairs: Vec<_> = images.iter().map(|(l, r)| (l.view(), r.view())).collect();
    let method = match args.method {
        Method::Minmax => RangeMethod::MinMax,
        Method::Mse => RangeMethod::Mse,
        Method::Percentile if (50.0..=100.0).contains(&args.percentile) => RangeMethod::Percentile(args.percentile / 100.0),
        Method::Percentile => return Err(format!("--percentile {} is not in [50, 100]", args.percentile)),
    };
    let bar = if std::io::stderr().is_terminal() { ProgressBar::new(pairs.len() as u64) } else { ProgressBar::hidden() };
    if let Ok(style) = ProgressStyle::with_template("calibrating {bar:30} {pos}/{len} pairs ({percent}%) {elapsed} elapsed, ETA {eta}") {
        bar.set_style(style);
    }
    let start = Instant::now();
    let iters = model.config().iters;
    let rounding = match args.rounding {
        RoundingArg::Gptq => Rounding::Gptq,
        RoundingArg::Nearest => Rounding::Nearest,
    };
    let cal = calibrate(&model, &pairs, CalibOptions { method, iters, rounding, wide_trunk: args.wide_trunk }, &mut |done, total| {
        bar.set_position(done as u64);
        if !std::io::stderr().is_terminal() {
            // Plain lines for logs: share done, time so far, time left at the rate so far.
            let t = start.elapsed().as_secs_f64();
            let left = if done > 0 { t / done as f64 * total.saturating_sub(done) as f64 } else { f64::NAN };
            eprintln!("calibration pair {done}/{total} ({:.0}%), {t:.0} s elapsed, ETA {left:.0} s", 100.0 * done as f64 / total.max(1) as f64);
        }
    })
    .map_err(|e| e.to_string())?;
    bar.finish_and_clear();
    let blob = muir_tools::writer::write(&cal.data);
    QuantModel::parse(&blob).map_err(|e| format!("internal error: written model does not parse: {e}"))?;
    std::fs::write(&args.out, &blob).map_err(|e| format!("{}: {e}", args.out.display()))?;
    if let Some(r) = &args.report {
        std::fs::write(r, cal.report()).map_err(|e| format!("{}: {e}", r.display()))?;
    }
    eprintln!(
        "muir: quantised {} ({method}, {rounding}) on {} pairs in {:.1} s: {} ({} bytes)",
        model.config().name,
        pairs.len(),
        start.elapsed().as_secs_f64(),
        args.out.display(),
        blob.len()
    );
    Ok(())
}

fn snap(args: &SnapArgs) -> Result<(), String> {
    check_output(&args.out)?;
    let at = |e: &dyn std::fmt::Display| format!("{}: {e}", args.model.display());
    let bytes = std::fs::read(&args.model).map_err(|e| at(&e))?;
    let mut file = parse_safetensors(&bytes).map_err(|e| at(&e))?;
    let config = model_config(&args.model, file.config, args.config)?;
    let weights = FloatWeights::from_state_dict(file.tensors.clone(), &config).map_err(|e| at(&e))?;
    let (snapped, rms) = muir_tools::calib::snap_to_grid(&weights);
    let mut layers = 0;
    for &id in muir::model::layers::ConvId::ALL {
        if let (Some(fc), Some(p)) = (snapped.get(id), file.tensors.get_mut(&format!("{}.weight", id.name()))) {
            p.data = ParamData::F32(fc.weight.clone());
            layers += 1;
        }
    }
    file.metadata.insert("muir_int8_grid".into(), "weights snapped to the int8 grid by `muir snap`".into());
    let extra: Vec<(&str, String)> =
        file.metadata.iter().filter(|(k, _)| k.as_str() != muir_tools::float::weights::CONFIG_KEY).map(|(k, v)| (k.as_str(), v.clone())).collect();
    let out = muir_tools::float::weights::to_safetensors(&file.tensors, &config, &extra).map_err(|e| e.to_string())?;
    std::fs::write(&args.out, out).map_err(|e| format!("{}: {e}", args.out.display()))?;
    eprintln!("muir: snapped {layers} layers of {} to the int8 grid (RMS relative change {rms:.2e}): {}", config.name, args.out.display());
    Ok(())
}

fn plan(args: &PlanArgs) -> Result<(), String> {
    let configs = if args.configs.is_empty() { Config::PRESETS.to_vec() } else { args.configs.clone() };
    let sizes = if args.sizes.is_empty() {
        vec![(160, 120), (320, 240), (640, 480), (1242, 375), (1280, 720), (Config::MAX_IMAGE_WIDTH, Config::MAX_IMAGE_HEIGHT)]
    } else {
        args.sizes.clone()
    };
    out!(
        "| config | input | trunk (conv1..layer2) | working RAM (bytes) | KiB | + stack budget (KiB) | frame zone | encoder rings | refinement rings | outputs (d + u) |"
    );
    out!("|---|---|---|---|---|---|---|---|---|---|");
    for c in &configs {
        for (&(w, h), wide_trunk) in sizes.iter().flat_map(|s| [(s, false), (s, true)]) {
            let p = muir::engine::Plan::new(&Config { wide_trunk, ..*c }, w, h);
            out!(
                "| {} | {w}x{h} | {} | {} | {:.1} | {:.1} | {} | {} | {} | {} |",
                c.name,
                if wide_trunk { "i16 (`--wide-trunk`)" } else { "u8" },
                p.ram_bytes,
                p.ram_bytes as f64 / 1024.0,
                (p.ram_bytes + muir::engine::STACK_BUDGET) as f64 / 1024.0,
                p.frame_bytes(),
                p.encoder_rings,
                p.refine_rings,
                p.output_bytes()
            );
        }
    }
    out!(
        "\nWorking RAM = the static arena (`Plan::ram_bytes`, all of the engine's buffers); reserve {} KiB of stack \
         beside it (`engine::STACK_BUDGET`: the QEMU firmware measures 20.0-22.3 KiB on Cortex-M7 and M55, any image size). \
         The model stays in flash; the caller's images are not included.",
        muir::engine::STACK_BUDGET / 1024
    );
    Ok(())
}

fn macs(args: &MacsArgs) -> Result<(), String> {
    use muir::model::macs::Macs;
    let configs = if args.configs.is_empty() { Config::PRESETS.to_vec() } else { args.configs.clone() };
    let sizes = if args.sizes.is_empty() { vec![(320, 240)] } else { args.sizes.clone() };
    let mut cols = Vec::new();
    for c in &configs {
        for &(w, h) in &sizes {
            let iters = args.iters.map_or(c.iters, |n| n as usize);
            cols.push((format!("{} {w}x{h}, {iters} it", c.name), Macs::new(c, w, h, iters)));
        }
    }
    let g = |v: u64| format!("{:.3}", v as f64 / 1e9);
    let row = |name: &str, what: &str, f: &dyn Fn(&Macs) -> u64| {
        let vals: Vec<String> = cols.iter().map(|(_, m)| g(f(m))).collect();
        out!("| {name} | {what} | {} |", vals.join(" | "));
    };
    out!("Multiply-accumulates per frame (G). Network: every tensor computed once, context convs merged into");
    out!("the GRU gates; engine: what the streaming fixed-point engine computes (network + recompute).");
    out!();
    let heads: Vec<&str> = cols.iter().map(|(h, _)| h.as_str()).collect();
    out!("| stage | covers | {} |", heads.join(" | "));
    out!("|---|---|{}", "---:|".repeat(cols.len()));
    let first = cols[0].1;
    for (i, s) in first.network().iter().enumerate() {
        row(s.name, s.what, &|m: &Macs| m.network()[i].macs);
    }
    row("**network total**", "", &|m: &Macs| m.total());
    for (i, s) in first.recompute().iter().enumerate() {
        row(s.name, s.what, &|m: &Macs| m.recompute()[i].macs);
    }
    row("**engine total**", "", &|m: &Macs| m.engine_total());
    row("gru16 context", "share of gru16 spent on the merged context conv", &|m: &Macs| m.gru16_context);
    row("gru08 context", "share of gru08 spent on the merged context conv", &|m: &Macs| m.gru08_context);
    for (i, s) in first.families().iter().enumerate() {
        row(&format!("family: {}", s.name), s.what, &|m: &Macs| m.families()[i].macs);
    }
    Ok(())
}

/// Fails early (before the network runs) when an output's folder does not exist.
/// True when `a` and `b` name the same existing file.
fn same_file(a: &Path, b: &Path) -> bool {
    match (std::fs::canonicalize(a), std::fs::canonicalize(b)) {
        (Ok(x), Ok(y)) => x == y,
        _ => false,
    }
}

fn check_output(path: &Path) -> Result<(), String> {
    if path.is_dir() {
        return Err(format!("{}: is a folder, not a file name", path.display()));
    }
    match path.parent() {
        Some(dir) if !dir.as_os_str().is_empty() && !dir.is_dir() => {
            Err(format!("{}: the folder {} does not exist", path.display(), dir.display()))
        }
        _ => Ok(()),
    }
}
