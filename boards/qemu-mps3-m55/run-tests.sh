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
mve=1
while [ $# -gt 0 ]; do
    case "$1" in
        --size) size="$2"; shift 2 ;;
        --size=*) size="${1#--size=}"; shift ;;
        --wide-trunk) wide=1; shift ;;
        --no-mve) mve=0; shift ;;
        -h|--help) sed -n '2,18p' "$0"; exit 0 ;;
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
expected="$expected.txt"
[ "$mve" = 1 ] && features+=(mve)
if [ ${#features[@]} -gt 0 ]; then
    features=(--no-default-features --features "$(IFS=,; echo "${features[*]}")")
else
    features=(--no-default-features)
fi
say() { echo "qemu-mps3-m55: $*"; }
die() { echo "qemu-mps3-m55: FAILED: $*" >&2; exit 1; }

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

plugin_args=()
plugin_src="$root/../shared/tools/qemu-icount/icount.c"
if [ -f "$plugin_src" ] && command -v gcc >/dev/null; then
    if gcc -O2 -shared -fPIC -fvisibility=hidden -o "$tmp/libicount.so" "$plugin_src"; then
        start=$(nm "$elf" | awk '$3=="bench_start"{print $1}')
        end=$(nm "$elf" | awk '$3=="bench_end"{print $1}')
        [ -n "$start" ] && [ -n "$end" ] || die "bench_start/bench_end markers not found in $elf"
        plugin_args=(-plugin "$tmp/libicount.so,start=0x$start,end=0x$end" -d plugin)
    else
        say "warning: could not build the icount plugin; running without instruction counts"
    fi
else
    say "warning: $plugin_src (or gcc) not found; running without instruction counts"
fi

say "running on qemu-system-arm -M mps3-an547"
t0=$(date +%s.%N)
set +e
timeout "${QEMU_TIMEOUT:-600}" qemu-system-arm -M mps3-an547 -nographic \
    -semihosting-config enable=on,target=native "${plugin_args[@]}" -kernel "$elf" >"$tmp/qemu.log" 2>&1
status=$?
set -e
wall=$(echo "$(date +%s.%N) $t0" | awk '{printf "%.1f", $1 - $2}')
grep -v '^icount:' "$tmp/qemu.log" || true
[ "$status" -ne 124 ] || die "QEMU timed out after ${QEMU_TIMEOUT:-600} s"
[ "$status" -eq 0 ] || die "the firmware exited with status $status"
say "firmware exit status 0, QEMU wall time $wall s"

got=$(grep -m1 '^MUIR-RESULT ' "$tmp/qemu.log" | tr -d '\r' || true)
want=$(grep -m1 '^MUIR-RESULT ' "$expected" || true)
[ -n "$got" ] || die "the firmware printed no MUIR-RESULT line"
if [ "$got" != "$want" ]; then
    echo "  expected: $want (boards/qemu-mps2/$(basename "$expected"))" >&2
    echo "  firmware: $got" >&2
    die "the firmware's results differ from boards/qemu-mps2/$(basename "$expected") (the host test checks the host engine against the same file)"
fi
say "MUIR-RESULT matches boards/qemu-mps2/$(basename "$expected") (bit-exact with the host engine via cargo test --test firmware)"
stack=$(grep -m1 '^MUIR-STACK ' "$tmp/qemu.log" | tr -d '\r' || true)
[ -n "$stack" ] || die "the firmware printed no MUIR-STACK line (painted-stack high-water mark)"
say "RAM: ${stack#MUIR-STACK } (bytes: stack high-water mark of the frame, painted; static arena from the plan)"

if [ ${#plugin_args[@]} -gt 0 ]; then
    # Region 0 is empty (the markers' own cost), region 1 the frame.
    empty=$(awk -F'delta=' '/^icount: region 0 /{print $2}' "$tmp/qemu.log")
    region=$(awk -F'delta=' '/^icount: region 1 /{print $2}' "$tmp/qemu.log")
    [ -n "$empty" ] && [ -n "$region" ] || die "the icount plugin reported no frame region"
    insns=$((region - empty))
    say "icount: region delta=$region, markers $empty -> $insns instructions per frame"
    w=${size%x*} h=${size#*x}
    # `muir macs` prints a Markdown table in G (3 decimals); the test profile reuses what
    # `cargo test` built (scripts/test.sh), where --release would build the whole crate again.
    if gmacs=$(cd "$root" && cargo run -q --profile test --bin muir -- macs --config muir-slim --size "${w}x${h}" \
        | awk -F'|' '/\*\*engine total\*\*/{gsub(/ /, "", $4); print $4}') && [ -n "$gmacs" ]; then
        awk -v g="$gmacs" -v n="$insns" 'BEGIN {
            printf "qemu-mps3-m55: engine MACs per frame %.3f G (muir macs) -> %.4f MAC/instruction, %.2f instructions/MAC\n",
                g, g * 1e9 / n, n / (g * 1e9) }'
    else
        say "warning: could not read the engine total of 'muir macs'; MACs per instruction not computed"
    fi
fi
say "passed"
