"""Oriented-box geometry in numpy (host side: baselines, renders, tests).

The jit-side separating-axis test used while sampling is `scenegen_jax.sampling.geometry`.
"""

from __future__ import annotations

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


def boxes_overlap(
    center: np.ndarray,
    size: np.ndarray,
    heading: float,
    others_center: np.ndarray,
    others_size: np.ndarray,
    others_heading: np.ndarray,
) -> np.ndarray:
    """bool [M]: one box overlaps each of M boxes (separating-axis test; touching is not)."""
    a = box_corners(center, size, heading)  # [4, 2]
    b = box_corners(others_center, others_size, others_heading)  # [M, 4, 2]
    if b.shape[0] == 0:
        return np.zeros((0,), bool)
    a = np.broadcast_to(a, b.shape)
    axes = np.concatenate([a[:, 1:3] - a[:, 0:2], b[:, 1:3] - b[:, 0:2]], axis=1)  # [M, 4, 2]
    proj_a = np.einsum("mpd,mad->mpa", a, axes)  # [M, 4 corners, 4 axes]
    proj_b = np.einsum("mpd,mad->mpa", b, axes)
    separated = (proj_a.max(1) <= proj_b.min(1)) | (proj_b.max(1) <= proj_a.min(1))
    return ~np.any(separated, axis=-1)
