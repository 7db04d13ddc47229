//! The Cortex-M firmware's expected results, computed on the host.
//!
//! `boards/qemu-mps2` runs the fixed-point engine on QEMU's `mps2-an500` (Cortex-M7) and prints a
//! `MUIR-RESULT` line (CRC-32 of the disparity and uncertainty outputs, kept-pixel count), which its
//! `run-tests.sh` compares with `boards/qemu-mps2/expected*.txt`. This test runs the same model on
//! the same pairs on the host and checks the same files, so host and target agree bit for bit.
//!
//! After changing the model (`models/muir-slim.muirq`), the board's assets or anything that
//! changes the engine's numbers, regenerate the files with
//!
//! ```text
//! MUIR_UPDATE_EXPECTED=1 cargo test --test firmware
//! ```
//!
//! then run `boards/qemu-mps2/run-tests.sh` to confirm the firmware agrees.

use std::path::{Path, PathBuf};

use muir::Config;
use muir::engine::{CHECKED_TAUS, EarlyStop, Engine, Output, Plan, reject, u_threshold};
use muir::format::{QuantModel, crc32};
use muir::input::{ImageView, PixelFormat};

/// Builds the firmware can run: expected-results file, size, trunk and adaptive iterations. The
/// 64x48 ones without adaptive iterations are what CI runs (`run-tests.sh`, `run-tests.sh
/// --wide-trunk`); the others are measurement builds (`--features frame-WxH`, `--features
/// early-stop`: `run-tests.sh --size WxH --early-stop`). The wide-trunk builds embed
/// `models/muir-slim-wide.muirq`; the early-stop builds stop by [`EarlyStop::RECOMMENDED`].
const FRAMES: [(&str, usize, usize, bool, bool); 6] = [
    ("expected.txt", 64, 48, false, false),
    ("expected-160x120.txt", 160, 120, false, false),
    ("expected-wide.txt", 64, 48, true, false),
    ("expected-wide-160x120.txt", 160, 120, true, false),
    ("expected-early.txt", 64, 48, false, true),
    ("expected-early-160x120.txt", 160, 120, false, true),
];

const HEADER: &str = "\
# Results of the firmware in this folder (first line starting with MUIR-RESULT; see README.md).
# Generated on the host by `MUIR_UPDATE_EXPECTED=1 cargo test --test firmware` from
# models/muir-slim.muirq (expected-wide*: models/muir-slim-wide.muirq) and assets/;
# `run-tests.sh` checks the firmware under QEMU against it.
";

fn root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
}

fn board() -> PathBuf {
    root().join("boards/qemu-mps2")
}

fn read(path: &Path) -> Vec<u8> {
    std::fs::read(path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

/// The quantised model the firmware embeds (`muir-slim-wide.muirq` with feature `wide-trunk`).
fn model_bytes_of(name: &str) -> Vec<u8> {
    let path = root().join("models").join(name);
    if !path.is_file() {
        panic!(
            "{} is missing: the firmware test needs the quantised muir-slim model that boards/qemu-mps2 embeds.\n\
             Produce it with `cargo run --release --bin muir -- quantize --model <muir-slim.safetensors> \
             --calib <pair folder> [--calib ...] --out models/muir-slim.muirq` (or `bash scripts/quantize-shipped.sh`), then \
             regenerate the expected results with `MUIR_UPDATE_EXPECTED=1 cargo test --test firmware`.",
            path.display()
        );
    }
    read(&path)
}

/// The u8-trunk model (the busy-pin test runs it).
#[cfg(feature = "hal")]
fn model_bytes() -> Vec<u8> {
    model_bytes_of("muir-slim.muirq")
}

/// The board's raw 8-bit pair of a size.
fn pair(w: usize, h: usize) -> (Vec<u8>, Vec<u8>) {
    let load = |view: &str| {
        let data = read(&board().join(format!("assets/{view}_{w}x{h}.gray")));
        assert_eq!(data.len(), w * h, "assets/{view}_{w}x{h}.gray must hold {w}x{h} 8-bit pixels");
        data
    };
    (load("left"), load("right"))
}

fn le_bytes(v: &[i16]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// What the firmware prints for a size: its `MUIR-RESULT` line.
fn result_line(model: &QuantModel<'_>, w: usize, h: usize, early: bool) -> String {
    let cfg = Config { wide_trunk: model.config().wide_trunk, ..Config::MUIR_SLIM };
    assert_eq!(*model.config(), cfg, "the firmware's memory plan is for muir-slim");
    let (l, r) = pair(w, h);
    let left = ImageView::new(w, h, PixelFormat::Gray8, &l).unwrap();
    let right = ImageView::new(w, h, PixelFormat::Gray8, &r).unwrap();
    let plan = Plan::new(&cfg, w, h);
    let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
    let mut engine = Engine::new(model, bytemuck::cast_slice_mut(&mut arena)).unwrap();
    let (mut d, mut u) = (vec![0i16; w * h], vec![0i16; w * h]);
    engine.set_early_stop(early.then_some(EarlyStop::RECOMMENDED));
    engine.run(&left, &right, &mut Output { disparity: &mut d, uncertainty: Some(&mut u) }).unwrap();
    let iters = engine.last_iterations();
    let (d_crc, u_crc) = (crc32(&le_bytes(&d)), crc32(&le_bytes(&u)));
    let mut kept = d.clone();
    let kept_1px = reject(&mut kept, &u, u_threshold(1.0));
    // Thresholds and kept pixels at several tau (the firmware computes the same on the target).
    let t = CHECKED_TAUS.map(u_threshold);
    let k = t.map(|th| {
        kept.copy_from_slice(&d);
        reject(&mut kept, &u, th)
    });
    let list = |v: &[String]| v.join(",");
    format!(
        "MUIR-RESULT width={w} height={h} ram={} disparity_crc=0x{d_crc:08x} uncertainty_crc=0x{u_crc:08x} kept_1px={kept_1px} u_thresholds={} kept={} iters={iters}",
        plan.ram_bytes,
        list(&t.map(|x| x.to_string())),
        list(&k.map(|x| x.to_string()))
    )
}

fn expected_line(text: &str) -> Option<&str> {
    text.lines().map(str::trim).find(|l| l.starts_with("MUIR-RESULT "))
}

#[test]
fn host_engine_matches_the_firmware_expected_results() {
    let blobs = [false, true].map(|wide| {
        let name = if wide { "muir-slim-wide.muirq" } else { "muir-slim.muirq" };
        (name, model_bytes_of(name))
    });
    let update = std::env::var_os("MUIR_UPDATE_EXPECTED").is_some_and(|v| v == "1");
    let mut mismatches = Vec::new();
    for (file, w, h, wide, early) in FRAMES {
        let (name, bytes) = &blobs[wide as usize];
        let model = QuantModel::parse(bytes).unwrap_or_else(|e| panic!("models/{name}: {e}"));
        assert_eq!(model.config().wide_trunk, wide, "models/{name}: trunk width");
        let got = result_line(&model, w, h, early);
        let path = board().join(file);
        if update {
            std::fs::write(&path, format!("{HEADER}{got}\n")).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            eprintln!("wrote {}: {got}", path.display());
            continue;
        }
        let text = std::fs::read_to_string(&path).unwrap_or_default();
        match expected_line(&text) {
            Some(want) if want == got => {}
            want => mismatches.push(format!("{file}:\n  expected {}\n  host     {got}", want.unwrap_or("(no MUIR-RESULT line, or no file)"))),
        }
    }
    assert!(
        mismatches.is_empty(),
        "the host engine disagrees with boards/qemu-mps2's expected results:\n{}\n\
         If the model, the assets or the engine's numbers changed on purpose, regenerate them with \
         `MUIR_UPDATE_EXPECTED=1 cargo test --test firmware` and run boards/qemu-mps2/run-tests.sh.",
        mismatches.join("\n")
    );
}

/// `run_with_busy_pin` (feature `hal`): the pin is high exactly around the frame, results equal a
/// plain run, and pin errors map to `EngineError::Pin`. Run with
/// `cargo test --test firmware --features hal`; the firmware exercises it on every CI run.
#[cfg(feature = "hal")]
mod busy_pin {
    use std::convert::Infallible;

    use embedded_hal::digital::{ErrorKind, ErrorType, OutputPin};
    use muir::engine::hal::run_with_busy_pin;
    use muir::engine::{Engine, EngineError, Output, Plan};
    use muir::format::QuantModel;
    use muir::input::{ImageView, PixelFormat};

    /// Records levels; fails the `fail_at`-th call (0-based) when set.
    #[derive(Default)]
    struct Probe {
        levels: Vec<bool>,
        fail_at: Option<usize>,
    }

    #[derive(Debug)]
    struct Broken;
    impl embedded_hal::digital::Error for Broken {
        fn kind(&self) -> ErrorKind {
            ErrorKind::Other
        }
    }
    impl ErrorType for Probe {
        type Error = Broken;
    }
    impl Probe {
        fn set(&mut self, high: bool) -> Result<(), Broken> {
            if self.fail_at == Some(self.levels.len()) {
                return Err(Broken);
            }
            self.levels.push(high);
            Ok(())
        }
    }
    impl OutputPin for Probe {
        fn set_high(&mut self) -> Result<(), Broken> {
            self.set(true)
        }
        fn set_low(&mut self) -> Result<(), Broken> {
            self.set(false)
        }
    }

    /// A pin that cannot fail, to check the helper accepts `Infallible` pins.
    struct Ideal;
    impl ErrorType for Ideal {
        type Error = Infallible;
    }
    impl OutputPin for Ideal {
        fn set_high(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
        fn set_low(&mut self) -> Result<(), Infallible> {
            Ok(())
        }
    }

    #[test]
    fn pin_is_high_around_the_frame_and_errors_map_to_pin() {
        let bytes = super::model_bytes();
        let model = QuantModel::parse(&bytes).unwrap();
        let (w, h) = (64, 48);
        let (l, r) = super::pair(w, h);
        let left = ImageView::new(w, h, PixelFormat::Gray8, &l).unwrap();
        let right = ImageView::new(w, h, PixelFormat::Gray8, &r).unwrap();
        let plan = Plan::new(model.config(), w, h);
        let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
        let mut engine = Engine::new(&model, bytemuck::cast_slice_mut(&mut arena)).unwrap();
        let run = |engine: &mut Engine<'_, '_, '_>, pin: &mut dyn FnMut(&mut Engine<'_, '_, '_>, &mut Output<'_>) -> Result<(), EngineError>| {
            let (mut d, mut u) = (vec![-7i16; w * h], vec![-7i16; w * h]);
            let res = pin(engine, &mut Output { disparity: &mut d, uncertainty: Some(&mut u) });
            (res, d, u)
        };

        let (plain, d0, u0) = run(&mut engine, &mut |e, o| e.run(&left, &right, o));
        plain.unwrap();

        let mut probe = Probe::default();
        let (res, d, u) = run(&mut engine, &mut |e, o| run_with_busy_pin(e, &left, &right, o, &mut probe));
        assert_eq!(res, Ok(()));
        assert_eq!(probe.levels, [true, false]);
        assert!(d == d0 && u == u0, "outputs differ from a plain run");

        let (res, ..) = run(&mut engine, &mut |e, o| run_with_busy_pin(e, &left, &right, o, &mut Ideal));
        assert_eq!(res, Ok(()));

        // The pin cannot go high: nothing is computed.
        let mut probe = Probe { fail_at: Some(0), ..Probe::default() };
        let (res, d, _) = run(&mut engine, &mut |e, o| run_with_busy_pin(e, &left, &right, o, &mut probe));
        assert_eq!(res, Err(EngineError::Pin));
        assert!(d.iter().all(|&v| v == -7), "the frame ran although the pin failed");

        // The pin cannot go low after a good frame: the outputs are there, the error is reported.
        let mut probe = Probe { fail_at: Some(1), ..Probe::default() };
        let (res, d, _) = run(&mut engine, &mut |e, o| run_with_busy_pin(e, &left, &right, o, &mut probe));
        assert_eq!(res, Err(EngineError::Pin));
        assert_eq!(d, d0);

        // The engine refuses the pair: the pin still goes low and the engine's error wins.
        let mut probe = Probe::default();
        let mut short = vec![0i16; 5];
        let res = run_with_busy_pin(&mut engine, &left, &right, &mut Output { disparity: &mut short, uncertainty: None }, &mut probe);
        assert!(matches!(res, Err(EngineError::OutputSize { .. })), "{res:?}");
        assert_eq!(probe.levels, [true, false]);
        assert_eq!(EngineError::Pin.to_string(), "the busy pin could not be driven");
    }
}
