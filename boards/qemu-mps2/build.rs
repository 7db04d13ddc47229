//! Puts `memory.x` on the linker search path (cortex-m-rt's `link.x` includes it), selects the
//! board in the firmware program (`muir_board = "an500"`) and checks that the quantised model the
//! firmware embeds exists.

use std::path::PathBuf;
use std::{env, fs};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap());
    fs::copy("memory.x", out.join("memory.x")).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");

    // The firmware program (src/bin/stereo.rs) is shared with boards/qemu-mps3-m55; this cfg picks
    // its board constants (FPGA IO address, CPU name).
    println!("cargo::rustc-check-cfg=cfg(muir_board, values(\"an500\", \"an547\"))");
    println!("cargo:rustc-cfg=muir_board=\"an500\"");

    let model = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").unwrap()).join("../../models/muir-slim.muirq");
    println!("cargo:rerun-if-changed={}", model.display());
    if !model.is_file() {
        panic!(
            "{} is missing: the firmware embeds the quantised muir-slim model. Produce it with \
             `cargo run --release --bin muir -- quantize --model <muir-slim.safetensors> --calib <pair folder> ... \
             --out models/muir-slim.muirq` (see boards/qemu-mps2/README.md)",
            model.display()
        );
    }
}
