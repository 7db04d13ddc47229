//! Puts `memory.x` on the linker search path, selects the board in the firmware program
//! (`muir_board = "an500"`; src/bin/stereo.rs is shared with boards/qemu-mps3-m55) and checks that
//! the quantised model the firmware embeds exists.

#[path = "../common/board_build.rs"]
mod board_build;

fn main() {
    board_build::link_memory_x();
    board_build::select_qemu_board("an500");
    board_build::require_model("muir-slim.muirq");
}
