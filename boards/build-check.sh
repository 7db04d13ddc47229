#!/usr/bin/env bash
# Builds the real-board firmware crates (boards/stm32h743, boards/rp2350) in release and prints,
# for each, the frame size and the size of every allocated section: code (.text), constants
# (.rodata), the model section (.qspi_model / .xip_model), .data, .bss and the NOLOAD RAM sections,
# with the engine arena (the ARENA static). Nothing runs: there is no emulator for these chips in
# CI, so this is a build check (compile, link against the real memory map, compile-time asserts
# that the arena fits). Exits non-zero if a build fails.
#
# Cold build (empty target/ folders, crates downloaded, 1 job): about 2 minutes per crate on a
# 2-core machine; warm: seconds.
#
# Usage: boards/build-check.sh [stm32h743|rp2350 ...]   (default: both)
set -euo pipefail
here="$(cd "$(dirname "$0")" && pwd)"
boards=("$@")
[ ${#boards[@]} -eq 0 ] && boards=(stm32h743 rp2350)

for board in "${boards[@]}"; do
  dir="$here/$board"
  target="$(sed -n 's/^target *= *"\([^"]*\)".*/\1/p' "$dir/.cargo/config.toml" | head -n 1)"
  w="$(sed -n 's/^pub const W: usize = \([0-9]*\);/\1/p' "$dir/src/bin/stereo.rs")"
  h="$(sed -n 's/^pub const H: usize = \([0-9]*\);/\1/p' "$dir/src/bin/stereo.rs")"
  echo "== $board ($target): building (cargo build --release)"
  start=$(date +%s)
  if ! (cd "$dir" && cargo build --release); then
    echo "build-check: $board: build FAILED" >&2
    exit 1
  fi
  elf="${CARGO_TARGET_DIR:-$dir/target}/$target/release/stereo"
  echo "== $board: built in $(( $(date +%s) - start )) s; frame ${w}x${h}; $elf"
  python3 - "$elf" <<'PY'
import struct, sys
path = sys.argv[1]
d = open(path, "rb").read()
assert d[:4] == b"\x7fELF" and d[4] == 1, "expected a 32-bit ELF"
(shoff,) = struct.unpack_from("<I", d, 0x20)
shentsize, shnum, shstrndx = struct.unpack_from("<HHH", d, 0x2E)
secs = [struct.unpack_from("<10I", d, shoff + i * shentsize) for i in range(shnum)]
def name(tab, off):
    s = secs[tab][4]
    return d[s + off : d.index(b"\0", s + off)].decode()
SHF_ALLOC, SHT_NOBITS, SHT_SYMTAB = 2, 8, 2
print(f"  {'section':<16}{'bytes':>10}{'KiB':>10}  {'address':<10}  kind")
for s in secs:
    if s[2] & SHF_ALLOC and s[5]:
        kind = "RAM (not in image)" if s[1] == SHT_NOBITS else ("RAM, initialised from flash" if s[2] & 1 else "image")
        print(f"  {name(shstrndx, s[0]):<16}{s[5]:>10}{s[5] / 1024:>10.1f}  0x{s[3]:08x}  {kind}")
stack = {}
for i, s in enumerate(secs):
    if s[1] == SHT_SYMTAB:
        for j in range(s[5] // 16):
            st_name, value, size, info, other, shndx = struct.unpack_from("<IIIBBH", d, s[4] + 16 * j)
            n = name(s[6], st_name)
            if "ARENA" in n and size:
                print(f"  engine arena (ARENA static): {size} bytes ({size / 1024:.1f} KiB) at 0x{value:08x}")
            if n in ("_stack_start", "_stack_end"):
                stack[n] = value
if len(stack) == 2:
    room = stack["_stack_start"] - stack["_stack_end"]
    print(f"  stack: {room} bytes ({room / 1024:.1f} KiB) from 0x{stack['_stack_start']:08x} down (engine::STACK_BUDGET: 24 KiB)")
PY
done
