//! One stereo frame of the muir fixed-point engine on a Cortex-M7 (QEMU `mps2-an500`) or, built
//! by `boards/qemu-mps3-m55`, on a Cortex-M55 (QEMU `mps3-an547`): the board's `build.rs` emits the
//! `muir_board` cfg (`"an500"`, `"an547"`) that picks the few board constants in [`board`].
//!
//! The quantised `muir-slim` model is read in place from flash, the working memory is one
//! `static` arena sized at compile time by the engine's memory plan (no heap), and the frame is
//! computed between the `bench_start` / `bench_end` markers that the QEMU instruction-count
//! plugin watches, with the board's user LED 0 lit while it runs (`run_with_busy_pin`).
//!
//! Output over semihosting: a machine-readable `MUIR-RESULT ...` line (compared with
//! `expected.txt` by `run-tests.sh`, and with the host engine by the host test
//! `host-tests/firmware.rs`), then a human-readable line; exit status 0, or 1 after a
//! `MUIR-ERROR ...` line when the engine refuses the model or the pair.

#![no_std]
#![no_main]

use core::fmt::{self, Write as _};
use core::ptr::{read_volatile, write_volatile};

use cortex_m_rt::entry;
use embedded_hal::digital::{ErrorKind, ErrorType, OutputPin};
use muir::Config;
use muir::engine::hal::run_with_busy_pin;
use muir::engine::{Arena, CHECKED_TAUS, Disparity, EarlyStop, Engine, Output, Plan, predicted_error_px, reject, u_threshold};
use muir::format::{QuantModel, crc32};
use muir::input::{ImageView, PixelFormat};
use semihosting::{eprintln, println, process};

#[cfg(not(feature = "frame-160x120"))]
mod frame {
    pub const W: usize = 64;
    pub const H: usize = 48;
    pub static LEFT: &[u8] = include_bytes!("../../assets/left_64x48.gray");
    pub static RIGHT: &[u8] = include_bytes!("../../assets/right_64x48.gray");
}
#[cfg(feature = "frame-160x120")]
mod frame {
    pub const W: usize = 160;
    pub const H: usize = 120;
    pub static LEFT: &[u8] = include_bytes!("../../assets/left_160x120.gray");
    pub static RIGHT: &[u8] = include_bytes!("../../assets/right_160x120.gray");
}
use frame::{H, LEFT, RIGHT, W};

/// The config the embedded model must have: muir-slim, with the i16 trunk under feature
/// `wide-trunk` (`muir quantize --wide-trunk`, models/muir-slim-wide.muirq).
const CONFIG: Config = Config { wide_trunk: cfg!(feature = "wide-trunk"), ..Config::MUIR_SLIM };

/// The memory plan of this model and image size, evaluated at compile time.
const PLAN: Plan = Plan::new(&CONFIG, W, H);

/// Adaptive iterations: with feature `early-stop`, the recommended criterion
/// ([`EarlyStop::RECOMMENDED`]); without it, all 7 iterations.
const EARLY_STOP: Option<EarlyStop> = if cfg!(feature = "early-stop") { Some(EarlyStop::RECOMMENDED) } else { None };

#[path = "../../../common/once_static.rs"]
mod once_static;
use once_static::Static;

/// All of the engine's working memory.
static ARENA: Static<Arena<{ PLAN.ram_bytes }>> = Static::new(Arena::new());
/// Outputs: disparity (Q10.5 px) and uncertainty (Q4.11), then a copy for the rejection count.
static DISPARITY: Static<[i16; W * H]> = Static::new([0; W * H]);
static UNCERTAINTY: Static<[i16; W * H]> = Static::new([0; W * H]);
static KEPT: Static<[i16; W * H]> = Static::new([0; W * H]);

/// The `.muirq` blob in flash, 8-byte aligned like the sections inside it.
#[repr(C, align(8))]
struct Aligned<B: ?Sized>(B);
#[cfg(not(feature = "wide-trunk"))]
macro_rules! model_file {
    () => {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/muir-slim.muirq")
    };
}
#[cfg(feature = "wide-trunk")]
macro_rules! model_file {
    () => {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/muir-slim-wide.muirq")
    };
}
/// The blob itself; on AN547 in its own section, which `memory.x` places in the QSPI flash (it
/// does not fit the 512 KiB ITCM that holds the code).
#[cfg_attr(muir_board = "an547", unsafe(link_section = ".muir_model"))]
static MODEL_BLOB: Aligned<[u8; include_bytes!(model_file!()).len()]> = Aligned(*include_bytes!(model_file!()));
static MODEL: &Aligned<[u8]> = &MODEL_BLOB;

/// Start of the measured region (the QEMU plugin counts instructions from here to `bench_end`).
/// The two markers have different bodies so that the compiler cannot fold them into one address.
#[unsafe(no_mangle)]
#[inline(never)]
pub extern "C" fn bench_start() {
    unsafe { write_volatile(BENCH_PHASE.as_ptr(), 1) };
}

/// End of the measured region.
#[unsafe(no_mangle)]
#[inline(never)]
pub extern "C" fn bench_end() {
    unsafe { write_volatile(BENCH_PHASE.as_ptr(), 2) };
}

/// 1 inside a measured region, 2 after it (visible to a debugger).
static BENCH_PHASE: Static<u32> = Static::new(0);

/// The board constants, chosen by the `muir_board` cfg of the crate's `build.rs`.
#[cfg(muir_board = "an500")]
mod board {
    /// MPS2 FPGA IO block: `FPGAIO->LED0` at offset 0 drives the user LEDs (bit n = USERLEDn). QEMU
    /// maps `mps2-fpgaio` at 0x4002_8000 on mps2-an385/an386/an500/an511 (`info mtree`) with two LEDs.
    pub const FPGAIO_LED0: usize = 0x4002_8000;
    /// The CPUID part number this board has, and its name.
    pub const CPU: &str = "0xc27: Cortex-M7";
}
#[cfg(muir_board = "an547")]
mod board {
    /// MPS3 AN547 FPGA IO block (same `mps2-fpgaio` registers, ten LEDs), behind peripheral
    /// protection controller `apb_ppcexp2` port 2 at 0x4930_2000; the core runs Secure, so its
    /// Secure alias 0x5930_2000 (QEMU hw/arm/mps2-tz.c, `info mtree` of mps3-an547).
    pub const FPGAIO_LED0: usize = 0x5930_2000;
    /// The CPUID part number this board has, and its name.
    pub const CPU: &str = "0xd22: Cortex-M55";
}
#[cfg(not(any(muir_board = "an500", muir_board = "an547")))]
compile_error!("build with a board crate (boards/qemu-mps2 or boards/qemu-mps3-m55): its build.rs sets `muir_board`");

/// `FPGAIO->LED0` of the board.
const FPGAIO_LED0: *mut u32 = board::FPGAIO_LED0 as *mut u32;

/// The stack's high-water mark, by painting: before the frame every word between the end of the
/// statics (`_stack_end`, cortex-m-rt) and a margin below the current stack pointer is set to
/// [`PAINT`]; after the frame the first word from the bottom that changed marks the deepest the
/// stack went. Reported with the arena so that a user sizing RAM sees both (the engine's working
/// memory is all in the arena; the stack holds only locals and call frames).
mod stack {
    use core::ptr::{read_volatile, write_volatile};

    const PAINT: u32 = 0x5354_4b21; // "STK!"
    /// Words below the stack pointer left alone while painting (this function's own frame).
    const MARGIN_WORDS: usize = 64;

    unsafe extern "C" {
        static mut _stack_end: u32; // lowest address the stack may reach (end of .bss/.uninit)
        static mut _stack_start: u32; // initial stack pointer (top of RAM)
    }

    fn sp() -> usize {
        let sp: usize;
        // SAFETY: reads the stack pointer register, no side effects.
        unsafe { core::arch::asm!("mov {}, sp", out(reg) sp, options(nomem, nostack, preserves_flags)) };
        sp
    }

    /// Paints the free stack below the caller. Returns the number of words painted.
    #[inline(never)]
    pub fn paint() -> usize {
        let bottom = core::ptr::addr_of_mut!(_stack_end);
        let limit = (sp() & !3) - 4 * MARGIN_WORDS;
        let n = limit.saturating_sub(bottom as usize) / 4;
        for i in 0..n {
            // SAFETY: [_stack_end, sp - margin) is RAM no static and no live frame uses.
            unsafe { write_volatile(bottom.add(i), PAINT) };
        }
        n
    }

    /// Bytes of stack used since [`paint`] (from the top of the stack to the deepest changed word).
    pub fn high_water(painted: usize) -> usize {
        let bottom = core::ptr::addr_of_mut!(_stack_end);
        let top = core::ptr::addr_of_mut!(_stack_start) as usize;
        // SAFETY: reads the words `paint` wrote.
        let untouched = (0..painted).take_while(|&i| unsafe { read_volatile(bottom.add(i)) } == PAINT).count();
        top - (bottom as usize + 4 * untouched)
    }
}

/// A user LED of the MPS2 FPGA IO block as an `embedded-hal` output pin. Each write is read back:
/// a register that does not hold the value (another board, no FPGA IO block) is a pin error.
struct FpgaLed {
    bit: u32,
    /// Level changes driven (a logic analyser would see as many edges).
    edges: u32,
}

#[derive(Debug)]
struct LedStuck;

impl embedded_hal::digital::Error for LedStuck {
    fn kind(&self) -> ErrorKind {
        ErrorKind::Other
    }
}

impl ErrorType for FpgaLed {
    type Error = LedStuck;
}

impl FpgaLed {
    fn set(&mut self, on: bool) -> Result<(), LedStuck> {
        let mask = 1 << self.bit;
        // SAFETY: a device register of the MPS2 FPGA IO block; single core, no interrupts use it.
        let old = unsafe { read_volatile(FPGAIO_LED0) };
        let new = if on { old | mask } else { old & !mask };
        unsafe { write_volatile(FPGAIO_LED0, new) };
        if (unsafe { read_volatile(FPGAIO_LED0) } & mask != 0) != on {
            return Err(LedStuck);
        }
        self.edges += u32::from((old & mask != 0) != on);
        Ok(())
    }
}

impl OutputPin for FpgaLed {
    fn set_high(&mut self) -> Result<(), LedStuck> {
        self.set(true)
    }
    fn set_low(&mut self) -> Result<(), LedStuck> {
        self.set(false)
    }
}

/// Prints `MUIR-ERROR <what>: <error>` and exits with status 1.
fn fail(what: &str, e: impl fmt::Display) -> ! {
    eprintln!("MUIR-ERROR {what}: {e}");
    process::exit(1)
}

/// A disparity of the engine's output as a number (Q10.5 px; printed without float).
fn px(v: i64) -> Disparity {
    Disparity::from_bits(v.clamp(i16::MIN.into(), i16::MAX.into()) as i16)
}

/// CRC-32 of `v` as little-endian i16 bytes (the in-memory layout on this little-endian core).
fn crc_i16(v: &[i16]) -> u32 {
    crc32(bytemuck::cast_slice(v))
}

#[entry]
fn main() -> ! {
    // SAFETY: `main` runs once and is the only user of these statics.
    let (arena, disparity, uncertainty, kept) = unsafe { (ARENA.take(), DISPARITY.take(), UNCERTAINTY.take(), KEPT.take()) };

    let model = QuantModel::parse(&MODEL.0).unwrap_or_else(|e| fail("model", e));
    if *model.config() != CONFIG {
        fail("model", "the embedded model's config (muir-slim, trunk width) is not the one of this firmware's memory plan");
    }
    let left = ImageView::new(W, H, PixelFormat::Gray8, LEFT).unwrap_or_else(|e| fail("left image", e));
    let right = ImageView::new(W, H, PixelFormat::Gray8, RIGHT).unwrap_or_else(|e| fail("right image", e));
    let mut engine = Engine::new(&model, &mut arena.0).unwrap_or_else(|e| fail("engine", e));
    engine.set_early_stop(EARLY_STOP);
    let mut led = FpgaLed { bit: 0, edges: 0 };
    let mut out = Output { disparity: &mut disparity[..], uncertainty: Some(&mut uncertainty[..]) };

    let painted = stack::paint();
    // An empty region first: the plugin's count for it is the markers' own cost.
    bench_start();
    bench_end();
    bench_start();
    let result = run_with_busy_pin(&mut engine, &left, &right, &mut out, &mut led);
    bench_end();
    result.unwrap_or_else(|e| fail("frame", e));
    let iters = engine.last_iterations();
    let stack_bytes = stack::high_water(painted);
    if stack_bytes > muir::engine::STACK_BUDGET {
        fail("stack", format_args!("the frame used {stack_bytes} bytes of stack, over engine::STACK_BUDGET ({})", muir::engine::STACK_BUDGET));
    }

    let d_crc = crc_i16(disparity);
    let u_crc = crc_i16(uncertainty);
    kept.copy_from_slice(disparity);
    let kept_1px = reject(kept, uncertainty, u_threshold(1.0));
    // The rejection thresholds of several tau, computed here (the same integers as on the host:
    // `u_threshold` uses IEEE-exact operations only), and the pixels each keeps.
    let t = CHECKED_TAUS.map(u_threshold);
    let k = t.map(|th| {
        kept.copy_from_slice(disparity);
        reject(kept, uncertainty, th)
    });
    // The two lists as comma-separated text, built without a heap whatever CHECKED_TAUS holds.
    let list = |v: &[i64]| {
        let mut s = heapless::String::<{ 8 * CHECKED_TAUS.len() }>::new();
        for (i, x) in v.iter().enumerate() {
            // Each value fits 7 characters (i16, or a pixel count below 10^7) plus its comma.
            write!(s, "{}{x}", if i > 0 { "," } else { "" }).unwrap_or_else(|_| fail("result line", "value too long"));
        }
        s
    };
    println!(
        "MUIR-RESULT width={W} height={H} ram={} disparity_crc=0x{d_crc:08x} uncertainty_crc=0x{u_crc:08x} kept_1px={kept_1px} \
         u_thresholds={} kept={} iters={iters}",
        PLAN.ram_bytes,
        list(&t.map(i64::from)),
        list(&k.map(|n| n as i64)),
    );
    // Not part of MUIR-RESULT: the host cannot compute it (it depends on the target's code).
    println!("MUIR-STACK bytes={stack_bytes} arena={} total={}", PLAN.ram_bytes, PLAN.ram_bytes + stack_bytes);

    let (min, max) = disparity.iter().fold((i16::MAX, i16::MIN), |(a, b), &d| (a.min(d), b.max(d)));
    // For the log only (micromath's exp; the result line above is integers).
    let mean_err = uncertainty.iter().map(|&u| predicted_error_px(u)).sum::<f32>() / (W * H) as f32;
    let sum: i64 = disparity.iter().map(|&d| i64::from(d)).sum();
    // SAFETY: read-only system register.
    let part = (unsafe { (*cortex_m::peripheral::CPUID::PTR).base.read() } >> 4) & 0xFFF;
    println!(
        "muir-slim{} {W}x{H} on CPU part 0x{part:03x} ({}): disparity {:.2}..{:.2} px, mean {:.2} px; \
         {kept_1px} of {} pixels with predicted error <= 1 px (mean predicted error {:.2} px); working RAM {} bytes (one static arena, no heap); \
         model {} bytes read in place from flash; busy LED edges {}",
        if CONFIG.wide_trunk { " (wide trunk)" } else { "" },
        board::CPU,
        px(min.into()),
        px(max.into()),
        px(sum / (W * H) as i64),
        W * H,
        mean_err,
        PLAN.ram_bytes,
        MODEL.0.len(),
        led.edges,
    );
    process::exit(0)
}
