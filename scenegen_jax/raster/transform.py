"""Rigid transforms of a cached scene's actors (jit side): rotation about the ego and the
grid's region.

The cache stores the actors within the disc that holds the grid under every rotation
(`cache_layout.canvas_radius`), so any rotation about the ego keeps every actor the rotated
grid covers; the map is drawn at the same rotation (`raster.jax_map`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.config import GridConfig
from scenegen_jax.scene import Actors, Scene, canonical_order, in_region, wrap_angle


def rotate_vectors(v, theta):
    """Rotates vectors [..., 2] counter-clockwise by theta rad."""
    c, s = jnp.cos(theta), jnp.sin(theta)
    return jnp.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]], -1)


def rotate_actors(actors: Actors, theta) -> Actors:
    """Actors rotated by theta about the ego (positions, headings, velocities)."""
    return actors.replace(
        position=rotate_vectors(actors.position, theta),
        heading=wrap_angle(actors.heading + theta),
        velocity=rotate_vectors(actors.velocity, theta),
    )


def scene_from_cached(actors: Actors, ego: Actors, theta, grid: GridConfig):
    """A cached scene's actors rotated by theta and kept to the grid's region.

    Args:
      actors: cached actors (any number of slots >= grid.max_actors), unrotated.
      ego: unbatched ego.
      theta: rotation about the ego, rad.
      grid: the grid (`GridConfig`).
    Returns:
      (Scene with grid.max_actors slots in canonical order, overflow count) where overflow
      counts in-region actors beyond grid.max_actors (dropped; the Scene is then not
      `complete`).
    """
    rotated = rotate_actors(actors, theta)
    rotated = rotated.replace(valid=rotated.valid & in_region(rotated.position, grid))
    ordered = canonical_order(rotated, grid)
    n = grid.max_actors
    overflow = jnp.maximum(jnp.sum(ordered.valid) - n, 0)
    pad = max(n - ordered.num_slots, 0)
    kept = jax.tree.map(lambda x: jnp.pad(x, [(0, pad)] + [(0, 0)] * (x.ndim - 1))[:n], ordered)
    return Scene(actors=kept, ego=rotate_actors(ego, theta), complete=overflow == 0), overflow
