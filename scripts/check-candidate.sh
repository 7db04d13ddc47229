#!/usr/bin/env bash
# Measures a trained float model against the shipped one's yardsticks without shipping it:
#   1. quantises it with the shipped calibration command (both blobs + reports in OUT_DIR)
#   2. fixed engine (u8 and wide trunk) vs float reference on the five fixed_vs_float crops (issue #4's figures)
#   3. the Middlebury evaluation of the float model (issue #3's figures) and of the fixed-point engine
#      on its blob (what the device delivers; ~3 min more), unless --no-eval
# Nothing under models/ changes; ship with scripts/ship-model.sh.
#
# Usage: bash scripts/check-candidate.sh [--no-eval] RUN_DIR/model.safetensors [OUT_DIR]
#        (OUT_DIR defaults to runs/check/<run>_<file>)
set -euo pipefail
cd "$(dirname "$0")/.."

eval_too=1
if [[ "${1:-}" == --no-eval ]]; then eval_too=0; shift; fi
if [[ $# -lt 1 || $# -gt 2 || "$1" == -h || "$1" == --help ]]; then
    sed -n '2,9p' "$0" | sed 's/^# \{0,1\}//'
    [[ $# -ge 1 && ( "$1" == -h || "$1" == --help ) ]] && exit 0 || exit 2
fi
src=$1
[[ -f "$src" ]] || { echo "error: no model file $src" >&2; exit 1; }
run=$(basename "$(dirname "$src")")
out=${2:-runs/check/${run}_$(basename "$src" .safetensors)}
mkdir -p "$out"

echo "== 1/3 quantise -> $out/model.muirq" >&2
bash scripts/quantize-shipped.sh "$src" "$out/model.muirq" "$out/calib.md"
bash scripts/quantize-shipped.sh "$src" "$out/model-wide.muirq" "$out/calib-wide.md" --wide-trunk

echo "== 2/3 fixed vs float (five crops) -> $out/fixed_vs_float.txt" >&2
MUIR_CANDIDATE_MODEL="$(realpath "$src")" MUIR_CANDIDATE_BLOB="$(realpath "$out/model.muirq")" \
    MUIR_CANDIDATE_WIDE_BLOB="$(realpath "$out/model-wide.muirq")" \
    cargo test --release --test fixed_vs_float -- --nocapture --test-threads 1 > "$out/fixed_vs_float.txt" 2>&1
grep -E '^float model|^\| |^target' "$out/fixed_vs_float.txt"

if [[ $eval_too == 1 ]]; then
    echo "== 3/3 Middlebury evaluation (float and fixed engine) -> $out/eval" >&2
    PYTHONPATH=python python -m muir.evaluate --model "$src" --name muir-slim --blob "$out/model.muirq" --blob-name muir-slim-fixed \
        --out "$out/eval" --vis 0 > "$out/eval.stdout"
    sed -n '/### headline/,/^### middlebury2003/p' "$out/eval/results.md" | grep '^|'
fi
