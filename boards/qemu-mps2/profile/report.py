"""Aggregates a pcprof.c dump: instructions per function, then the hottest straight-line regions
(loop bodies) with their instructions, then (with ELF and MACS) instructions and MACs per
instruction by kernel family. Usage: report.py PCS SYMS DISASSEMBLY [ELF MACS]

MACS is the output of `muir macs --config muir-slim --size WxH` (its `family:` rows). Families
come from the inlined call chain of each executed address (llvm-addr2line, the firmware's debug
information): the innermost frame that belongs to a family's kernel names it (building blocks
such as dot products are looked through), so a dot product inlined into the correlation lookup
counts as correlation and one inside a convolution as convolution."""
import bisect
import os
import re
import subprocess
import sys

# (family, substrings of a frame's function path), checked innermost frame first.
FAMILIES = [
    ("convolutions", ("kernels::conv::", "encoder::run_conv")),
    ("attention", ("kernels::attention::", "muir_mve_aggregate")),
    ("correlation", ("kernels::corr::", "refine::lookup_row")),
    ("upsampling", ("kernels::upsample::", "refine::upsample")),
    ("full-resolution refinement", ("kernels::fullres::",)),
    ("instance norm", ("kernels::norm::",)),
    ("element-wise (GRU gates, residuals, resampling)", ("kernels::eltwise::", "kernels::resample::", "refine::gru08", "refine::gru16")),
    ("model parse and checks", ("crc::crc32", "QuantModel::parse", "format::")),
]


# Building blocks several families inline (dot products, integer arithmetic): skipped when looking
# for the family, so that a dot product inside the correlation lookup counts as correlation.
PRIMITIVES = ("kernels::dsp::", "kernels::mve::", "kernels..Elem", "kernels::Elem", "arith::", "core::", "compiler_builtins")


def family_of(frames):
    # The 2x2 (two pixels x two channels) dot products, the widening of their weights
    # (`muir_dsp_widen_w16`, `muir_dsp_widen_nat`), the in-place block loop (`muir_dsp_nat_block`),
    # the gathers' group copies (`muir_dsp_put_groups_i16`, `muir_dsp_widen_u8`), the short
    # epilogues' requantisation loops (`muir_dsp_requant_parts`, `muir_dsp_requant_add`) and the Helium
    # block products (`muir_mve_dots_i16`, `muir_mve_dots3_i16`, ...) exist only for the
    # convolutions.
    if any("dot2x2" in f or "widen_w16" in f or "widen_nat" in f or "nat_block" in f or "muir_dsp_put_groups" in f or "muir_dsp_widen_u8" in f or "muir_dsp_requant_" in f or "muir_mve_dots" in f for f in frames):
        return "convolutions"
    # The MGA value sums' paired loop (`dsp::aggregate`'s, not inlined) exists only for attention.
    if any("dsp::paired_sums" in f for f in frames):
        return "attention"
    for fn in frames:
        if any(p in fn for p in PRIMITIVES):
            continue
        for name, keys in FAMILIES:
            if any(k in fn for k in keys):
                return name
    return "other (engine control, shared dot products, firmware)"


def families(counts, syms, starts, elf, macs_path):
    total = sum(counts.values())
    addrs = sorted(counts)
    out = subprocess.run(["llvm-addr2line", "-e", elf, "-a", "-f", "-i", "-C"], input="\n".join(hex(a) for a in addrs),
                         capture_output=True, text=True, check=True).stdout
    chains, cur = {}, None
    lines = out.split("\n")
    i = 0
    while i < len(lines):
        line = lines[i]
        if line.startswith("0x"):
            cur = int(line, 16)
            chains[cur] = []
            i += 1
            continue
        if line and cur is not None:
            chains[cur].append(line)  # function name; the next line is its file:line
            i += 2
            continue
        i += 1
    per = {}
    for a, c in counts.items():
        frames = [f for f in chains.get(a, []) if f != "??"]
        j = bisect.bisect_right(starts, a) - 1
        if j >= 0:
            frames.append(syms[j][2])  # the symbol (assembly functions have no debug lines)
        fam = family_of(frames)
        per[fam] = per.get(fam, 0) + c
    macs = {}
    for line in open(macs_path):
        m = re.match(r"\| family: ([^|]+) \|[^|]*\| ([0-9.]+) \|", line)
        if m:
            macs[m.group(1).strip()] = float(m.group(2)) * 1e9
    print("\nby kernel family (whole run: boot and model parse included; MACs from `muir macs`):")
    print("| family | instructions | share | MACs | MAC per instruction |")
    print("|---|---:|---:|---:|---:|")
    for name, c in sorted(per.items(), key=lambda x: -x[1]):
        mac = macs.get(name)
        extra = f"{mac / 1e9:.3f} G | {mac / c:.3f}" if mac else "– | –"
        print(f"| {name} | {c:,} | {100 * c / total:.1f} % | {extra} |")
    all_macs = sum(macs.values())
    if all_macs:
        print(f"| **all** | {total:,} | 100 % | {all_macs / 1e9:.3f} G | {all_macs / total:.3f} |")


def main(pcs_path, syms_path, dis_path, elf=None, macs_path=None):
    counts = {}
    for line in open(pcs_path):
        a, c = line.split()
        counts[int(a, 16)] = int(c)
    total = sum(counts.values())
    syms = []
    for line in open(syms_path):
        parts = line.split(None, 3)
        syms.append((int(parts[0], 16) & ~1, int(parts[1], 16), parts[3].strip()))
    syms.sort()
    starts = [s[0] for s in syms]
    per_fn = {}
    for a, c in counts.items():
        i = bisect.bisect_right(starts, a) - 1
        name = syms[i][2] if i >= 0 and a < syms[i][0] + max(syms[i][1], 2) else "?"
        name = re.sub(r"::h[0-9a-f]{16}$", "", name)
        per_fn[name] = per_fn.get(name, 0) + c
    print(f"{total:,} instructions executed\n\nby function:")
    for name, c in sorted(per_fn.items(), key=lambda x: -x[1])[:int(os.environ.get("MUIR_PROFILE_TOP", "15"))]:
        print(f"  {100 * c / total:5.1f} %  {c:>15,}  {name[:110]}")

    if elf and macs_path:
        families(counts, syms, starts, elf, macs_path)

    dis = {}
    for line in open(dis_path):
        head, sep, rest = line.strip().partition(":")
        if sep and re.fullmatch(r"[0-9a-f]+", head):
            dis[int(head, 16)] = rest.strip()
    if not dis:
        return
    # Contiguous addresses executed about equally often form one region (a loop body).
    regions, cur = [], None
    for a, c in sorted(counts.items()):
        if cur and a - cur[1] <= 8 and abs(c - cur[3]) <= 0.5 * cur[3] + 10:
            cur[1], cur[2] = a, cur[2] + c
        else:
            if cur:
                regions.append(cur)
            cur = [a, a, c, c]
    if cur:
        regions.append(cur)
    print("\nhottest regions (executions of the first instruction, then the instructions):")
    for lo, hi, c, n in sorted(regions, key=lambda r: -r[2])[:int(os.environ.get("MUIR_PROFILE_REGIONS", "6"))]:
        ins = [dis[k].split()[0] for k in sorted(dis) if lo <= k <= hi]
        print(f"  {100 * c / total:5.1f} %  {lo:#x}..{hi:#x}  x{n:,}  {len(ins)} instructions: {' '.join(ins[:32])}")


if __name__ == "__main__":
    main(*sys.argv[1:6])
