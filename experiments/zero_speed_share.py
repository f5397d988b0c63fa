"""Share of standing actors (speed below zero_speed) in real val scenes and in samples with
M = 1 and M = 10 proposals. Best-of-M must keep it at pi_0: standing is drawn once and only
moving proposals compete (`sampling.rollout.sample_attributes`); the earlier sampler, which
compared the v = 0 point mass's probability with speed densities, raised it to 0.67.

  .venv/bin/python experiments/zero_speed_share.py --workdir runs/cpu_map --data runs/cache_cpu_val
"""

from __future__ import annotations

import argparse

import numpy as np

from scenegen_jax.data.cache import load_cache
from scenegen_jax.eval.evaluate import real_scenes, sample_scenegen
from scenegen_jax.train.loop import load_trained


def standing_share(actors_list, zero_speed: float) -> tuple[float, int]:
    v = np.concatenate([np.hypot(*a.velocity[a.valid].T) for a in actors_list])
    return float((v < zero_speed).mean()), len(v)


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--workdir", required=True)
    p.add_argument("--data", required=True)
    p.add_argument("--num", type=int, default=16)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    cfg, state = load_trained(args.workdir)
    cache = load_cache(args.data)
    idx = np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int)
    maps, scenes = real_scenes(cache, idx, cfg)
    share, n = standing_share([s.actors for s in scenes], cfg.zero_speed)
    print(f"real: {share:.2f} of {n} actors standing")
    for m in (1, 10):
        out = sample_scenegen(state.params, cfg.replace(proposals=m), maps, scenes, args.seed)
        share, n = standing_share(out, cfg.zero_speed)
        print(f"M={m}: {share:.2f} of {n} sampled actors standing")


if __name__ == "__main__":
    main()
