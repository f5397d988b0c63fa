"""Placing one actor of a class (steps 4 and 5 of `rollout`): candidate actors drawn round
by round from the location distribution, each with its attributes, until one overlaps no
earlier vehicle or bicyclist box nor the ego (collision rejection)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jax import lax

from scenegen_jax.config import ModelConfig
from scenegen_jax.distributions import offsets_in_bin, sample_bins, uniforms
from scenegen_jax.model.network import map_at_bins
from scenegen_jax.sampling.attributes import sample_attributes
from scenegen_jax.sampling.geometry import collides
from scenegen_jax.sampling.model import Model
from scenegen_jax.scene import PEDESTRIAN, Actors, bin_center, empty_actors, tree_take


def draw_candidates(key, params, model: Model, f, map_raster, cls, log_probs, cfg: ModelConfig,
                    proposals, count):
    """`count` i.i.d. candidate actors of class `cls`: bins from `log_probs` [H*W] (-inf
    outside the allowed set), positions uniform in the bins, attributes (`sample_attributes`)
    from the features f [1, H, W, h] and map channels map_raster [1, H, W, Cm] at the bins."""
    k_bin, k_pos, k_attr = jax.random.split(key, 3)
    bins = sample_bins(k_bin, log_probs, count, cfg.grid.grid_size)
    position = bin_center(bins, cfg.grid) + offsets_in_bin(uniforms(k_pos, (count, 2)), cfg.grid)
    feat = f[0].reshape(-1, f.shape[-1])[bins]  # [R, hidden]
    classes = jnp.full((count,), cls, jnp.int32)
    box_raw, heading_raw, velocity_raw = model.attributes(
        params, feat, classes, map_at_bins(map_raster, bins[None])[0])
    size, heading, velocity = sample_attributes(
        jax.random.split(k_attr, count), box_raw, heading_raw, velocity_raw, classes, cfg,
        proposals)
    return bins, Actors(
        cls=classes,
        position=position.astype(jnp.float32),
        size=size,
        heading=heading,
        velocity=velocity,
        valid=jnp.ones((count,), bool),
    )


def place_actor(key, params, model: Model, f, map_raster, cls, log_probs, placed: Actors,
                ego: Actors, cfg: ModelConfig, proposals: int, candidates: int, rounds: int):
    """Draws candidates round by round until one overlaps none of the `placed` actors' boxes
    nor the ego's (`rollout`'s module docstring).

    Returns:
      (actor, found, rejected): the first accepted candidate (any candidate if none), whether
      one was accepted, and how many candidates were rejected.
    """
    boxed = cls != PEDESTRIAN
    n_bins = log_probs.shape[0]

    def draw(r, banned):
        lp = jnp.where(banned, -jnp.inf, log_probs)
        any_left = jnp.any(jnp.isfinite(lp))
        lp = jnp.where(any_left, lp, 0.0)  # keeps the categorical finite; result unused then
        bins, cands = draw_candidates(jax.random.fold_in(key, r), params, model, f, map_raster,
                                  cls, lp, cfg, proposals, candidates)
        hit = jax.vmap(collides, in_axes=(0, None, None))(cands, placed, ego)
        ok = any_left & jnp.logical_not(boxed & hit)
        return bins, cands, ok, any_left

    def cond(c):
        r, _, found, any_left, *_ = c
        return (r < rounds) & jnp.logical_not(found) & any_left

    def body(c):
        r, banned, _, _, _, rejected = c
        bins, cands, ok, any_left = draw(r, banned)
        first = jnp.argmax(ok)  # the first accepted candidate (0 if none)
        found = jnp.any(ok)
        # Rejections before the accepted one (all R if none was accepted).
        n_rejected = jnp.where(found, first, jnp.where(any_left, candidates, 0))
        tried = jnp.zeros((n_bins,), bool).at[bins].set(True)
        banned = banned | (tried & jnp.logical_not(found))
        left = jnp.any(jnp.isfinite(jnp.where(banned, -jnp.inf, log_probs)))
        return r + 1, banned, found, left, tree_take(cands, first), rejected + n_rejected

    any_valid = jnp.any(jnp.isfinite(log_probs))
    init = (
        jnp.int32(0),
        jnp.zeros((n_bins,), bool),
        jnp.bool_(False),
        any_valid,
        tree_take(empty_actors(1), 0),
        jnp.int32(0),
    )
    init = jax.tree.map(jnp.asarray, init)
    _, _, found, _, actor, rejected = lax.while_loop(cond, body, init)
    return actor, found, rejected
