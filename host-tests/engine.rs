//! Fixed-point engine tests: the streaming engine equals the plain fixed-point engine bit for bit,
//! runs without a single heap allocation, and refuses bad blobs, arenas and outputs with typed
//! errors.

use std::alloc::{GlobalAlloc, Layout, System};
use std::cell::Cell;
use std::sync::atomic::{AtomicUsize, Ordering};

use muir::Config;
use muir_tools::calib::{CalibOptions, RangeMethod, Rounding, calibrate};
use muir::engine::{Engine, EngineError, Output, Plan, REJECTED, reject, u_threshold};
use muir_tools::float::{FloatModel, FloatWeights, NoTrace, seeded};
use muir::format::{BlobError, QuantModel};
use muir_tools::writer;
use muir::input::{ImageView, PixelFormat};
use muir::model::graph::Act;
use muir_tools::reference::Reference;

/// Counts the allocations of the thread that set `COUNTING` (tests run in parallel threads).
struct Counting;
static ALLOCS: AtomicUsize = AtomicUsize::new(0);
thread_local! {
    static COUNTING: Cell<bool> = const { Cell::new(false) };
}

fn counting() -> bool {
    COUNTING.try_with(|c| c.get()).unwrap_or(false)
}

unsafe impl GlobalAlloc for Counting {
    unsafe fn alloc(&self, l: Layout) -> *mut u8 {
        if counting() {
            ALLOCS.fetch_add(1, Ordering::SeqCst);
        }
        unsafe { System.alloc(l) }
    }
    unsafe fn dealloc(&self, p: *mut u8, l: Layout) {
        unsafe { System.dealloc(p, l) }
    }
    unsafe fn realloc(&self, p: *mut u8, l: Layout, n: usize) -> *mut u8 {
        if counting() {
            ALLOCS.fetch_add(1, Ordering::SeqCst);
        }
        unsafe { System.realloc(p, l, n) }
    }
}

#[global_allocator]
static GLOBAL: Counting = Counting;

/// A deterministic textured pair: a random-dot image and its copy shifted by a smooth disparity
/// field (so correlation peaks, UFI proposals and the iterations all see structure).
fn pair(w: usize, h: usize, seed: u64, gray: bool) -> (Vec<u8>, Vec<u8>) {
    let mut s = seed;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let c = if gray { 1 } else { 3 };
    let tex: Vec<u8> = (0..(w + 64) * h * c).map(|_| (next() % 256) as u8).collect();
    let mut l = vec![0u8; w * h * c];
    let mut r = vec![0u8; w * h * c];
    for y in 0..h {
        for x in 0..w {
            let d = 4 + (x * 12 / w) + (y % 7);
            for ch in 0..c {
                l[(y * w + x) * c + ch] = tex[(y * (w + 64) + x + 32) * c + ch];
                r[(y * w + x) * c + ch] = tex[(y * (w + 64) + x + 32 + d) * c + ch];
            }
        }
    }
    (l, r)
}

fn view(d: &[u8], w: usize, h: usize, gray: bool) -> ImageView<'_> {
    ImageView::new(w, h, if gray { PixelFormat::Gray8 } else { PixelFormat::Rgb8 }, d).unwrap()
}

/// Seeded float weights quantised with formats calibrated on one textured pair.
fn blob(cfg: &Config) -> Vec<u8> {
    let model = FloatModel::new(FloatWeights::from_state_dict(seeded::state_dict(cfg, 11), cfg).unwrap());
    let (l, r) = pair(96, 64, 3, false);
    let pairs = [(view(&l, 96, 64, false), view(&r, 96, 64, false))];
    let opts = CalibOptions {
        method: RangeMethod::Percentile(0.9999),
        iters: 3,
        rounding: Rounding::Nearest,
        wide_trunk: cfg.wide_trunk,
    };
    let cal = calibrate(&model, &pairs, opts, &mut |_, _| {}).unwrap();
    assert_eq!(cal.data.config, *cfg);
    writer::write(&cal.data)
}

fn arena(plan: &Plan) -> Vec<u64> {
    vec![0u64; plan.ram_bytes.div_ceil(8)]
}

fn check_bit_exact(cfg: &Config, w: usize, h: usize, iters: usize, gray: bool) {
    let blob = blob(cfg);
    let qm = QuantModel::parse(&blob).unwrap();
    let (l, r) = pair(w, h, 99 + w as u64, gray);
    let (lv, rv) = (view(&l, w, h, gray), view(&r, w, h, gray));
    let mut want = Reference::new(&qm).predict(&lv, &rv, Some(iters), &mut NoTrace).unwrap();
    // The engine ends with the full-resolution refinement; the plain twin of it on the reference.
    muir::kernels::fullres::refine_image_plain(&lv, &rv, &mut want.disparity, want.uncertainty.as_deref());
    let plan = Plan::new(cfg, w, h);
    let mut mem = arena(&plan);
    let mut engine = Engine::new(&qm, bytemuck::cast_slice_mut(&mut mem)).unwrap();
    let mut d = vec![0i16; w * h];
    let mut u = vec![0i16; w * h];
    let unc = if cfg.mud { Some(&mut u[..]) } else { None };
    engine.run_iters(&lv, &rv, iters, &mut Output { disparity: &mut d, uncertainty: unc }).unwrap();
    let bad = d.iter().zip(&want.disparity).filter(|(a, b)| a != b).count();
    assert_eq!(bad, 0, "{} {w}x{h}: {bad} disparities differ", cfg.name);
    if let Some(wu) = &want.uncertainty {
        assert_eq!(&u, wu, "{} {w}x{h}: uncertainty differs", cfg.name);
    }
    // The outputs carry signal (not a constant map).
    let (lo, hi) = (d.iter().min().unwrap(), d.iter().max().unwrap());
    assert!(hi > lo, "{}: constant disparity", cfg.name);
}

#[test]
fn streaming_equals_plain_muir_slim() {
    check_bit_exact(&Config::MUIR_SLIM, 100, 70, 7, false);
    check_bit_exact(&Config::MUIR_SLIM, 64, 48, 2, true);
}

/// The wide trunk (conv1 .. layer2 in i16, `muir quantize --wide-trunk`).
#[test]
fn streaming_equals_plain_wide_trunk() {
    let wide = Config { wide_trunk: true, ..Config::MUIR_SLIM };
    check_bit_exact(&wide, 100, 70, 7, false);
    check_bit_exact(&wide, 64, 48, 2, true);
    check_bit_exact(&Config { wide_trunk: true, ..Config::MUIR_FAST }, 90, 66, 2, false);
    // A wide-trunk blob in an arena planned for the u8 trunk is refused, not overrun.
    let blob = blob(&wide);
    let qm = QuantModel::parse(&blob).unwrap();
    let (w, h) = (64, 48);
    let (narrow, wide_plan) = (Plan::new(&Config::MUIR_SLIM, w, h), Plan::new(&wide, w, h));
    assert!(wide_plan.ram_bytes > narrow.ram_bytes);
    let mut mem = arena(&narrow);
    let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut mem)).unwrap();
    let (l, r) = pair(w, h, 7, true);
    let mut d = vec![0i16; w * h];
    let res = e.run(&view(&l, w, h, true), &view(&r, w, h, true), &mut Output { disparity: &mut d, uncertainty: None });
    assert!(matches!(res, Err(EngineError::ArenaTooSmall { needed, .. }) if needed == wide_plan.ram_bytes), "{res:?}");
}

#[test]
fn streaming_equals_plain_muir_fast() {
    check_bit_exact(&Config::MUIR_FAST, 90, 66, 4, false);
}

#[test]
fn streaming_equals_plain_raft_stereo_realtime() {
    check_bit_exact(&Config::RAFT_STEREO_REALTIME, 80, 48, 4, false);
}

#[test]
fn inference_allocates_nothing() {
    let cfg = Config::MUIR_SLIM;
    let blob = blob(&cfg);
    let (w, h) = (96, 64);
    let (l, r) = pair(w, h, 5, false);
    let plan = Plan::new(&cfg, w, h);
    let mut mem = arena(&plan);
    let mut d = vec![0i16; w * h];
    let mut u = vec![0i16; w * h];
    let (lv, rv) = (view(&l, w, h, false), view(&r, w, h, false));
    let frame = |d: &mut [i16], u: &mut [i16], mem: &mut [u64]| {
        let qm = QuantModel::parse(&blob)?;
        let mut engine = Engine::new(&qm, bytemuck::cast_slice_mut(mem)).map_err(|_| BlobError::BadMagic)?;
        engine.run(&lv, &rv, &mut Output { disparity: d, uncertainty: Some(u) }).map_err(|_| BlobError::BadMagic)?;
        Ok::<(), BlobError>(())
    };
    // A first frame outside the count: on the host, the x86-64 kernels (feature `std`) grow a
    // per-thread scratch on first use and keep it (the no_std core has no allocator at all).
    frame(&mut d, &mut u, &mut mem).unwrap();
    ALLOCS.store(0, Ordering::SeqCst);
    COUNTING.with(|c| c.set(true));
    let res = frame(&mut d, &mut u, &mut mem);
    COUNTING.with(|c| c.set(false));
    res.unwrap();
    assert_eq!(ALLOCS.load(Ordering::SeqCst), 0, "heap allocations during parse + inference (after the first frame)");
    assert!(d.iter().any(|v| *v != d[0]));
}

#[test]
fn malformed_blobs_are_typed_errors() {
    let cfg = Config::MUIR_SLIM;
    let good = blob(&cfg);
    QuantModel::parse(&good).unwrap();
    // truncated anywhere
    for cut in [0, 3, 15, 100, good.len() / 3, good.len() - 1] {
        let e = QuantModel::parse(&good[..cut]).unwrap_err();
        assert!(matches!(e, BlobError::Truncated { .. } | BlobError::BadMagic), "cut {cut}: {e:?}");
    }
    let mut long = good.clone();
    long.push(0);
    assert!(matches!(QuantModel::parse(&long), Err(BlobError::TrailingBytes { .. })));
    let mut bad = good.clone();
    bad[0] = b'X';
    assert_eq!(QuantModel::parse(&bad).unwrap_err(), BlobError::BadMagic);
    let mut bad = good.clone();
    bad[4] = 9;
    assert_eq!(QuantModel::parse(&bad).unwrap_err(), BlobError::UnsupportedVersion { found: 9 });
    // any flipped content byte breaks the checksum
    for at in [20, 500, good.len() / 2, good.len() - 3] {
        let mut bad = good.clone();
        bad[at] ^= 0x40;
        assert!(matches!(QuantModel::parse(&bad), Err(BlobError::Checksum { .. })), "byte {at}");
    }
    // consistent checksum but content inconsistent with the config
    let cal = {
        let model = FloatModel::new(FloatWeights::from_state_dict(seeded::state_dict(&cfg, 11), &cfg).unwrap());
        let (l, r) = pair(64, 48, 3, false);
        let opts = CalibOptions { method: RangeMethod::MinMax, iters: 1, rounding: Rounding::Nearest, wide_trunk: false };
        calibrate(&model, &[(view(&l, 64, 48, false), view(&r, 64, 48, false))], opts, &mut |_, _| {})
            .unwrap()
            .data
    };
    // A wide-trunk config whose trunk slots are stored in 8 bits, and the reverse.
    let mut d = cal.clone();
    d.config.wide_trunk = true;
    assert_eq!(QuantModel::parse(&writer::write(&d)).unwrap_err(), BlobError::Format { act: Act::C1 });
    let mut d = cal.clone();
    d.formats[Act::L2b1o.index()] = muir::arith::QFormat::i16(9);
    assert_eq!(QuantModel::parse(&writer::write(&d)).unwrap_err(), BlobError::Format { act: Act::L2b1o });
    let mut d = cal.clone();
    d.layers.retain(|l| l.id != muir::ConvId::Gru08Q);
    assert_eq!(QuantModel::parse(&writer::write(&d)).unwrap_err(), BlobError::MissingLayer { layer: muir::ConvId::Gru08Q });
    let mut d = cal.clone();
    let l = d.layers.iter_mut().find(|l| l.id == muir::ConvId::Flow1).unwrap();
    l.cout -= 1;
    let k = l.patch_len();
    l.weights.truncate(l.cout * k);
    l.bias.pop();
    l.mult.pop();
    assert!(matches!(QuantModel::parse(&writer::write(&d)), Err(BlobError::LayerShape { layer: muir::ConvId::Flow1, .. })));
    let mut d = cal.clone();
    d.config.hidden_dim = 0;
    assert!(matches!(QuantModel::parse(&writer::write(&d)), Err(BlobError::Config(_))));
    let mut d = cal.clone();
    d.formats[muir::model::graph::Act::Unit.index()].frac = 3;
    assert!(matches!(QuantModel::parse(&writer::write(&d)), Err(BlobError::Format { .. })));
    // a layer of another config
    let mut d = cal.clone();
    let mut extra = d.layers[0].clone();
    extra.id = muir::ConvId::X32n;
    d.layers.push(extra);
    assert!(matches!(QuantModel::parse(&writer::write(&d)), Err(BlobError::UnexpectedLayer { .. })));
}

#[test]
fn engine_argument_errors() {
    let cfg = Config::MUIR_SLIM;
    let blob = blob(&cfg);
    let qm = QuantModel::parse(&blob).unwrap();
    let (w, h) = (64, 48);
    let (l, r) = pair(w, h, 1, true);
    let (lv, rv) = (view(&l, w, h, true), view(&r, w, h, true));
    let plan = Plan::new(&cfg, w, h);
    let mut small = vec![0u64; plan.ram_bytes / 16];
    let mut d = vec![0i16; w * h];
    let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut small)).unwrap();
    assert!(matches!(e.run(&lv, &rv, &mut Output { disparity: &mut d, uncertainty: None }), Err(EngineError::ArenaTooSmall { .. })));
    let mut mem = arena(&plan);
    let bytes: &mut [u8] = bytemuck::cast_slice_mut(&mut mem);
    assert!(matches!(Engine::new(&qm, &mut bytes[1..]), Err(EngineError::ArenaAlignment)));
    let mut e = Engine::new(&qm, bytes).unwrap();
    let mut short = vec![0i16; w * h - 1];
    assert!(matches!(e.run(&lv, &rv, &mut Output { disparity: &mut short, uncertainty: None }), Err(EngineError::OutputSize { .. })));
    let tiny = vec![0u8; 20 * 20];
    let tv = view(&tiny, 20, 20, true);
    assert!(matches!(e.run(&tv, &tv, &mut Output { disparity: &mut d, uncertainty: None }), Err(EngineError::Input(_))));
    // uncertainty needs MUD
    let rt = blob_realtime_small();
    let qrt = QuantModel::parse(&rt).unwrap();
    let plan = Plan::new(&Config::RAFT_STEREO_REALTIME, w, h);
    let mut mem = arena(&plan);
    let mut e = Engine::new(&qrt, bytemuck::cast_slice_mut(&mut mem)).unwrap();
    let mut u = vec![0i16; w * h];
    assert_eq!(e.run(&lv, &rv, &mut Output { disparity: &mut d, uncertainty: Some(&mut u) }), Err(EngineError::NoUncertainty));
}

fn blob_realtime_small() -> Vec<u8> {
    blob(&Config::RAFT_STEREO_REALTIME)
}

#[test]
fn rejection_threshold() {
    // exp(u/2) > tau  <=>  u > 2 ln tau;  tau = 1 px -> u > 0
    assert_eq!(u_threshold(1.0), 0);
    // The deterministic ln (the same code on host and target) matches exact math, every tau.
    for i in 1..400 {
        let tau = i as f32 * 0.05;
        let exact = (2.0f64 * (tau as f64).ln() * 2048.0).round() as i32;
        assert_eq!(u_threshold(tau) as i32, exact, "tau {tau}");
    }
    assert_eq!(u_threshold(f32::NAN), u_threshold(1e-6));
    for u in (-20000i16..20000).step_by(997) {
        let exact = (u as f64 / 4096.0).exp();
        let got = muir::engine::predicted_error_px(u) as f64;
        assert!((got / exact - 1.0).abs() < 5e-3, "u {u}: {got} vs {exact}");
    }
    assert_eq!(u_threshold(1e30), 32767);
    let mut d = vec![10i16, 20, 30];
    let kept = reject(&mut d, &[-5, 0, 7], 0);
    assert_eq!(kept, 2);
    assert_eq!(d, [10, 20, REJECTED]);
}

#[test]
fn plan_ram_is_reported_per_preset() {
    for cfg in Config::PRESETS {
        let a = Plan::new(&cfg, 160, 120).ram_bytes;
        let b = Plan::new(&cfg, 320, 240).ram_bytes;
        assert!(b > 3 * a, "{}: {a} -> {b}", cfg.name);
    }
}

/// Adaptive iterations: a criterion every frame meets stops at `min_iters` with exactly the
/// output of that many iterations; one no frame meets runs them all; the count is reported.
#[test]
fn early_stop_is_the_same_as_fewer_iterations() {
    use muir::engine::EarlyStop;
    let cfg = Config::MUIR_SLIM;
    let (w, h) = (64, 48);
    let blob = blob(&cfg);
    let qm = QuantModel::parse(&blob).unwrap();
    let (l, r) = pair(w, h, 5, false);
    let (lv, rv) = (view(&l, w, h, false), view(&r, w, h, false));
    let plan = Plan::new(&cfg, w, h);
    let mut mem = arena(&plan);
    let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut mem)).unwrap();
    let run = |e: &mut Engine<'_, '_, '_>, iters: usize| {
        let (mut d, mut u) = (vec![0i16; w * h], vec![0i16; w * h]);
        e.run_iters(&lv, &rv, iters, &mut Output { disparity: &mut d, uncertainty: Some(&mut u) }).unwrap();
        (d, u, e.last_iterations())
    };
    let (d3, u3, n3) = run(&mut e, 3);
    assert_eq!(n3, 3);
    e.set_early_stop(Some(EarlyStop { min_iters: 3, settled: u16::MAX, max_moving_per_mille: 0 }));
    let (d, u, n) = run(&mut e, 7);
    assert_eq!((n, &d, &u), (3, &d3, &u3), "everything settled: stop after min_iters");
    e.set_early_stop(Some(EarlyStop { min_iters: 1, settled: 0, max_moving_per_mille: 0 }));
    let (_, _, n) = run(&mut e, 5);
    assert_eq!(n, 5, "nothing settles: every iteration runs");
}

/// Host threads (`Engine::set_threads`): the right image's encoder on a second thread with its
/// own scratch, and the convolution rows split into ranges of pixels (264 px: 33 pixels at 1/8,
/// three blocks of 16), give the same bits as one thread, whatever the arena held before and
/// whichever thread computes an MGA output row.
#[test]
fn threads_give_the_same_bits() {
    // With threads the refinement runs in two streams (`engine::side`) as far as the model has
    // the passes they hold: every valid combination of the paper's modules (MGA needs MUD).
    let s = Config::MUIR_SLIM;
    let configs = [
        s,
        Config { wide_trunk: true, ..s },
        Config { mga: false, ..s },
        Config { ufi: false, ..s },
        Config { mud: false, mga: false, ..s },
    ];
    for cfg in configs {
        let (w, h) = (264, 48);
        let blob = blob(&cfg);
        let qm = QuantModel::parse(&blob).unwrap();
        let (l, r) = pair(w, h, 17, false);
        let (lv, rv) = (view(&l, w, h, false), view(&r, w, h, false));
        let plan = Plan::new(&cfg, w, h);
        let run = |threads: usize, fill: u64| {
            let mut mem = arena(&plan);
            mem.fill(fill);
            let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut mem)).unwrap();
            e.set_threads(threads);
            let (mut d, mut u) = (vec![0i16; w * h], vec![0i16; w * h]);
            e.run_iters(&lv, &rv, 3, &mut Output { disparity: &mut d, uncertainty: cfg.mud.then_some(&mut u[..]) }).unwrap();
            (d, u)
        };
        let one = run(1, 0);
        assert_eq!(run(2, 0), one, "{}: 2 threads", cfg.name);
        // The MGA output rows on both threads, whatever the timing (`engine::side`).
        muir::engine::side::ALTERNATE_GLB_ROWS.store(true, std::sync::atomic::Ordering::Relaxed);
        let alternate = run(2, 0);
        muir::engine::side::ALTERNATE_GLB_ROWS.store(false, std::sync::atomic::Ordering::Relaxed);
        assert_eq!(alternate, one, "{}: 2 threads, MGA rows alternating", cfg.name);
        assert_eq!(run(3, 0xA5A5_A5A5_A5A5_A5A5), one, "{}: 3 threads on a dirty arena", cfg.name);
    }
}
