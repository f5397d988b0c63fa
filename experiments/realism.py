"""Realism check of sampled scenes on a split's maps (issue 5).

Compares, on the same conditioning scenes, the share of vehicle centres within 40 m of the ego
that lie on the drivable area, and the class mix, of real scenes and of SceneGen samples.

  .venv/bin/python experiments/realism.py --workdir runs/cpu_map --data runs/cache_cpu_val \
      --num 64 --out experiments/results/realism_cpu.json
"""

from __future__ import annotations

import argparse
import json
import os

import numpy as np

from scenegen_jax.data.cache import cached_scene, load_cache
from scenegen_jax.eval.evaluate import real_scenes, sample_scenegen
from scenegen_jax.eval.realism import class_mix, drivable_share
from scenegen_jax.train.loop import load_trained


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--workdir", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--num", type=int, default=64, help="conditioning scenes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True)
    args = p.parse_args()
    cfg, state = load_trained(args.workdir)
    cache = load_cache(args.data)
    cache.check_config(cfg)
    indices = np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int)
    maps, scenes = real_scenes(cache, indices, cfg)
    samples = sample_scenegen(state.params, cfg, maps, scenes, args.seed)
    report = {"workdir": args.workdir, "data": args.data, "scenes": len(indices),
              "step": int(state.step)}
    for name, actors_list in (("real", [s.actors for s in scenes]), ("sampled", samples)):
        on = total = 0
        for i, actors in zip(indices, actors_list, strict=True):
            canvas, _, _ = cached_scene(cache, int(i), cfg)
            a, b = drivable_share(canvas, actors, cfg)
            on, total = on + a, total + b
        report[name] = {
            "vehicles_within_40m": total,
            "on_drivable_share": on / total if total else None,
            "class_mix": class_mix(actors_list),
            "mean_actors": float(np.mean([np.sum(a.valid) for a in actors_list])),
        }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    with open(args.out, "w") as f:
        json.dump(report, f, indent=1)
    print(json.dumps(report))


if __name__ == "__main__":
    main()
