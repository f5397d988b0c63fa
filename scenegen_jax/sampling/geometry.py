"""Collision rejection while sampling (jnp; unbatched, vmap outside), with the overlap test of
`scenegen_jax.geometry.boxes_overlap`.

A box is (centre [2] m, size [2] = (width, length) m, heading rad); its length lies along the
heading, as everywhere in the library (`scenegen_jax.raster.actors`, `viz.render`).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from scenegen_jax.geometry import boxes_overlap
from scenegen_jax.scene import PEDESTRIAN, Actors


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
