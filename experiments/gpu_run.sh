#!/usr/bin/env bash
# The map model and its no-map twin trained side by side on one GPU (issue 21, session 36):
# the shipped model's inputs (pixel coordinates, the canonical order's channel, the map
# layers with the nearest lane's direction and the `dataset` planes, the map at the actor's
# bin in the attribute MLPs, the heading mixture in the lane's frame) all present from step 0,
# at batch 8, and the same recipe with the `dataset` planes as its only layers. Each process
# gets 40 % of the GPU's memory; on the lent H200 the pair ran at 5.5-6.7 steps/s each.
#
# Session 36 ran the same two `scenegen train` commands in two calls on the workplace's lent
# H200 (jax 0.11.2 there), from a wrapper that also timed a 100-step probe first; as this
# script:
#   experiments/gpu_run.sh 1960 1e-3 21                   # from scratch, 6.4 min
#   experiments/gpu_run.sh 900 3e-4 22 runs/gpu/map runs/gpu/nomap    # fine-tune, 3.7 min
# (1960 steps was what a 100-step probe said would fit the lease's minutes; the second call
# starts a fresh optimizer from the first call's last step, `--init-from`.) Each phase warms
# up over 50 steps and then decays to 0 by a cosine over the rest.
# The lent machine has jax, flax, optax and orbax but not shapely (nor distrax, which the
# package needed until session 44): session 36 carried their cp312 wheels and the three caches
# (tar.gz, 23 MB; the data stay out of the repository) in a folder that .git/info/exclude
# ignores, installed the wheels with `pip install --no-index --no-deps --target`, and ran
# this script with PYTHONPATH and CACHES set (PY=python3, the machine's Python).
#
# Without a GPU the same recipe runs on two CPU cores, one process pinned to each
# (CORES="0 1"), at batch 4 for twice the updates per core-hour (a step of batch 8 took
# 9-11 s on one core of a Zen 5); session 59 ran the third phase so, committing the resumable checkpoints
# under experiments/step0_run/ (MINUTES bounds a call; a later call with the same arguments
# resumes it):
#   CORES="0 1" OUT_DIR=experiments/step0_run SAVE_EVERY=50 KEEP=1 MINUTES=100 BATCH=4 \
#       PY=.venv/bin/python experiments/gpu_run.sh 1000 3e-4 23 \
#       experiments/gpu_run/map experiments/gpu_run/nomap
#
# Usage: experiments/gpu_run.sh STEPS PEAK_LR SEED [INIT_MAP INIT_NOMAP]
# Env: CACHES, the folder with the `scenegen prepare --config cpu` train caches
#      cache_cpu_{av2,womdjson,womdpkl}_train (default runs; experiments/pretrained_run.sh
#      prepares them); OUT_DIR, the workdirs' parent (default runs/gpu; a workdir is resumed
#      if it has a checkpoint); PY, the Python with scenegen_jax (default: python3);
#      CORES, two CPU cores to pin the map and the no-map process to, one each, each
#      single-threaded (default: none, the GPU); SAVE_EVERY and KEEP, the checkpoints
#      (default STEPS / 4 and 4); MINUTES, a wall-time budget per process (default none);
#      BATCH, the batch size (default 8).
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=$1 LR=$2 SEED=$3
CACHES=${CACHES:-runs} OUT_DIR=${OUT_DIR:-runs/gpu} PY=${PY:-python3}
CORES=${CORES:-} SAVE_EVERY=${SAVE_EVERY:-$((STEPS / 4))} KEEP=${KEEP:-4} MINUTES=${MINUTES:-}
export XLA_PYTHON_CLIENT_MEM_FRACTION=0.4
DATA="$CACHES/cache_cpu_av2_train $CACHES/cache_cpu_womdjson_train $CACHES/cache_cpu_womdpkl_train"
SCHEDULE="batch_size=${BATCH:-8} learning_rate=$LR warmup_steps=50 decay_steps=$((STEPS - 50)) seed=$SEED"
MAP="map_layers=lanes,drivable,crosswalks,nearest_lane,dataset attribute_map_input=true"
MAP="$MAP attribute_map_skip=true heading_lane_frame=true"
read -r -a CORE <<< "$CORES"
train() {  # NAME INPUTS CORE [INIT]
    mkdir -p "$OUT_DIR"
    local pin=()
    [ -z "$3" ] || pin=(env XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c "$3")
    # shellcheck disable=SC2086  # word splitting of DATA and the --set fields is intended
    "${pin[@]}" $PY -m scenegen_jax.cli train --config cpu --data $DATA \
        --workdir "$OUT_DIR/$1" --steps "$STEPS" --save-every "$SAVE_EVERY" --keep "$KEEP" \
        --log-every 20 ${MINUTES:+--minutes "$MINUTES"} ${4:+--init-from "$4"} \
        --set coord_channels=true order_channel=true $SCHEDULE $2 > "$OUT_DIR/$1.log" 2>&1
}
train map "$MAP" "${CORE[0]:-}" "${4:-}" &
MAP_PID=$!
train nomap "map_layers=dataset" "${CORE[1]:-}" "${5:-}" &
wait $!
wait $MAP_PID
tail -n 1 "$OUT_DIR/map/metrics.jsonl" "$OUT_DIR/nomap/metrics.jsonl"
