#!/usr/bin/env bash
# The demo: prepare the built-in Argoverse 2 logs, render real scenes, train the tiny model
# for a few minutes, score the validation log and sample new scenes on its maps; then, with
# the pretrained model shipped in the package, sample and score on Argoverse 2 and Waymo
# (womd_mini) validation maps without any training.
# Usage: experiments/demo.sh DATA_ROOT OUT_DIR CONFIG [MINUTES] [WOMD_ROOT]
set -euo pipefail
DATA=${1:-../shared/data/av2_sensor_mini}
OUT=${2:-out/demo}
CONFIG=${3:-tiny}
MINUTES=${4:-3}
WOMD=${5:-$(dirname "$DATA")/womd_mini}
BIN=.venv/bin
mkdir -p "$OUT"

echo "== 1. prepare train and val caches ($CONFIG config)"
$BIN/scenegen prepare --source av2 --root "$DATA" --split train --out "$OUT/cache_train" --config "$CONFIG" --stride 1
$BIN/scenegen prepare --source av2 --root "$DATA" --split val --out "$OUT/cache_val" --config "$CONFIG" --stride 1

echo "== 2. render real validation scenes (cpu grid, 1.25 m/px)"
$BIN/scenegen prepare --source av2 --root "$DATA" --split val --out "$OUT/cache_val_cpu" --config cpu --stride 25
$BIN/scenegen render --cache "$OUT/cache_val_cpu" --index 0 2 4 6 --out "$OUT/real/val.png"
$BIN/scenegen render --cache "$OUT/cache_val_cpu" --index 2 --rotate 45 --out "$OUT/real/val_rotated45.png"

echo "== 3. train the $CONFIG model for $MINUTES minutes (resumes if run again)"
$BIN/scenegen train --config "$CONFIG" --data "$OUT/cache_train" --workdir "$OUT/model" \
    --steps 100000 --minutes "$MINUTES" --save-every 50 --log-every 10

echo "== 4. score the validation log"
$BIN/scenegen score --workdir "$OUT/model" --data "$OUT/cache_val" --out "$OUT/val_scores.csv"

echo "== 5. sample scenes on validation maps"
$BIN/scenegen sample --workdir "$OUT/model" --data "$OUT/cache_val" --num 8 --out "$OUT/samples" \
    --heatmaps

# `scenegen models` prints one line per shipped model: "NAME<TAB>config CONFIG, grid ...".
MODEL_LINE=$($BIN/scenegen models | head -n 1)
PRETRAINED=$(printf '%s\n' "$MODEL_LINE" | cut -f 1)
if [ -n "$PRETRAINED" ]; then
    PCONFIG=$(printf '%s\n' "$MODEL_LINE" | cut -f 2 | sed -n 's/^config \([^,]*\),.*/\1/p')
    echo "== 6. pretrained model $PRETRAINED ($PCONFIG config): val caches of Argoverse 2 and Waymo"
    $BIN/scenegen prepare --source av2 --root "$DATA" --split val --out "$OUT/pre_av2_val" \
        --config "$PCONFIG" --stride 10
    $BIN/scenegen prepare --source womd_json --root "$WOMD/gpudrive_json" --split val \
        --out "$OUT/pre_womd_val" --config "$PCONFIG" --stride 30
    echo "== 7. sample scenes from the pretrained model on both sources' val maps"
    for SRC in av2 womd; do
        $BIN/scenegen sample --pretrained "$PRETRAINED" --data "$OUT/pre_${SRC}_val" --num 8 \
            --out "$OUT/pretrained_samples_$SRC"
    done
    echo "== 8. score the val scenes and render the least likely ones"
    $BIN/scenegen score --pretrained "$PRETRAINED" --data "$OUT/pre_av2_val" "$OUT/pre_womd_val" \
        --out "$OUT/pretrained_val_scores.csv" --top-k 4 --render "$OUT/pretrained_least_likely"
fi

echo "== demo outputs in $OUT: real/*.png, val_scores.csv, samples/, pretrained_*"
