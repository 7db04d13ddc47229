#!/usr/bin/env bash
# Builds the Cortex-M firmware, runs it on QEMU's mps2-an500 (Cortex-M7 with FPU) and checks its
# MUIR-RESULT line against expected.txt, which the host test `cargo test --test firmware` checks
# against the host engine: host and target are bit-exact when both pass. Prints the instructions
# per frame (QEMU TCG plugin ../shared/tools/qemu-icount, when present) and MACs per instruction.
#
#   boards/qemu-mps2/run-tests.sh                  # CI: the 64x48 pair, expected.txt
#   boards/qemu-mps2/run-tests.sh --size 160x120   # measurement: feature frame-160x120, expected-160x120.txt
#   boards/qemu-mps2/run-tests.sh --wide-trunk     # CI too: models/muir-slim-wide.muirq, expected-wide.txt
#   boards/qemu-mps2/run-tests.sh --early-stop     # measurement: adaptive iterations (EarlyStop::RECOMMENDED), expected-early*.txt
#
# Needs: the thumbv7em-none-eabihf Rust target, qemu-system-arm, models/muir-slim.muirq; gcc for the
# plugin (without it, or without ../shared, the run is checked but not counted).
# Environment: QEMU_TIMEOUT (seconds, default 600).
set -euo pipefail

board="$(cd "$(dirname "$0")" && pwd)"
root="$(cd "$board/../.." && pwd)"
size=64x48
wide=0
early=0
while [ $# -gt 0 ]; do
    case "$1" in
        --size) size="$2"; shift 2 ;;
        --size=*) size="${1#--size=}"; shift ;;
        --wide-trunk) wide=1; shift ;;
        --early-stop) early=1; shift ;;
        -h|--help) sed -n '2,15p' "$0"; exit 0 ;;
        *) echo "run-tests.sh: unknown argument '$1' (try --help)" >&2; exit 2 ;;
    esac
done
if [ "$size" = 64x48 ]; then
    features=() expected="$board/expected"
else
    features=("frame-$size") expected="$board/expected-$size"
fi
model=muir-slim.muirq
if [ "$wide" = 1 ]; then
    features+=(wide-trunk) model=muir-slim-wide.muirq
    expected="$board/expected-wide${expected#"$board/expected"}"
fi
if [ "$early" = 1 ]; then
    [ "$wide" = 0 ] || { echo "run-tests.sh: --early-stop runs the u8 trunk only" >&2; exit 2; }
    features+=(early-stop)
    expected="$board/expected-early${expected#"$board/expected"}"
fi
expected="$expected.txt"
if [ ${#features[@]} -gt 0 ]; then features=(--features "$(IFS=,; echo "${features[*]}")"); fi
name=qemu-mps2 machine=mps2-an500
say() { echo "$name: $*"; }
die() { echo "$name: FAILED: $*" >&2; exit 1; }

[ -f "$root/models/$model" ] || die "models/$model is missing (the firmware embeds it; see boards/qemu-mps2/README.md)"
[ -f "$expected" ] || die "$expected is missing (MUIR_UPDATE_EXPECTED=1 cargo test --test firmware writes it)"
command -v qemu-system-arm >/dev/null || die "qemu-system-arm is not installed (apt-get install qemu-system-arm)"

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT

say "building the firmware ($size, $model, release)"
t0=$(date +%s)
(cd "$board" && cargo build --release --bin stereo "${features[@]}")
elf="$board/target/thumbv7em-none-eabihf/release/stereo"
say "build took $(( $(date +%s) - t0 )) s"

source "$root/boards/qemu-frame.sh"
