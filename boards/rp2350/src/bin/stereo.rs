//! The muir fixed-point stereo engine on an RP2350 (Cortex-M33 at 150 MHz, e.g. Raspberry Pi
//! Pico 2): a camera-shaped loop that captures a grey stereo pair, computes its disparity and
//! uncertainty maps and logs frame time, disparity range and kept pixels over defmt/RTT.
//!
//! Memory (memory.x): the engine's working memory is one static arena in the 520 KiB SRAM (sized
//! at compile time by the engine's memory plan, no heap), beside the camera frames, the output
//! maps and the stack; the 2.47 MB quantised model is read in place from the external QSPI flash
//! through the XIP window at 0x1000_0000 (the boot ROM leaves XIP enabled).
//!
//! The camera is the [`Camera`] trait; [`TestPattern`] implements it with a synthetic textured
//! pair of known disparity (no camera driver is in scope). The status LED (GPIO25, the Pico 2's
//! LED) is high while a frame is computed (`run_with_busy_pin`).

#![no_std]
#![no_main]


use defmt::{Display2Format, info, unwrap};
use defmt_rtt as _;
use muir::Config;
use muir::engine::hal::run_with_busy_pin;
use muir::engine::{Arena, Engine, Output, Plan, STACK_BUDGET, reject, u_threshold};
use muir::format::QuantModel;
use muir::input::{ImageView, PixelFormat};
use panic_probe as _;
use rp235x_hal::{self as hal, Clock};

/// Tells the boot ROM how to boot this image (Arm, Secure): must be in the first 4 KiB of flash
/// (`.start_block` in memory.x).
#[unsafe(link_section = ".start_block")]
#[used]
pub static IMAGE_DEF: hal::block::ImageDef = hal::block::ImageDef::secure_exe();

/// The Pico 2's crystal.
const XTAL_FREQ_HZ: u32 = 12_000_000;

// ---------------------------------------------------------------------------------------------
// Frame size and memory budget
// ---------------------------------------------------------------------------------------------

/// Frame width: the largest muir-slim frame (sides multiples of 16) whose arena, frames, output
/// maps and stack budget fit the 520 KiB SRAM (`muir plan --config muir-slim --size 176x128`:
/// arena 366,736 bytes, + 135,168 of frames and maps + 24 KiB stack = 526,480 of 532,480;
/// 192x128 needs 571,512; 160x144 fits with 2 % more pixels but a near-square frame).
pub const W: usize = 176;
/// Frame height.
pub const H: usize = 128;

/// SRAM0-9, `RAM` in memory.x.
const RAM_BYTES: usize = 520 * 1024;
/// Room kept for the other statics (defmt-rtt's buffer, ...).
const OTHER_STATICS: usize = 4 * 1024;

/// The model's config (the memory plan depends on it).
const CONFIG: Config = Config::MUIR_SLIM;
/// The engine's memory plan for this model and frame size, evaluated at compile time.
const PLAN: Plan = Plan::new(&CONFIG, W, H);

/// Two 8-bit frames and two i16 maps (disparity, uncertainty).
const FRAME_BUFFERS: usize = 2 * W * H + 2 * 2 * W * H;
const _: () = assert!(
    PLAN.ram_bytes + FRAME_BUFFERS + STACK_BUDGET + OTHER_STATICS <= RAM_BYTES,
    "the engine arena, frames, output maps and stack do not fit the 520 KiB SRAM: lower W x H"
);

// ---------------------------------------------------------------------------------------------
// Statics
// ---------------------------------------------------------------------------------------------

#[path = "../../../common/once_static.rs"]
mod once_static;
use once_static::Static;

/// All of the engine's working memory (`.bss`).
static ARENA: Static<Arena<{ PLAN.ram_bytes }>> = Static::new(Arena::new());
/// Camera frames (8-bit grey) and output maps (disparity Q10.5 px, uncertainty Q4.11).
static LEFT: Static<[u8; W * H]> = Static::new([0; W * H]);
static RIGHT: Static<[u8; W * H]> = Static::new([0; W * H]);
static DISPARITY: Static<[i16; W * H]> = Static::new([0; W * H]);
static UNCERTAINTY: Static<[i16; W * H]> = Static::new([0; W * H]);

/// The `.muirq` blob, 8-byte aligned like the sections inside it.
#[repr(C, align(8))]
struct Aligned<B: ?Sized>(B);
macro_rules! model_file {
    () => {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/muir-slim.muirq")
    };
}
/// The model in the XIP flash (`.xip_model`, after the code), read in place.
#[unsafe(link_section = ".xip_model")]
static MODEL_BLOB: Aligned<[u8; include_bytes!(model_file!()).len()]> = Aligned(*include_bytes!(model_file!()));
static MODEL: &Aligned<[u8]> = &MODEL_BLOB;

// ---------------------------------------------------------------------------------------------
// Camera
// ---------------------------------------------------------------------------------------------

#[path = "../../../common/camera.rs"]
mod camera;
use camera::{Camera, TestPattern};

// ---------------------------------------------------------------------------------------------
// Main loop
// ---------------------------------------------------------------------------------------------

#[hal::entry]
fn main() -> ! {
    let mut pac = unwrap!(hal::pac::Peripherals::take());
    let mut watchdog = hal::Watchdog::new(pac.WATCHDOG);
    // 150 MHz system clock from the 12 MHz crystal.
    let clocks = unwrap!(
        hal::clocks::init_clocks_and_plls(XTAL_FREQ_HZ, pac.XOSC, pac.CLOCKS, pac.PLL_SYS, pac.PLL_USB, &mut pac.RESETS, &mut watchdog).ok()
    );
    // 1 MHz, 64-bit: frame times in microseconds.
    let timer = hal::Timer::new_timer0(pac.TIMER0, &mut pac.RESETS, &clocks);
    let sio = hal::Sio::new(pac.SIO);
    let pins = hal::gpio::Pins::new(pac.IO_BANK0, pac.PADS_BANK0, sio.gpio_bank0, &mut pac.RESETS);
    // Status LED: GPIO25 (the Pico 2's LED). rp235x-hal implements embedded-hal 1.0's OutputPin.
    let mut led = pins.gpio25.into_push_pull_output();

    // SAFETY: `main` runs once and is the only user of these statics.
    let (arena, left, right, disparity, uncertainty) =
        unsafe { (ARENA.take(), LEFT.take(), RIGHT.take(), DISPARITY.take(), UNCERTAINTY.take()) };

    let model = match QuantModel::parse(&MODEL.0) {
        Ok(m) => m,
        Err(e) => defmt::panic!("model: {}", Display2Format(&e)),
    };
    if *model.config() != CONFIG {
        defmt::panic!("the embedded model is not muir-slim (u8 trunk), the config of this firmware's memory plan");
    }
    let mut engine = match Engine::new(&model, &mut arena.0) {
        Ok(e) => e,
        Err(e) => defmt::panic!("engine: {}", Display2Format(&e)),
    };
    let u_1px = u_threshold(1.0);
    let mut camera = TestPattern::new();
    info!(
        "muir-slim {=usize}x{=usize} on RP2350 at {=u32} MHz: arena {=usize} B in SRAM, model {=usize} B in XIP flash; test pattern disparity {=i32} / {=i32} px",
        W,
        H,
        clocks.system_clock.freq().to_MHz(),
        PLAN.ram_bytes,
        MODEL.0.len(),
        TestPattern::BG_PX,
        TestPattern::FG_PX,
    );

    for frame in 0u32.. {
        if let Err(e) = camera.capture(&mut left[..], &mut right[..]) {
            defmt::warn!("frame {=u32}: capture failed: {}", frame, e);
            continue;
        }
        let l = unwrap!(ImageView::new(W, H, PixelFormat::Gray8, &left[..]).ok());
        let r = unwrap!(ImageView::new(W, H, PixelFormat::Gray8, &right[..]).ok());
        let mut out = Output { disparity: &mut disparity[..], uncertainty: Some(&mut uncertainty[..]) };
        let t0 = timer.get_counter();
        let result = run_with_busy_pin(&mut engine, &l, &r, &mut out, &mut led);
        let dt_us = (timer.get_counter() - t0).to_micros();
        if let Err(e) = result {
            defmt::error!("frame {=u32}: {}", frame, Display2Format(&e));
            continue;
        }
        let (min, max) = disparity.iter().fold((i16::MAX, i16::MIN), |(a, b), &d| (a.min(d), b.max(d)));
        let kept = reject(&mut disparity[..], &uncertainty[..], u_1px);
        let scale = (1u32 << muir::arith::DISP_FRAC) as f32;
        info!(
            "frame {=u32}: {=u64} ms; disparity {=f32}..{=f32} px; {=usize} of {=usize} pixels kept (predicted error <= 1 px)",
            frame,
            dt_us / 1000,
            min as f32 / scale,
            max as f32 / scale,
            kept,
            W * H,
        );
    }
    unreachable!()
}

/// Program metadata for `picotool info`.
#[unsafe(link_section = ".bi_entries")]
#[used]
pub static PICOTOOL_ENTRIES: [hal::binary_info::EntryAddr; 3] = [
    hal::binary_info::rp_program_name!(c"muir-stereo"),
    hal::binary_info::rp_program_description!(c"muir fixed-point stereo matching, test-pattern camera"),
    hal::binary_info::rp_program_build_attribute!(),
];
