#!/usr/bin/env bash
# The shipped model's training run (issue 21): Argoverse 2 train + womd_mini train (GPUDrive
# JSON and ScenarioNet), `cpu` config. Prepares the caches if they are missing, then starts
# or resumes the run in experiments/pretrained_run/ (committed: config.json, data.json,
# metrics.jsonl and the newest checkpoint only), pinned to one core so the other stays free.
# Usage: experiments/pretrained_run.sh [STEPS] [CORE] [MINUTES]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-20000}
CORE=${2:-1}
MINUTES=${3:-}
SHARED=../shared/data
BIN=.venv/bin
prep() {  # SOURCE ROOT SPLIT OUT [prepare options]
    [ -f "$4/meta.json" ] || $BIN/scenegen prepare --source "$1" --root "$2" --split "$3" \
        --out "$4" --config cpu --workers 2 "${@:5}"
}
prep av2 "$SHARED/av2_sensor_mini" train runs/cache_cpu_av2_train --stride 1
prep womd_json "$SHARED/womd_mini/gpudrive_json" train runs/cache_cpu_womdjson_train
prep scenarionet "$SHARED/womd_mini/scenarionet" train runs/cache_cpu_womdpkl_train
XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c "$CORE" $BIN/scenegen train \
    --config cpu --workdir experiments/pretrained_run --steps "$STEPS" --save-every 50 \
    --keep 1 --log-every 10 ${MINUTES:+--minutes "$MINUTES"} \
    --data "$PWD/runs/cache_cpu_av2_train" "$PWD/runs/cache_cpu_womdjson_train" \
    "$PWD/runs/cache_cpu_womdpkl_train"
