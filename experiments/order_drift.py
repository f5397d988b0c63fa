"""How far along the canonical order each actor lands: real scenes, the model teacher forced on
them, and the model's own samples on the same maps (issue 21: why sampled scenes hold fewer
actors than real ones).

The canonical order runs over the grid's rows from the top (ahead of the ego) down, so the row
of the t-th actor measures how much of the grid the first t actors used up. For each of the
first `--steps` steps it prints the mean over scenes of: the real t-th actor's row; the row
expected under the model's location distribution at step t given the real actors before it
(teacher forced: `sample_scenes` with the real actors given records the distribution of each
given step); the expected row when the model samples the earlier actors itself; and the row of
the sampled t-th actor. It also prints actors per scene, real and sampled, why the sampled
scenes ended, and, over every real vehicle of the scenes, the share on the drivable area and
the model's teacher-forced location mass there (all vehicles on the grid, not only within
40 m as `scenegen evaluate`).

  .venv/bin/python experiments/order_drift.py --pretrained cpu-av2-womd \
      --data runs/cache_cpu_av2_val --num 32

`--index` takes the scenes by index instead (for example one log's: the Argoverse 2 training
cache holds its three logs' 156 scenes each in turn, `--index $(seq 156 5 311)`).
"""

from __future__ import annotations

import argparse
import collections

import jax
import numpy as np

from scenegen_jax.cli.common import add_model_args, load_model
from scenegen_jax.data.cache import load_cache
from scenegen_jax.eval.evaluate import real_scenes
from scenegen_jax.sampling.batch import sample_scenes
from scenegen_jax.sampling.rollout import STOP_REASONS, SamplerOptions
from scenegen_jax.scene import VEHICLE, bin_index


def _stack(trees):
    return jax.tree.map(lambda *x: np.stack(x), *trees)


def _rows(actors, cfg, steps: int) -> np.ndarray:
    """[steps] row of each of the first actors (NaN where the slot is empty)."""
    rows = np.asarray(bin_index(np.asarray(actors.position[:steps]), cfg)) // cfg.grid_size
    return np.where(np.asarray(actors.valid[:steps]), rows, np.nan)


def order_drift(params, cfg, cache, indices, steps: int, seed: int, batch: int = 8) -> dict:
    """Per-step rows (see the module docstring), each [scenes, steps], and per-scene counts,
    for the cache's scenes `indices`."""
    maps, scenes = real_scenes(cache, indices, cfg)
    options = SamplerOptions(heatmap_steps=tuple(range(cfg.max_actors)))
    row_of_bin = np.arange(cfg.grid_size**2) // cfg.grid_size
    drivable = cfg.map_channels.index("drivable_area")
    out = collections.defaultdict(list)
    key = jax.random.key(seed)
    for start in range(0, len(scenes), batch):
        chunk = scenes[start : start + batch]
        egos, given = _stack([s.ego for s in chunk]), _stack([s.actors for s in chunk])
        m = maps[start : start + batch]
        forced = jax.device_get(sample_scenes(key, params, cfg, m, egos, given, options=options))
        free = jax.device_get(sample_scenes(key, params, cfg, m, egos, first=start,
                                            options=options))
        for j, scene in enumerate(chunk):
            real = _rows(scene.actors, cfg, steps)
            out["real"].append(real)
            # A given step records the distribution of the real actor's class.
            out["teacher_forced"].append(np.where(np.isnan(real), np.nan,
                                                  forced.heatmaps[j, 0, :steps] @ row_of_bin))
            sampled = _rows(jax.tree.map(lambda x, j=j: x[j, 0], free.actors), cfg, steps)
            out["sampled"].append(sampled)
            out["expected_when_sampling"].append(np.where(
                np.isnan(sampled), np.nan, free.heatmaps[j, 0, :steps] @ row_of_bin))
            vehicle = np.asarray(scene.actors.valid & (scene.actors.cls == VEHICLE))
            on = np.asarray(m[j, ..., drivable] > 0.5).reshape(-1)
            real_bins = np.asarray(bin_index(np.asarray(scene.actors.position), cfg))
            out["vehicle_on_drivable"].extend(on[real_bins[vehicle]])
            out["vehicle_mass_on_drivable"].extend(forced.heatmaps[j, 0][vehicle] @ on)
            out["real_actors"].append(int(np.sum(scene.actors.valid)))
            out["sampled_actors"].append(int(np.sum(free.actors.valid[j, 0])))
            out["stop_reason"].append(STOP_REASONS[int(free.stop_reason[j, 0])])
    return {k: np.asarray(v) if k != "stop_reason" else v for k, v in out.items()}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model_args(p)
    p.add_argument("--data", required=True, help="prepared cache of real scenes")
    p.add_argument("--num", type=int, default=32, help="scenes spread over the cache")
    p.add_argument("--index", type=int, nargs="+", help="these scenes instead of --num")
    p.add_argument("--steps", type=int, default=8, help="steps to report")
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    cfg, params, _, _ = load_model(args)
    cache = load_cache(args.data)
    indices = (np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int)
               if args.index is None else np.asarray(args.index))
    if np.any((indices < 0) | (indices >= len(cache))):
        p.error(f"--index: {args.data} holds scenes 0 to {len(cache) - 1}")
    r = order_drift(params, cfg, cache, indices, args.steps, args.seed)
    print(f"{args.data}: {len(r['real'])} scenes; mean row of the t-th actor (0 = top)")
    print("step | real | teacher forced, expected | sampling, expected | sampled")
    for t in range(args.steps):
        cols = [np.nanmean(r[k][:, t]) for k in ("real", "teacher_forced",
                                                 "expected_when_sampling", "sampled")]
        print(f"{t} | " + " | ".join(f"{c:.1f}" for c in cols))
    print(f"actors per scene: real {r['real_actors'].mean():.1f}, "
          f"sampled {r['sampled_actors'].mean():.1f}; sampled scenes ended by "
          f"{dict(collections.Counter(r['stop_reason']))}")
    print(f"real vehicles on the drivable area: {r['vehicle_on_drivable'].mean():.3f}; the "
          f"model's location mass there, teacher forced: "
          f"{r['vehicle_mass_on_drivable'].mean():.3f} ({len(r['vehicle_on_drivable'])} vehicles)")


if __name__ == "__main__":
    main()
