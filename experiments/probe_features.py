"""Is the trunk alive? Teacher-forces real val scenes (no rotation) through a model and reports,
at every vehicle's bin: a linear probe of its heading (cos, sin) from the backbone features,
from the attribute head's hidden layer and from the raw map channels (R^2 and median angle
error on held-out vehicles), the spread of every backbone channel, and the heading mixture's
concentrations and weights. A collapsed trunk shows channels with zero spread and mixture
weights that do not depend on the actor.

Usage: python experiments/probe_features.py WORKDIR|init CACHE [STEP (or SEED for init)]
"""

from __future__ import annotations

import functools
import sys

import jax
import jax.numpy as jnp
import numpy as np

from scenegen_jax.config import get_config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.distributions import params as P
from scenegen_jax.likelihood.batch import crop_batch, gather_batch
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.raster.actors import draw_actor
from scenegen_jax.scene import VEHICLE, bin_index
from scenegen_jax.train.step import init_state


def load(src: str, arg: int | None):
    if src == "init":
        cfg = get_config("cpu")
        return cfg, init_state(cfg, seed=arg or 0).params
    from scenegen_jax.train.loop import load_trained

    cfg, state = load_trained(src, arg)
    return cfg, state.params


def vehicle_rows(params, cfg, cache, scenes: int = 24, rotate_seed: int | None = None
                 ) -> dict[str, np.ndarray]:
    """Per vehicle: backbone features, attribute hidden layer, raw map channels at its bin,
    raw heading head output, heading. Scenes in the ego frame, or with `rotate_seed` each
    turned by a random angle as in training."""
    net = SceneGenNet(cfg)
    idx = np.arange(0, len(cache), max(1, len(cache) // scenes))[:scenes]
    b = len(idx)
    thetas = np.zeros(b, np.float32)
    if rotate_seed is not None:
        thetas = np.random.default_rng(rotate_seed).uniform(0, 2 * np.pi, b).astype(np.float32)
    maps, scene = crop_batch(gather_batch(cache, idx, cfg), jnp.asarray(thetas), cfg)
    draw = jax.vmap(functools.partial(draw_actor, cfg=cfg))
    grid = (b, cfg.grid_size, cfg.grid_size, 9)
    raster = draw(jnp.zeros(grid), scene.ego, jnp.ones((b,), bool))
    state = net.apply({"params": params}, b, method=SceneGenNet.initial_state)
    # Each map channel normalised over its scene, as GroupNorm with one channel per group
    # normalises every backbone channel.
    normed = (maps - maps.mean((1, 2), keepdims=True)) / (maps.std((1, 2), keepdims=True) + 1e-5)

    def apply(method, *args):
        return net.apply({"params": params}, *args, method=method)

    map_gates = apply(SceneGenNet.map_gates, maps)  # every map input option of the config

    @jax.jit
    def step(state, raster, prev_bin, cls, position):
        gates = map_gates + apply(SceneGenNet.actor_gates, raster)
        state, h2 = apply(SceneGenNet.recur, state,
                          gates + apply(SceneGenNet.order_gates, prev_bin))
        f = apply(SceneGenNet.features, h2)
        bins = bin_index(position, cfg)
        feat = f.reshape(b, -1, f.shape[-1])[jnp.arange(b), bins]
        mp, mpn = (m.reshape(b, -1, m.shape[-1])[jnp.arange(b), bins] for m in (maps, normed))
        cls = jnp.clip(cls, 0, 2)
        mlp = "heading" if cfg.separate_attribute_mlps else "attr"
        x, w0 = feat, params[f"{mlp}0_w"][cls]  # the hidden layer of the heading's MLP
        if cfg.attribute_map_input:
            x, w0 = jnp.concatenate([feat, mp], -1), jnp.concatenate(
                [w0, params[f"{mlp}0_map_w"][cls]], axis=1)
        for i, w in enumerate((w0, params[f"{mlp}1_w"][cls])):
            x = jax.nn.relu(jnp.einsum("bi,bio->bo", x, w) + params[f"{mlp}{i}_b"][cls])
        out = apply(SceneGenNet.attributes, feat, cls, mp)[1]  # the heading mixture's parameters
        return state, {"features": feat, "hidden": x, "map": mp, "map_normed": mpn, "out": out}

    rows: dict[str, list] = {k: [] for k in ("features", "hidden", "map", "map_normed", "out",
                                                 "heading")}
    prev_bin = jnp.zeros((b,), jnp.int32)
    for t in range(int(jnp.max(jnp.sum(scene.actors.valid, axis=1)))):
        a = jax.tree.map(lambda x, t=t: x[:, t], scene.actors)
        state, got = step(state, raster, prev_bin, a.cls, a.position)
        prev_bin = bin_index(a.position, cfg)
        m = np.asarray(a.valid & (a.cls == VEHICLE))
        for k, v in got.items():
            rows[k].append(np.asarray(v)[m])
        rows["heading"].append(np.asarray(a.heading)[m])
        raster = draw(raster, a, jnp.zeros((b,), bool))
    return {k: np.concatenate(v) for k, v in rows.items()}


def probe(x: np.ndarray, heading: np.ndarray, name: str) -> None:
    y = np.stack([np.cos(heading), np.sin(heading)], 1)
    x = np.concatenate([x, np.ones((len(x), 1))], 1)
    train = np.arange(len(x)) % 4 != 0
    w, *_ = np.linalg.lstsq(x[train], y[train], rcond=None)
    p = x[~train] @ w
    r2 = 1 - ((p - y[~train]) ** 2).sum() / ((y[~train] - y[train].mean(0)) ** 2).sum()
    err = np.abs(np.angle(np.exp(1j * (np.arctan2(p[:, 1], p[:, 0]) - heading[~train]))))
    print(f"{name:>26}: R2 {r2:.3f}, median error {np.degrees(np.median(err)):.0f} deg "
          f"({len(x)} vehicles)")


def main() -> None:
    src, cache_dir = sys.argv[1], sys.argv[2]
    cfg, params = load(src, int(sys.argv[3]) if len(sys.argv) > 3 else None)
    rows = vehicle_rows(params, cfg, load_cache(cache_dir))
    for k, name in (("features", "backbone features"), ("hidden", "heading MLP hidden layer"),
                    ("map", "raw map channels")):
        probe(rows[k], rows["heading"], name)
    print("backbone channel spread:", np.round(rows["features"].std(0), 3))
    print("hidden units never active:", int((rows["hidden"].max(0) <= 0).sum()), "of",
          rows["hidden"].shape[1])
    k = cfg.num_mixtures
    split = jax.vmap(P.split_heading)(jnp.asarray(rows["out"]))
    w = np.asarray(jax.nn.softmax(split.logits, -1))
    kappa = np.round(np.asarray(split.log_kappa).mean(0), 2)
    print("heading log kappa (mean per component):", kappa)
    print(f"heading weight entropy {float(-(w * np.log(w + 1e-12)).sum(1).mean()):.3f} "
          f"(uniform {np.log(k):.3f}); weight logits' spread over vehicles:",
          np.round(np.asarray(split.logits).std(0), 3))


if __name__ == "__main__":
    main()
