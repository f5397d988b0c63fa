"""The teacher-forced terms computed the obvious way, to test the fast unroll against."""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp

from scenegen_jax.config import Config
from scenegen_jax.distributions import TERMS
from scenegen_jax.likelihood.unroll import _bound, _pad_slots, head_terms, step_heads
from scenegen_jax.model.convlstm import lstm_gates
from scenegen_jax.model.layers import conv
from scenegen_jax.model.network import SceneGenNet
from scenegen_jax.raster.actors import draw_actor
from scenegen_jax.scene import STOP, Scene, bin_index


@functools.partial(jax.jit, static_argnums=1)
def _reference_cell(params, cfg: Config, maps, raster, state, prev):
    """One ConvLSTM step on the concatenated input (map ++ actors ++ h1 ++ the canonical
    order's channel: 1 on the bins at or after `prev` [B], the previous actor's bin):
    (state, backbone features [B, H, W, h]). Jitted so that the loop below compiles one step,
    not thousands of operations one by one (the same operations either way)."""
    b = maps.shape[0]
    w_in = jnp.concatenate(
        ([params["lstm1_map"]] if cfg.grid.map_channels else [])
        + [params["lstm1_act"], params["lstm1_rec"]]
        + ([params["lstm1_order"]] if cfg.model.order_channel else []),
        axis=2,
    )
    (h1, c1), (h2, c2) = state
    allowed = jnp.arange(cfg.grid.grid_size**2)[None] >= prev[:, None]
    order = allowed.reshape(b, cfg.grid.grid_size, cfg.grid.grid_size, 1).astype(maps.dtype)
    x = jnp.concatenate([maps, raster, h1] + ([order] if cfg.model.order_channel else []), axis=-1)
    h1, c1 = lstm_gates(conv(x, w_in, params["lstm1_b"]), c1)
    h2, c2 = lstm_gates(
        conv(jnp.concatenate([h1, h2], -1), params["lstm2_w"], params["lstm2_b"]), c2
    )
    features = _bound(SceneGenNet(cfg.model), params)(SceneGenNet.features, h2)
    return ((h1, c1), (h2, c2)), features


@functools.partial(jax.jit, static_argnums=0)
def _draw(cfg: Config, raster, actor, is_ego):
    return jax.vmap(functools.partial(draw_actor, grid=cfg.grid))(raster, actor, is_ego)


def _reference_steps(params, cfg: Config, maps, scene: Scene, steps: int):
    """The obvious per-step loop: each step a full ConvLSTM step (`_reference_cell`), teacher
    forced with the scene's actors. Yields (t, backbone features [B, H, W, h], the actors
    padded to `steps` slots)."""
    b = maps.shape[0]
    actors = _pad_slots(scene.actors, max(steps, scene.actors.cls.shape[1]))
    raster = _draw(cfg.model, jnp.zeros((b, cfg.grid.grid_size, cfg.grid.grid_size, 9)), scene.ego,
                   jnp.ones((b,), bool))
    state = _bound(SceneGenNet(cfg.model), params)(SceneGenNet.initial_state, b)
    for t in range(steps):
        # The previous actor's bin (0 at t = 0: every bin allowed).
        prev = bin_index(actors.position[:, t - 1], cfg.grid) if t else jnp.zeros((b,), jnp.int32)
        state, features = _reference_cell(params, cfg, maps, raster, state, prev)
        yield t, features, actors
        a = jax.tree.map(lambda x, t=t: x[:, t], actors)
        raster = _draw(cfg.model, raster, a, jnp.zeros((b,), bool))


@functools.partial(jax.jit, static_argnums=(1, 6))
def _reference_terms(params, cfg: Config, f, target, is_stop, map_feat, hard_negatives):
    """The terms of one step's target actor given the backbone features `f` (jitted, as
    `_reference_cell`)."""
    net = SceneGenNet(cfg.model)
    heads = step_heads(net, params, f, target.cls, bin_index(target.position, cfg.grid))
    return head_terms(net, params, heads, target, is_stop, cfg.model, hard_negatives, map_feat)


def reference_step_terms(params, cfg: Config, maps, scene: Scene, hard_negatives: int | None):
    """The teacher-forced terms of every step, step by step (`_reference_steps`)."""
    n_actors = jnp.sum(scene.actors.valid, axis=1)
    complete = jnp.broadcast_to(jnp.asarray(scene.complete), n_actors.shape)
    out = {k: [] for k in TERMS}
    for t, f, actors in _reference_steps(params, cfg, maps, scene, int(jnp.max(n_actors)) + 1):
        a = jax.tree.map(lambda x, t=t: x[:, t], actors)
        is_stop = (n_actors == t) & complete  # a truncated scene has no stop token
        target = a.replace(cls=jnp.where(is_stop, STOP, a.cls))
        bins = bin_index(target.position, cfg.grid)
        map_feat = maps.reshape(maps.shape[0], -1, maps.shape[-1])[jnp.arange(maps.shape[0]), bins]
        terms = _reference_terms(params, cfg, f, target, is_stop, map_feat, hard_negatives)
        for k in TERMS:
            out[k].append(terms[k] * ((t < n_actors) | is_stop))
    return {k: jnp.stack(v, axis=1) for k, v in out.items()}


def reference_location_logits(params, cfg: Config, maps, scene: Scene, step: int, cls):
    """Location logits [B, H*W] of class `cls` [B] at `step`, after the scene's first `step`
    actors (teacher forced, `_reference_steps`)."""
    net = SceneGenNet(cfg.model)
    for t, f, _ in _reference_steps(params, cfg, maps, scene, step + 1):
        if t == step:
            return net.apply({"params": params}, f, cls, method=SceneGenNet.location_logits)
