"""Aggregates a pcprof.c dump: instructions per function, then the hottest straight-line regions
(loop bodies) with their instructions. Usage: report.py PCS SYMS DISASSEMBLY"""
import bisect
import re
import sys


def main(pcs_path, syms_path, dis_path):
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
    for name, c in sorted(per_fn.items(), key=lambda x: -x[1])[:15]:
        print(f"  {100 * c / total:5.1f} %  {c:>15,}  {name[:110]}")

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
    for lo, hi, c, n in sorted(regions, key=lambda r: -r[2])[:6]:
        ins = [dis[k].split()[0] for k in sorted(dis) if lo <= k <= hi]
        print(f"  {100 * c / total:5.1f} %  {lo:#x}..{hi:#x}  x{n:,}  {len(ins)} instructions: {' '.join(ins[:32])}")


if __name__ == "__main__":
    main(*sys.argv[1:4])
