"""Rigid transforms of a cached scene (jit side): rotation about the ego and crop to the grid.

The cache stores each scene's map on a canvas larger than the grid (`Config.canvas_size`) and
the actors within the canvas, so any rotation about the ego can be cropped to the H x W grid
without missing map or actors.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.config import Config
from scenegen_jax.raster.map import VECTOR_CHANNELS, select_channels
from scenegen_jax.scene import Actors, Scene, canonical_order, in_region, pixel_centers, wrap_angle


def rotate_vectors(v, theta):
    """Rotates vectors [..., 2] counter-clockwise by theta rad."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def crop_map(canvas, theta, cfg: Config):
    """The H x W grid of a map canvas rotated by theta about the ego (bilinear).

    Args:
      canvas: [S, S, len(ALL_MAP_CHANNELS)] map canvas at cfg.m_per_px, S = cfg.canvas_size.
      theta: rotation, rad (counter-clockwise; 0 is a plain centre crop).
      cfg: config (grid, resolution, map layers).
    Returns:
      [H, W, len(cfg.map_channels)] float32 map channels.
    """
    if not cfg.map_channels:
        return jnp.zeros((cfg.grid_size, cfg.grid_size, 0), jnp.float32)
    s = canvas.shape[0]
    centers = jnp.asarray(pixel_centers(cfg))  # [H, W, 2] (x, y) in the rotated frame
    src = rotate_vectors(centers, -theta)  # where each output pixel comes from
    half = s * cfg.m_per_px / 2
    col = (src[..., 0] + half) / cfg.m_per_px - 0.5
    row = (half - src[..., 1]) / cfg.m_per_px - 0.5
    coords = jnp.stack([row.ravel(), col.ravel()])

    def sample(channel):
        return jax.scipy.ndimage.map_coordinates(channel, coords, order=1, mode="constant")

    channels = select_channels(canvas, cfg).astype(jnp.float32)  # only the config's
    out = jax.vmap(sample, in_axes=-1, out_axes=-1)(channels)
    out = out.reshape(cfg.grid_size, cfg.grid_size, -1)
    # Direction vectors (lane orientation, nearest lane) turn with the frame.
    for pair in VECTOR_CHANNELS:
        if pair[0] in cfg.map_channels:
            ic, is_ = (cfg.map_channels.index(c) for c in pair)
            turned = rotate_vectors(jnp.stack([out[..., ic], out[..., is_]], -1), theta)
            out = out.at[..., ic].set(turned[..., 0]).at[..., is_].set(turned[..., 1])
    return out


def rotate_actors(actors: Actors, theta) -> Actors:
    """Actors rotated by theta about the ego (positions, headings, velocities)."""
    return actors.replace(
        position=rotate_vectors(actors.position, theta),
        heading=wrap_angle(actors.heading + theta),
        velocity=rotate_vectors(actors.velocity, theta),
    )


def scene_from_cached(canvas, actors: Actors, ego: Actors, theta, cfg: Config):
    """Rotates a cached scene by theta and crops it to the grid.

    Args:
      canvas: [S, S, C_all] map canvas.
      actors: cached actors (any number of slots >= cfg.max_actors), unrotated.
      ego: unbatched ego.
      theta: rotation about the ego, rad.
      cfg: config.
    Returns:
      (map [H, W, C], Scene with cfg.max_actors slots in canonical order, overflow count)
      where overflow counts in-region actors beyond cfg.max_actors (dropped; the Scene is
      then not `complete`).
    """
    rotated = rotate_actors(actors, theta)
    rotated = rotated.replace(valid=rotated.valid & in_region(rotated.position, cfg))
    ordered = canonical_order(rotated, cfg)
    n = cfg.max_actors
    overflow = jnp.maximum(jnp.sum(ordered.valid) - n, 0)
    pad = max(n - ordered.num_slots, 0)
    kept = jax.tree.map(lambda x: jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1))[:n], ordered)
    scene = Scene(actors=kept, ego=rotate_actors(ego, theta), complete=overflow == 0)
    return crop_map(canvas, theta, cfg), scene, overflow
