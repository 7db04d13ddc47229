#!/usr/bin/env bash
# Trains on a leased GPU machine inside its device-time budget (docs/training.md, "On a leased GPU").
# A lease is short (15 min of device time, 10 min per command, machine start included), so the run is
# one prepared command: fail fast, then train for a fixed wall-clock budget, then hand the files back.
#
#   here:   bash scripts/device-train.sh prepare
#             copies the texture photographs (left views of ../shared/data/nogt; ../shared does not
#             travel) into .device-data/, which git ignores; the run tool carries it
#   there:  bash scripts/device-train.sh run BUDGET_S [muir.train options]
#             a 12-step CUDA smoke run (about a minute), then muir.train --time-budget BUDGET_S with
#             the given options; model, log.csv, loss.png, args.json and train.log land in $OUT, the
#             model cut into 15 MiB parts (files come back at 16 MiB at most)
#   here:   bash scripts/device-train.sh collect FILES_AT RUN_DIR
#             joins the parts into RUN_DIR/model.safetensors, checks its SHA-256, copies the logs
#
# Defaults for `run` (override by repeating the option): --config muir-slim --batch 16 --crop 128x320
# --workers (cores - 2) --log-every 50 --ckpt-every 100000. Outside a lease, OUT=dir and --device cpu
# try the same path on this machine.
set -euo pipefail
cd "$(dirname "$0")/.."
PY=${PYTHON:-python3}

usage() { sed -n '2,18p' "$0" | sed 's/^# \{0,1\}//'; }

case "${1:-}" in
prepare)
    src=../shared/data/nogt
    [[ -d $src ]] || { echo "error: $src not found (run from a checkout with ../shared beside it)" >&2; exit 1; }
    rm -rf .device-data/nogt
    n=0
    for f in "$src"/*/left.png; do
        d=.device-data/nogt/$(basename "$(dirname "$f")")
        mkdir -p "$d" && cp "$f" "$d/left.png"
        n=$((n + 1))
    done
    echo "copied $n left views into .device-data/nogt ($(du -sh .device-data | cut -f1)); carry [\".device-data\"]" >&2
    ;;
run)
    shift
    [[ $# -ge 1 && $1 =~ ^[0-9]+$ ]] || { usage >&2; exit 2; }
    budget=$1; shift
    out=${OUT:?set OUT to the folder that comes back (the run tool sets it)}
    [[ -d .device-data/nogt ]] || { echo "error: .device-data/nogt missing: run 'prepare' here and carry it" >&2; exit 1; }
    export MUIR_NOGT_DIR=$PWD/.device-data/nogt PYTHONPATH=$PWD/python${PYTHONPATH:+:$PYTHONPATH} PYTHONUNBUFFERED=1
    workers=$(( $(nproc) > 3 ? $(nproc) - 2 : 1 ))
    log=$out/train.log
    t0=$(date +%s)
    {
        echo "== $(date -u +%FT%TZ) $(git rev-parse --short HEAD 2>/dev/null || echo '?') budget ${budget}s"
        nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader 2>/dev/null || echo "no nvidia-smi"
        "$PY" -c "import torch; print('torch', torch.__version__, 'cuda', torch.cuda.is_available())"
        echo "== smoke: 12 steps"
        "$PY" -m muir.train "$@" --out /tmp/muir-smoke --steps 12 --batch 2 --crop 64x128 --log-every 4 \
            --ckpt-every 100000 --workers 2
        spent=$(( $(date +%s) - t0 ))
        echo "== train: $((budget - spent))s left of the budget"
        "$PY" -m muir.train --out /tmp/muir-run --config muir-slim --batch 16 --crop 128x320 \
            --workers "$workers" --log-every 50 --ckpt-every 100000 --steps 1000000 "$@" \
            --time-budget $((budget - spent))
        (cd /tmp/muir-run && sha256sum model.safetensors)
    } 2>&1 | tee "$log"
    cp /tmp/muir-run/{args.json,log.csv,loss.png} "$out"/
    split -b 15M -d /tmp/muir-run/model.safetensors "$out/model.safetensors.part"
    ls -l "$out" >&2
    ;;
collect)
    [[ $# -eq 3 ]] || { usage >&2; exit 2; }
    from=$2 run=$3
    mkdir -p "$run"
    cat "$from"/model.safetensors.part* >"$run/model.safetensors"
    cp "$from"/{args.json,log.csv,loss.png,train.log} "$run"/
    want=$(grep -E '^[0-9a-f]{64}  model.safetensors$' "$run/train.log" | tail -1 | cut -d' ' -f1)
    got=$(sha256sum "$run/model.safetensors" | cut -d' ' -f1)
    [[ -n $want && $want == "$got" ]] || { echo "error: SHA-256 mismatch ($got, log says ${want:-nothing})" >&2; exit 1; }
    PYTHONPATH=python "$PY" -c "import sys; from muir.checkpoint import load_model; load_model(sys.argv[1])" "$run/model.safetensors"
    echo "ok: $run/model.safetensors; evaluate with" >&2
    echo "  PYTHONPATH=python python -m muir.evaluate --model $run/model.safetensors --name device --out $run/eval --vis 0" >&2
    ;;
-h | --help) usage ;;
*) usage >&2; exit 2 ;;
esac
