"""Where does the heading information get lost? Fits fresh heading heads (the model's own
von Mises mixture, Adam on every vehicle at once) on what a trained model sees at each
vehicle's bin, teacher-forced through real train scenes, and scores them on the val scenes:

- the model's own heading head, as trained;
- the mixture's bias alone (no input: the best unconditional heading density);
- fresh 3-layer MLPs (16 and 64 hidden units) on the backbone features the head reads;
- a fresh 64-unit MLP on the raw map channels at the bin (what the map itself tells), and on
  the same channels each normalised over its scene (mean 0, std 1 per scene and channel),
  as GroupNorm with one channel per group normalises each backbone channel.

If a fresh head on the backbone features is no better than the trained one while the raw map
channels are, the backbone, not the head, loses the heading. Scenes are turned by random
angles as in training (`--ego-frame`: unturned, where the ego's heading is a strong prior).

Usage: python experiments/heading_fit.py WORKDIR STEP [--scenes N] [--ego-frame]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
import optax
from probe_features import load, vehicle_rows

from scenegen_jax.data.cache import load_cache
from scenegen_jax.distributions import params as P
from scenegen_jax.distributions.mixtures import heading_log_prob
from scenegen_jax.raster.map import ORIENTATION_CHANNELS

TRAIN = ("runs/cache_cpu_av2_train", "runs/cache_cpu_womdjson_train",
         "runs/cache_cpu_womdpkl_train")
VAL = ("runs/cache_cpu_av2_val", "runs/cache_cpu_womdjson_val", "runs/cache_cpu_womdpkl_val")


def nll(raw, heading):
    """Mean heading NLL per vehicle (nats) of raw heading head outputs [N, 4K]."""
    return -jnp.mean(jax.vmap(heading_log_prob)(raw, heading))


def mlp_init(key, din: int, hidden: int, k: int):
    g = jax.nn.initializers.lecun_normal()
    k1, k2 = jax.random.split(key)
    return {"w0": g(k1, (din, hidden)), "b0": jnp.zeros(hidden),
            "w1": g(k2, (hidden, hidden)), "b1": jnp.zeros(hidden),
            "w2": jnp.zeros((hidden, P.heading_params_size(k))),
            "b2": jnp.asarray(P.initial_heading_bias(k))}


def mlp(p, x):
    x = jax.nn.relu(x @ p["w0"] + p["b0"])
    x = jax.nn.relu(x @ p["w1"] + p["b1"])
    return x @ p["w2"] + p["b2"]


def fit(name, p, f, train, val, steps: int = 400, lr: float = 3e-3) -> None:
    """Full-batch Adam; prints train and val NLL along the way (the val minimum is what the
    input supports; later iterations overfit the few thousand vehicles)."""
    opt = optax.adam(lr)
    state = opt.init(p)

    @jax.jit
    def update(p, state):
        loss, g = jax.value_and_grad(lambda p: nll(f(p, train[0]), train[1]))(p)
        u, state = opt.update(g, state)
        return optax.apply_updates(p, u), state, loss

    for i in range(steps):
        p, state, loss = update(p, state)
        if i in (50, 150) or i == steps - 1:
            print(f"{name:>32} iteration {i}: train {float(loss):.3f}, "
                  f"val {float(nll(f(p, val[0]), val[1])):.3f}", flush=True)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("workdir")
    ap.add_argument("step", type=int)
    ap.add_argument("--scenes", type=int, default=100, help="train scenes per cache")
    ap.add_argument("--ego-frame", action="store_true", help="scenes unturned")
    args = ap.parse_args()
    cfg, params = load(args.workdir, args.step)
    seed = None if args.ego_frame else 0
    rows = {
        split: [vehicle_rows(params, cfg, load_cache(c), scenes=n, rotate_seed=seed)
                for c in caches]
        for split, caches, n in (("train", TRAIN, args.scenes), ("val", VAL, 40))
    }

    def cat(split, key):
        return jnp.asarray(np.concatenate([r[key] for r in rows[split]]))

    k = cfg.num_mixtures
    nh = P.heading_params_size(k)
    heading = {s: cat(s, "heading") for s in rows}
    print(f"vehicles: train {len(heading['train'])}, val {len(heading['val'])}")
    ic, is_ = (cfg.map_channels.index(c) for c in ORIENTATION_CHANNELS)
    lane = np.asarray(cat("val", "map"))[:, [ic, is_]]
    on = (lane**2).sum(1) > 0.5
    off = np.angle(np.exp(1j * (np.asarray(heading["val"])[on] - np.arctan2(lane[on, 1],
                                                                             lane[on, 0]))))
    print(f"val vehicles on a lane: {on.mean():.1%}; of those within 20 deg of the lane's "
          f"direction: {(np.abs(off) < np.radians(20)).mean():.1%}")
    own = {s: nll(cat(s, "out"), heading[s]) for s in rows}  # the heading mixture
    print(f"{'the model head, as trained':>32}: train {float(own['train']):.3f}, "
          f"val {float(own['val']):.3f}")
    key = jax.random.key(0)
    for name, field, hidden in (("bias only", "features", 0),
                                ("fresh MLP 16 on backbone", "features", 16),
                                ("fresh MLP 64 on backbone", "features", 64),
                                ("fresh MLP 64 on raw map", "map", 64),
                                ("... each channel normed per scene", "map_normed", 64)):
        train, val = (cat("train", field), heading["train"]), (cat("val", field), heading["val"])
        if hidden:
            fit(name, mlp_init(key, train[0].shape[1], hidden, k), mlp, train, val)
        else:
            fit(name, {"b": jnp.asarray(P.initial_heading_bias(k))},
                lambda p, x: jnp.broadcast_to(p["b"], (x.shape[0], nh)), train, val)


if __name__ == "__main__":
    main()
