#!/usr/bin/env bash
# The demo: prepare the built-in Argoverse 2 logs and render real scenes.
# Usage: experiments/demo.sh DATA_ROOT OUT_DIR CONFIG
set -euo pipefail
DATA=${1:-../shared/data/av2_sensor_mini}
OUT=${2:-out/demo}
CONFIG=${3:-tiny}
BIN=.venv/bin
mkdir -p "$OUT"
echo "== prepare train and val caches ($CONFIG config)"
$BIN/scenegen prepare --source av2 --root "$DATA" --split train --out "$OUT/cache_train" --config "$CONFIG"
$BIN/scenegen prepare --source av2 --root "$DATA" --split val --out "$OUT/cache_val" --config "$CONFIG"
echo "== render real scenes at 1 m/px (cpu grid)"
$BIN/scenegen prepare --source av2 --root "$DATA" --split val --out "$OUT/cache_val_cpu" --config cpu --stride 25
$BIN/scenegen render --cache "$OUT/cache_val_cpu" --index 0 2 4 6 --out "$OUT/real/val.png"
$BIN/scenegen render --cache "$OUT/cache_val_cpu" --index 2 --rotate 45 --out "$OUT/real/val_rotated45.png"
echo "== demo outputs in $OUT"
