#!/usr/bin/env bash
# Builds the Cortex-M55 firmware (the program of boards/qemu-mps2, board cfg "an547"), runs it on
# QEMU's mps3-an547 (Cortex-M55, Helium) and checks its MUIR-RESULT line against
# boards/qemu-mps2/expected*.txt, which the host test `cargo test --test firmware` checks against
# the host engine: host, Cortex-M7 and Cortex-M55 are bit-exact when all pass. First runs
# src/bin/kernels.rs (the dot products of this build against the plain loops). Prints the
# instructions per frame (QEMU TCG plugin ../shared/tools/qemu-icount, when present) and MACs per
# instruction.
#
#   boards/qemu-mps3-m55/run-tests.sh                  # CI: the 64x48 pair, expected.txt
#   boards/qemu-mps3-m55/run-tests.sh --size 160x120   # measurement: feature frame-160x120, expected-160x120.txt
#   boards/qemu-mps3-m55/run-tests.sh --wide-trunk     # CI too: models/muir-slim-wide.muirq, expected-wide.txt
#   boards/qemu-mps3-m55/run-tests.sh --early-stop     # measurement: adaptive iterations (EarlyStop::RECOMMENDED), expected-early*.txt
#   boards/qemu-mps3-m55/run-tests.sh --no-mve         # without the Helium kernels (DSP ones only)
#
# Needs: the thumbv8m.main-none-eabihf Rust target, qemu-system-arm (7.2+), models/muir-slim.muirq;
# gcc for the plugin (without it, or without ../shared, the run is checked but not counted).
# Environment: QEMU_TIMEOUT (seconds, default 600).
set -euo pipefail

board="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$board/../.." && pwd)"
results="$root/boards/qemu-mps2" # the expected*.txt files: one set for every board
size=64x48
wide=0
early=0
mve=1
while [ $# -gt 0 ]; do
    case "$1" in
        --size) size="$2"; shift 2 ;;
        --size=*) size="${1#--size=}"; shift ;;
        --wide-trunk) wide=1; shift ;;
        --early-stop) early=1; shift ;;
        --no-mve) mve=0; shift ;;
        -h|--help) sed -n '2,19p' "$0"; exit 0 ;;
        *) echo "run-tests.sh: unknown argument '$1' (try --help)" >&2; exit 2 ;;
    esac
done
if [ "$size" = 64x48 ]; then
    features=() expected="$results/expected"
else
    features=("frame-$size") expected="$results/expected-$size"
fi
model=muir-slim.muirq
if [ "$wide" = 1 ]; then
    features+=(wide-trunk) model=muir-slim-wide.muirq
    expected="$results/expected-wide${expected#"$results/expected"}"
fi
if [ "$early" = 1 ]; then
    [ "$wide" = 0 ] || { echo "run-tests.sh: --early-stop runs the u8 trunk only" >&2; exit 2; }
    features+=(early-stop)
    expected="$results/expected-early${expected#"$results/expected"}"
fi
expected="$expected.txt"
[ "$mve" = 1 ] && features+=(mve)
if [ ${#features[@]} -gt 0 ]; then
    features=(--no-default-features --features "$(IFS=,; echo "${features[*]}")")
else
    features=(--no-default-features)
fi
name=qemu-mps3-m55 machine=mps3-an547
say() { echo "$name: $*"; }
die() { echo "$name: FAILED: $*" >&2; exit 1; }

[ -f "$root/models/$model" ] || die "models/$model is missing (the firmware embeds it; see boards/qemu-mps2/README.md)"
[ -f "$expected" ] || die "$expected is missing (MUIR_UPDATE_EXPECTED=1 cargo test --test firmware writes it)"
command -v qemu-system-arm >/dev/null || die "qemu-system-arm is not installed (apt-get install qemu-system-arm)"

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

say "building the firmware ($size, $model, $([ "$mve" = 1 ] && echo "Helium + DSP" || echo "DSP only"), release)"
t0=$(date +%s)
(cd "$board" && cargo build --release --bin stereo --bin kernels "${features[@]}")
elf="$board/target/thumbv8m.main-none-eabihf/release/stereo"
say "build took $(( $(date +%s) - t0 )) s"

# The kernels of this build against the plain integer loops, on the target (src/bin/kernels.rs).
set +e
timeout "${QEMU_TIMEOUT:-600}" qemu-system-arm -M mps3-an547 -nographic \
    -semihosting-config enable=on,target=native -kernel "$board/target/thumbv8m.main-none-eabihf/release/kernels" \
    >"$tmp/kernels.log" 2>&1
status=$?
set -e
cat "$tmp/kernels.log"
[ "$status" -eq 0 ] && grep -q '^MUIR-KERNELS ok' "$tmp/kernels.log" \
    || die "the kernel check failed (status $status): the dot products differ from the plain loops"

source "$root/boards/qemu-frame.sh"
