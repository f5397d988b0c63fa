"""Where a map model's location term loses to a no-map model's: actors that stand next to an
earlier actor of their class (a group of pedestrians, a row of bicycles) against the others.

Both models scored on the same cache (`scenegen score --data CACHE --actors-out F.npz`); the
actors of `--class` are split by whether an actor of the same class placed earlier in the
canonical order stands within `--radius` m, and the location NLL per actor, A minus B, is
paired on each part with `scenegen compare`'s block bootstrap (`diff`, `low`, `high`), beside
each model's own location NLL per actor of the part (`a_nll`, `b_nll`):

    .venv/bin/python experiments/group_cue.py --cache runs/cache_cpu_womdjson_val \
        --a runs/scores/phase12_womd.npz --b runs/scores/nomap12_womd.npz --class pedestrian

The scenes are ordered as the scorer orders them (unrotated, canonical order); a step whose
class differs from the score file's is an error naming the scene.
"""

from __future__ import annotations

import argparse
import json

import jax
import numpy as np

from scenegen_jax.data.cache import cached_scene, load_cache
from scenegen_jax.eval.compare import actor_sums, load_scores, paired_difference
from scenegen_jax.eval.nll import actor_steps
from scenegen_jax.raster.transform import scene_from_cached
from scenegen_jax.scene import CLASS_NAMES
from scenegen_jax.workdir import load_workdir_config


def grouped_steps(cache, cfg, scores: dict, cls: int, radius: float) -> np.ndarray:
    """[S, T] bool: the steps that place an actor of class `cls` within `radius` m of an earlier
    actor of the same class."""
    ordered = jax.jit(lambda c, a, e: scene_from_cached(c, a, e, 0.0, cfg)[1].actors)
    steps = actor_steps(scores)
    out = np.zeros_like(steps)
    for s in range(len(cache)):
        actors = jax.tree.map(np.asarray, ordered(*cached_scene(cache, s, cfg)))
        n = actors.valid.shape[0]  # the actor steps; the step after them is the stop token's
        placed = steps[s, :n] & actors.valid
        if np.any(actors.cls[placed] != scores["step_cls"][s, :n][placed]):
            raise ValueError(f"{cache.scene_ids[s]}: classes differ from the score file's order")
        pos = actors.position
        for i in np.flatnonzero(placed & (actors.cls == cls)):
            same = np.flatnonzero(placed[:i] & (actors.cls[:i] == cls))
            gaps = np.linalg.norm(pos[same] - pos[i], axis=1)
            out[s, i] = gaps.size > 0 and gaps.min() < radius
    return out


def restricted(scores: dict, mask: np.ndarray) -> dict:
    """The scores with only the steps of `mask` counted."""
    return {**scores, "step_valid": scores["step_valid"] & mask}


def main():
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cache", required=True, help="the cache both models were scored on")
    p.add_argument("--a", required=True, help="`--actors-out` file of model A (the map model)")
    p.add_argument("--b", required=True, help="`--actors-out` file of model B")
    p.add_argument("--config-from", default="experiments/pretrained_run",
                   help="a workdir of the cache's config (grid, actors)")
    p.add_argument("--class", dest="cls", choices=CLASS_NAMES, default="pedestrian")
    p.add_argument("--radius", type=float, default=3.0, help="m")
    args = p.parse_args()
    cfg = load_workdir_config(args.config_from)
    cache = load_cache(args.cache)
    a, b = load_scores(args.a), load_scores(args.b)
    if not np.array_equal(a["step_cls"], b["step_cls"]):
        raise ValueError(f"{args.b}: field 'step_cls' differs from {args.a}'s: not the same scenes")
    cls = CLASS_NAMES.index(args.cls)
    grouped = grouped_steps(cache, cfg, a, cls, args.radius)
    of_class = actor_steps(a) & (a["step_cls"] == cls)
    rows = {}
    for name, mask in (("grouped", grouped), ("alone", of_class & ~grouped), ("all", of_class)):
        a_part, b_part = restricted(a, mask), restricted(b, mask)
        rows[name] = paired_difference([a_part], [b_part], "location", cls)
        for key, part in (("a_nll", a_part), ("b_nll", b_part)):
            total, count = actor_sums(part, "location", cls)
            rows[name][key] = float(total.sum() / max(count.sum(), 1))
    print(json.dumps({"cache": args.cache, "a": args.a, "b": args.b, "class": args.cls,
                      "radius_m": args.radius, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
