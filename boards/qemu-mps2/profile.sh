#!/usr/bin/env bash
# Per-instruction profile of one frame of the firmware under QEMU: which functions and which hot
# loops execute the instructions (QEMU models no cycles; instruction counts are the speed figure).
#
#   boards/qemu-mps2/profile.sh                  # the 64x48 CI pair
#   boards/qemu-mps2/profile.sh --size 160x120   # feature frame-160x120
#   boards/qemu-mps2/profile.sh --m55 [--size 160x120]   # the Cortex-M55 firmware (qemu-mps3-m55, Helium)
#
# Needs what run-tests.sh needs, plus gcc (builds profile/pcprof.c), python3 and llvm-objdump
# (the hot-loop listing is skipped without it); llvm-addr2line for the table by kernel family
# (instructions and MACs per instruction per family, MACs from `muir macs`). Counts cover the whole run (boot, model parse and
# the frame); the frame is almost all of it.
set -euo pipefail

board="$(cd "$(dirname "$0")" && pwd)"
size=64x48
m55=0
while [ $# -gt 0 ]; do
    case "$1" in
        --m55) m55=1; shift ;;
        --size) size="$2"; shift 2 ;;
        --size=*) size="${1#--size=}"; shift ;;
        -h|--help) sed -n '2,11p' "$0"; exit 0 ;;
        *) echo "profile.sh: unknown argument '$1' (try --help)" >&2; exit 2 ;;
    esac
done
features=()
[ "$size" = 64x48 ] || features=(--features "frame-$size")
for tool in gcc python3 qemu-system-arm nm; do
    command -v "$tool" >/dev/null || { echo "profile.sh: $tool is not installed" >&2; exit 1; }
done

tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
if [ "$m55" = 1 ]; then
    fw="$board/../qemu-mps3-m55"
    feats=mve
    [ "$size" = 64x48 ] || feats="mve,frame-$size"
    (cd "$fw" && cargo build --release --bin stereo --no-default-features --features "$feats")
    elf="$fw/target/thumbv8m.main-none-eabihf/release/stereo"
    machine=mps3-an547 base=0x10000000
else
    (cd "$board" && cargo build --release --bin stereo "${features[@]}")
    elf="$board/target/thumbv7em-none-eabihf/release/stereo"
    machine=mps2-an500 base=0
fi
gcc -O2 -shared -fPIC -fvisibility=hidden -o "$tmp/libpcprof.so" "$board/profile/pcprof.c"
timeout "${QEMU_TIMEOUT:-900}" qemu-system-arm -M "$machine" -nographic \
    -semihosting-config enable=on,target=native -plugin "$tmp/libpcprof.so,out=$tmp/pcs.txt,base=$base" -d plugin \
    -kernel "$elf" >"$tmp/qemu.log" 2>&1 || { cat "$tmp/qemu.log" >&2; exit 1; }
grep -m1 '^MUIR-RESULT' "$tmp/qemu.log" || true
nm -n -S -C "$elf" | awk 'NF >= 4 && ($3 == "t" || $3 == "T")' >"$tmp/syms.txt"
if command -v llvm-objdump >/dev/null; then
    llvm-objdump -d --no-show-raw-insn "$elf" >"$tmp/dis.txt"
else
    : >"$tmp/dis.txt"
fi
# MACs per kernel family of the frame (host build of the CLI), for the family table.
family=()
if command -v llvm-addr2line >/dev/null && [ -s "$tmp/dis.txt" ]; then
    (cd "$board/../.." && cargo run -q --release --bin muir -- macs --config muir-slim --size "$size") >"$tmp/macs.md"
    family=("$elf" "$tmp/macs.md")
fi
python3 "$board/profile/report.py" "$tmp/pcs.txt" "$tmp/syms.txt" "$tmp/dis.txt" "${family[@]}"
