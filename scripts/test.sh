#!/usr/bin/env bash
# The project's test command (README "Two commands", and .ci/run): installs what it needs on a fresh
# machine, then runs every test.
#   1. host tests (unit, parity with the PyTorch twin's golden files, fixed vs float on real pairs,
#      streaming vs plain fixed-point engine, model files, CLI), optimised ([profile.test]);
#   2. the aarch64 host build (the core's tests and the engine tests under qemu-aarch64), and the
#      core crate (crates/muir) without std for thumbv7em-none-eabihf (Cortex-M4F/M7), and what its
#      published package would hold;
#   3. the PyTorch twin's own tests (python/tests: the split, the refinement's integer helpers, ONNX export vs the twin, a
#      data-parallel training step under torchrun against the single-process step);
#   4. the QEMU firmware in boards/ (bit-exact with the host), u8 and wide-trunk blobs: Cortex-M7
#      (qemu-mps2, DSP kernels) and Cortex-M55 (qemu-mps3-m55, Helium kernels, checked on the target
#      against the plain loops first); the real-board crates (STM32H743, RP2350) are built and sized.
set -euo pipefail
cd "$(dirname "$0")/.."

need_root() { if [ "$(id -u)" -eq 0 ]; then "$@"; else sudo "$@"; fi; }

if ! rustup target list --installed | grep -q '^thumbv7em-none-eabihf$'; then
    echo "== installing rust target thumbv7em-none-eabihf"
    rustup target add thumbv7em-none-eabihf
fi
if { [ -d boards/qemu-mps3-m55 ] || [ -d boards/rp2350 ]; } && ! rustup target list --installed | grep -q '^thumbv8m.main-none-eabihf$'; then
    echo "== installing rust target thumbv8m.main-none-eabihf"
    rustup target add thumbv8m.main-none-eabihf
fi
if [ -d boards/qemu-mps2 ] && ! command -v qemu-system-arm >/dev/null 2>&1; then
    echo "== installing qemu-system-arm"
    need_root apt-get update -qq
    need_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq qemu-system-arm >/dev/null
fi
if ! rustup target list --installed | grep -q '^aarch64-unknown-linux-gnu$'; then
    echo "== installing rust target aarch64-unknown-linux-gnu"
    rustup target add aarch64-unknown-linux-gnu
fi
if ! command -v qemu-aarch64 >/dev/null 2>&1 || ! command -v aarch64-linux-gnu-gcc >/dev/null 2>&1; then
    echo "== installing qemu-user and the aarch64 cross linker (the aarch64 host build's tests)"
    need_root apt-get update -qq
    need_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq qemu-user gcc-aarch64-linux-gnu libc6-dev-arm64-cross >/dev/null
fi
if [ -d boards/qemu-mps2 ] && ! command -v llvm-objdump >/dev/null 2>&1; then
    echo "== installing llvm (llvm-objdump: panic and float sites of the firmware)"
    need_root apt-get update -qq
    need_root env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq llvm >/dev/null
fi

echo "== Python packages of the twin (torch CPU, numpy, OpenCV, ...; python/pyproject.toml)"
python3 -m pip install -q --disable-pip-version-check "torch>=2.2" "numpy>=1.24" "opencv-python-headless>=4.8" \
    "pillow>=10.0" "matplotlib>=3.7" "safetensors>=0.4" "pytest>=7.4" \
    "onnx>=1.15" "onnxruntime>=1.17"

echo "== host tests"
cargo test --workspace --all-targets --no-fail-fast 2>&1 | tee /tmp/muir-test.log
cargo test --workspace --doc

echo "== aarch64 host build (Linux-class Arm modules): the core's tests and the engine tests under qemu-aarch64"
# The NEON convolution rows (sdot on qemu's default CPU), the portable kernels elsewhere and the
# kernel pool without the x86 paths (host_rows' per-row forms, threads). Then the core's tests
# again (same binary, ~15 s each): on a CPU without the dot-product extension (Cortex-A72: the
# detection's NEON-only level), and with MUIR_ARM_SIMD=0 (the portable conv rows, which the NEON
# ones replace otherwise).
(
    export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_LINKER=aarch64-linux-gnu-gcc
    export CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -L /usr/aarch64-linux-gnu"
    cargo test -q --release --target aarch64-unknown-linux-gnu -p muir --features std,internals --lib
    cargo test -q --release --target aarch64-unknown-linux-gnu --test engine
    CARGO_TARGET_AARCH64_UNKNOWN_LINUX_GNU_RUNNER="qemu-aarch64 -cpu cortex-a72 -L /usr/aarch64-linux-gnu" \
        cargo test -q --release --target aarch64-unknown-linux-gnu -p muir --features std,internals --lib
    MUIR_ARM_SIMD=0 cargo test -q --release --target aarch64-unknown-linux-gnu -p muir --features std,internals --lib
)

echo "== no_std build of the core (crates/muir) for thumbv7em-none-eabihf, and its package (no model files, < 10 MiB)"
cargo build -p muir --lib --target thumbv7em-none-eabihf
python3 scripts/package-size.py

echo "== clippy on the core: no unwrap / expect / panic! outside tests (crate-level deny), target and host builds"
rustup component list --installed 2>/dev/null | grep -q '^clippy' || rustup component add clippy
cargo clippy -q -p muir --lib --target thumbv7em-none-eabihf --features dsp
CARGO_TARGET_THUMBV8M_MAIN_NONE_EABIHF_RUSTFLAGS="-C target-cpu=cortex-m55" cargo clippy -q -p muir --lib --target thumbv8m.main-none-eabihf --features mve
cargo clippy -q -p muir --lib --features std,internals

echo "== the core's API docs build without warnings (broken or private intra-doc links)"
RUSTDOCFLAGS="-D warnings" cargo doc -q -p muir --no-deps
RUSTDOCFLAGS="-D warnings" cargo doc -q -p muir --features std,internals --no-deps

echo "== Python twin tests (split, refinement helpers, one DDP step = one single-process step)"
(cd python && PYTHONPATH=. python3 -m pytest -q)

if [ -x boards/qemu-mps2/run-tests.sh ]; then
    echo "== Cortex-M firmware under QEMU"
    boards/qemu-mps2/run-tests.sh
    boards/qemu-mps2/run-tests.sh --wide-trunk
fi
if [ -x boards/qemu-mps3-m55/run-tests.sh ]; then
    echo "== Cortex-M55 (Helium) firmware under QEMU"
    boards/qemu-mps3-m55/run-tests.sh
    boards/qemu-mps3-m55/run-tests.sh --wide-trunk
    # The Armv7E-M DSP kernels (the Cortex-M7 build's assembly loops) against the plain loops on
    # random and extreme values, on the target; the M7 frame above checks them on real data.
    boards/qemu-mps3-m55/run-tests.sh --no-mve
fi
if [ -x boards/build-check.sh ]; then
    echo "== real-board firmware (STM32H743, RP2350): release build + section sizes (build check only, no hardware)"
    boards/build-check.sh
fi
if [ -f boards/qemu-mps2/panic-sites.py ]; then
    echo "== branches into panic paths in the firmware: none from muir's code (a gate; issue #22)"
    python3 boards/qemu-mps2/panic-sites.py --max-muir 0
    [ -d boards/qemu-mps3-m55 ] && python3 boards/qemu-mps2/panic-sites.py --max-muir 0 \
        boards/qemu-mps3-m55/target/thumbv8m.main-none-eabihf/release/stereo
fi
if [ -f boards/qemu-mps2/float-sites.py ]; then
    echo "== floating point in the firmware: none on muir's inference path (a gate; issue #22 item 4)"
    python3 boards/qemu-mps2/float-sites.py
    [ -d boards/qemu-mps3-m55 ] && python3 boards/qemu-mps2/float-sites.py \
        boards/qemu-mps3-m55/target/thumbv8m.main-none-eabihf/release/stereo
fi
echo "== all tests passed"
