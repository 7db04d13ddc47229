#!/usr/bin/env python3
"""What the core crate (crates/muir) would publish: the files `cargo package --list` names, their
total size against crates.io's 10 MiB limit, and no model or image files among them.
Usage: python3 scripts/package-size.py (from anywhere; exit status 1 on a violation)."""
import os
import subprocess
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CRATE = os.path.join(ROOT, "crates", "muir")
LIMIT = 10 * 1024 * 1024
FORBIDDEN = (".muirq", ".safetensors", ".png", ".pfm", ".gray", ".pt")

out = subprocess.run(["cargo", "package", "-p", "muir", "--list", "--allow-dirty", "--offline"], cwd=ROOT,
                     capture_output=True, text=True)
if out.returncode != 0:
    sys.exit(f"package-size: cargo package --list failed:\n{out.stderr}")
files = [f for f in out.stdout.split() if f]
# Cargo.toml and Cargo.lock are generated in the package; the listed originals stand in for them.
sizes = {f: os.path.getsize(os.path.join(CRATE, f)) for f in files if os.path.exists(os.path.join(CRATE, f))}
total = sum(sizes.values())
bad = [f for f in files if f.endswith(FORBIDDEN)]
print(f"core package muir: {len(files)} files, {total / 1024:.1f} KiB uncompressed (limit {LIMIT // (1024 * 1024)} MiB)")
if bad or total > LIMIT:
    sys.exit(f"package-size: {'model or image files: ' + ', '.join(bad) if bad else 'over the limit'}")
