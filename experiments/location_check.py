"""Location NLL per vehicle of trained models on a subset of a cache, next to a map-only
reference: uniform over the scene's drivable bins (what knowing only "vehicles are on the
road" gives). Used to tell overfitting from a map the model does not use (issue 4).

  .venv/bin/python experiments/location_check.py --data runs/cache_cpu_train --every 8 \
      runs/cpu_map runs/cpu_nomap
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import jax.numpy as jnp
import numpy as np

from scenegen_jax.data.cache import ACTOR_FIELDS, load_cache
from scenegen_jax.eval.nll import score_cache, summarize_scores
from scenegen_jax.raster.transform import crop_map
from scenegen_jax.scene import VEHICLE, Actors, bin_index, in_region
from scenegen_jax.train.loop import load_trained


def subset(cache, idx):
    return dataclasses.replace(
        cache,
        meta={**cache.meta, "scene_ids": [cache.scene_ids[i] for i in idx]},
        maps=cache.maps[idx],
        actors=Actors(**{k: getattr(cache.actors, k)[idx] for k in ACTOR_FIELDS}),
        ego_velocity=cache.ego_velocity[idx],
        ego_size=cache.ego_size[idx],
        city_from_ego=cache.city_from_ego[idx],
    )


def drivable_uniform(cache, cfg) -> tuple[float, float]:
    """(mean location NLL per vehicle under uniform-over-drivable, share of vehicles on it)."""
    full = cfg.replace(map_layers=("lanes", "drivable", "crosswalks"))
    channel = full.map_channels.index("drivable_area")
    nll, on = [], []
    for i in range(len(cache)):
        drivable = np.asarray(crop_map(jnp.asarray(cache.maps[i]), 0.0, full))[..., channel] > 0.5
        a = cache.actors
        pos = jnp.asarray(a.position[i])
        keep = np.asarray(in_region(pos, cfg)) & a.valid[i] & (a.cls[i] == VEHICLE)
        bins = np.asarray(bin_index(pos, cfg))[keep]
        nll += [np.log(drivable.sum() * cfg.bin_area)] * len(bins)
        on += list(drivable.reshape(-1)[bins])
    return float(np.mean(nll)), float(np.mean(on))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data", required=True)
    p.add_argument("--every", type=int, default=1, help="score every N-th scene")
    p.add_argument("workdirs", nargs="+")
    args = p.parse_args()
    cache = load_cache(args.data)
    sub = subset(cache, np.arange(0, len(cache), args.every))
    out = {"data": args.data, "scenes": len(sub)}
    for w in args.workdirs:
        cfg, state = load_trained(w)
        s = summarize_scores(score_cache(state.params, sub, cfg, progress=False))
        out[w] = {"step": int(state.step), "location_nll_per_vehicle": s[
            "location_nll_per_vehicle"]}
    nll, on = drivable_uniform(sub, cfg)
    out["uniform_over_drivable"] = {"location_nll_per_vehicle": nll, "vehicles_on_drivable": on}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
