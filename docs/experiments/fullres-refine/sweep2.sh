#!/bin/bash
cd "$(dirname "$0")/../../.."
run() { SET=train QUIET=1 nice -n 5 python3 docs/experiments/fullres-refine/proto.py runs/refine/r1000 k=3 rmin=3 rmax=12 "$@" | tail -1; }
run
run occ=0.5
run occ=1.5
run bil=10
run bil=20
run bil=20 bilmin=0.1
