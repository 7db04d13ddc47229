#!/usr/bin/env bash
# The shipped calibration command (models/README.md, "Quantisation"), written once for
# scripts/ship-model.sh and scripts/check-candidate.sh: four real pairs without ground truth
# (none an evaluation scene), cropped to at most 320x240, the default percentile rule.
#
# Usage: bash scripts/quantize-shipped.sh MODEL.safetensors OUT.muirq REPORT.md [--wide-trunk]
#        (--wide-trunk: conv1 .. layer2 activations in i16, the models/<name>-wide.muirq blobs)
set -euo pipefail
cd "$(dirname "$0")/.."
if [[ $# -lt 3 || $# -gt 4 || ( $# -eq 4 && "$4" != --wide-trunk ) ]]; then
    sed -n '2,7p' "$0" | sed 's/^# \{0,1\}//' >&2
    exit 2
fi
data=../shared/data
[[ -d "$data/nogt" ]] || { echo "error: $data/nogt not found (calibration pairs)" >&2; exit 1; }
cargo build --release --bin muir
./target/release/muir quantize --model "$1" \
    --calib "$data/nogt/oakd_desk" --calib "$data/nogt/oakd_living_room" \
    --calib "$data/nogt/kitti2015_000051_11" --calib "$data/nogt/oakd_stairs" \
    --max-size 320x240 --out "$2" --report "$3" ${4:+"$4"}
