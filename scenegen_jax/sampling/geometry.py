"""Oriented-box geometry for collision rejection (jnp; unbatched, vmap outside).

A box is (centre [2] m, size [2] = (width, length) m, heading rad); its length lies along the
heading, as everywhere in the library (`scenegen_jax.raster.actors`, `viz.render`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.scene import PEDESTRIAN, Actors


def box_axes(heading: jnp.ndarray) -> jnp.ndarray:
    """[2, 2] unit vectors of a box: row 0 along its length (heading), row 1 along its width."""
    c, s = jnp.cos(heading), jnp.sin(heading)
    return jnp.stack([jnp.stack([c, s]), jnp.stack([-s, c])])


def boxes_overlap(
    center_a: jnp.ndarray,
    size_a: jnp.ndarray,
    heading_a: jnp.ndarray,
    center_b: jnp.ndarray,
    size_b: jnp.ndarray,
    heading_b: jnp.ndarray,
) -> jnp.ndarray:
    """Whether two oriented boxes overlap with positive area (separating-axis test).

    Two convex polygons are disjoint iff their projections onto some edge normal are disjoint;
    a rectangle has two edge directions, so four axes decide. Boxes that only touch (a
    shared edge or corner) do not overlap.

    Args:
      center_a, center_b: [2] (x, y), m.
      size_a, size_b: [2] (width, length), m.
      heading_a, heading_b: [] rad.

    Returns:
      bool [].
    """
    axes_a, axes_b = box_axes(heading_a), box_axes(heading_b)
    axes = jnp.concatenate([axes_a, axes_b])  # [4, 2] candidate separating axes
    half_a = jnp.stack([size_a[1], size_a[0]]) / 2  # half extents along (length, width) axes
    half_b = jnp.stack([size_b[1], size_b[0]]) / 2
    # Projected radius of each box on each axis: sum_j half_j |axis . box_axis_j|.
    radius_a = jnp.abs(axes @ axes_a.T) @ half_a
    radius_b = jnp.abs(axes @ axes_b.T) @ half_b
    distance = jnp.abs(axes @ (center_b - center_a))
    return jnp.logical_not(jnp.any(distance >= radius_a + radius_b))


def collides(candidate: Actors, actors: Actors, ego: Actors) -> jnp.ndarray:
    """Whether `candidate`'s box overlaps the ego or any valid non-pedestrian box of `actors`.

    Only vehicles and bicyclists are tested (pedestrians are points and neither reject nor
    are rejected); the caller decides which candidates are subject to rejection.

    Args:
      candidate: one actor (no leading axis).
      actors: [N] actors placed so far (invalid slots ignored).
      ego: the ego (no leading axis).

    Returns:
      bool [].
    """

    def hit(other: Actors) -> jnp.ndarray:
        return boxes_overlap(
            candidate.position, candidate.size, candidate.heading,
            other.position, other.size, other.heading,
        )

    boxed = actors.valid & (actors.cls != PEDESTRIAN)
    return hit(ego) | jnp.any(jax.vmap(hit)(actors) & boxed)
