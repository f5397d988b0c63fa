#!/usr/bin/env bash
# The three training caches of the shipped model's runs (issue 21), `cpu` config, under runs/:
# Argoverse 2 train (stride 1), womd_mini train as GPUDrive JSON and as ScenarioNet. Prepares
# each one that is missing (about 3 minutes in all on 2 cores); used by
# experiments/pretrained_run.sh and experiments/finetune_run.sh.
set -euo pipefail
cd "$(dirname "$0")/.."
SHARED=../shared/data
prep() {  # SOURCE ROOT SPLIT OUT [prepare options]
    [ -f "$4/meta.json" ] || .venv/bin/scenegen prepare --source "$1" --root "$2" --split "$3" \
        --out "$4" --config cpu --workers 2 "${@:5}"
}
prep av2 "$SHARED/av2_sensor_mini" train runs/cache_cpu_av2_train --stride 1
prep womd_json "$SHARED/womd_mini/gpudrive_json" train runs/cache_cpu_womdjson_train
prep scenarionet "$SHARED/womd_mini/scenarionet" train runs/cache_cpu_womdpkl_train
