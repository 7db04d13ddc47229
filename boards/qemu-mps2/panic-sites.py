#!/usr/bin/env python3
"""Counts the branches into panic paths in a firmware ELF (issue #22 item 3): every `bl`/`b`
whose target is a `core::panicking` / slice-index / unwrap-failure function, grouped by the kind of
panic and by the function that contains the branch (muir's inference path, the firmware's own code,
or core/other crates). A measurement, not a gate: a panic on a camera module is a reset loop, and
this shows how many are still reachable in the shipped code.

    python3 boards/qemu-mps2/panic-sites.py [ELF]   # default: the qemu-mps2 release build
    python3 boards/qemu-mps2/panic-sites.py --max-muir 0 [ELF]   # CI: fails if muir's code has any

Needs llvm-objdump (Debian `llvm`); prints a note and exits 0 without it.
"""
from __future__ import annotations

import collections
import os
import re
import sys

from elf_sites import disassembly, instructions, owner

BRANCH = re.compile(r"^\s*[0-9a-f]+:\s+(?:bl|b|b\.w|blx)\s+0x[0-9a-f]+ <(?P<target>[^>]+)>")
KINDS = [
    ("bounds check", ("panic_bounds_check", "slice_start_index", "slice_end_index", "slice_index_order", "slice_index_fail",
                      "str_index_overflow", "copy_from_slice::len_mismatch", "len_mismatch_fail")),
    ("division by zero / overflow", ("panic_const_div", "panic_const_rem", "panic_const_add", "panic_const_sub",
                                     "panic_const_mul", "panic_const_neg", "panic_const_shl", "panic_const_shr")),
    ("unwrap / expect", ("unwrap_failed", "expect_failed", "option::unwrap", "unwrap_none")),
    ("panic_fmt / panic!", ("panic_fmt", "panicking::panic", "panic_display", "panic_nounwind", "assert_failed")),
]


def kind_of(target: str):
    for name, keys in KINDS:
        if any(k in target for k in keys):
            return name
    return None


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    max_muir = None
    if argv[:1] == ["--max-muir"] and len(argv) >= 2:
        max_muir, argv = int(argv[1]), argv[2:]
    got = disassembly("panic-sites", argv, "not counted")
    if isinstance(got, int):
        return got
    elf, lines = got
    by_kind = collections.Counter()
    by_owner = collections.Counter()
    names = {"muir": "muir (engine, kernels, format)", "firmware": "firmware (stereo.rs, with what it inlines)",
             "other": "core / compiler_builtins / other crates"}
    for func, line in instructions(lines):
        m = BRANCH.match(line)
        if not m:
            continue
        k = kind_of(m.group("target"))
        if k is None or kind_of(func) is not None:  # branches between panic helpers are not sites
            continue
        by_kind[k] += 1
        by_owner[names[owner(func)]] += 1
    total = sum(by_kind.values())
    print(f"panic-sites: {total} branches into panic paths in {os.path.relpath(elf)}")
    for k, n in by_kind.most_common():
        print(f"  by kind: {k}: {n}")
    for o, n in by_owner.most_common():
        print(f"  by containing function: {o}: {n}")
    muir = by_owner[names["muir"]]
    if max_muir is not None and muir > max_muir:
        print(f"panic-sites: FAILED: {muir} branches into panic paths from muir's code (at most {max_muir})")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
