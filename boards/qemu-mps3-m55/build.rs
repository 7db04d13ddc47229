//! Puts `memory.x` on the linker search path, selects the board in the shared firmware program
//! (`muir_board = "an547"`) and checks that the quantised model the firmware embeds exists.

#[path = "../common/board_build.rs"]
mod board_build;

fn main() {
    board_build::link_memory_x();
    board_build::select_qemu_board("an547");
    let wide = std::env::var_os("CARGO_FEATURE_WIDE_TRUNK").is_some();
    board_build::require_model(if wide { "muir-slim-wide.muirq" } else { "muir-slim.muirq" });
}
