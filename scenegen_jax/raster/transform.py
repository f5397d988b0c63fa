"""Rigid transforms of a cached scene (jit side): rotation about the ego and crop to the grid.

The cache stores each scene's map on a canvas larger than the grid (`GridConfig.canvas_size`) and
the actors within the canvas, so any rotation about the ego can be cropped to the H x W grid
without missing map or actors.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.config import GridConfig
from scenegen_jax.raster.map import VECTOR_CHANNELS, select_channels
from scenegen_jax.scene import Actors, Scene, canonical_order, in_region, pixel_centers, wrap_angle


def rotate_vectors(v, theta):
    """Rotates vectors [..., 2] counter-clockwise by theta rad."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def crop_map(canvas, theta, grid: GridConfig):
    """The H x W grid of a map canvas rotated by theta about the ego (bilinear).

    Args:
      canvas: [S, S, len(ALL_MAP_CHANNELS)] map canvas at grid.m_per_px, S = grid.canvas_size.
      theta: rotation, rad (counter-clockwise; 0 is a plain centre crop).
      grid: the grid (`GridConfig`: size, resolution, map layers).
    Returns:
      [H, W, len(grid.map_channels)] float32 map channels.
    """
    if not grid.map_channels:
        return jnp.zeros((grid.grid_size, grid.grid_size, 0), jnp.float32)
    s = canvas.shape[0]
    centers = jnp.asarray(pixel_centers(grid))  # [H, W, 2] (x, y) in the rotated frame
    src = rotate_vectors(centers, -theta)  # where each output pixel comes from
    half = s * grid.m_per_px / 2
    col = (src[..., 0] + half) / grid.m_per_px - 0.5
    row = (half - src[..., 1]) / grid.m_per_px - 0.5
    coords = jnp.stack([row.ravel(), col.ravel()])

    def sample(channel):
        return jax.scipy.ndimage.map_coordinates(channel, coords, order=1, mode="constant")

    channels = select_channels(canvas, grid).astype(jnp.float32)  # only the config's
    out = jax.vmap(sample, in_axes=-1, out_axes=-1)(channels)
    out = out.reshape(grid.grid_size, grid.grid_size, -1)
    # Direction vectors (lane orientation, nearest lane) turn with the frame.
    for pair in VECTOR_CHANNELS:
        if pair[0] in grid.map_channels:
            ic, is_ = (grid.map_channels.index(c) for c in pair)
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


def scene_from_cached(canvas, actors: Actors, ego: Actors, theta, grid: GridConfig):
    """Rotates a cached scene by theta and crops it to the grid.

    Args:
      canvas: [S, S, C_all] map canvas.
      actors: cached actors (any number of slots >= grid.max_actors), unrotated.
      ego: unbatched ego.
      theta: rotation about the ego, rad.
      grid: the grid (`GridConfig`).
    Returns:
      (map [H, W, C], Scene with grid.max_actors slots in canonical order, overflow count)
      where overflow counts in-region actors beyond grid.max_actors (dropped; the Scene is
      then not `complete`).
    """
    rotated = rotate_actors(actors, theta)
    rotated = rotated.replace(valid=rotated.valid & in_region(rotated.position, grid))
    ordered = canonical_order(rotated, grid)
    n = grid.max_actors
    overflow = jnp.maximum(jnp.sum(ordered.valid) - n, 0)
    pad = max(n - ordered.num_slots, 0)
    kept = jax.tree.map(lambda x: jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1))[:n], ordered)
    scene = Scene(actors=kept, ego=rotate_actors(ego, theta), complete=overflow == 0)
    return crop_map(canvas, theta, grid), scene, overflow
