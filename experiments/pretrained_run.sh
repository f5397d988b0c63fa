#!/usr/bin/env bash
# The shipped model's training run (issue 21): Argoverse 2 train + womd_mini train (GPUDrive
# JSON and ScenarioNet), `cpu` config. Prepares the caches if they are missing, then starts
# or resumes the run in experiments/pretrained_run/ (committed: config.json, data.json,
# metrics.jsonl and the newest checkpoint only), pinned to one core so the other stays free.
# The `cpu` preset (separate attribute MLPs since session 18) with pixel coordinates, the
# canonical order's channel, the map at the actor's bin as an attribute input (first and last
# layer), the nearest lane's direction as two more map channels (the `nearest_lane` layers),
# the heading mixture turned by that direction (`heading_lane_frame`) and a 50-step warm-up.
# Since session 33 both runs also read the `dataset` layers (which data set a scene comes
# from; the no-map run's only layers). The thirteenth phase (session 68) trains only the box
# MLP's weights (`train_params=box0_b,...`), from the twelfth phase's step 300 (the model
# shipped in sessions 33-67): peak learning rate 3e-3, decay over 250 steps, seed 70, 300
# steps (session 68 ran the same `scenegen train` with LD_PRELOAD of tcmalloc); the committed
# experiments/pretrained_run already holds its step 300, so move it aside first:
#   git worktree add /tmp/p12 f81cb43; mv experiments/pretrained_run runs/phase13; \
#       INIT_FROM=/tmp/p12/experiments/pretrained_run experiments/pretrained_run.sh 300 1
# Its step 300 was the shipped cpu-av2-womd in sessions 68-71 (experiments/results/README.md,
# session 68); experiments/finetune_run.sh takes it and the no-map run's last phase on to the
# model shipped since session 72 (the fourteenth to sixteenth phases). The
# location term reads no box weight, so the no-map twin needs no thirteenth phase: both
# models' location NLL is the twelfth phase's to the last digit. The no-map run's last phase
# is the twelfth: only the `dataset` layers' weights (`train_layers=dataset`), from the
# ninth phase's step 700 and the no-map run's eighth phase's step 700, the new weights at
# zero: peak learning rate 1e-3, decay over 250 steps, seed 12, 300 steps (session 33 ran
# the same `scenegen train` on both cores; the map run's twelfth phase is this script at
# commit f81cb43 with INIT_FROM=runs/phase9_700):
#   NOMAP=1 INIT_FROM=runs/nomap8_700 experiments/pretrained_run.sh 300 0
# runs/phase9_700 and runs/nomap8_700 are not committed; on a fresh clone the ninth phase is
# the package's model at commit b217040 and the no-map eighth phase the run at bff20b5:
#   git worktree add /tmp/p9 b217040; INIT_FROM=/tmp/p9/scenegen_jax/pretrained/cpu-av2-womd
#   git worktree add /tmp/n8 bff20b5; INIT_FROM=/tmp/n8/experiments/nomap_run
# The eleventh phase (session 33, the same start with every weight training, peak 3e-4,
# decay over 350 steps, seed 11, 400 steps; metrics
# experiments/results/{pretrained,nomap}_run_phase11_metrics.jsonl) got a better likelihood
# and worse samples, and was not shipped (experiments/results/README.md, session 33). The
# tenth phase went to runs/phase10_700 and runs/nomap10_700.
# The tenth phase of the model's training: session 32 started it from the ninth
# phase's step 700 (the shipped model; INIT_FROM=runs/phase9_700, a copy of that workdir;
# the ninth phase's metrics experiments/results/pretrained_run_phase9_metrics.jsonl), a
# second decay at a third of the ninth phase's peak learning rate (1e-4) with a new seed:
#   INIT_FROM=runs/phase9_700 experiments/pretrained_run.sh 700 1
# It finished the same session with a better likelihood and worse samples on womd_mini, and
# was not shipped (experiments/results/README.md, session 32).
# The ninth phase (session 31, shipped as cpu-av2-womd) started from the sixth phase's
# step 950 (`INIT_FROM=cpu-av2-womd`, then the shipped model; the new channels' weights
# start at zero and the heading MLP's last layer afresh; metrics of the sixth phase
# experiments/results/pretrained_run_decay_metrics.jsonl), with a peak learning rate of 3e-4
# and otherwise the eighth phase's schedule and seed (decay_steps=650 seed=8).
# The eighth phase (session 30, the same at the preset's peak learning rate of 1e-3, a cosine
# decay to 0 over 650 steps after the warm-up, seed 8; metrics
# experiments/results/pretrained_run_lane_frame_metrics.jsonl) learnt the headings but put
# fewer sampled vehicles on the drivable area, and was not shipped (experiments/results/
# README.md, session 30): the ninth asks whether a smaller step keeps the placement.
# The seventh phase (session 28, the same from the same start without `heading_lane_frame`,
# decay over 550 steps, seed 7, 600 steps; metrics
# experiments/results/pretrained_run_nearest_lane_metrics.jsonl) was not shipped: its samples
# were less realistic than the sixth phase's (experiments/results/README.md, sessions 28-29).
# Session 25 started the sixth phase from the fifth phase's step 425, the shipped model
# (`INIT_FROM=cpu-av2-womd`; the fifth phase went on to step 742 at a constant learning rate
# and got worse on Argoverse 2 val, experiments/results/pretrained_run_skip_metrics.jsonl),
# with a cosine decay of the learning rate to 0 over 900 steps after the warm-up, and a new
# seed (a new order of the scenes and rotations). Session 20 started the fifth phase from
# the fourth phase's step 830 (the same without attribute_map_skip; metrics
# experiments/results/pretrained_run_mapattr_metrics.jsonl),
# itself started from the third's step 350 (pretrained_run_order_metrics.jsonl), started from
# the second (pretrained_run_split_metrics.jsonl), started from the first
# (pretrained_run_shared_metrics.jsonl). A new phase starts with:
#   INIT_FROM=DIR experiments/pretrained_run.sh   (DIR: the previous phase's workdir or a
#   pretrained model; only used when experiments/pretrained_run has no checkpoint yet)
# NOMAP=1 experiments/pretrained_run.sh ... trains the same recipe without map layers (and so
# without attribute_map_input and attribute_map_skip) in experiments/nomap_run/: the model the
# shipped one is compared with by `scenegen compare` (issue 21). Its first phase went from
# scratch to step 4,142 at a constant learning rate (session 24; metrics
# experiments/results/nomap_run_const_metrics.jsonl); session 26 started its decay phase, the
# same as the shipped model's sixth, from that step 4,142 (INIT_FROM=runs/nomap_run_const4142,
# a copy of that workdir): NOMAP=1 INIT_FROM=DIR experiments/pretrained_run.sh 950 1 (its
# metrics experiments/results/nomap_run_decay_metrics.jsonl). Session 30 started the same
# schedule as the eighth phase's from that run's step 950 (INIT_FROM=runs/nomap_run_decay950,
# a copy of that workdir): NOMAP=1 INIT_FROM=DIR experiments/pretrained_run.sh 700 1. Session
# 32 started the tenth phase's schedule from that run's step 700 (INIT_FROM=runs/nomap8_700;
# its eighth phase's metrics experiments/results/nomap_run_phase8_metrics.jsonl), so that the
# two models stay at equal steps:
#   NOMAP=1 INIT_FROM=runs/nomap8_700 experiments/pretrained_run.sh 700 0
# Usage: [NOMAP=1] experiments/pretrained_run.sh [STEPS] [CORE] [MINUTES]
set -euo pipefail
cd "$(dirname "$0")/.."
STEPS=${1:-20000}
CORE=${2:-1}
MINUTES=${3:-}
BIN=.venv/bin
experiments/train_caches.sh
# Each run's last phase: for the no-map run the twelfth (the `dataset` layers' weights only,
# peak learning rate 1e-3, decay over 250 steps); for the map run the thirteenth (the box
# MLP's weights only, peak 3e-3, decay over 250 steps).
if [ -n "${NOMAP:-}" ]; then
    WORKDIR=experiments/nomap_run
    INPUTS="map_layers=dataset train_layers=dataset learning_rate=1e-3 decay_steps=250 seed=12"
else
    WORKDIR=experiments/pretrained_run
    BOX=box0_b,box0_map_w,box0_w,box1_b,box1_w,box2_b,box2_map_w,box2_w
    INPUTS="map_layers=lanes,drivable,crosswalks,nearest_lane,dataset attribute_map_input=true"
    INPUTS="$INPUTS attribute_map_skip=true heading_lane_frame=true"
    INPUTS="$INPUTS train_params=$BOX learning_rate=3e-3 decay_steps=250 seed=70"
fi
XLA_FLAGS=--xla_cpu_multi_thread_eigen=false taskset -c "$CORE" $BIN/scenegen train \
    --config cpu --set coord_channels=true order_channel=true $INPUTS \
    warmup_steps=50 ${INIT_FROM:+--init-from "$INIT_FROM"} \
    --workdir "$WORKDIR" --steps "$STEPS" --save-every 50 \
    --keep 1 --log-every 10 ${MINUTES:+--minutes "$MINUTES"} \
    --data "$PWD/runs/cache_cpu_av2_train" "$PWD/runs/cache_cpu_womdjson_train" \
    "$PWD/runs/cache_cpu_womdpkl_train"
