//! Puts `memory.x` on the linker search path and checks that the quantised model the firmware
//! places in the external QSPI flash exists.

#[path = "../common/board_build.rs"]
mod board_build;

fn main() {
    board_build::link_memory_x();
    board_build::require_model("muir-slim.muirq");
}
