//! The muir fixed-point stereo engine on an STM32H743 (Cortex-M7 at 400 MHz, e.g. NUCLEO-H743ZI):
//! a camera-shaped loop that captures a grey stereo pair, computes its disparity and uncertainty
//! maps and logs frame time, disparity range and kept pixels over defmt/RTT.
//!
//! Memory (memory.x): the engine's working memory is one static arena in the 512 KiB AXI SRAM
//! (sized at compile time by the engine's memory plan, no heap), the camera frames and output maps
//! are in SRAM1-3 (D2 domain: a DCMI DMA can write there), the stack and small statics are in the
//! DTCM, and the 2.47 MB quantised model, larger than the 2 MiB internal flash, is read in place
//! from an external QSPI NOR flash that [`qspi_memory_mapped`] maps at 0x9000_0000.
//!
//! The camera is the [`Camera`] trait; [`TestPattern`] implements it with a synthetic textured
//! pair of known disparity (no camera driver is in scope). The status LED (PB0, green LED LD1 of
//! the NUCLEO-H743ZI) is high while a frame is computed (`run_with_busy_pin`).

#![no_std]
#![no_main]

use core::convert::Infallible;
use core::sync::atomic::{AtomicU32, Ordering};

use cortex_m::peripheral::syst::SystClkSource;
use cortex_m::peripheral::DWT;
use cortex_m_rt::{entry, exception};
use defmt::{Display2Format, info, unwrap};
use defmt_rtt as _;
use embedded_hal::digital::{ErrorType, OutputPin};
use muir::Config;
use muir::engine::hal::run_with_busy_pin;
use muir::engine::{Arena, Engine, Output, Plan, STACK_BUDGET, reject, u_threshold};
use muir::format::QuantModel;
use muir::input::{ImageView, PixelFormat};
use panic_probe as _;
use stm32h7xx_hal::gpio::{Output as GpioOutput, Pin, PushPull};
use stm32h7xx_hal::{pac, prelude::*, xspi::Qspi};

// ---------------------------------------------------------------------------------------------
// Frame size and memory budget
// ---------------------------------------------------------------------------------------------

/// Frame width: a muir-slim frame (sides multiples of 16, about 4:3) whose arena fits the AXI SRAM
/// (`muir plan --config muir-slim --size 208x160`: 506,064 bytes of 524,288; 224x160 needs 544,488
/// since the patch scratch holds a whole 1/8 row of pixel pairs, 224x144 fits with 504,728).
pub const W: usize = 208;
/// Frame height.
pub const H: usize = 160;

/// AXI SRAM (D1 domain), `AXISRAM` in memory.x: the arena and nothing else.
const AXISRAM_BYTES: usize = 512 * 1024;
/// SRAM1 + SRAM2 + SRAM3 (D2 domain, contiguous), `SRAM123` in memory.x: frames and outputs.
const SRAM123_BYTES: usize = 288 * 1024;
/// DTCM, `RAM` in memory.x: stack and the small statics (defmt-rtt's buffer, the cycle counter).
const DTCM_BYTES: usize = 128 * 1024;

/// The model's config (the memory plan depends on it).
const CONFIG: Config = Config::MUIR_SLIM;
/// The engine's memory plan for this model and frame size, evaluated at compile time.
const PLAN: Plan = Plan::new(&CONFIG, W, H);

const _: () = assert!(PLAN.ram_bytes <= AXISRAM_BYTES, "the engine arena does not fit the 512 KiB AXI SRAM: lower W x H");
/// Two 8-bit frames and two i16 maps (disparity, uncertainty).
const FRAME_BUFFERS: usize = 2 * W * H + 2 * 2 * W * H;
const _: () = assert!(FRAME_BUFFERS <= SRAM123_BYTES, "the frames and output maps do not fit SRAM1-3");
const _: () = assert!(STACK_BUDGET + 8 * 1024 <= DTCM_BYTES, "the engine's stack budget does not fit the DTCM");

/// The core clock.
const SYSCLK_MHZ: u32 = 400;

// ---------------------------------------------------------------------------------------------
// Statics
// ---------------------------------------------------------------------------------------------

#[path = "../../../common/once_static.rs"]
mod once_static;
use once_static::Static;

/// All of the engine's working memory, in the AXI SRAM (NOLOAD: not zeroed at boot).
#[unsafe(link_section = ".axisram")]
static ARENA: Static<Arena<{ PLAN.ram_bytes }>> = Static::new(Arena::new());
/// Camera frames (8-bit grey) and output maps (disparity Q10.5 px, uncertainty Q4.11), in SRAM1-3.
#[unsafe(link_section = ".sram123")]
static LEFT: Static<[u8; W * H]> = Static::new([0; W * H]);
#[unsafe(link_section = ".sram123")]
static RIGHT: Static<[u8; W * H]> = Static::new([0; W * H]);
#[unsafe(link_section = ".sram123")]
static DISPARITY: Static<[i16; W * H]> = Static::new([0; W * H]);
#[unsafe(link_section = ".sram123")]
static UNCERTAINTY: Static<[i16; W * H]> = Static::new([0; W * H]);

/// The `.muirq` blob, 8-byte aligned like the sections inside it.
#[repr(C, align(8))]
struct Aligned<B: ?Sized>(B);
macro_rules! model_file {
    () => {
        concat!(env!("CARGO_MANIFEST_DIR"), "/../../models/muir-slim.muirq")
    };
}
/// The model in the external QSPI flash (`.qspi_model`, 0x9000_0000): readable only once the
/// QUADSPI is in memory-mapped mode.
#[unsafe(link_section = ".qspi_model")]
static MODEL_BLOB: Aligned<[u8; include_bytes!(model_file!()).len()]> = Aligned(*include_bytes!(model_file!()));
static MODEL: &Aligned<[u8]> = &MODEL_BLOB;

// ---------------------------------------------------------------------------------------------
// Camera
// ---------------------------------------------------------------------------------------------

#[path = "../../../common/camera.rs"]
mod camera;
use camera::{Camera, TestPattern};

// ---------------------------------------------------------------------------------------------
// Board support
// ---------------------------------------------------------------------------------------------

/// The status LED as an `embedded-hal` 1.0 output pin (stm32h7xx-hal 0.16 implements the 0.2
/// traits only; its inherent `set_high` / `set_low` are infallible).
struct StatusPin(Pin<'B', 0, GpioOutput<PushPull>>);

impl ErrorType for StatusPin {
    type Error = Infallible;
}

impl OutputPin for StatusPin {
    fn set_high(&mut self) -> Result<(), Infallible> {
        self.0.set_high();
        Ok(())
    }
    fn set_low(&mut self) -> Result<(), Infallible> {
        self.0.set_low();
        Ok(())
    }
}

/// Puts the QUADSPI (bank 1, already clocked and pinned by the HAL) in memory-mapped mode for a
/// 16 MiB SPI NOR flash: command 0x6B "Quad Output Fast Read" (instruction and 24-bit address
/// on one line, data on four, 8 dummy cycles), which W25Q128JV, MX25L12835F, IS25LP128 and most
/// others implement. The chip's Quad Enable bit must be set (factory default on W25Q..IQ/JQ
/// parts; otherwise set it once, e.g. with the programmer). The HAL offers indirect mode only,
/// hence the register writes (RM0433 section 23.3.5).
fn qspi_memory_mapped(qspi: &mut Qspi<pac::QUADSPI>) {
    let regs = qspi.inner_mut();
    while regs.sr.read().busy().bit_is_set() {}
    // FSIZE: 2^(23 + 1) = 16 MiB; CSHT: chip select high for 2 cycles between commands.
    regs.dcr.write(|w| unsafe { w.fsize().bits(23).csht().bits(1) });
    // Writing CCR with FMODE = 0b11 starts memory-mapped mode.
    regs.ccr.write(|w| unsafe {
        w.fmode()
            .bits(0b11) // memory-mapped
            .dmode()
            .bits(0b11) // data on 4 lines
            .dcyc()
            .bits(8)
            .adsize()
            .bits(0b10) // 24-bit address
            .admode()
            .bits(0b01) // address on 1 line
            .imode()
            .bits(0b01) // instruction on 1 line
            .instruction()
            .bits(0x6B)
    });
}

/// DWT cycle counter extended to 64 bits (a frame takes longer than the 10.7 s the 32-bit
/// counter spans at 400 MHz): SysTick fires every 2^24 cycles and counts the wraps.
static CYC_HI: AtomicU32 = AtomicU32::new(0);
static CYC_LAST: AtomicU32 = AtomicU32::new(0);

#[exception]
fn SysTick() {
    let now = DWT::cycle_count();
    if now < CYC_LAST.load(Ordering::Relaxed) {
        CYC_HI.fetch_add(1, Ordering::Relaxed);
    }
    CYC_LAST.store(now, Ordering::Relaxed);
}

fn cycles() -> u64 {
    cortex_m::interrupt::free(|_| {
        let now = DWT::cycle_count();
        let mut hi = CYC_HI.load(Ordering::Relaxed);
        if now < CYC_LAST.load(Ordering::Relaxed) {
            hi += 1;
        }
        (u64::from(hi) << 32) | u64::from(now)
    })
}

// ---------------------------------------------------------------------------------------------
// Main loop
// ---------------------------------------------------------------------------------------------

#[entry]
fn main() -> ! {
    let mut cp = unwrap!(cortex_m::Peripherals::take());
    let dp = unwrap!(pac::Peripherals::take());

    // SRAM1-3 clocks (RCC_AHB2ENR) before the first access to `.sram123`.
    dp.RCC.ahb2enr.modify(|_, w| w.sram1en().set_bit().sram2en().set_bit().sram3en().set_bit());
    cortex_m::asm::dsb();

    let pwrcfg = dp.PWR.constrain().freeze(); // VOS1: up to 400 MHz
    let ccdr = dp.RCC.constrain().sys_ck(SYSCLK_MHZ.MHz()).freeze(pwrcfg, &dp.SYSCFG);

    cp.SCB.enable_icache();
    cp.SCB.enable_dcache(&mut cp.CPUID);
    // A DMA camera driver must invalidate the D-cache over the frame buffers after each capture
    // (or map SRAM1-3 non-cacheable with the MPU); the test pattern is written by the core.

    // Cycle counter and its 64-bit extension.
    cp.DCB.enable_trace();
    DWT::unlock();
    cp.DWT.enable_cycle_counter();
    cp.SYST.set_clock_source(SystClkSource::Core);
    cp.SYST.set_reload(0x00FF_FFFF);
    cp.SYST.clear_current();
    cp.SYST.enable_interrupt();
    cp.SYST.enable_counter();

    let gpiob = dp.GPIOB.split(ccdr.peripheral.GPIOB);
    let gpiod = dp.GPIOD.split(ccdr.peripheral.GPIOD);
    let gpioe = dp.GPIOE.split(ccdr.peripheral.GPIOE);
    let gpiog = dp.GPIOG.split(ccdr.peripheral.GPIOG);

    // Status LED: PB0 (LD1, green, on the NUCLEO-H743ZI).
    let mut led = StatusPin(gpiob.pb0.into_push_pull_output());

    // External QSPI flash, bank 1: CLK PB2, NCS PG6, IO0 PD11, IO1 PD12, IO2 PE2, IO3 PD13 (the
    // pins of stm32h7xx-hal's QSPI example; on the NUCLEO-H743ZI's headers, see README.md).
    let _ncs = gpiog.pg6.into_alternate::<10>().speed(stm32h7xx_hal::gpio::Speed::VeryHigh);
    let pins = (
        gpiob.pb2.into_alternate().speed(stm32h7xx_hal::gpio::Speed::VeryHigh),
        gpiod.pd11.into_alternate().speed(stm32h7xx_hal::gpio::Speed::VeryHigh),
        gpiod.pd12.into_alternate().speed(stm32h7xx_hal::gpio::Speed::VeryHigh),
        gpioe.pe2.into_alternate().speed(stm32h7xx_hal::gpio::Speed::VeryHigh),
        gpiod.pd13.into_alternate().speed(stm32h7xx_hal::gpio::Speed::VeryHigh),
    );
    // QUADSPI kernel clock: HCLK3 (200 MHz), divided by 4.
    let mut qspi = dp.QUADSPI.bank1(pins, 50.MHz(), &ccdr.clocks, ccdr.peripheral.QSPI);
    qspi_memory_mapped(&mut qspi);

    // SAFETY: `main` runs once and is the only user of these statics.
    let (arena, left, right, disparity, uncertainty) =
        unsafe { (ARENA.take(), LEFT.take(), RIGHT.take(), DISPARITY.take(), UNCERTAINTY.take()) };
    arena.0.fill(0); // NOLOAD: whatever the SRAM held at reset

    let model = match QuantModel::parse(&MODEL.0) {
        Ok(m) => m,
        Err(e) => defmt::panic!("model at 0x9000_0000 (QSPI flash programmed? memory-mapped?): {}", Display2Format(&e)),
    };
    if *model.config() != CONFIG {
        defmt::panic!("the model in the QSPI flash is not muir-slim (u8 trunk), the config of this firmware's memory plan");
    }
    let mut engine = match Engine::new(&model, &mut arena.0) {
        Ok(e) => e,
        Err(e) => defmt::panic!("engine: {}", Display2Format(&e)),
    };
    let u_1px = u_threshold(1.0);
    let mut camera = TestPattern::new();
    info!(
        "muir-slim {=usize}x{=usize} on STM32H743 at {=u32} MHz: arena {=usize} B in AXI SRAM, model {=usize} B in QSPI flash; test pattern disparity {=i32} / {=i32} px",
        W,
        H,
        ccdr.clocks.c_ck().raw() / 1_000_000,
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
        let t0 = cycles();
        let result = run_with_busy_pin(&mut engine, &l, &r, &mut out, &mut led);
        let dt = cycles() - t0;
        if let Err(e) = result {
            defmt::error!("frame {=u32}: {}", frame, Display2Format(&e));
            continue;
        }
        let (min, max) = disparity.iter().fold((i16::MAX, i16::MIN), |(a, b), &d| (a.min(d), b.max(d)));
        let kept = reject(&mut disparity[..], &uncertainty[..], u_1px);
        let scale = (1u32 << muir::arith::DISP_FRAC) as f32;
        info!(
            "frame {=u32}: {=u64} ms ({=u64} cycles); disparity {=f32}..{=f32} px; {=usize} of {=usize} pixels kept (predicted error <= 1 px)",
            frame,
            dt / (u64::from(SYSCLK_MHZ) * 1000),
            dt,
            min as f32 / scale,
            max as f32 / scale,
            kept,
            W * H,
        );
    }
    unreachable!()
}
