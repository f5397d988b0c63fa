"""The teacher-forced terms computed the obvious way, to test the fast unroll against."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from scenegen_jax.config import Config
from scenegen_jax.distributions import TERMS
from scenegen_jax.likelihood.unroll import _bound, _pad_slots, head_terms, step_heads
from scenegen_jax.model.network import SceneGenNet, conv, lstm_gates
from scenegen_jax.raster.actors import draw_actor
from scenegen_jax.scene import STOP, Scene, bin_index


def reference_step_terms(params, cfg: Config, maps, scene: Scene, hard_negatives: int | None):
    """The same terms computed the obvious way: a Python loop over steps, each step a full
    ConvLSTM step on the concatenated input (map ++ actors ++ h1)."""
    net = SceneGenNet(cfg)

    apply = _bound(net, params)
    b = maps.shape[0]
    w_in = jnp.concatenate(
        ([params["lstm1_map"]] if cfg.map_channels else [])
        + [params["lstm1_act"], params["lstm1_rec"]],
        axis=2,
    )
    n_actors = jnp.sum(scene.actors.valid, axis=1)
    steps = int(jnp.max(n_actors)) + 1
    actors = _pad_slots(scene.actors, max(steps, scene.actors.cls.shape[1]))
    raster = jax.vmap(functools.partial(draw_actor, cfg=cfg))(
        jnp.zeros((b, cfg.grid_size, cfg.grid_size, 9)), scene.ego, jnp.ones((b,), bool)
    )
    state = apply(SceneGenNet.initial_state, b)
    out = {k: [] for k in TERMS}
    for t in range(steps):
        (h1, c1), (h2, c2) = state
        x = jnp.concatenate([maps, raster, h1], axis=-1)
        h1, c1 = lstm_gates(conv(x, w_in, params["lstm1_b"]), c1)
        h2, c2 = lstm_gates(
            conv(jnp.concatenate([h1, h2], -1), params["lstm2_w"], params["lstm2_b"]), c2
        )
        state = ((h1, c1), (h2, c2))
        f = apply(SceneGenNet.features, h2)
        a = jax.tree.map(lambda x, t=t: x[:, t], actors)
        is_stop = n_actors == t
        target = a.replace(cls=jnp.where(is_stop, STOP, a.cls))
        heads = step_heads(net, params, f, target.cls, bin_index(target.position, cfg))
        terms = head_terms(net, params, heads, target, is_stop, cfg, hard_negatives)
        for k in TERMS:
            out[k].append(terms[k] * (t <= n_actors))
        raster = jax.vmap(functools.partial(draw_actor, cfg=cfg))(raster, a, jnp.zeros((b,), bool))
    return {k: jnp.stack(v, axis=1) for k, v in out.items()}
