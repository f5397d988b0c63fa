"""`make bench`: our train step, batched scoring and batched sampling, as JSON.

Measures on random-weight models over synthetic scenes of a fixed size (shapes, not learning,
set the cost): warm-up first (compile time reported separately), then `--repeats` timed runs;
median and spread. Waits for an idle machine before each timed run, like the PyTorch
reference's harness (`../shared/bench/torch_ref/bench.py`), and records the foreign CPU load.

  .venv/bin/python bench/run.py --config cpu --out bench/results.json

The comparison with the PyTorch reference at the reference's shapes is issue 7 (not yet here).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import statistics
import time

import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.config import get_config
from scenegen_jax.eval.nll import score_batch
from scenegen_jax.raster.map import ALL_MAP_CHANNELS
from scenegen_jax.sampling.rollout import sample_scenes
from scenegen_jax.scene import Actors, canonical_order, make_ego
from scenegen_jax.train.loop import load_trained
from scenegen_jax.train.step import Batch, crop_batch, init_state, make_train_step


def cpu_busy_fraction(seconds: float = 0.5) -> float:
    """Fraction of all cores busy over `seconds` (from /proc/stat)."""

    def read():
        with open("/proc/stat") as f:
            v = [int(x) for x in f.readline().split()[1:]]
        return sum(v), v[3] + v[4]

    t0, i0 = read()
    time.sleep(seconds)
    t1, i1 = read()
    return 1.0 - (i1 - i0) / max(t1 - t0, 1)


def wait_idle(limit: float = 0.15, timeout: float = 120.0) -> float:
    """Waits until the machine is mostly idle; returns the last busy fraction seen."""
    deadline = time.time() + timeout
    busy = cpu_busy_fraction()
    while busy > limit and time.time() < deadline:
        busy = cpu_busy_fraction()
    return busy


def synthetic_batch(cfg, b: int, n_actors: int, seed: int = 0) -> Batch:
    """b cached-layout scenes with n_actors random vehicles each and a random binary map."""
    rng = np.random.default_rng(seed)
    s = cfg.canvas_size
    canvas = (rng.random((b, s, s, len(ALL_MAP_CHANNELS))) < 0.3).astype(np.float16)
    slots = max(cfg.max_actors, n_actors)
    half = cfg.region_m / 2 - 1
    actors = []
    for _ in range(b):
        a = Actors(
            cls=rng.integers(0, 3, slots).astype(np.int32),
            position=rng.uniform(-half, half, (slots, 2)).astype(np.float32),
            size=np.tile(np.float32([1.9, 4.6]), (slots, 1)),
            heading=rng.uniform(0, 2 * np.pi, slots).astype(np.float32),
            velocity=rng.normal(0, 3, (slots, 2)).astype(np.float32),
            valid=np.arange(slots) < n_actors,
        )
        actors.append(jax.tree.map(np.asarray, canonical_order(a, cfg)))
    stacked = jax.tree.map(lambda *x: np.stack(x), *actors)
    egos = jax.tree.map(lambda *x: np.stack(x), *[make_ego(cfg)] * b)
    return Batch(canvas=canvas, actors=stacked, ego=egos)


def timed(fn, repeats: int) -> dict:
    t = time.perf_counter()
    jax.block_until_ready(fn())
    compile_s = time.perf_counter() - t
    runs, busy = [], []
    for _ in range(repeats):
        busy.append(wait_idle())
        t = time.perf_counter()
        jax.block_until_ready(fn())
        runs.append(time.perf_counter() - t)
    return {
        "compile_and_first_s": compile_s,
        "median_s": statistics.median(runs),
        "min_s": min(runs),
        "max_s": max(runs),
        "runs": len(runs),
        "busy_before_runs": max(busy),
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--config", default="cpu")
    p.add_argument("--actors", type=int, default=24, help="actors per synthetic scene")
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--out", default="bench/results.json")
    p.add_argument("--workdir", help="sample with a trained model of the same config (a random"
                   " one stops after a few actors, which flatters sampling throughput)")
    args = p.parse_args()
    cfg = get_config(args.config, max_actors=args.actors, rotate_augment=False)
    if args.workdir:
        cfg = load_trained(args.workdir)[0].replace(max_actors=args.actors, rotate_augment=False)
    state = init_state(cfg)
    results = {"config": cfg.name, "grid": cfg.grid_size, "hidden": cfg.hidden,
               "actors_per_scene": args.actors, "steps_per_scene": args.actors + 1,
               "machine": platform.processor() or platform.machine(), "cpus": os.cpu_count(),
               "jax": jax.__version__, "devices": [str(d) for d in jax.devices()]}

    b = cfg.batch_size
    batch = jax.device_put(synthetic_batch(cfg, b, args.actors))
    step = make_train_step(cfg)
    holder = {"state": state}

    def train():
        holder["state"], stats = step(holder["state"], batch)
        return stats["loss"]

    r = timed(train, args.repeats)
    r["scenes_per_s"] = b / r["median_s"]
    results[f"train_step_B{b}"] = r

    score = jax.jit(lambda p, bt: score_batch(p, bt, cfg))
    for bs in (1, 8):
        sb = jax.device_put(synthetic_batch(cfg, bs, args.actors, seed=1))
        r = timed(lambda sb=sb: score(holder["state"].params, sb)["class"], args.repeats)
        r["scenes_per_s"] = bs / r["median_s"]
        results[f"score_B{bs}"] = r

    params = holder["state"].params
    if args.workdir:
        params = load_trained(args.workdir)[1].params
    for bs in (1, 32):
        sb = synthetic_batch(cfg, bs, 0, seed=2)
        maps, scenes = crop_batch(sb, jnp.zeros(bs), cfg)
        counter = iter(range(10**6))

        def sample(m=maps, s=scenes, c=counter):
            return sample_scenes(jax.random.key(next(c)), params, cfg, m, s.ego).actors.valid

        r = timed(sample, args.repeats)
        r["scenes_per_s"] = bs / r["median_s"]
        results[f"sample_B{bs}_M{cfg.proposals}"] = r
    results["peak_rss_gib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(results, f, indent=1)
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
