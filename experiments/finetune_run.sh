#!/usr/bin/env bash
# The shipped model's last three phases (issue 21, session 71; MODEL_CARD.md, phases 14-16),
# from the thirteenth phase (experiments/pretrained_run) and its no-map twin
# (experiments/nomap_run). Starts or resumes each run in experiments/finetune_run/ (committed:
# config.json, data.json, metrics.jsonl and the newest checkpoint; a finished run is left as
# it is) and writes the model as a pretrained directory, OUT/a1:
#  14. every weight on womd_mini train alone: 50 warm-up steps to 3e-4, then constant, with a
#      moving average of the parameters (ema_decay=0.99, which the later phases and
#      `scenegen score` read), seed 71, 400 steps: experiments/finetune_run/map on one core,
#      the no-map twin (the `dataset` layers only) experiments/finetune_run/nomap on the other;
#  15. the box MLP alone, on the fourteenth phase's average with the thirteenth phase's box MLP
#      (experiments/interpolate.py --keep), on all three training caches, as the thirteenth
#      phase trained it: peak 3e-3, cosine decay over 250 steps, seed 71, 300 steps, both
#      cores: experiments/finetune_run/box;
#  16. no training: the thirteenth phase's heading and class MLPs in place of the fifteenth's
#      (the class MLP since session 72).
# Session 71 ran these commands (with LD_PRELOAD of tcmalloc, as here when it is installed):
# 7.2 s per step for the fourteenth phase (one core each) and 3.7 s for the fifteenth (both),
# AMD EPYC Zen 3 (AVX2). Rerun from scratch: rm -r experiments/finetune_run first.
# Usage: experiments/finetune_run.sh [OUT]   (default runs/finetune_model)
set -euo pipefail
cd "$(dirname "$0")/.."
OUT=${1:-runs/finetune_model}
BIN=.venv/bin
RUN=experiments/finetune_run
TCMALLOC=/usr/lib/x86_64-linux-gnu/libtcmalloc_minimal.so.4
[ -f "$TCMALLOC" ] && export LD_PRELOAD=$TCMALLOC
export XLA_FLAGS=--xla_cpu_multi_thread_eigen=false
experiments/train_caches.sh
AV2=$PWD/runs/cache_cpu_av2_train
WOMD="$PWD/runs/cache_cpu_womdjson_train $PWD/runs/cache_cpu_womdpkl_train"
MAP="map_layers=lanes,drivable,crosswalks,nearest_lane,dataset attribute_map_input=true"
MAP="$MAP attribute_map_skip=true heading_lane_frame=true"
BOX=(box0_b box0_map_w box0_w box1_b box1_w box2_b box2_map_w box2_w)
PHASE13=(heading0_b heading0_map_w heading0_w heading1_b heading1_w heading2_b heading2_map_w
         heading2_w class_mlp0 class_mlp1 class_mlp2)
train() {  # CORES WORKDIR INIT STEPS "SET FIELDS" CACHE...
    taskset -c "$1" $BIN/scenegen train --config cpu --set coord_channels=true \
        order_channel=true separate_attribute_mlps=true $5 warmup_steps=50 seed=71 \
        --init-from "$3" --workdir "$2" --steps "$4" --save-every 50 --keep 1 \
        --log-every 10 --data "${@:6}"
}
FT="learning_rate=3e-4 decay_steps=0 ema_decay=0.99"
train 0 $RUN/map experiments/pretrained_run 400 "$MAP $FT" $WOMD &
MAP_RUN=$!
train 1 $RUN/nomap experiments/nomap_run 400 "map_layers=dataset $FT" $WOMD &
NOMAP_RUN=$!
wait $MAP_RUN
wait $NOMAP_RUN
$BIN/python experiments/interpolate.py --start experiments/pretrained_run --tuned $RUN/map \
    --alpha 1 --keep "${BOX[@]}" --out "$OUT/box_start"
train 0,1 $RUN/box "$OUT/box_start/a1" 300 \
    "$MAP train_params=$(IFS=,; echo "${BOX[*]}") learning_rate=3e-3 decay_steps=250" \
    "$AV2" $WOMD
$BIN/python experiments/interpolate.py --start experiments/pretrained_run --tuned $RUN/box \
    --alpha 1 --keep "${PHASE13[@]}" --out "$OUT"
