//! Seeded mutation harness for the blob parser and a small engine run (issue #22 item 3; no
//! nightly toolchain here for `cargo fuzz`). Each execution mutates a valid `.muirq` blob of a
//! tiny MUIR config, fixes its length and checksum fields most of the time (so the mutation
//! reaches the parser's deeper checks instead of stopping at the CRC), parses it, and runs every
//! blob that parses on a 48x32 pair in a fixed 16 MiB arena. Anything but `Ok` or a typed error
//! is a failure: a panic (caught and counted) or an execution slower than the hang limit.
//!
//! Used by `host-tests/fuzz_blob.rs` (a short run in the default tests) and
//! `examples/fuzz_blob.rs` (the long, documented run).

use std::panic::{AssertUnwindSafe, catch_unwind};
use std::time::{Duration, Instant};

use muir::Config;
use muir_tools::calib::{CalibOptions, RangeMethod, Rounding, calibrate};
use muir::engine::{Engine, Output};
use muir_tools::float::{FloatModel, FloatWeights, seeded};
use muir::format::{HEADER_LEN, QuantModel, crc32};
use muir_tools::writer;
use muir::input::{ImageView, PixelFormat};
use muir::model::config::MaxDisparity;

/// Image size of the engine runs.
pub const W: usize = 48;
/// Image height of the engine runs.
pub const H: usize = 32;
/// Arena of every engine run: a mutated config that needs more gets `ArenaTooSmall`.
pub const ARENA: usize = 16 << 20;
/// An execution slower than this counts as a hang.
pub const HANG: Duration = Duration::from_secs(5);

/// A MUIR config with every width small, so that one execution takes about a millisecond.
pub fn tiny_config() -> Config {
    Config {
        backbone_dims: [8, 8, 16],
        hidden_dim: 8,
        context_dim: 8,
        fmap_dim: 16,
        corr_levels: 2,
        corr_radius: 2,
        motion_corr_dims: [8, 8],
        motion_flow_dims: [8, 8],
        motion_dim: 16,
        flow_head_dim: 8,
        mask_head_dim: 8,
        iters: 2,
        mud_dim: 8,
        ufi_corr_dim: 8,
        ufi_flow_dim: 8,
        ufi_dim: 8,
        ufi_head_dim: 8,
        mga_qk_dim: 8,
        ..Config::MUIR_SLIM
    }
}

/// xorshift64*.
pub struct Rng(pub u64);

impl Rng {
    pub fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545_F491_4F6C_DD1D)
    }
    pub fn below(&mut self, n: usize) -> usize {
        (self.next() % n.max(1) as u64) as usize
    }
}

/// A textured pair with a small disparity ramp (RGB).
pub fn pair(seed: u64) -> (Vec<u8>, Vec<u8>) {
    let mut r = Rng(seed | 1);
    let tex: Vec<u8> = (0..(W + 16) * H * 3).map(|_| r.next() as u8).collect();
    let (mut a, mut b) = (vec![0u8; W * H * 3], vec![0u8; W * H * 3]);
    for y in 0..H {
        for x in 0..W {
            let d = 2 + x / 12;
            for c in 0..3 {
                a[(y * W + x) * 3 + c] = tex[(y * (W + 16) + x + 8) * 3 + c];
                b[(y * W + x) * 3 + c] = tex[(y * (W + 16) + x + 8 + d) * 3 + c];
            }
        }
    }
    (a, b)
}

/// The valid blobs mutations start from: seeded weights of [`tiny_config`] calibrated on one
/// pair, with the 8-bit trunk and with the wide (16-bit) trunk.
pub fn base_blobs() -> [Vec<u8>; 2] {
    [base_blob(false), base_blob(true)]
}

fn base_blob(wide_trunk: bool) -> Vec<u8> {
    let cfg = Config { wide_trunk, ..tiny_config() };
    let model = FloatModel::new(FloatWeights::from_state_dict(seeded::state_dict(&cfg, 7), &cfg).expect("seeded weights"));
    let (l, r) = pair(3);
    let (lv, rv) = (ImageView::new(W, H, PixelFormat::Rgb8, &l).expect("view"), ImageView::new(W, H, PixelFormat::Rgb8, &r).expect("view"));
    let opts = CalibOptions { method: RangeMethod::Percentile(0.9999), iters: 2, rounding: Rounding::Nearest, wide_trunk };
    writer::write(&calibrate(&model, &[(lv, rv)], opts, &mut |_, _| {}).expect("calibration").data)
}

/// Header offsets of the fields the harness keeps consistent (`format`: total length at 8,
/// CRC-32 of everything after the 16-byte header at 12).
const TOTAL_AT: usize = 8;
const CRC_AT: usize = 12;
const HEADER: usize = HEADER_LEN;

/// One mutation of `blob` in place (it may change the length).
pub fn mutate(r: &mut Rng, blob: &mut Vec<u8>) {
    if blob.is_empty() {
        // An earlier mutation of this execution truncated everything.
        blob.push(r.next() as u8);
        return;
    }
    let n = blob.len();
    // Most mutations hit the config and table region (the first few hundred bytes after the
    // header), where the parser's structure lives; the rest anywhere.
    let at = |r: &mut Rng| if r.below(2) == 0 { (HEADER + r.below(512)).min(n - 1) } else { r.below(n) };
    match r.below(9) {
        0 => {
            let i = at(r);
            blob[i] ^= 1 << r.below(8);
        }
        1 => {
            let i = at(r);
            blob[i] = r.next() as u8;
        }
        2 => {
            // An interesting value in a 16- or 32-bit field.
            let vals: [u32; 8] = [0, 1, 2, 0x7F, 0x80, 0xFFFF, 0x7FFF_FFFF, 0xFFFF_FFFF];
            let v = vals[r.below(vals.len())];
            let i = at(r);
            let bytes = v.to_le_bytes();
            let w = if r.below(2) == 0 { 2 } else { 4 };
            for k in 0..w {
                if let Some(b) = blob.get_mut(i + k) {
                    *b = bytes[k];
                }
            }
        }
        3 => {
            // An f32 field set to a special value (NaN, infinities, zero, negative, huge).
            let vals = [f32::NAN, f32::INFINITY, f32::NEG_INFINITY, 0.0, -1.0, 1e30, 1.0e-30];
            let v = vals[r.below(vals.len())].to_le_bytes();
            let i = at(r) & !3;
            for k in 0..4 {
                if let Some(b) = blob.get_mut(i + k) {
                    *b = v[k];
                }
            }
        }
        4 => {
            let cut = r.below(n);
            blob.truncate(cut);
        }
        5 => {
            let i = at(r);
            let len = 1 + r.below(64);
            let ins: Vec<u8> = (0..len).map(|_| r.next() as u8).collect();
            blob.splice(i..i, ins);
        }
        6 => {
            let i = at(r);
            let len = (1 + r.below(64)).min(blob.len() - i);
            blob.drain(i..i + len);
        }
        7 => {
            // A chunk copied over another place.
            let (src, dst) = (r.below(n), at(r));
            let len = (1 + r.below(256)).min(n - src).min(n - dst);
            let chunk = blob[src..src + len].to_vec();
            blob[dst..dst + len].copy_from_slice(&chunk);
        }
        _ => {
            // Several flips at once.
            for _ in 0..1 + r.below(16) {
                let i = at(r);
                blob[i] ^= r.next() as u8;
            }
        }
    }
}

/// Rewrites the length and checksum fields so that they match the (mutated) content.
pub fn fix_header(blob: &mut [u8]) {
    if blob.len() < HEADER {
        return;
    }
    let total = blob.len() as u32;
    blob[TOTAL_AT..TOTAL_AT + 4].copy_from_slice(&total.to_le_bytes());
    let crc = crc32(&blob[HEADER..]);
    blob[CRC_AT..CRC_AT + 4].copy_from_slice(&crc.to_le_bytes());
}

/// What a run found.
#[derive(Debug, Default)]
pub struct Report {
    pub executions: u64,
    pub parsed: u64,
    pub ran_ok: u64,
    pub engine_errors: u64,
    pub panics: u64,
    pub hangs: u64,
    pub slowest: Duration,
    /// Parse errors by kind (the error's `Debug` name).
    pub parse_errors: std::collections::BTreeMap<String, u64>,
    /// The first few failures: (execution, what).
    pub failures: Vec<(u64, String)>,
}

/// Runs `executions` mutations from `seed`, calling `progress` every 10,000.
#[allow(dead_code)] // the test calls it; the example calls run_from
pub fn run(executions: u64, seed: u64, progress: impl FnMut(&Report)) -> Report {
    run_from(0, executions, seed, progress)
}

/// [`run`] from execution `first` on (the earlier mutations are generated, not executed, so a
/// long run's execution `e` can be replayed alone).
pub fn run_from(first: u64, executions: u64, seed: u64, mut progress: impl FnMut(&Report)) -> Report {
    let bases = base_blobs();
    for b in &bases {
        QuantModel::parse(b).expect("the base blobs parse");
    }
    let (l, r) = pair(5);
    let (lv, rv) = (ImageView::new(W, H, PixelFormat::Rgb8, &l).expect("view"), ImageView::new(W, H, PixelFormat::Rgb8, &r).expect("view"));
    let mut arena = vec![0u64; ARENA / 8];
    let (mut d, mut u) = (vec![0i16; W * H], vec![0i16; W * H]);
    let mut rng = Rng(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) | 1);
    let trace = std::env::var_os("MUIR_FUZZ_TRACE").is_some();
    let mut rep = Report::default();
    // Panics under test are caught and counted; the hook stays quiet only while one runs, so a
    // panic of the harness itself still prints.
    let quiet = std::sync::Arc::new(std::sync::atomic::AtomicBool::new(false));
    let hook = std::panic::take_hook();
    {
        let quiet = quiet.clone();
        std::panic::set_hook(Box::new(move |info| {
            if !quiet.load(std::sync::atomic::Ordering::Relaxed) {
                eprintln!("{info}");
            }
        }));
    }
    for e in 0..executions {
        let mut blob = bases[rng.below(2)].clone();
        for _ in 0..1 + rng.below(3) {
            mutate(&mut rng, &mut blob);
        }
        if rng.below(10) != 0 {
            fix_header(&mut blob);
        }
        let small_disparity = rng.below(4) == 0;
        if e < first {
            continue;
        }
        if trace {
            eprintln!("execution {e}: {} bytes", blob.len());
        }
        let t0 = Instant::now();
        quiet.store(true, std::sync::atomic::Ordering::Relaxed);
        let outcome = catch_unwind(AssertUnwindSafe(|| {
            let q = match QuantModel::parse(&blob) {
                Ok(q) => q,
                Err(e) => return (Some(e), false),
            };
            let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut arena);
            let Ok(mut engine) = Engine::new(&q, bytes) else { return (None, false) };
            if small_disparity {
                engine.set_max_disparity(MaxDisparity::new(16).unwrap_or_default());
            }
            let unc = if q.config().mud { Some(&mut u[..]) } else { None };
            let ok = engine.run(&lv, &rv, &mut Output { disparity: &mut d, uncertainty: unc }).is_ok();
            (None, ok)
        }));
        quiet.store(false, std::sync::atomic::Ordering::Relaxed);
        let dt = t0.elapsed();
        rep.executions += 1;
        rep.slowest = rep.slowest.max(dt);
        match outcome {
            Ok((err, ok)) => {
                let parsed = err.is_none();
                if let Some(e) = err {
                    let name = format!("{e:?}");
                    let kind = name.split(['{', '(', ' ']).next().unwrap_or_default().to_string();
                    *rep.parse_errors.entry(kind).or_default() += 1;
                }
                rep.parsed += parsed as u64;
                rep.ran_ok += ok as u64;
                rep.engine_errors += (parsed && !ok) as u64;
            }
            Err(p) => {
                rep.panics += 1;
                let what = p.downcast_ref::<String>().cloned().or_else(|| p.downcast_ref::<&str>().map(|s| s.to_string()));
                if rep.failures.len() < 8 {
                    rep.failures.push((e, format!("panic: {}", what.unwrap_or_default())));
                }
            }
        }
        if dt > HANG {
            rep.hangs += 1;
            if rep.failures.len() < 8 {
                rep.failures.push((e, format!("took {dt:?}")));
            }
        }
        if (e + 1) % 10_000 == 0 {
            progress(&rep);
        }
    }
    std::panic::set_hook(hook);
    rep
}
