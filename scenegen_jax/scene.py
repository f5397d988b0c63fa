"""Scene and actor PyTrees, the raster grid convention, canonical order and validation.

Frame: ego-centred, metres, ego at the origin heading along +x, y to the ego's left.

Raster convention (used by every raster in the library): an H x W grid covers the square
[-R/2, R/2) x [-R/2, R/2) with R = H * m_per_px. Row r grows towards -y (image "down") and
column c grows towards +x (image "right"), so pixel (r, c) has its centre at
    x = (c + 0.5) * m_per_px - R/2,    y = R/2 - (r + 0.5) * m_per_px.
The location bin of an actor is the pixel holding its centre, flattened row-major
(bin = r * W + c); canonical order is ascending bin ("left to right, top to bottom").
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from scenegen_jax.config import GridConfig

VEHICLE, PEDESTRIAN, BICYCLIST, STOP = 0, 1, 2, 3
NUM_CLASSES = 3
CLASS_NAMES = ("vehicle", "pedestrian", "bicyclist")


@struct.dataclass
class Actors:
    """A padded set of actors (leading axis N), or one actor (no leading axis).

    Attributes:
      cls: int32 [N], VEHICLE / PEDESTRIAN / BICYCLIST.
      position: float32 [N, 2], centre (x, y), m.
      size: float32 [N, 2], box (width, length), m (unused for pedestrians).
      heading: float32 [N], rad in [0, 2pi) (unused for pedestrians).
      velocity: float32 [N, 2], (vx, vy) over the ground, m/s.
      valid: bool [N], slot holds an actor.
      size_measured: bool [N], the source measured the box size; None: every box was. An
        unmeasured size is a placeholder to draw the actor with: the likelihood leaves its
        box term out, so nothing learns it or is scored on it.
    """

    cls: jnp.ndarray
    position: jnp.ndarray
    size: jnp.ndarray
    heading: jnp.ndarray
    velocity: jnp.ndarray
    valid: jnp.ndarray
    size_measured: jnp.ndarray | None = None

    @property
    def num_slots(self) -> int:
        return self.cls.shape[-1]

    def validate(self, where: str = "actors") -> None:
        """Raises ValueError naming the field when valid slots hold impossible values."""
        valid = np.asarray(self.valid, bool)
        cls = np.asarray(self.cls)
        if np.any((cls[valid] < 0) | (cls[valid] >= NUM_CLASSES)):
            raise ValueError(f"{where}.cls: class ids must be in [0, {NUM_CLASSES})")
        for name in ("position", "size", "heading", "velocity"):
            values = np.asarray(getattr(self, name))[valid]
            if not np.all(np.isfinite(values)):
                raise ValueError(f"{where}.{name}: NaN or inf in a valid slot")
        boxed = valid & (cls != PEDESTRIAN)
        if np.any(np.asarray(self.size)[boxed] <= 0):
            raise ValueError(f"{where}.size: box width and length must be positive")
        heading = np.asarray(self.heading)[valid]
        if np.any((heading < 0) | (heading >= 2 * np.pi + 1e-5)):
            raise ValueError(f"{where}.heading: must lie in [0, 2pi)")


@struct.dataclass
class Scene:
    """One scene: the ego and a padded, canonically ordered set of other actors.

    Attributes:
      actors: Actors with N = config.max_actors slots, valid slots first in canonical order.
      ego: Actors without a leading axis (class VEHICLE).
      complete: bool (batched: [B]): the slots hold every actor of the region. False when the
        region held more than N actors and those after the N-th in canonical order were
        dropped (`raster.transform.scene_from_cached`): the likelihood is then that of the
        N kept actors, without the stop token, since the next actor is not the end.
    """

    actors: Actors
    ego: Actors
    complete: jnp.ndarray | bool = True

    def validate(self, grid: GridConfig, where: str = "scene") -> None:
        """Checks values, region and canonical order; raises ValueError naming the field."""
        self.actors.validate(f"{where}.actors")
        self.ego.validate(f"{where}.ego")
        valid = np.asarray(self.actors.valid, bool)
        n = int(valid.sum())
        if not np.all(valid[:n]):
            raise ValueError(f"{where}.actors.valid: valid slots must come first")
        pos = np.asarray(self.actors.position)[:n]
        if not np.all(np.asarray(in_region(pos, grid))):
            raise ValueError(f"{where}.actors.position: actor outside the {grid.region_m} m region")
        bins = np.asarray(bin_index(pos, grid))
        if np.any(np.diff(bins) < 0):
            raise ValueError(f"{where}.actors: not in canonical (row-major bin) order")


def empty_actors(n: int) -> Actors:
    """n invalid actor slots (numpy)."""
    return Actors(
        cls=np.zeros((n,), np.int32),
        position=np.zeros((n, 2), np.float32),
        size=np.zeros((n, 2), np.float32),
        heading=np.zeros((n,), np.float32),
        velocity=np.zeros((n, 2), np.float32),
        valid=np.zeros((n,), bool),
    )


def make_ego(size, velocity=(0.0, 0.0), heading: float = 0.0) -> Actors:
    """The ego at the origin (class VEHICLE, valid), one or a batch: size [..., 2] (width,
    length) m, velocity [..., 2] m/s broadcast to it, heading rad."""
    size = np.asarray(size, np.float32)
    lead = size.shape[:-1]
    return Actors(
        cls=np.full(lead, VEHICLE, np.int32),
        position=np.zeros((*lead, 2), np.float32),
        size=size,
        heading=np.full(lead, heading, np.float32),
        velocity=np.broadcast_to(np.asarray(velocity, np.float32), (*lead, 2)).copy(),
        valid=np.ones(lead, bool),
    )


def pixel_of(position, grid: GridConfig):
    """(row, col) int32 of positions [..., 2] in m; may fall outside the grid."""
    half = grid.region_m / 2
    col = jnp.floor((position[..., 0] + half) / grid.m_per_px)
    row = jnp.floor((half - position[..., 1]) / grid.m_per_px)
    return row.astype(jnp.int32), col.astype(jnp.int32)


def pixel_centers(grid: GridConfig, size: int | None = None) -> np.ndarray:
    """[S, S, 2] (x, y) centres of an S x S grid at grid.m_per_px around the ego (S = H default)."""
    s = grid.grid_size if size is None else size
    half = s * grid.m_per_px / 2
    coords = (np.arange(s) + 0.5) * grid.m_per_px - half
    xx, yy = np.meshgrid(coords, -coords)
    return np.stack([xx, yy], axis=-1).astype(np.float32)


def in_region(position, grid: GridConfig):
    """bool [...]: position [..., 2] lies inside the square region of interest (float32, as
    on the device; a NumPy input gives a NumPy result without a compiled call)."""
    half = grid.region_m / 2
    if isinstance(position, np.ndarray):
        position = position.astype(np.float32, copy=False)
        return np.all((position >= -half) & (position < half), axis=-1)
    return jnp.all((position >= -half) & (position < half), axis=-1)


def bin_index(position, grid: GridConfig):
    """Row-major location bin of positions [..., 2]; clipped into the grid."""
    row, col = pixel_of(position, grid)
    h = grid.grid_size
    return jnp.clip(row, 0, h - 1) * h + jnp.clip(col, 0, h - 1)


def bin_center(index, grid: GridConfig):
    """(x, y) m of the centre of row-major bin `index`."""
    h = grid.grid_size
    row, col = index // h, index % h
    half = grid.region_m / 2
    x = (col + 0.5) * grid.m_per_px - half
    y = half - (row + 0.5) * grid.m_per_px
    return jnp.stack([x, y], axis=-1)


def canonical_order(actors: Actors, grid: GridConfig) -> Actors:
    """Sorts actors by ascending row-major bin, invalid slots last (stable; jit-friendly)."""
    n_bins = grid.grid_size * grid.grid_size
    key = jnp.where(actors.valid, bin_index(actors.position, grid), n_bins)
    order = jnp.argsort(key, stable=True)
    return tree_take(actors, order)


def tree_take(tree, index):
    """Gathers `index` along the leading axis of every leaf of `tree` (e.g. actor slots of
    `Actors`; jax or numpy leaves)."""
    return jax.tree.map(lambda x: x[index], tree)


def wrap_angle(theta):
    """Angle (rad) in [0, 2pi); NaN stays NaN.

    A jax array in (traced or not) gives a jax array out; anything else a numpy array of
    theta's float dtype (float64 for integers and Python numbers), so float64 host data keeps
    its precision.
    """
    if isinstance(theta, jax.Array):
        xp = jnp
        if not jnp.issubdtype(theta.dtype, jnp.floating):
            theta = theta.astype(float)
    else:
        xp = np
        theta = np.asarray(theta)
        if not np.issubdtype(theta.dtype, np.floating):
            theta = theta.astype(np.float64)
    two_pi = xp.asarray(2 * np.pi, theta.dtype)
    wrapped = xp.mod(theta, two_pi)
    # The modulo rounds a tiny negative angle up to exactly 2pi (float32: -1e-8 -> 2pi) and
    # gives -0.0 for -2pi in jax; both are 0.
    return xp.where((wrapped >= two_pi) | (wrapped == 0), xp.zeros((), theta.dtype), wrapped)
