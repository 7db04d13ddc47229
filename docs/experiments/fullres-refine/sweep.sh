#!/bin/bash
cd "$(dirname "$0")/../../.."
run() { SET=train QUIET=1 nice -n 5 python3 docs/experiments/fullres-refine/proto.py runs/refine/r1000 "$@" | tail -1; }
for w in 5 7 11 13; do run win=$w; done
run cr=2
for c in 0 1 4 8; do run curv=$c; done
for k in 1 3 4; do run k=$k; done
run rmax=4; run rmax=12; run rmin=1; run rmin=3
run lam=0.5; run lam=1
