"""Oriented-box geometry: corners (numpy, for renders) and the separating-axis overlap test,
written once for numpy (host: baselines, given actors) and jax (the sampler, under jit)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def box_corners(center: np.ndarray, size: np.ndarray, heading: np.ndarray) -> np.ndarray:
    """[..., 4, 2] corners of oriented boxes; size (width, length), length along heading."""
    center, size, heading = np.asarray(center), np.asarray(size), np.asarray(heading)
    c, s = np.cos(heading)[..., None], np.sin(heading)[..., None]
    along = np.concatenate([c, s], -1) * (size[..., 1:2] / 2)  # [..., 2]
    across = np.concatenate([-s, c], -1) * (size[..., 0:1] / 2)
    signs = np.array([[1, 1], [1, -1], [-1, -1], [-1, 1]], np.float64)
    return (
        center[..., None, :]
        + signs[:, :1] * along[..., None, :]
        + signs[:, 1:] * across[..., None, :]
    )


def _array_module(*xs):
    """jax.numpy if any input is a jax array (or a tracer under jit), else numpy."""
    return jnp if any(isinstance(x, jax.Array) for x in xs) else np


def box_axes(heading):
    """[..., 2, 2] unit vectors of boxes: row 0 along the length (heading), row 1 across."""
    xp = _array_module(heading)
    c, s = xp.cos(heading), xp.sin(heading)
    return xp.stack([xp.stack([c, s], -1), xp.stack([-s, c], -1)], -2)


def boxes_overlap(center_a, size_a, heading_a, center_b, size_b, heading_b):
    """bool [...]: whether boxes a and b overlap with positive area (separating-axis test),
    broadcast over leading axes (e.g. one box against M boxes). numpy in, numpy out; jax
    arrays (and tracers under jit) in, jax out.

    Two convex polygons are disjoint iff their projections onto some edge normal are
    disjoint; a rectangle has two edge directions, so four axes decide. Boxes that only touch
    (a shared edge or corner) do not overlap.

    Args:
      center_a, center_b: [..., 2] (x, y), m.
      size_a, size_b: [..., 2] (width, length), m.
      heading_a, heading_b: [...] rad.
    """
    xp = _array_module(center_a, size_a, heading_a, center_b, size_b, heading_b)
    ha, hb = xp.broadcast_arrays(xp.asarray(heading_a), xp.asarray(heading_b))
    batch = ha.shape
    axes_a, axes_b = box_axes(ha), box_axes(hb)  # [..., 2, 2]
    axes = xp.concatenate([axes_a, axes_b], axis=-2)  # [..., 4, 2] candidate separating axes

    def radius(axes_box, size):  # projected half extent of a box on each axis: [..., 4]
        half = xp.broadcast_to(xp.flip(xp.asarray(size), -1) / 2, (*batch, 2))  # (len, wid)
        return xp.sum(xp.abs(axes @ xp.swapaxes(axes_box, -1, -2)) * half[..., None, :], -1)

    offset = xp.broadcast_to(xp.asarray(center_b) - xp.asarray(center_a), (*batch, 2))
    distance = xp.abs(xp.sum(axes * offset[..., None, :], -1))
    return ~xp.any(distance >= radius(axes_a, size_a) + radius(axes_b, size_b), axis=-1)
