#!/usr/bin/env bash
# Training throughput of two processes x one core (jax.distributed, coordinator on
# 127.0.0.1) against one process x one core, `cpu` config, the same global batch of 4.
# Run on an idle machine (pause any training: pkill -STOP -f "scenegen train"). Prints the
# scenes per second of each logged block after the first (which holds the compilation).
# Usage: experiments/two_process_speed.sh [CACHE] [STEPS]
set -euo pipefail
cd "$(dirname "$0")/.."
CACHE=${1:-$PWD/runs/cache_cpu_av2_train}
STEPS=${2:-16}
OUT=$(mktemp -d)
export XLA_FLAGS=--xla_cpu_multi_thread_eigen=false JAX_PLATFORMS=cpu SCENEGEN_COMPILE_CACHE=off
ARGS="--config cpu --data $CACHE --steps $STEPS --log-every 4 --save-every 100000"
taskset -c 0 .venv/bin/scenegen train $ARGS --workdir "$OUT/one" > "$OUT/one.log" 2>&1
PAIR="--distributed --coordinator 127.0.0.1:$((20000 + RANDOM % 10000)) --num-processes 2"
taskset -c 1 .venv/bin/scenegen train $ARGS --workdir "$OUT/two" $PAIR --process-id 1 \
    > "$OUT/two_1.log" 2>&1 &
taskset -c 0 .venv/bin/scenegen train $ARGS --workdir "$OUT/two" $PAIR --process-id 0 \
    > "$OUT/two_0.log" 2>&1
wait
.venv/bin/python - "$OUT" <<'PY'
import json, sys
rates = {}
for run in ("one", "two"):
    rows = [json.loads(line) for line in open(f"{sys.argv[1]}/{run}/metrics.jsonl")][1:]
    rates[run] = sum(r["steps_per_s"] for r in rows) / len(rows) * 4  # global batch 4
print(json.dumps({"scenes_per_s_one_process": rates["one"],
                  "scenes_per_s_two_processes": rates["two"],
                  "ratio": rates["two"] / rates["one"]}))
PY
rm -rf "$OUT"
