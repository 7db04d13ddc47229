#!/usr/bin/env bash
# Ships a trained float model as the default `muir-slim` and re-makes everything that depends on
# it, in order:
#   1. models/muir-slim.safetensors      <- the given model file
#   2. models/muir-slim.muirq + .calib.md and models/muir-slim-wide.muirq + .calib.md (`muir quantize`,
#      the calibration command of models/README.md; the second with --wide-trunk), and their
#      .formats.json (`muir info --json`: the slot formats python/muir/qat.py reads)
#   3. host-tests/fixtures/golden/shipped* and fullres-teddy* (float and refinement parity fixtures)
#   4. boards/qemu-mps2 expected CRCs     (MUIR_UPDATE_EXPECTED=1 cargo test --test firmware)
#   5. models/muir-slim.eval.{json,md}, models/muir-slim-fixed.eval.json,
#      models/muir-slim-wide-fixed.eval.json, models/sgbm.eval.json, docs/results/*_middlebury*.png
#      (`python -m muir.evaluate --sgbm` on the 11 held-out scenes of muir.split, the float model
#      and the fixed-point engine on both blobs, all with the full-resolution refinement)
# What it does not touch: the figures quoted in README.md / models/README.md (re-measure them with
# the commands given there) and the fixed_vs_float regression bounds.
#
# Usage: bash scripts/ship-model.sh RUN_DIR/model.safetensors
# Needs ../shared/data, PyTorch (python/README.md) and, for step 4, qemu-system-arm.
set -euo pipefail
cd "$(dirname "$0")/.."

if [[ $# -ne 1 || "$1" == -h || "$1" == --help ]]; then
    sed -n '2,16p' "$0" | sed 's/^# \{0,1\}//'
    [[ $# -eq 1 ]] && exit 0 || exit 2
fi
src=$1
[[ -f "$src" ]] || { echo "error: no model file $src" >&2; exit 1; }
data=../shared/data
[[ -d "$data/nogt" ]] || { echo "error: $data/nogt not found (calibration pairs)" >&2; exit 1; }

step() { echo "== $*" >&2; }

step "1/5 model"
cargo build --release --bin muir
./target/release/muir info --model "$src" >/dev/null
[[ "$(realpath "$src")" == "$(realpath models/muir-slim.safetensors)" ]] || cp "$src" models/muir-slim.safetensors

step "2/5 quantised blob"
bash scripts/quantize-shipped.sh models/muir-slim.safetensors models/muir-slim.muirq models/muir-slim.calib.md
bash scripts/quantize-shipped.sh models/muir-slim.safetensors models/muir-slim-wide.muirq models/muir-slim-wide.calib.md --wide-trunk
for b in muir-slim muir-slim-wide; do   # the slot formats the twin's QAT reads (python/muir/qat.py)
    cargo run --release --quiet --bin muir -- info --model "models/$b.muirq" --json > "models/$b.formats.json"
done

step "3/5 float parity fixture"
PYTHONPATH=python python -m muir.golden --shipped models/muir-slim.safetensors
PYTHONPATH=python python -m muir.golden --fullres models/muir-slim.safetensors

step "4/5 firmware CRCs"
MUIR_UPDATE_EXPECTED=1 cargo test --release --test firmware

step "5/5 evaluation"
out=runs/eval/shipped
rm -rf "$out"
PYTHONPATH=python python -m muir.evaluate --model models/muir-slim.safetensors --name muir-slim --sgbm --out "$out" \
    --blob models/muir-slim.muirq --blob-name muir-slim-fixed \
    --blob models/muir-slim-wide.muirq --blob-name muir-slim-wide-fixed \
    --vis middlebury2003/teddy,middlebury2005/Art,middlebury2005/Books
cp "$out/muir-slim.json" models/muir-slim.eval.json
cp "$out/muir-slim-fixed.json" models/muir-slim-fixed.eval.json
cp "$out/muir-slim-wide-fixed.json" models/muir-slim-wide-fixed.eval.json
cp "$out/sgbm.json" models/sgbm.eval.json
sed 's|model=[^,]*/models/muir-slim\.|model=models/muir-slim.|g' "$out/results.md" > models/muir-slim.eval.md
for f in docs/results/*_middlebury*.png; do      # docs/results/<method>_<data set>_<scene>.png
    b=$(basename "$f")
    method=${b%%_middlebury*}
    cp "$out/vis/$method/${b#"${method}"_}" "$f"
done
step "done: now re-measure the README figures (README.md, models/README.md) and commit"
