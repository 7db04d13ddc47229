//! The `muir` binary, run as a user would: outputs on a real pair, exit codes and messages on
//! wrong input.
//!
//! Models are seeded (`float::seeded`), written to a scratch folder. The run on real data uses a
//! 128x96 crop of Middlebury 2001 tsukuba from `../shared/data` and fails when that folder is
//! absent (skipped, with a note, with `MUIR_SKIP_DATA=1`); the error cases use synthetic images.

mod support;

#[path = "support/crops.rs"]
#[allow(dead_code)]
mod crops;

use std::path::{Path, PathBuf};
use std::process::{Command, Output};

use muir_tools::float::seeded;
use muir_tools::float::weights::to_safetensors;
use muir::input::PixelFormat;
use muir_tools::io::{OwnedImage, read_ground_truth, read_pfm, read_png, write_pfm, write_png};
use muir::model::config::Config;

use crops::DATA;

/// A scratch folder, removed when dropped.
struct Scratch(PathBuf);

impl Scratch {
    fn new(name: &str) -> Self {
        let dir = std::env::temp_dir().join(format!("muir-cli-{}-{name}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        std::fs::create_dir_all(&dir).unwrap();
        Self(dir)
    }

    fn path(&self, name: &str) -> PathBuf {
        self.0.join(name)
    }
}

impl Drop for Scratch {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

fn muir(args: &[&dyn AsRef<std::ffi::OsStr>]) -> Output {
    Command::new(env!("CARGO_BIN_EXE_muir")).args(args.iter().map(|a| a.as_ref())).output().unwrap()
}

fn stderr(o: &Output) -> String {
    String::from_utf8_lossy(&o.stderr).into_owned()
}

/// Asserts a runtime failure: status 1 and an `error:` line holding every one of `needles`.
fn assert_fails(o: &Output, needles: &[&str]) {
    let err = stderr(o);
    assert_eq!(o.status.code(), Some(1), "expected exit status 1, stderr:\n{err}");
    assert!(err.starts_with("error: "), "stderr:\n{err}");
    for n in needles {
        assert!(err.contains(n), "stderr lacks '{n}':\n{err}");
    }
}

/// Writes a seeded model of `config`; without `metadata` the file carries no config at all.
fn write_model(dir: &Scratch, name: &str, config: &Config, metadata: bool) -> PathBuf {
    let mut bytes = to_safetensors(&seeded::state_dict(config, 1), config, &[]).unwrap();
    if !metadata {
        bytes = support::strip_safetensors_metadata(&bytes);
    }
    let path = dir.path(name);
    std::fs::write(&path, bytes).unwrap();
    path
}

/// A textured synthetic gray image.
fn synthetic(width: usize, height: usize) -> OwnedImage {
    let data = (0..width * height).map(|i| ((i % width) * 37 + (i / width) * 11) as u8).collect();
    OwnedImage { width, height, format: PixelFormat::Gray8, data }
}

fn tsukuba() -> Option<(PathBuf, PathBuf)> {
    let dir = Path::new(DATA).join("middlebury2001/tsukuba");
    let (l, r) = (dir.join("left.png"), dir.join("right.png"));
    if l.exists() && r.exists() {
        Some((l, r))
    } else {
        // A failure unless MUIR_SKIP_DATA=1 (then None: skipped with a note).
        crops::data_missing(&dir.display().to_string());
        None
    }
}

#[test]
fn run_on_a_real_pair() {
    let Some((l, r)) = tsukuba() else { return };
    let s = Scratch::new("run");
    let (w, h) = (128, 96);
    let crop = |p: &Path, name: &str| {
        let im = read_png(p).unwrap();
        assert_eq!((im.width, im.height), (384, 288));
        let c = im.crop(128, 96, w, h).unwrap();
        let out = s.path(name);
        write_png(&out, &c).unwrap();
        out
    };
    let (left, right) = (crop(&l, "left.png"), crop(&r, "right.png"));
    // Ground truth of the crop as PFM (unknown = +inf).
    let g = read_ground_truth(l.parent().unwrap()).unwrap();
    let gt: Vec<f32> = (96..96 + h)
        .flat_map(|y| g.data[y * g.width + 128..y * g.width + 128 + w].to_vec())
        .map(|v| if v.is_finite() { v } else { f32::INFINITY })
        .collect();
    let gt_path = s.path("gt.pfm");
    write_pfm(&gt_path, w, h, &gt).unwrap();
    let model = write_model(&s, "slim.safetensors", &Config::MUIR_SLIM, true);
    let (disp, unc, png, unc_png) = (s.path("d.pfm"), s.path("u.pfm"), s.path("d.png"), s.path("u.png"));
    let o = muir(&[
        &"run",
        &"--model",
        &model,
        &"--left",
        &left,
        &"--right",
        &right,
        &"--iters",
        &"3",
        &"--engine",
        &"float",
        &"--disparity",
        &disp,
        &"--uncertainty",
        &unc,
        &"--png",
        &png,
        &"--uncertainty-png",
        &unc_png,
        &"--gt",
        &gt_path,
    ]);
    let err = stderr(&o);
    assert!(o.status.success(), "stderr:\n{err}");
    println!("{err}");
    assert!(err.contains("128x96") && err.contains("disparity min/median/max"), "{err}");

    let d = read_pfm(&disp).unwrap();
    assert_eq!((d.width, d.height, d.data.len()), (w, h, w * h));
    assert!(d.data.iter().all(|v| v.is_finite()), "non-finite disparity");
    // The reported EPE is the one of the written disparity against the ground truth.
    let known: Vec<(f32, f32)> = d.data.iter().zip(&gt).filter(|(_, g)| g.is_finite()).map(|(a, b)| (*a, *b)).collect();
    let epe = known.iter().map(|(a, b)| (a - b).abs() as f64).sum::<f64>() / known.len() as f64;
    let want = format!("vs ground truth ({} known pixels): EPE {epe:.3} px", known.len());
    assert!(err.contains(&want), "expected '{want}' in:\n{err}");
    let u = read_pfm(&unc).unwrap();
    assert_eq!((u.width, u.height), (w, h));
    assert!(u.data.iter().all(|v| v.is_finite() && *v > 0.0), "predicted error must be finite and positive");
    for p in [&png, &unc_png] {
        let im = read_png(p).unwrap();
        assert_eq!((im.width, im.height, im.format), (w, h, PixelFormat::Rgb8));
    }
}

#[test]
fn info_prints_config_and_counts() {
    let s = Scratch::new("info");
    let model = write_model(&s, "slim.safetensors", &Config::MUIR_SLIM, true);
    let o = muir(&[&"info", &"--model", &model]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    let n = seeded::state_dict(&Config::MUIR_SLIM, 1).len();
    assert!(out.contains("\"name\":\"muir-slim\"") && out.contains(&format!("tensors: {n} (")), "{out}");

    // A file without config metadata loads with --config and fails without it.
    let bare = write_model(&s, "bare.safetensors", &Config::MUIR_SLIM, false);
    let o = muir(&[&"info", &"--model", &bare, &"--config", &"muir-slim"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert_fails(&muir(&[&"info", &"--model", &bare]), &["bare.safetensors", "no config metadata", "--config"]);
    // ... and with the wrong preset, the tensors do not match.
    assert_fails(&muir(&[&"info", &"--model", &bare, &"--config", &"muir-fast"]), &["bare.safetensors", "shape"]);
}

/// `muir info` on a quantised blob (recognised by its magic, whatever the file is called): its
/// config and slot formats, as text and as JSON; the committed `models/*.formats.json` (the table
/// the twin's QAT reads, python/muir/qat.py) are exactly what the shipped blobs say.
#[test]
fn info_reads_blobs_and_the_committed_formats_match() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    for name in ["muir-slim", "muir-slim-wide"] {
        let blob = root.join(format!("models/{name}.muirq"));
        let o = muir(&[&"info", &"--model", &blob]);
        assert!(o.status.success(), "{}", stderr(&o));
        let out = String::from_utf8_lossy(&o.stdout);
        assert!(out.contains("quantised, format version") && out.contains("| c1 | ") && out.contains("| fmap | i8 |"), "{out}");
        let o = muir(&[&"info", &"--model", &blob, &"--json"]);
        assert!(o.status.success(), "{}", stderr(&o));
        let got: serde_json::Value = serde_json::from_slice(&o.stdout).expect("info --json prints JSON");
        let committed: serde_json::Value = serde_json::from_str(&std::fs::read_to_string(root.join(format!("models/{name}.formats.json"))).unwrap()).unwrap();
        // (the path differs with the working directory; everything else must be equal)
        let strip = |mut v: serde_json::Value| {
            v.as_object_mut().unwrap().remove("model");
            v
        };
        assert_eq!(strip(got.clone()), strip(committed), "models/{name}.formats.json is stale: regenerate with `muir info --model models/{name}.muirq --json`");
        let c1 = got["slots"].as_array().unwrap().iter().find(|s| s["name"] == "c1").unwrap();
        assert_eq!(c1["bits"], if name.ends_with("wide") { 16 } else { 8 });
    }
    // Another name, same bytes: still a blob. A corrupted one: a typed error naming the file.
    let s = Scratch::new("info-blob");
    let bytes = std::fs::read(root.join("models/muir-slim.muirq")).unwrap();
    let renamed = s.path("model.bin");
    std::fs::write(&renamed, &bytes).unwrap();
    assert!(muir(&[&"info", &"--model", &renamed]).status.success());
    let mut bad = bytes.clone();
    let mid = bad.len() / 2;
    bad[mid] ^= 0x55;
    let corrupt = s.path("corrupt.muirq");
    std::fs::write(&corrupt, &bad).unwrap();
    assert_fails(&muir(&[&"info", &"--model", &corrupt]), &["corrupt.muirq"]);
}

/// `--threads` splits the float engine's matrix products; every output bit stays the same.
#[test]
fn float_engine_threads_give_the_same_bits() {
    let s = Scratch::new("threads");
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let (left, right) = (root.join("assets/teddy/left.png"), root.join("assets/teddy/right.png"));
    let mut outs = Vec::new();
    for t in ["1", "2", "4"] {
        let (d, u) = (s.path(&format!("d{t}.pfm")), s.path(&format!("u{t}.pfm")));
        let o = muir(&[&"run", &"--engine", &"float", &"--left", &left, &"--right", &right, &"--threads", &t, &"--disparity", &d, &"--uncertainty", &u]);
        assert!(o.status.success(), "{}", stderr(&o));
        outs.push((std::fs::read(&d).unwrap(), std::fs::read(&u).unwrap()));
    }
    assert!(outs.iter().all(|o| *o == outs[0]), "outputs differ between thread counts");
    let o = muir(&[&"run", &"--threads", &"0"]);
    assert!(!o.status.success() && stderr(&o).contains("--threads"), "{}", stderr(&o));
}

/// A reader that stops early (`muir plan | head -1`) ends the program quietly, not with a panic.
#[cfg(unix)]
#[test]
fn closed_stdout_pipe_is_not_a_panic() {
    use std::io::Read;
    let mut child = Command::new(env!("CARGO_BIN_EXE_muir"))
        .args(["macs"])
        .stdout(std::process::Stdio::piped())
        .stderr(std::process::Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take()); // the reader goes away before the first line
    let mut err = String::new();
    child.stderr.take().unwrap().read_to_string(&mut err).unwrap();
    let status = child.wait().unwrap();
    assert!(!err.contains("panicked"), "{err}");
    assert!(status.success(), "{status:?}: {err}");
}

#[test]
fn help_for_every_subcommand() {
    for (args, needle) in
        [(&["--help"][..], "run"), (&["run", "--help"], "--disparity"), (&["info", "--help"], "--model")]
    {
        let o = Command::new(env!("CARGO_BIN_EXE_muir")).args(args).output().unwrap();
        assert!(o.status.success());
        assert!(String::from_utf8_lossy(&o.stdout).contains(needle));
    }
}

#[test]
fn wrong_input_fails_with_a_message() {
    let s = Scratch::new("errors");
    let model = write_model(&s, "slim.safetensors", &Config::MUIR_SLIM, true);
    let (left, right, small) = (s.path("l.png"), s.path("r.png"), s.path("small.png"));
    write_png(&left, &synthetic(64, 48)).unwrap();
    write_png(&right, &synthetic(64, 48)).unwrap();
    write_png(&small, &synthetic(48, 48)).unwrap();
    let disp = s.path("d.pfm");
    let run = |model: &Path, left: &Path, right: &Path, extra: &[&str]| {
        let mut args: Vec<&dyn AsRef<std::ffi::OsStr>> =
            vec![&"run", &"--model", &model, &"--left", &left, &"--right", &right, &"--disparity", &disp];
        args.extend(extra.iter().map(|a| a as &dyn AsRef<std::ffi::OsStr>));
        muir(&args)
    };

    // Missing input file.
    assert_fails(&run(&model, &s.path("nope.png"), &right, &[]), &["nope.png"]);
    // Not a PNG.
    let junk = s.path("junk.png");
    std::fs::write(&junk, b"not a png at all").unwrap();
    assert_fails(&run(&model, &left, &junk, &[]), &["junk.png", "PNG"]);
    // Left and right sizes differ.
    assert_fails(&run(&model, &left, &small, &[]), &["64x48", "48x48", "l.png"]);
    // Output folder missing (caught before the network runs).
    let o = run(&model, &left, &right, &["--png", s.path("no/such/dir/d.png").to_str().unwrap()]);
    assert_fails(&o, &["d.png", "does not exist"]);
    // Missing and truncated model files.
    assert_fails(&run(&s.path("none.safetensors"), &left, &right, &[]), &["none.safetensors"]);
    let bytes = std::fs::read(&model).unwrap();
    let truncated = s.path("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    assert_fails(&run(&truncated, &left, &right, &[]), &["truncated.safetensors", "not a valid safetensors"]);
    // No config metadata and no --config.
    let bare = write_model(&s, "bare.safetensors", &Config::MUIR_SLIM, false);
    assert_fails(&run(&bare, &left, &right, &[]), &["bare.safetensors", "--config"]);
    // --config disagrees with the file.
    assert_fails(&run(&model, &left, &right, &["--config", "muir-fast"]), &["muir-slim", "muir-fast", "differs"]);
    // --uncertainty from a model without MUD.
    let rt = write_model(&s, "realtime.safetensors", &Config::RAFT_STEREO_REALTIME, true);
    let unc = s.path("u.pfm");
    let o = run(&rt, &left, &right, &["--uncertainty", unc.to_str().unwrap()]);
    assert_fails(&o, &["raft-stereo-realtime", "uncertainty"]);
    assert!(!disp.exists() && !unc.exists(), "no output may be written on failure");

    // Ground truth of another size.
    let gt = s.path("gt.pfm");
    write_pfm(&gt, 48, 48, &[1.0; 48 * 48]).unwrap();
    assert_fails(&run(&model, &left, &right, &["--gt", gt.to_str().unwrap()]), &["gt.pfm", "48x48", "64x48"]);

    // The fixed engine needs a quantised model.
    let o = run(&model, &left, &right, &["--engine", "fixed"]);
    assert_fails(&o, &["slim.safetensors", "not a quantised muir model"]);

    // Usage errors are clap's: status 2.
    for extra in [&["--engine", "gpu"][..], &["--config", "no-such-preset"], &["--iters", "0"], &["--reject-above", "-1"], &["--max-disparity", "4"], &["--max-disparity", "2000"]] {
        let o = run(&model, &left, &right, extra);
        assert_eq!(o.status.code(), Some(2), "{extra:?}: {}", stderr(&o));
    }
    // --left without --right (and the reverse) is a usage error; neither runs the shipped demo pair.
    let o = muir(&[&"run", &"--model", &model, &"--left", &left]);
    assert_eq!(o.status.code(), Some(2));
    let o = muir(&[&"run", &"--model", &model, &"--right", &right]);
    assert_eq!(o.status.code(), Some(2));
    // An output that is an input or a folder is refused before the network runs.
    let o = run(&model, &left, &right, &["--png", left.to_str().unwrap()]);
    assert_fails(&o, &["would overwrite the input"]);
}

#[test]
fn quantize_then_run_fixed_with_rejection() {
    let Some((l, r)) = tsukuba() else { return };
    let s = Scratch::new("fixed");
    let (w, h) = (96, 64);
    let calib = s.path("calib");
    std::fs::create_dir_all(&calib).unwrap();
    let crop = |p: &Path, x: usize, out: PathBuf| {
        write_png(&out, &read_png(p).unwrap().crop(x, 100, w, h).unwrap()).unwrap();
        out
    };
    crop(&l, 20, calib.join("left.png"));
    crop(&r, 20, calib.join("right.png"));
    let left = crop(&l, 200, s.path("left.png"));
    let right = crop(&r, 200, s.path("right.png"));
    let model = write_model(&s, "slim.safetensors", &Config::MUIR_SLIM, true);
    let (q, report) = (s.path("slim.muirq"), s.path("report.md"));
    let o = muir(&[&"quantize", &"--model", &model, &"--calib", &calib, &"--out", &q, &"--report", &report]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(std::fs::read_to_string(&report).unwrap().contains("| corr |"));
    // GPTQ rounding and the least-squared-error range rule give a valid blob as well, with
    // different weights (same layers, same formats table size).
    let q2 = s.path("slim-gptq.muirq");
    let o = muir(&[&"quantize", &"--model", &model, &"--calib", &calib, &"--out", &q2, &"--rounding", &"gptq", &"--method", &"mse"]);
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("GPTQ"), "{}", stderr(&o));
    let (b1, b2) = (std::fs::read(&q).unwrap(), std::fs::read(&q2).unwrap());
    assert_eq!(b1.len(), b2.len());
    assert_ne!(b1, b2);
    let o = muir(&[&"quantize", &"--model", &model, &"--calib", &calib, &"--out", &q2, &"--rounding", &"best"]);
    assert_eq!(o.status.code(), Some(2));
    // The wide trunk: 16-bit trunk slots in the report, and a blob the fixed engine runs.
    let (qw, report_w) = (s.path("slim-wide.muirq"), s.path("report-wide.md"));
    let o = muir(&[&"quantize", &"--model", &model, &"--calib", &calib, &"--out", &qw, &"--report", &report_w, &"--wide-trunk"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let rep = std::fs::read_to_string(&report_w).unwrap();
    assert!(rep.contains("wide trunk") && rep.contains("| l2b1o | 16 |") && rep.contains("| l3b0o | 8 |"), "{rep}");
    let disp_w = s.path("d-wide.pfm");
    let o = muir(&[&"run", &"--engine", &"fixed", &"--model", &qw, &"--left", &left, &"--right", &right, &"--disparity", &disp_w]);
    assert!(o.status.success(), "{}", stderr(&o));
    let (disp, unc, png) = (s.path("d.pfm"), s.path("u.pfm"), s.path("d.png"));
    let o = muir(&[
        &"run", &"--engine", &"fixed", &"--model", &q, &"--left", &left, &"--right", &right, &"--disparity", &disp,
        &"--uncertainty", &unc, &"--png", &png, &"--reject-above", &"1.0",
    ]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert!(err.contains("fixed engine") && err.contains("rejected"), "{err}");
    let d = read_pfm(&disp).unwrap();
    let u = read_pfm(&unc).unwrap();
    assert_eq!((d.width, d.height), (w, h));
    // rejected pixels are +inf exactly where the predicted error exceeds 1 px (the engine
    // compares u in Q4.11, so allow the threshold's rounding)
    for (dv, uv) in d.data.iter().zip(&u.data) {
        if *uv > 1.001 {
            assert!(dv.is_infinite(), "error {uv} px kept");
        } else if *uv < 0.999 {
            assert!(dv.is_finite(), "error {uv} px rejected");
        }
    }
    assert!(read_png(&png).is_ok());
    // quantised model + --config of another preset is refused
    let o = muir(&[&"run", &"--engine", &"fixed", &"--model", &q, &"--config", &"muir-fast", &"--left", &left, &"--right", &right, &"--disparity", &disp]);
    assert_fails(&o, &["muir-fast"]);
}

#[test]
fn plan_prints_ram_per_preset() {
    let o = muir(&[&"plan"]);
    assert!(o.status.success());
    let out = String::from_utf8_lossy(&o.stdout);
    for c in ["muir-slim", "muir-fast", "raft-stereo-realtime"] {
        for size in ["160x120", "320x240", "640x480"] {
            assert!(out.lines().any(|l| l.contains(c) && l.contains(size)), "{c} {size}:\n{out}");
        }
    }
    let o = muir(&[&"plan", &"--config", &"muir-slim", &"--size", &"64x48"]);
    let out = String::from_utf8_lossy(&o.stdout);
    assert!(out.contains("| muir-slim | 64x48 | u8 |"), "{out}");
    // The wide trunk's line buffers are wider, so its plan is larger.
    let ram = |trunk: &str| -> usize {
        let row = format!("| muir-slim | 64x48 | {trunk}");
        let l = out.lines().find(|l| l.starts_with(&row)).unwrap_or_else(|| panic!("{trunk}:\n{out}"));
        l.split('|').nth(4).and_then(|v| v.trim().parse().ok()).unwrap_or_else(|| panic!("{l}"))
    };
    assert!(ram("i16") > ram("u8"), "{out}");
    let o = muir(&[&"plan", &"--size", &"10x10"]);
    assert_eq!(o.status.code(), Some(2));
}

#[test]
fn macs_prints_a_table_per_preset() {
    let o = muir(&[&"macs"]);
    assert!(o.status.success(), "{}", stderr(&o));
    let out = String::from_utf8_lossy(&o.stdout);
    let header = out.lines().find(|l| l.starts_with("| stage |")).unwrap_or_else(|| panic!("no table:\n{out}"));
    for c in ["muir-slim 320x240, 7 it", "muir-fast 320x240, 7 it", "raft-stereo-realtime 320x240, 7 it"] {
        assert!(header.contains(c), "{c}:\n{out}");
    }
    // The totals are the library's, in G with three decimals.
    let m = muir::model::macs::Macs::new(&Config::MUIR_SLIM, 160, 120, 2);
    let o = muir(&[&"macs", &"--config", &"muir-slim", &"--size", &"160x120", &"--iters", &"2"]);
    let out = String::from_utf8_lossy(&o.stdout);
    let want = format!("| **engine total** |  | {:.3} |", m.engine_total() as f64 / 1e9);
    assert!(out.lines().any(|l| l == want), "{want}:\n{out}");
    assert!(out.lines().any(|l| l.starts_with("| gru08 | ")), "{out}");
    assert_eq!(muir(&[&"macs", &"--size", &"10x10"]).status.code(), Some(2));
}

#[test]
fn snap_writes_a_model_on_the_int8_grid() {
    let s = Scratch::new("snap");
    let model = write_model(&s, "seeded.safetensors", &Config::MUIR_SLIM, true);
    let out = s.path("snapped.safetensors");
    let o = muir(&[&"snap", &"--model", &model, &"--out", &out]);
    assert!(o.status.success(), "{}", stderr(&o));
    let first = o;
    // The output is a valid model of the same config, with every weight moved by at most half an
    // int8 step of its group (so by well under its group's largest magnitude / 127).
    let a = muir_tools::float::FloatWeights::from_safetensors(&std::fs::read(&model).unwrap(), None).unwrap();
    let b = muir_tools::float::FloatWeights::from_safetensors(&std::fs::read(&out).unwrap(), None).unwrap();
    assert_eq!(b.config, Config::MUIR_SLIM);
    let conv = muir::model::layers::ConvId::Conv1;
    let (wa, wb) = (&a.get(conv).unwrap().weight, &b.get(conv).unwrap().weight);
    assert_ne!(wa, wb);
    let max = wa.iter().fold(0f32, |m, v| m.max(v.abs()));
    assert!(wa.iter().zip(wb).all(|(x, y)| (x - y).abs() <= max / 127.0), "conv1 moved by more than a step");
    // Snapping again moves nothing beyond f32 rounding; a missing input is a runtime error.
    let again = s.path("again.safetensors");
    let o = muir(&[&"snap", &"--model", &out, &"--out", &again]);
    assert!(o.status.success(), "{}", stderr(&o));
    let rms = |o: &Output| -> f64 {
        let e = stderr(o);
        let at = e.find("RMS relative change ").map(|i| i + "RMS relative change ".len()).unwrap();
        e[at..].split(')').next().unwrap().parse().unwrap()
    };
    assert!(rms(&first) > 1e-4, "{}", stderr(&first));
    assert!(rms(&o) < 1e-6, "{}", stderr(&o));
    assert_fails(&muir(&[&"snap", &"--model", &s.path("missing.safetensors"), &"--out", &again]), &["missing.safetensors"]);
}

/// The README's main job: `muir run` with no arguments, from a folder outside the repository,
/// runs the shipped model on the shipped pair, scores it against the pair's ground truth and
/// writes its outputs under ./muir-out.
#[test]
fn main_job_runs_from_any_directory() {
    let s = Scratch::new("demo");
    let o = Command::new(env!("CARGO_BIN_EXE_muir")).arg("run").current_dir(&s.0).output().unwrap();
    assert!(o.status.success(), "{}", stderr(&o));
    assert!(stderr(&o).contains("vs ground truth"), "{}", stderr(&o));
    for f in ["disparity.pfm", "disparity.png", "error.pfm", "error.png"] {
        assert!(s.path("muir-out").join(f).is_file(), "muir-out/{f} missing");
    }
}

/// `--adaptive` is `--early-stop 100 --settled 1 --min-iters 2` (`EarlyStop::RECOMMENDED`): the
/// same iterations and bits on the shipped pair, fewer iterations than the maximum there, and the
/// float engine refuses it.
#[test]
fn adaptive_is_the_recommended_criterion() {
    let s = Scratch::new("adaptive");
    let (a, b) = (s.path("a.pfm"), s.path("b.pfm"));
    let o = muir(&[&"run", &"--adaptive", &"--disparity", &a]);
    let err_a = stderr(&o);
    assert!(o.status.success(), "{err_a}");
    let o = muir(&[&"run", &"--early-stop", &"100", &"--settled", &"1", &"--min-iters", &"2", &"--disparity", &b]);
    let err_b = stderr(&o);
    assert!(o.status.success(), "{err_b}");
    let iters = |e: &str| e.split(" iters").next().and_then(|h| h.rsplit(", ").next()).map(str::to_owned).unwrap_or_default();
    assert_eq!(iters(&err_a), iters(&err_b), "{err_a}\n{err_b}");
    let used: usize = iters(&err_a).split(" of ").next().and_then(|n| n.parse().ok()).unwrap_or(0);
    assert!((2..7).contains(&used), "{err_a}");
    assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    let o = muir(&[&"run", &"--engine", &"float", &"--adaptive", &"--disparity", &a]);
    assert_fails(&o, &["--adaptive", "fixed engine"]);
}

/// `--timings` prints one line per phase of the fixed engine's frame and their sum; the float
/// engine refuses it.
#[test]
fn timings_list_every_phase() {
    let s = Scratch::new("timings");
    let d = s.path("d.pfm");
    let o = muir(&[&"run", &"--timings", &"--disparity", &d]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    for p in muir::engine::Phase::ALL {
        assert!(err.lines().any(|l| l.contains(p.name()) && l.ends_with('%')), "no line for {}:\n{err}", p.name());
    }
    let frame = err.lines().find(|l| l.contains(" frame ")).and_then(|l| l.trim_end_matches(" ms").rsplit(' ').next()?.parse::<f64>().ok());
    assert!(frame.is_some_and(|f| f > 0.0), "{err}");
    let o = muir(&[&"run", &"--engine", &"float", &"--timings", &"--disparity", &d]);
    assert_fails(&o, &["--timings", "fixed engine"]);
}

/// `--repeat N` runs N more frames on the same engine and buffers after the first and prints
/// their times; every frame gives the first one's bits (a frame that left state behind for the
/// next would fail the run), so the outputs are those of a run without it, in both engines and
/// on two threads.
#[test]
fn repeated_frames_give_the_first_frames_bits() {
    let s = Scratch::new("repeat");
    for engine in ["fixed", "float"] {
        let (a, b) = (s.path(&format!("{engine}-a.pfm")), s.path(&format!("{engine}-b.pfm")));
        let (ua, ub) = (s.path(&format!("{engine}-ua.pfm")), s.path(&format!("{engine}-ub.pfm")));
        let o = muir(&[&"run", &"--engine", &engine, &"--threads", &"2", &"--disparity", &a, &"--uncertainty", &ua]);
        assert!(o.status.success(), "{}", stderr(&o));
        assert!(!stderr(&o).contains("repeated"), "{}", stderr(&o));
        let o = muir(&[&"run", &"--engine", &engine, &"--threads", &"2", &"--repeat", &"2", &"--disparity", &b, &"--uncertainty", &ub]);
        let err = stderr(&o);
        assert!(o.status.success(), "{err}");
        assert!(err.contains("2 repeated frame(s), the same bits as the first: min "), "{err}");
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap(), "{engine}: disparity");
        assert_eq!(std::fs::read(&ua).unwrap(), std::fs::read(&ub).unwrap(), "{engine}: uncertainty");
    }
    let o = muir(&[&"run", &"--repeat", &"1", &"--timings", &"--disparity", &s.path("t.pfm")]);
    let err = stderr(&o);
    assert!(o.status.success(), "{err}");
    assert_eq!(err.lines().filter(|l| l.contains(" frame ") && l.ends_with(" ms")).count(), 2, "{err}");
    assert!(err.contains("the last repeated frame's phases"), "{err}");
    let o = muir(&[&"run", &"--repeat", &"x"]);
    assert!(!o.status.success() && stderr(&o).contains("--repeat"), "{}", stderr(&o));
}
