"""Where a train step's time goes: XLA:CPU thunk times from a `jax.profiler` trace.

    .venv/bin/python bench/profile_step.py cpu max_actors=24                 # cpu config, T = 40
    .venv/bin/python bench/profile_step.py paper grid_size=128 m_per_px=0.625 max_actors=24 \
        bptt_window=25 batch_size=1                                     # the reference's shape

Prints XLA's buffer plan of the compiled step (`memory_analysis`: the temporaries are most
of the step's peak memory), the step time (after compilation) and the thunk kinds that take
the most time (`ynn_fusion`: convolutions and dots through YNNPACK; `*_fusion`: XLA loop
fusions). Run
alone on a quiet machine. XLA_FLAGS=--xla_dump_to=DIR --xla_dump_hlo_as_text adds the HLO
that names each thunk.
"""

from __future__ import annotations

import collections
import glob
import gzip
import json
import re
import sys
import tempfile
import time

import jax
from run import peak_rss_gib
from synthetic import synthetic_batch

from scenegen_jax.config import get_config
from scenegen_jax.train.step import compile_train_step, init_state


def thunk_times(trace_dir: str) -> collections.Counter:
    """Total microseconds per thunk kind (name without its numeric suffix)."""
    path = sorted(glob.glob(f"{trace_dir}/**/*.json.gz", recursive=True))[-1]
    with gzip.open(path) as f:
        trace = json.load(f)
    events = trace["traceEvents"] if isinstance(trace, dict) else trace
    total: collections.Counter = collections.Counter()
    for e in events:
        name = e.get("name", "")
        if e.get("ph") == "X" and "dur" in e and not name.startswith(("ThunkExecutor", "$")):
            total[re.sub(r"\.\d+$", "", name)] += e["dur"]
    return total


def main() -> None:
    name, *pairs = sys.argv[1:] or ["cpu"]
    cfg = get_config(name, rotate_augment=False, **dict(p.split("=", 1) for p in pairs))
    state = init_state(cfg)
    batch = jax.device_put(synthetic_batch(cfg, cfg.train.batch_size, cfg.grid.max_actors))
    print(f"peak RSS before compiling {peak_rss_gib():.2f} GiB")
    t = time.perf_counter()
    step = compile_train_step(cfg, state, batch)
    print(f"compile {time.perf_counter() - t:.2f} s, peak RSS {peak_rss_gib():.2f} GiB")
    mem = step.memory_analysis()
    print(f"XLA buffers: temporaries {mem.temp_size_in_bytes / 2**30:.2f} GiB, arguments "
          f"{mem.argument_size_in_bytes / 2**30:.2f} GiB, outputs "
          f"{mem.output_size_in_bytes / 2**30:.2f} GiB")
    t = time.perf_counter()
    state, stats = step(state, batch)
    jax.block_until_ready(stats)
    print(f"first step {time.perf_counter() - t:.2f} s, peak RSS {peak_rss_gib():.2f} GiB")
    for _ in range(2):
        t = time.perf_counter()
        state, stats = step(state, batch)
        jax.block_until_ready(stats)
        print(f"step {time.perf_counter() - t:.3f} s")
    with tempfile.TemporaryDirectory() as d:
        jax.profiler.start_trace(d, create_perfetto_trace=True)
        state, stats = step(state, batch)
        jax.block_until_ready(stats)
        jax.profiler.stop_trace()
        total = thunk_times(d)
    print(f"thunk time {sum(total.values()) / 1e3:.0f} ms (threads overlap)")
    for kind, us in total.most_common(12):
        print(f"{us / 1e3:9.1f} ms  {kind}")


if __name__ == "__main__":
    main()
