//! Build-script steps the boards share (included by each board's `build.rs` with `#[path]`).
// Each board calls the steps it needs (the real boards do not select a QEMU board).
#![allow(dead_code)]

use std::path::PathBuf;
use std::{env, fs};

/// Puts the board's `memory.x` on the linker search path (cortex-m-rt's `link.x` includes it).
pub fn link_memory_x() {
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap());
    fs::copy("memory.x", out.join("memory.x")).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");
    println!("cargo:rerun-if-changed=../common/board_build.rs");
}

/// Selects the board in the shared QEMU firmware program (`boards/qemu-mps2/src/bin/stereo.rs`):
/// `board` is `an500` (Cortex-M7) or `an547` (Cortex-M55).
pub fn select_qemu_board(board: &str) {
    println!("cargo::rustc-check-cfg=cfg(muir_board, values(\"an500\", \"an547\"))");
    println!("cargo:rustc-cfg=muir_board=\"{board}\"");
}

/// Fails the build, saying how to make it, if `models/<name>` (the quantised model the firmware
/// embeds or places in flash) is missing.
pub fn require_model(name: &str) {
    let model = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").unwrap()).join("../../models").join(name);
    println!("cargo:rerun-if-changed={}", model.display());
    if !model.is_file() {
        panic!(
            "{} is missing: the firmware embeds the quantised muir-slim model. Produce it with \
             `cargo run --release --bin muir -- quantize --model <muir-slim.safetensors> --calib <pair folder> ... \
             --out models/{name}` (see boards/qemu-mps2/README.md)",
            model.display()
        );
    }
}
