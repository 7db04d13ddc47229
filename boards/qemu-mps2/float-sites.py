#!/usr/bin/env python3
"""Lists every function of a firmware ELF that executes floating point (issue #22 item 4): VFP /
FPU instructions (`v*.f32`, `v*.f64`, conversions to and from float) and calls into soft-float
routines (`__aeabi_dmul`, ...: doubles on a single-precision FPU) found by disassembly, per
containing function. The inference path must have none: its results are integers, bit-exact with
the host, and a float operation there could round differently on another FPU or compiler. Float is
allowed only where a person's number becomes an integer once, before a frame (the rejection
limit in pixels, `engine::u_threshold`, IEEE-exact operations only) or where an integer becomes a
number for a person after it (`engine::predicted_error_px`, logging), and in the firmware's own
reporting code.

    python3 boards/qemu-mps2/float-sites.py [ELF]   # default: the qemu-mps2 release build

Exits 1 if a muir function outside ALLOWED executes float; prints a note and exits 0 without
llvm-objdump (Debian `llvm`).
"""
from __future__ import annotations

import collections
import os
import re
import sys

from elf_sites import disassembly, instructions, owner

# A VFP data-processing or conversion instruction on a float type (vldr/vstr/vmov of raw bits, and
# the integer MVE/DSP instructions, are not float arithmetic).
FLOAT = re.compile(r"^\s*[0-9a-f]+:\s+(?P<op>v(?:add|sub|mul|div|fma|fms|nmul|nmla|nmls|mla|mls|sqrt|abs|neg|cmp|cmpe|"
                   r"cvt[a-z]*|rint[a-z]*|sel[a-z]*|maxnm|minnm|max|min)(?:\.[a-z0-9]+)*\.(?:f16|f32|f64)[^\s]*)")
# A call into a soft-float routine (doubles on a single-precision FPU, or no FPU at all).
SOFT = re.compile(r"^\s*[0-9a-f]+:\s+(?:bl|b|b\.w|blx)\s+0x[0-9a-f]+ <(?P<target>(?:__aeabi_[df](?:add|sub|mul|div|cmp\w*|2\w+)"
                  r"|__aeabi_[iul]\w*2[df]|__(?:add|sub|mul|div|neg|pow)[sdt]f\d|__(?:float|fix)\w+|__(?:eq|ne|lt|le|gt|ge|un|cmp)[sdt]f2"
                  r"|__extendsfdf2|__truncdfsf2|compiler_builtins::float::[^>]*))>")
# muir functions allowed to execute float, and why (see the module docs).
ALLOWED = {
    "u_threshold": "rejection limit in px -> Q4.11 integer, once per setting (IEEE-exact ops)",
    "ln_exact": "u_threshold's logarithm (IEEE-exact ops)",
    "predicted_error_px": "Q4.11 uncertainty -> px for display and logging",
}


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    got = disassembly("float-sites", argv, "not listed")
    if isinstance(got, int):
        return got
    elf, lines = got
    sites: dict[str, collections.Counter] = collections.defaultdict(collections.Counter)
    for func, line in instructions(lines):
        m = FLOAT.match(line)
        if m:
            sites[func][m.group("op").split(".")[0]] += 1
            continue
        m = SOFT.match(line)
        if m and not SOFT.match(f"0: bl 0x0 <{func}>"):  # calls between soft-float routines are not sites
            sites[func]["soft-float call " + m.group("target").split("::")[-1]] += 1
    bad = []
    print(f"float-sites: {len(sites)} functions execute floating point in {os.path.relpath(elf)}")
    for f in sorted(sites, key=lambda f: (owner(f), f)):
        o = owner(f)
        why = next((w for k, w in ALLOWED.items() if f"::{k}" in f), None)
        if o == "muir" and why is None:
            bad.append(f)
        tag = {"muir": "muir", "firmware": "firmware", "other": "other crates"}[o]
        n = sum(sites[f].values())
        print(f"  [{tag}] {f}: {n} ({', '.join(f'{k} {v}' for k, v in sites[f].most_common(4))})"
              + (f" -- allowed: {why}" if why else ""))
    if bad:
        print(f"float-sites: {len(bad)} muir functions outside the allowed list execute float: {bad}")
        return 1
    print("float-sites: no float on muir's inference path")
    return 0


if __name__ == "__main__":
    sys.exit(main())
