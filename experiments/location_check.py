"""Location NLL per vehicle of trained models on a subset of a cache, next to a map-only
reference: uniform over the scene's drivable bins (what knowing only "vehicles are on the
road" gives). Used to tell overfitting from a map the model does not use (issue 4).

Per model it also splits the vehicle location term in two: the share of the location mass on
drivable bins (teacher forced, at the step of each real vehicle) and the NLL given that the
vehicle is on the drivable area (renormalised over drivable bins; vehicles on it only).

  .venv/bin/python experiments/location_check.py --data runs/cache_cpu_train --every 8 \
      runs/cpu_map runs/cpu_nomap
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json

import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.data.cache import ACTOR_FIELDS, load_cache
from scenegen_jax.eval.nll import score_cache, summarize_scores
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.raster.actors import draw_actor, empty_actor_raster
from scenegen_jax.raster.transform import crop_map
from scenegen_jax.scene import VEHICLE, Actors, bin_index, in_region
from scenegen_jax.train.data import gather_batch
from scenegen_jax.train.loop import load_trained
from scenegen_jax.train.step import crop_batch


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


def drivable_masks(cache, cfg) -> np.ndarray:
    """[S, H*W] bool: the drivable-area bins of each scene (unrotated crop)."""
    full = cfg.replace(map_layers=("lanes", "drivable", "crosswalks"))
    channel = full.map_channels.index("drivable_area")
    return np.stack([
        np.asarray(crop_map(jnp.asarray(cache.maps[i]), 0.0, full))[..., channel].reshape(-1) > 0.5
        for i in range(len(cache))
    ])


def vehicle_steps(scene, cfg) -> tuple[np.ndarray, np.ndarray]:
    """(keep [S, N]: valid vehicles inside the region, bins [S, N]) of cropped scenes, slot t
    being teacher-forced step t."""
    a = scene.actors
    pos = jnp.asarray(a.position)
    keep = np.asarray(in_region(pos, cfg) & a.valid & (a.cls == VEHICLE))
    return keep, np.asarray(bin_index(pos, cfg))


def cropped(cache, cfg):
    """(maps, scene) of every cached scene, unrotated."""
    return crop_batch(gather_batch(cache, np.arange(len(cache)), cfg), jnp.zeros(len(cache)), cfg)


def vehicle_location_log_probs(params, cfg, maps, scene) -> np.ndarray:
    """[S, N, H*W] teacher-forced vehicle-head location log-probabilities at every step (the
    unroll's recurrence written as a plain loop: analysis only, the scores come from
    `score_cache`)."""
    net = SceneGenNet(cfg)

    @jax.jit
    def one(params, maps, scene):
        def apply(method, *args):
            return net.apply({"params": params}, *args, method=method)

        b = maps.shape[0]
        draw = jax.vmap(functools.partial(draw_actor, cfg=cfg))
        empty = empty_actor_raster(cfg)
        raster = draw(jnp.broadcast_to(empty, (b, *empty.shape)), scene.ego, jnp.ones((b,), bool))
        gates0, state = apply(SceneGenNet.map_gates, maps), apply(SceneGenNet.initial_state, b)
        out = []
        for t in range(scene.actors.cls.shape[1]):
            gates = gates0 + apply(SceneGenNet.actor_gates, raster)
            state, h2 = apply(SceneGenNet.recur, state, gates)
            logits = apply(SceneGenNet.location_logits, apply(SceneGenNet.features, h2),
                           jnp.full((b,), VEHICLE, jnp.int32))
            out.append(jax.nn.log_softmax(logits))
            actor = jax.tree.map(lambda x, t=t: x[:, t], scene.actors)
            raster = draw(raster, actor, jnp.zeros((b,), bool))
        return jnp.stack(out, axis=1)

    chunks = [jax.tree.map(lambda x, i=i: x[i : i + 8], (maps, scene))
              for i in range(0, maps.shape[0], 8)]
    return np.concatenate([np.asarray(one(params, *c)) for c in chunks])


def drivable_split(params, cfg, maps, scene, drivable) -> dict:
    """Mean share of the vehicle location mass on drivable bins and the location NLL per
    on-drivable vehicle given the drivable area (nats, density per m^2)."""
    logp = vehicle_location_log_probs(params, cfg, maps, scene)
    keep, bins = vehicle_steps(scene, cfg)
    mass, given = [], []
    for s, t in zip(*np.nonzero(keep), strict=True):
        m = float(np.exp(logp[s, t])[drivable[s]].sum())
        mass.append(m)
        if drivable[s, bins[s, t]]:
            given.append(-logp[s, t, bins[s, t]] + np.log(m) + np.log(cfg.bin_area))
    return {"mass_on_drivable": float(np.mean(mass)),
            "location_nll_given_drivable": float(np.mean(given))}


def drivable_uniform(scene, cfg, drivable) -> tuple[float, float]:
    """(mean location NLL per vehicle under uniform-over-drivable, share of vehicles on it)."""
    keep, bins = vehicle_steps(scene, cfg)
    nll, on = [], []
    for i in range(len(bins)):
        b = bins[i][keep[i]]
        nll += [np.log(drivable[i].sum() * cfg.bin_area)] * len(b)
        on += list(drivable[i][b])
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
        drivable = drivable_masks(sub, cfg)
        maps, scene = cropped(sub, cfg)
        s = summarize_scores(score_cache(state.params, sub, cfg, progress=False))
        out[w] = {"step": int(state.step), "location_nll_per_vehicle": s[
            "location_nll_per_vehicle"], **drivable_split(state.params, cfg, maps, scene, drivable)}
    nll, on = drivable_uniform(scene, cfg, drivable)
    out["uniform_over_drivable"] = {"location_nll_per_vehicle": nll, "vehicles_on_drivable": on}
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
