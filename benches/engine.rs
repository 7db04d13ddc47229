//! Engine benchmarks on the host: whole frames (fixed-point engine against the float reference,
//! one criterion group so the ratio comes from one run), the fixed engine's phases, the
//! kernels against their plain twins, and the full-resolution refinement (one and two threads,
//! its plain twin; `cargo bench --bench engine -- refinement`).
//!
//! `cargo bench --bench engine -- --quick` (a few minutes on 2 cores). Models are seeded
//! (`float::seeded`) and quantised by `calib::calibrate` on a crop of Middlebury 2003 teddy
//! (`../shared/data`); the benchmarked pair is another 320x240 crop of teddy (a synthetic
//! textured pair when the data folder is absent). Throughput is reported in elements = MACs
//! (`model::macs`), so criterion's `Gelem/s` reads as GMAC/s.

use std::hint::black_box;
use std::time::Duration;

use criterion::{BenchmarkId, Criterion, SamplingMode, Throughput, criterion_group, criterion_main};

use muir::Config;
use muir_tools::calib::{CalibOptions, RangeMethod, Rounding, calibrate};
use muir::engine::{Engine, Output, Plan, encode_image, refine, refine_ctx};
use muir_tools::float::{FloatModel, FloatWeights, seeded};
use muir::format::QuantModel;
use muir::input::PixelFormat;
use muir_tools::io::{OwnedImage, read_png};
use muir::kernels::attention::aggregate_query;
use muir::kernels::conv::{PartRows, conv_plain, conv_row};
use muir::kernels::corr::{LookupParams, LookupScratch, lookup_pixel, lookup_pixel_plain, window_len};
use muir::kernels::OutRow;
use muir::model::ConvId;
use muir::model::graph::Act;
use muir::model::macs::{Macs, conv_macs};

const W: usize = 320;
const H: usize = 240;
const TEDDY: &str = concat!(env!("CARGO_MANIFEST_DIR"), "/../shared/data/middlebury2003/teddy");

/// (left, right) 320x240: the centre crop of teddy; and a calibration crop (bottom right).
fn images() -> ((OwnedImage, OwnedImage), (OwnedImage, OwnedImage), &'static str) {
    if let (Ok(l), Ok(r)) = (read_png(format!("{TEDDY}/left.png")), read_png(format!("{TEDDY}/right.png"))) {
        let crop = |x: usize, y: usize| (l.crop(x, y, W, H).unwrap(), r.crop(x, y, W, H).unwrap());
        let (cx, cy) = ((l.width - W) / 2, (l.height - H) / 2);
        return (crop(cx, cy), crop(l.width - W, l.height - H), "teddy (Middlebury 2003), 320x240 crops");
    }
    eprintln!("note: {TEDDY} not found, benchmarking a synthetic textured pair");
    (synthetic(7), synthetic(8), "synthetic textured pair")
}

/// A random-dot image and its copy shifted by a smooth disparity field.
fn synthetic(seed: u64) -> (OwnedImage, OwnedImage) {
    let mut s = seed;
    let mut next = || {
        s ^= s << 13;
        s ^= s >> 7;
        s ^= s << 17;
        s
    };
    let tex: Vec<u8> = (0..(W + 64) * H * 3).map(|_| (next() % 256) as u8).collect();
    let (mut l, mut r) = (vec![0u8; W * H * 3], vec![0u8; W * H * 3]);
    for y in 0..H {
        for x in 0..W {
            let d = 4 + x * 24 / W + y % 7;
            for c in 0..3 {
                l[(y * W + x) * 3 + c] = tex[(y * (W + 64) + x + 32) * 3 + c];
                r[(y * W + x) * 3 + c] = tex[(y * (W + 64) + x + 32 + d) * 3 + c];
            }
        }
    }
    let img = |data| OwnedImage { width: W, height: H, format: PixelFormat::Rgb8, data };
    (img(l), img(r))
}

/// A config's float model and its calibrated blob.
struct Model {
    cfg: Config,
    float: FloatModel,
    blob: Vec<u8>,
}

impl Model {
    /// Benchmark name: the config, `-wide` for a wide-trunk blob.
    fn name(&self) -> String {
        format!("{}{}", self.cfg.name.as_str(), if self.cfg.wide_trunk { "-wide" } else { "" })
    }
}

fn model(cfg: Config, calib: &(OwnedImage, OwnedImage)) -> Model {
    let narrow = Config { wide_trunk: false, ..cfg };
    let float = FloatModel::new(FloatWeights::from_state_dict(seeded::state_dict(&narrow, 11), &narrow).unwrap());
    let pairs = [(calib.0.view(), calib.1.view())];
    let opts = CalibOptions {
        method: RangeMethod::Percentile(0.9999),
        iters: cfg.iters,
        rounding: Rounding::Nearest,
        wide_trunk: cfg.wide_trunk,
    };
    let cal = calibrate(&float, &pairs, opts, &mut |_, _| {}).unwrap();
    Model { cfg, float, blob: muir_tools::writer::write(&cal.data) }
}

/// MACs of the float reference: the network items with the context convs once per frame
/// instead of merged into every gate call.
fn float_macs(cfg: &Config, m: &Macs) -> u64 {
    let g = muir::engine::Grid::new(W, H);
    m.total() - m.gru08_context - m.gru16_context + conv_macs(ConvId::Czqr08, cfg, g.n8()) + conv_macs(ConvId::Czqr16, cfg, g.n16())
}

fn gmac(v: u64) -> f64 {
    v as f64 / 1e9
}

/// Criterion's estimate (slope, else mean) of a benchmark run by this process, in seconds.
fn estimate_s(group: &str, id: &str) -> Option<f64> {
    let target = std::env::var("CARGO_TARGET_DIR").unwrap_or_else(|_| concat!(env!("CARGO_MANIFEST_DIR"), "/target").to_string());
    let text = std::fs::read_to_string(format!("{target}/criterion/{group}/{id}/new/estimates.json")).ok()?;
    let v: serde_json::Value = serde_json::from_str(&text).ok()?;
    let pick = |k: &str| v.get(k).and_then(|e| e.get("point_estimate")).and_then(|p| p.as_f64());
    pick("slope").or_else(|| pick("mean")).map(|ns| ns * 1e-9)
}

/// (a) Whole frames: fixed-point engine and float reference in one group.
fn frames(c: &mut Criterion, models: &[Model], pair: &(OwnedImage, OwnedImage)) {
    let (lv, rv) = (pair.0.view(), pair.1.view());
    // Which benchmarks this process ran (the others may be filtered out).
    let ran = std::cell::RefCell::new(vec![[false; 2]; models.len()]);
    let mark = |i: usize, j: usize| ran.borrow_mut()[i][j] = true;
    let group = "frame 320x240";
    let mut g = c.benchmark_group(group);
    g.sampling_mode(SamplingMode::Flat).sample_size(10).warm_up_time(Duration::from_millis(1)).measurement_time(Duration::from_secs(5));
    for (i, md) in models.iter().enumerate() {
        let name = &md.name();
        let m = Macs::new(&md.cfg, W, H, md.cfg.iters);
        println!(
            "MACs per frame, {name} 320x240, {} iterations: fixed engine {:.3} G (network {:.3} G + recompute {:.3} G), float reference {:.3} G",
            md.cfg.iters,
            gmac(m.engine_total()),
            gmac(m.total()),
            gmac(m.recompute_total()),
            gmac(float_macs(&md.cfg, &m))
        );
        let qm = QuantModel::parse(&md.blob).unwrap();
        let plan = Plan::new(&md.cfg, W, H);
        let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
        let (mut d, mut u) = (vec![0i16; W * H], vec![0i16; W * H]);
        let mud = md.cfg.mud;
        g.throughput(Throughput::Elements(m.engine_total()));
        g.bench_function(BenchmarkId::new("fixed", name), |b| {
            mark(i, 0);
            let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut arena)).unwrap();
            b.iter(|| {
                let unc = if mud { Some(&mut u[..]) } else { None };
                e.run(&lv, &rv, &mut Output { disparity: &mut d, uncertainty: unc }).unwrap();
                black_box(&d);
            })
        });
        g.throughput(Throughput::Elements(float_macs(&md.cfg, &m)));
        g.bench_function(BenchmarkId::new("float", name), |b| {
            mark(i, 1);
            b.iter(|| black_box(md.float.predict(&lv, &rv, None).unwrap()))
        });
    }
    g.finish();
    for (i, md) in models.iter().enumerate() {
        let name = &md.name();
        if ran.borrow()[i] != [true, true] {
            continue;
        }
        if let (Some(fx), Some(fl)) = (estimate_s(group, &format!("fixed/{name}")), estimate_s(group, &format!("float/{name}"))) {
            println!("{name} 320x240: fixed engine {fx:.3} s, float reference {fl:.3} s per frame: fixed / float = {:.2}", fx / fl);
        }
    }
}

/// One refinement iteration as `Engine::run_iters` runs it.
fn iteration(c: &mut refine::Ctx<'_, '_, '_>, cfg: &Config) {
    if cfg.mud {
        refine::mud_pass(c);
    }
    if cfg.mga {
        refine::mga_values(c);
    }
    refine::gru16(c);
    refine::gru16(c);
    refine::gru08(c);
    refine::flow_head(c, 0);
}

/// MGA state of a real frame after one iteration: keys, masked values, and the last pixel's
/// query with its softmax statistics.
struct Attention {
    keys: Vec<i16>,
    values: Vec<i16>,
    query: Vec<i16>,
    stats: (i64, i64),
    shift: i8,
}

/// (b) The fixed engine's phases, on the state of a real frame. Returns the MGA state of the
/// last model with MGA.
fn stages(c: &mut Criterion, models: &[Model], pair: &(OwnedImage, OwnedImage)) -> Option<Attention> {
    let (lv, rv) = (pair.0.view(), pair.1.view());
    let mut attention = None;
    for md in models.iter().filter(|m| !m.cfg.wide_trunk) {
        let cfg = md.cfg;
        let name = cfg.name.as_str();
        let qm = QuantModel::parse(&md.blob).unwrap();
        let plan = Plan::new(&cfg, W, H);
        let mut mem = vec![0u64; plan.ram_bytes.div_ceil(8)];
        let arena: &mut [u8] = bytemuck::cast_slice_mut(&mut mem);
        let m = Macs::new(&cfg, W, H, cfg.iters);
        let m0 = Macs::new(&cfg, W, H, 0);
        let mut g = c.benchmark_group(format!("stages {name} 320x240"));
        g.sample_size(10).warm_up_time(Duration::from_millis(300)).measurement_time(Duration::from_secs(2));
        let half = |v: u64| v / 2;
        let enc_right = half(m.backbone() + m.features + m.features_recompute);
        let enc_left = enc_right + m.layer4 + m.context_heads;
        g.throughput(Throughput::Elements(enc_right));
        g.bench_function("encoder right (features)", |b| b.iter(|| encode_image(&qm, &plan, arena, &rv, false)));
        g.throughput(Throughput::Elements(enc_left));
        g.bench_function("encoder left (features + context)", |b| b.iter(|| encode_image(&qm, &plan, arena, &lv, true)));
        // The refinement phases run on the encoded pair, in frame order; each phase is timed on
        // the state the previous ones left (repeating a phase does not change its cost).
        encode_image(&qm, &plan, arena, &rv, false);
        encode_image(&qm, &plan, arena, &lv, true);
        let mut ctx = refine_ctx(&qm, &plan, arena);
        ctx.st.flow.fill(0);
        if cfg.ufi {
            g.throughput(Throughput::Elements(m.ufi_peaks + m.ufi_lookups + m.ufi_convs + m.ufi_recompute));
            g.bench_function("ufi", |b| b.iter(|| refine::ufi(&mut ctx, muir::model::config::MaxDisparity::DEFAULT.grid8())));
        }
        if cfg.mga {
            g.throughput(Throughput::Elements(m.mga_setup + m0.mga_recompute));
            g.bench_function("mga setup", |b| b.iter(|| refine::mga_setup(&mut ctx)));
        }
        g.throughput(Throughput::Elements(Macs::per_iteration(&cfg, W, H)));
        g.bench_function("one iteration", |b| b.iter(|| iteration(&mut ctx, &cfg)));
        if cfg.mga {
            let p = plan.grid.n8() - 1; // gru08 computed this pixel's query last
            let frac = |a| qm.format(a).frac;
            attention = Some(Attention {
                keys: ctx.st.keys.to_vec(),
                values: ctx.st.values.to_vec(),
                query: ctx.px.query[..cfg.mga_qk_dim].to_vec(),
                stats: (ctx.st.stats[2 * p], ctx.st.stats[2 * p + 1]),
                shift: frac(Act::Glb) - frac(Act::MgaV),
            });
        }
        let (mut d, mut u) = (vec![0i16; W * H], vec![0i16; W * H]);
        g.throughput(Throughput::Elements(m.final_mud + m.mask_head + m.upsample));
        g.bench_function("output (mud + upsample)", |b| {
            b.iter(|| {
                if cfg.mud {
                    refine::mud_pass(&mut ctx);
                }
                let unc = if cfg.mud { Some(&mut u[..]) } else { None };
                refine::upsample(&mut ctx, W, H, &mut d, unc);
            })
        });
        g.finish();
    }
    attention
}

/// Deterministic test data.
struct Rng(u64);
impl Rng {
    fn next(&mut self) -> u64 {
        self.0 ^= self.0 >> 12;
        self.0 ^= self.0 << 25;
        self.0 ^= self.0 >> 27;
        self.0.wrapping_mul(0x2545F4914F6CDD1D)
    }
    fn i8(&mut self) -> i8 {
        (self.next() >> 56) as i8
    }
    fn i16(&mut self) -> i16 {
        ((self.next() >> 48) as i16) >> 3 // 13-bit signed, activations with headroom
    }
}

/// (c) Kernels: row kernels against their plain twins, with muir-fast's layers and widths.
fn kernels(c: &mut Criterion, fast: &Model, att: Option<&Attention>) {
    let cfg = fast.cfg;
    let qm = QuantModel::parse(&fast.blob).unwrap();
    let g8 = muir::engine::Grid::new(W, H);
    let mut r = Rng(42);
    let mut g = c.benchmark_group("kernels muir-fast 320x240");
    g.sample_size(10).warm_up_time(Duration::from_millis(300)).measurement_time(Duration::from_secs(2));

    // GRU08 gate conv (i16 input, 3x3, 640 -> 128) over 4 rows of the 1/8 grid.
    let rows = 4;
    let p = qm.conv(ConvId::Gru08Z).unwrap();
    let (w, parts) = (g8.w8, p.parts);
    let tensors: Vec<Vec<i16>> = parts.iter().map(|&ch| (0..rows * w * ch).map(|_| r.i16()).collect()).collect();
    let mut out = vec![0i16; rows * w * p.cout];
    let mut patch = vec![0i16; p.patch_len()];
    g.throughput(Throughput::Elements((kernel_rows(rows) * w * p.patch_len() / 3 * p.cout) as u64));
    g.bench_function(format!("conv_row gru08 i16 3x3 {}->{} ({rows} rows of {w})", p.patch_len() / 9, p.cout), |b| {
        b.iter(|| {
            for y in 0..rows {
                let pr: Vec<PartRows<'_, i16>> = tensors.iter().zip(parts).map(|(t, &ch)| PartRows::of_tensor(t, rows, w * ch, y, 3, 1)).collect();
                conv_row(&p, &pr, w, &mut OutRow::I16(&mut out[y * w * p.cout..(y + 1) * w * p.cout]), &mut patch);
            }
            black_box(&out);
        })
    });
    // The same inside an engine frame (x86-64): the layer's weights widened to i16 once, as the
    // engine's frames do, instead of per call (the figure the engine's refinement sees).
    #[cfg(target_arch = "x86_64")]
    g.bench_function(format!("conv_row gru08 i16 3x3 {}->{} ({rows} rows of {w}), in a frame", p.patch_len() / 9, p.cout), |b| {
        let _frame = muir::kernels::conv::FrameScope::new();
        b.iter(|| {
            for y in 0..rows {
                let pr: Vec<PartRows<'_, i16>> = tensors.iter().zip(parts).map(|(t, &ch)| PartRows::of_tensor(t, rows, w * ch, y, 3, 1)).collect();
                conv_row(&p, &pr, w, &mut OutRow::I16(&mut out[y * w * p.cout..(y + 1) * w * p.cout]), &mut patch);
            }
            black_box(&out);
        })
    });
    let refs: Vec<&[i16]> = tensors.iter().map(|t| t.as_slice()).collect();
    g.bench_function(format!("conv_plain gru08 i16 3x3 {}->{} ({rows} rows of {w})", p.patch_len() / 9, p.cout), |b| {
        b.iter(|| {
            conv_plain(&p, &refs, rows, w, &mut OutRow::I16(&mut out));
            black_box(&out);
        })
    });

    // Backbone layer1 conv (u8 input and output, 3x3, 64 -> 64) over 4 rows of the 1/2 grid.
    let p = qm.conv(ConvId::L1b0c1).unwrap();
    let w = g8.w2;
    let x: Vec<u8> = (0..rows * w * p.parts[0]).map(|_| r.i8() as u8).collect();
    let mut out = vec![0u8; rows * w * p.cout];
    let mut patch = vec![0u8; p.patch_len()];
    g.throughput(Throughput::Elements((kernel_rows(rows) * w * p.patch_len() / 3 * p.cout) as u64));
    g.bench_function(format!("conv_row layer1 u8 3x3 64->64 ({rows} rows of {w})"), |b| {
        b.iter(|| {
            for y in 0..rows {
                let pr = [PartRows::of_tensor(&x, rows, w * p.parts[0], y, 3, 1)];
                conv_row(&p, &pr, w, &mut OutRow::U8(&mut out[y * w * p.cout..(y + 1) * w * p.cout]), &mut patch);
            }
            black_box(&out);
        })
    });
    // The same inside an engine frame (x86-64): the layer's weights re-laid once per frame where
    // the row takes the output-channels-along-the-vector path, as the engine runs it.
    #[cfg(target_arch = "x86_64")]
    g.bench_function(format!("conv_row layer1 u8 3x3 64->64 ({rows} rows of {w}), in a frame"), |b| {
        let _frame = muir::kernels::conv::FrameScope::new();
        b.iter(|| {
            for y in 0..rows {
                let pr = [PartRows::of_tensor(&x, rows, w * p.parts[0], y, 3, 1)];
                conv_row(&p, &pr, w, &mut OutRow::U8(&mut out[y * w * p.cout..(y + 1) * w * p.cout]), &mut patch);
            }
            black_box(&out);
        })
    });
    g.bench_function(format!("conv_plain layer1 u8 3x3 64->64 ({rows} rows of {w})"), |b| {
        b.iter(|| {
            conv_plain(&p, &[&x[..]], rows, w, &mut OutRow::U8(&mut out));
            black_box(&out);
        })
    });

    // Correlation lookup of one row (w8 pixels, fmap 256, 4 levels radius 4, post-pooled), at a
    // disparity of 5.3 px on the 1/8 grid.
    let (w, fd) = (g8.w8, cfg.fmap_dim);
    let f1: Vec<i8> = (0..w * fd).map(|_| r.i8()).collect();
    let f2: Vec<i8> = (0..w * fd).map(|_| r.i8()).collect();
    let mults = qm.corr_mults();
    let lp = LookupParams { levels: cfg.corr_levels, radius: cfg.corr_radius, post_pool: cfg.post_pool, mults: &mults };
    let wl = window_len(cfg.corr_levels, cfg.corr_radius);
    let (mut win, mut pre) = (vec![0i32; wl], vec![0i64; wl + 1]);
    let cc = cfg.corr_channels();
    let mut o = vec![0i16; w * cc];
    let flow = -(5.3f32 * 256.0) as i16;
    g.throughput(Throughput::Elements(muir::model::macs::lookup_dots_per_row(&cfg, w) * fd as u64));
    g.bench_function(format!("lookup_pixel tiled (row of {w})"), |b| {
        b.iter(|| {
            let mut s = LookupScratch { window: &mut win, prefix: &mut pre };
            for x in 0..w {
                lookup_pixel(&lp, &f1[x * fd..(x + 1) * fd], &f2, w, x, flow, &mut s, &mut o[x * cc..(x + 1) * cc]);
            }
            black_box(&o);
        })
    });
    // The same row with the AVX-512 VNNI window (x86-64 hosts that have it): the right row laid
    // out once, then every pixel's window 16 columns at a time.
    #[cfg(target_arch = "x86_64")]
    if muir::kernels::x86::has_avx512() {
        let mut row = muir::kernels::corr::avx512::Row::new();
        g.bench_function(format!("lookup_with AVX-512 window (row of {w})"), |b| {
            b.iter(|| {
                row.fill(&f2, w, fd);
                let mut s = LookupScratch { window: &mut win, prefix: &mut pre };
                for x in 0..w {
                    let f1x = &f1[x * fd..(x + 1) * fd];
                    muir::kernels::corr::lookup_with(&lp, w, x, flow, &mut s, &mut o[x * cc..(x + 1) * cc], |lo, wv| {
                        if !row.window(f1x, lo, wv) {
                            muir::kernels::corr::window(f1x, &f2, w, lo, wv);
                        }
                    });
                }
                black_box(&o);
            })
        });
    }
    g.bench_function(format!("lookup_pixel_plain (row of {w})"), |b| {
        b.iter(|| {
            for x in 0..w {
                lookup_pixel_plain(&lp, &f1[x * fd..(x + 1) * fd], &f2, w, x, flow, &mut o[x * cc..(x + 1) * cc]);
            }
            black_box(&o);
        })
    });

    // MGA aggregation of one query over all N = n8 keys, on a real frame's keys and values.
    if let Some(a) = att {
        let (n, qk, hd) = (g8.n8(), cfg.mga_qk_dim, cfg.hidden_dim);
        let am = qm.att_mult();
        let (mut acc, mut glb) = (vec![0i64; hd], vec![0i16; hd]);
        g.throughput(Throughput::Elements((n * (qk + hd)) as u64));
        g.bench_function(format!("aggregate_query (one query, {n} keys, qk {qk}, values {hd})"), |b| {
            b.iter(|| {
                aggregate_query(&a.query, &a.keys, &a.values, hd, a.stats, am, a.shift, &mut acc, &mut glb);
                black_box(&glb);
            })
        });
        // Sixteen queries at once with the AVX-512 VNNI kernel (the query repeated; keys and
        // values laid out once, as once per pass in the engine).
        #[cfg(target_arch = "x86_64")]
        {
            let mut prep = muir::kernels::attention::avx512::Prepared::new();
            if prep.fill(&a.keys, &a.values, qk, hd) {
                let qs: Vec<i16> = (0..16).flat_map(|_| a.query.iter().copied()).collect();
                let stats: Vec<i64> = (0..16).flat_map(|_| [a.stats.0, a.stats.1]).collect();
                let mut out = vec![0i16; 16 * hd];
                g.throughput(Throughput::Elements((16 * n * (qk + hd)) as u64));
                g.bench_function(format!("aggregate AVX-512 (16 queries, {n} keys, qk {qk}, values {hd})"), |b| {
                    b.iter(|| {
                        prep.aggregate(&qs, &stats, am, a.shift, &mut out);
                        black_box(&out);
                    })
                });
            }
        }
    }
    g.finish();
}

/// (d) The full-resolution refinement on the network's output for the pair (the fixed engine's
/// disparity and uncertainty before it): the streaming stage on one thread (vector kernels where
/// the CPU has them), its plain twin, and the pool's schedule on two threads. Elements = pixels.
fn refinement(c: &mut Criterion, md: &Model, pair: &(OwnedImage, OwnedImage)) {
    use muir::kernels::{fullres, pool};
    let (lv, rv) = (pair.0.view(), pair.1.view());
    let qm = QuantModel::parse(&md.blob).unwrap();
    let plan = Plan::new(&md.cfg, W, H);
    let mut arena = vec![0u64; plan.ram_bytes.div_ceil(8)];
    let (mut d0, mut u) = (vec![0i16; W * H], vec![0i16; W * H]);
    let mut e = Engine::new(&qm, bytemuck::cast_slice_mut(&mut arena)).unwrap();
    e.set_full_res_refinement(false);
    e.run(&lv, &rv, &mut Output { disparity: &mut d0, uncertainty: Some(&mut u) }).unwrap();
    let mut g = c.benchmark_group(format!("refinement {} 320x240", md.name()));
    g.sample_size(20).warm_up_time(Duration::from_millis(300)).measurement_time(Duration::from_secs(2));
    g.throughput(Throughput::Elements((W * H) as u64));
    let mut d = d0.clone();
    let mut scratch = fullres::ScratchVec::new(W);
    for threads in [1, 2] {
        pool::set_threads(threads);
        g.bench_function(format!("refine_image, {threads} thread(s)"), |b| {
            b.iter(|| {
                d.copy_from_slice(&d0);
                black_box(fullres::refine_image(&lv, &rv, &mut d, Some(&u), scratch.view()))
            })
        });
    }
    pool::set_threads(1);
    g.bench_function("refine_image_plain (portable twin)", |b| {
        b.iter(|| {
            d.copy_from_slice(&d0);
            black_box(fullres::refine_image_plain(&lv, &rv, &mut d, Some(&u)))
        })
    });
    g.finish();
}

/// Kernel rows a 3x3 layer's `rows` output rows read inside the image: the first and the last
/// read two of three, the padding rows being skipped (counting them, until 2026-12-06, overstated
/// the rate by 12 / 10 for 4 rows).
fn kernel_rows(rows: usize) -> usize {
    (0..rows).map(|y| (y.saturating_sub(1)..(y + 2).min(rows)).len()).sum()
}

/// The shipped model's 1/8 ConvGRU gate as the engine runs it on Teddy (x86-64): muir-slim's
/// `Gru08Z` (six i16 parts, 64 channels out) on rows of 58, inside an engine frame, the context
/// part's sums kept (`with_constant_part`, computed once and reused, as in six of a frame's seven
/// iterations).
#[cfg(target_arch = "x86_64")]
fn slim_gate(c: &mut Criterion, slim: &Model) {
    let qm = QuantModel::parse(&slim.blob).unwrap();
    let mut r = Rng(43);
    let mut g = c.benchmark_group("kernels muir-slim");
    g.sample_size(10).warm_up_time(Duration::from_millis(300)).measurement_time(Duration::from_secs(2));
    let (rows, w) = (4, 58);
    let p = qm.conv(ConvId::Gru08Z).unwrap();
    let parts = p.parts;
    let tensors: Vec<Vec<i16>> = parts.iter().map(|&ch| (0..rows * w * ch).map(|_| r.i16()).collect()).collect();
    let mut out = vec![0i16; rows * w * p.cout];
    let mut patch = vec![0i16; p.patch_len()];
    let ctx_ch = parts.last().copied().unwrap_or(0);
    g.throughput(Throughput::Elements((kernel_rows(rows) * 3 * w * (p.patch_len() / 9 - ctx_ch) * p.cout) as u64));
    g.bench_function(format!("conv_row gru08 i16 3x3 {:?}->{} ({rows} rows of {w}), in a frame, context kept", parts, p.cout), |b| {
        let _frame = muir::kernels::conv::FrameScope::new();
        b.iter(|| {
            for y in 0..rows {
                let pr: Vec<PartRows<'_, i16>> = tensors.iter().zip(parts).map(|(t, &ch)| PartRows::of_tensor(t, rows, w * ch, y, 3, 1)).collect();
                muir::kernels::conv::with_constant_part(parts.len() - 1, y, || {
                    conv_row(&p, &pr, w, &mut OutRow::I16(&mut out[y * w * p.cout..(y + 1) * w * p.cout]), &mut patch)
                });
            }
            black_box(&out);
        })
    });
    g.finish();
}

fn all(c: &mut Criterion) {
    let (pair, calib, source) = images();
    println!("pair: {source}; models: seeded weights, calibrated on another crop");
    // The wide-trunk slim blob last: models[1] is muir-fast (kernels), stages skip it.
    let wide = Config { wide_trunk: true, ..Config::MUIR_SLIM };
    let models: Vec<Model> =
        [Config::MUIR_SLIM, Config::MUIR_FAST, wide].into_iter().map(|cfg| model(cfg, &calib)).collect();
    frames(c, &models, &pair);
    let att = stages(c, &models, &pair);
    kernels(c, &models[1], att.as_ref());
    #[cfg(target_arch = "x86_64")]
    slim_gate(c, &models[0]);
    refinement(c, &models[0], &pair);
}

criterion_group!(benches, all);
criterion_main!(benches);
