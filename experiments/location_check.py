"""Location NLL per actor of one class for trained models on a subset of a cache, next to
map-only references: uniform over the scene's drivable bins, and uniform over its other bins
(what knowing only "this class is on / off the road" gives). Used to tell overfitting from a
map the model does not use (issue 4).

Per model it also splits the class's location term: the share of the location mass on
drivable bins (teacher forced, at the step of each real actor of the class), the NLL given
that the actor is on the drivable area (renormalised over drivable bins; actors on it only),
and the NLL given that it is off (renormalised over the other bins; actors off it only). Per
data set it prints how far the class's actors are from the drivable area.

  .venv/bin/python experiments/location_check.py --data runs/cache_cpu_train --every 8 \
      runs/cpu_map runs/cpu_nomap
  .venv/bin/python experiments/location_check.py --cls pedestrian --data runs/cache_cpu_val \
      runs/cpu_map_lr1e4_s0 runs/cpu_nomap_lr1e4_s0
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
from scenegen_jax.likelihood.batch import crop_batch, gather_batch
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.raster.actors import draw_actor, empty_actor_raster
from scenegen_jax.raster.transform import crop_map
from scenegen_jax.scene import CLASS_NAMES, Actors, bin_index, in_region
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


def drivable_masks(cache, cfg) -> np.ndarray:
    """[S, H*W] bool: the drivable-area bins of each scene (unrotated crop)."""
    full = cfg.replace(map_layers=("drivable",), train_layers=(), heading_lane_frame=False,
                       attribute_map_input=False, attribute_map_skip=False)
    channel = full.map_channels.index("drivable_area")
    return np.stack([
        np.asarray(crop_map(jnp.asarray(cache.maps[i]), 0.0, full))[..., channel].reshape(-1) > 0.5
        for i in range(len(cache))
    ])


def class_steps(scene, cfg, cls: int) -> tuple[np.ndarray, np.ndarray]:
    """(keep [S, N]: valid actors of class `cls` inside the region, bins [S, N]) of cropped
    scenes, slot t being teacher-forced step t."""
    a = scene.actors
    pos = jnp.asarray(a.position)
    keep = np.asarray(in_region(pos, cfg) & a.valid & (a.cls == cls))
    return keep, np.asarray(bin_index(pos, cfg))


def cropped(cache, cfg):
    """(maps, scene) of every cached scene, unrotated."""
    return crop_batch(gather_batch(cache, np.arange(len(cache)), cfg), jnp.zeros(len(cache)), cfg)


def location_log_probs(params, cfg, maps, scene, cls: int) -> np.ndarray:
    """[S, N, H*W] teacher-forced location log-probabilities of class `cls`'s head at every
    step (the unroll's recurrence written as a plain loop: analysis only, the scores come
    from `score_cache`)."""
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
                           jnp.full((b,), cls, jnp.int32))
            out.append(jax.nn.log_softmax(logits))
            actor = jax.tree.map(lambda x, t=t: x[:, t], scene.actors)
            raster = draw(raster, actor, jnp.zeros((b,), bool))
        return jnp.stack(out, axis=1)

    chunks = [jax.tree.map(lambda x, i=i: x[i : i + 8], (maps, scene))
              for i in range(0, maps.shape[0], 8)]
    return np.concatenate([np.asarray(one(params, *c)) for c in chunks])


def mean(x: list) -> float | None:
    """Mean of a list of numbers, None for an empty one (no actor of that kind)."""
    return float(np.mean(x)) if x else None


def drivable_split(params, cfg, maps, scene, drivable, cls: int) -> dict:
    """Mean share of the class's location mass on drivable bins, and its location NLL per
    actor given that the actor is on (off) the drivable area, over the actors on (off) it
    (nats, density per m^2; None where no actor is)."""
    logp = location_log_probs(params, cfg, maps, scene, cls)
    keep, bins = class_steps(scene, cfg, cls)
    mass, on, off = [], [], []
    for s, t in zip(*np.nonzero(keep), strict=True):
        m = float(np.exp(logp[s, t])[drivable[s]].sum())
        mass.append(m)
        nll = -logp[s, t, bins[s, t]] + np.log(cfg.bin_area)
        if drivable[s, bins[s, t]]:
            on.append(nll + np.log(m))
        else:
            off.append(nll + np.log1p(-m))
    return {"mass_on_drivable": mean(mass),
            "location_nll_given_drivable": mean(on),
            "location_nll_given_off_drivable": mean(off)}


def map_only_references(scene, cfg, drivable, cls: int) -> dict:
    """The class's actors against the drivable area: their share on it, quantiles of their
    distance to it (m, from their bin's centre to the nearest drivable bin's centre), and the
    location NLL per actor of the two map-only references, uniform over the drivable bins
    (actors on them) and uniform over the others (actors off)."""
    keep, bins = class_steps(scene, cfg, cls)
    g = cfg.grid_size
    rows, cols = np.divmod(np.arange(g * g), g)
    on_nll, off_nll, dist = [], [], []  # one entry per actor
    for i in range(len(bins)):
        b = bins[i][keep[i]]
        on = drivable[i][b]
        n_on = drivable[i].sum()
        on_nll += [np.log(n_on * cfg.bin_area)] * int(on.sum())
        off_nll += [np.log((g * g - n_on) * cfg.bin_area)] * int((~on).sum())
        if n_on:
            d2 = ((rows[b, None] - rows[None, drivable[i]]) ** 2
                  + (cols[b, None] - cols[None, drivable[i]]) ** 2)
            dist += list(np.sqrt(d2.min(axis=1)) * cfg.m_per_px)
    q = (10, 25, 50, 75, 90)

    return {"actors": int(keep.sum()),
            "share_on_drivable": mean([1.0] * len(on_nll) + [0.0] * len(off_nll)),
            f"distance_to_drivable_m_quantiles_{'_'.join(map(str, q))}":
                [round(float(x), 2) for x in np.percentile(dist, q)] if dist else None,
            "uniform_over_drivable_nll_given_drivable": mean(on_nll),
            "uniform_over_off_drivable_nll_given_off_drivable": mean(off_nll)}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--data", required=True)
    p.add_argument("--every", type=int, default=1, help="score every N-th scene")
    p.add_argument("--cls", choices=CLASS_NAMES, default="vehicle", help="class to check")
    p.add_argument("workdirs", nargs="+")
    args = p.parse_args()
    cls = CLASS_NAMES.index(args.cls)
    cache = load_cache(args.data)
    sub = subset(cache, np.arange(0, len(cache), args.every))
    out = {"data": args.data, "scenes": len(sub), "class": args.cls}
    for w in args.workdirs:
        cfg, state = load_trained(w)
        drivable = drivable_masks(sub, cfg)
        maps, scene = cropped(sub, cfg)
        s = summarize_scores(score_cache(state.params, sub, cfg, progress=False))
        out[w] = {"step": int(state.step),
                  f"location_nll_per_{args.cls}": s[f"location_nll_per_{args.cls}"],
                  **drivable_split(state.params, cfg, maps, scene, drivable, cls)}
    out["map_only"] = map_only_references(scene, cfg, drivable, cls)
    print(json.dumps(out, indent=1))


if __name__ == "__main__":
    main()
