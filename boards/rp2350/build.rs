//! Puts `memory.x` on the linker search path (cortex-m-rt's `link.x` includes it) and checks that
//! the quantised model the firmware places in the XIP flash exists.

use std::path::PathBuf;
use std::{env, fs};

fn main() {
    let out = PathBuf::from(env::var_os("OUT_DIR").unwrap());
    fs::copy("memory.x", out.join("memory.x")).unwrap();
    println!("cargo:rustc-link-search={}", out.display());
    println!("cargo:rerun-if-changed=memory.x");
    println!("cargo:rerun-if-changed=build.rs");

    let model = PathBuf::from(env::var_os("CARGO_MANIFEST_DIR").unwrap()).join("../../models/muir-slim.muirq");
    println!("cargo:rerun-if-changed={}", model.display());
    if !model.is_file() {
        panic!("{} is missing: the firmware embeds the quantised muir-slim model (see boards/qemu-mps2/README.md)", model.display());
    }
}
