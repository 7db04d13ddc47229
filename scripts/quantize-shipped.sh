#!/usr/bin/env bash
# The shipped calibration command (models/README.md, "Quantisation"), written once for
# scripts/ship-model.sh and scripts/check-candidate.sh: four real pairs without ground truth
# (none an evaluation scene) at full size (KITTI frames 1242 px wide: the disparity-driven slots must
# see the largest disparities and farthest proposals), the default rule (percentile for 8-bit slots,
# the largest value for 16-bit ones).
#
# Usage: bash scripts/quantize-shipped.sh MODEL.safetensors OUT.muirq REPORT.md [--wide-trunk]
#        (--wide-trunk: conv1 .. layer2 activations in i16, the models/<name>-wide.muirq blobs)
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ $# -lt 3 || $# -gt 4 || ( $# -eq 4 && "$4" != --wide-trunk ) ]]; then
    sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
data=../shared/data
[[ -d "$data/nogt" ]] || { echo "error: $data/nogt not found (calibration pairs)" >&2; exit 1; }
cargo build --release --bin muir
./target/release/muir quantize --model "$1" \
    --calib "$data/nogt/oakd_desk" --calib "$data/nogt/oakd_living_room" \
    --calib "$data/nogt/kitti2015_000051_11" --calib "$data/nogt/oakd_stairs" \
    --out "$2" --report "$3" ${4:+"$4"}
