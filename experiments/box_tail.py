"""Does the model's box mixture give the large vehicles (buses, trucks) their share when it is
teacher forced? For every real vehicle of the scenes it prints the share whose box area
(width x length) exceeds `--area` m^2 beside the model's probability of that at the same
step, given the real actors before it (the mean over the vehicles of P(area > a) under the
box mixture at the vehicle's bin), split by whether the vehicle stands on the drivable area.
Sampled scenes' shares come from `experiments/box_areas.py`.

  .venv/bin/python experiments/box_tail.py --pretrained cpu-av2-womd \
      --data runs/cache_cpu_av2_val --num 157

P(area > a) is exact: under one component the log area, log w + log l, is normal with mean
mu_w + mu_l and variance var_w + var_l + 2 rho sd_w sd_l. The probability rides along the
scorer (`scenegen_jax.eval.nll.score_cache`) as one more per-step term: this script wraps the
per-actor likelihood that the unroll calls (`likelihood.unroll.actor_log_likelihood`) before
anything is compiled.
"""

from __future__ import annotations

import argparse
import json

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy import special

from scenegen_jax.cli.common import add_model_args, load_model
from scenegen_jax.data.cache import load_cache
from scenegen_jax.distributions import params as P
from scenegen_jax.eval import nll
from scenegen_jax.likelihood import unroll
from scenegen_jax.likelihood.batch import batch_scenes, gather_batch
from scenegen_jax.scene import VEHICLE, bin_index


def prob_area_above(raw: jnp.ndarray, area: float) -> jnp.ndarray:
    """P(width x length > area) under the box mixture `raw` [6K]."""
    box = P.split_box(raw)
    var = jnp.exp(box.log_var)
    mean = box.mu[:, 0] + box.mu[:, 1]
    sd = jnp.sqrt(var[:, 0] + var[:, 1] + 2.0 * box.rho * jnp.sqrt(var[:, 0] * var[:, 1]))
    tail = special.ndtr((mean - jnp.log(area)) / sd)
    return jnp.sum(jax.nn.softmax(box.logits) * tail)


def with_tail_term(area: float):
    """`actor_log_likelihood` plus a term "p_large": P(area > `area`) at the target's step
    (the scorer negates every term into an NLL, so it returns -P)."""
    inner = unroll.actor_log_likelihood

    def wrapped(head, target, is_stop, cfg, hard_negatives=None):
        out = inner(head, target, is_stop, cfg, hard_negatives)
        out["p_large"] = prob_area_above(head.box, area)
        return out

    return wrapped


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    add_model_args(p)
    p.add_argument("--data", required=True, help="prepared cache of real scenes")
    p.add_argument("--num", type=int, default=64, help="scenes spread over the cache")
    p.add_argument("--area", type=float, default=15.0, help="m^2")
    args = p.parse_args()
    cfg, params, _, _ = load_model(args)
    cache = load_cache(args.data)
    unroll.actor_log_likelihood = with_tail_term(args.area)
    indices = np.unique(np.linspace(0, len(cache) - 1, min(args.num, len(cache))).astype(int))
    drivable = cfg.grid.map_channels.index("drivable_area")
    real, model, on_road = [], [], []
    for i in indices:  # one scene per call: score_cache scores a contiguous range
        s = nll.score_cache(params, cache, cfg, batch_size=1, progress=False,
                            scenes=range(int(i), int(i) + 1))
        # The scene as the scorer sees it: step t is actor t in canonical order.
        maps, scene = batch_scenes(gather_batch(cache, np.array([i]), cfg.grid), cfg.grid)
        n = scene.actors.cls.shape[1]  # slots; the scorer's later steps hold no actor
        vehicle = (nll.actor_steps(s)[0] & (s["step_cls"][0] == VEHICLE))[:n]
        size = np.asarray(scene.actors.size[0])[vehicle]
        bins = np.asarray(bin_index(scene.actors.position[0], cfg.grid))[vehicle]
        real.extend(size[:, 0] * size[:, 1] > args.area)
        model.extend(-s["p_large"][0][:n][vehicle])
        on_road.extend(np.asarray(maps[0, ..., drivable]).reshape(-1)[bins] > 0.5)
    real, model, on_road = map(np.asarray, (real, model, on_road))
    rows = {"all": np.ones_like(on_road), "on the drivable area": on_road,
            "off it": ~on_road}
    for name, mask in rows.items():
        if not mask.any():
            continue
        print(json.dumps({"data": args.data, "vehicles": name, "count": int(mask.sum()),
                          f"real_share_over_{args.area:g}": round(float(real[mask].mean()), 4),
                          "model_probability": round(float(model[mask].mean()), 4)}))


if __name__ == "__main__":
    main()
