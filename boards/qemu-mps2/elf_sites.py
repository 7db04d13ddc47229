"""Shared by panic-sites.py and float-sites.py: the firmware ELF's disassembly walked function by
function, and which part of the program a function belongs to."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
from typing import Iterator

BOARD = os.path.dirname(os.path.abspath(__file__))
DEFAULT_ELF = os.path.join(BOARD, "target", "thumbv7em-none-eabihf", "release", "stereo")
FUNC = re.compile(r"^[0-9a-f]+ <(?P<name>[^>]+)>:$")


def disassembly(tool_name: str, argv: list[str], missing_tool: str) -> tuple[str, list[str]] | int:
    """(ELF path, disassembly lines) of `argv[0]` or the qemu-mps2 release build; or the exit code
    after a note: 0 without llvm-objdump (`missing_tool` says what is then not done), 2 without the
    ELF."""
    elf = argv[0] if argv else DEFAULT_ELF
    tool = shutil.which("llvm-objdump")
    if tool is None:
        print(f"{tool_name}: llvm-objdump not found (apt-get install llvm); {missing_tool}")
        return 0
    if not os.path.exists(elf):
        print(f"{tool_name}: {elf} not found (build the firmware first: run-tests.sh)", file=sys.stderr)
        return 2
    out = subprocess.run([tool, "-d", "--no-show-raw-insn", "-C", elf], capture_output=True, text=True, check=True).stdout
    return elf, out.splitlines()


def instructions(lines: list[str]) -> Iterator[tuple[str, str]]:
    """(containing function, line) for every line that is not a function label."""
    func = "?"
    for line in lines:
        m = FUNC.match(line)
        if m:
            if not m.group("name").startswith("$"):  # $t/$d/$a: Arm mapping symbols, not functions
                func = m.group("name")
            continue
        yield func, line


def owner(func: str) -> str:
    """'muir' (engine, kernels, format), 'firmware' (the board's own code, with what it inlines) or
    'other' (core, compiler_builtins, other crates)."""
    if "muir::" in func or "muir.." in func:
        return "muir"
    if func.startswith(("stereo::", "main", "__cortex_m_rt_main", "kernels::")):
        return "firmware"
    return "other"
