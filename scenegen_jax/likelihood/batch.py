"""A batch of cached scenes as the unroll reads it: actors gathered on the host, maps drawn
at the batch's rotations (`raster.jax_map`), checked, put on device(s)."""

from __future__ import annotations

import functools
import itertools
from typing import Any, NamedTuple

import jax
import numpy as np

from scenegen_jax.config import GridConfig
from scenegen_jax.data.cache import Cache
from scenegen_jax.data.cache_layout import ACTOR_FIELDS
from scenegen_jax.data.union import CacheUnion
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.raster.transform import scene_from_cached
from scenegen_jax.scene import Actors


class Batch(NamedTuple):
    """A batch of cached scenes, each rotated by its theta about the ego.

    maps: float32 [B, H, W, C] the grid's map channels, drawn at the rotations;
    thetas: float32 [B] rad; actors: Actors [B, A] as cached (unrotated); ego: Actors [B].
    """

    maps: Any
    thetas: Any
    actors: Actors
    ego: Actors


def gather_batch(cache: Cache | CacheUnion, indices: np.ndarray, grid: GridConfig,
                 thetas=None) -> Batch:
    """The scenes `indices` rotated by `thetas` [B] rad (default 0): actors as host arrays,
    maps drawn on the default device from the cached vector maps."""
    indices = np.asarray(indices)
    thetas = np.zeros(len(indices), np.float32) if thetas is None else np.asarray(
        thetas, np.float32)
    actors = Actors(**{k: np.asarray(getattr(cache.actors, k)[indices]) for k in ACTOR_FIELDS})
    maps = draw_maps([cache.map_store.frame_map(int(i)) for i in indices], thetas, grid)
    return Batch(maps=maps, thetas=thetas, actors=actors, ego=cache.ego(indices))


def grid_scene(cache: Cache | CacheUnion, index: int, grid: GridConfig, theta: float = 0.0):
    """(map [H, W, C], Scene) of one cached scene rotated by theta, as numpy."""
    if not 0 <= index < len(cache):
        raise IndexError(f"{cache.path}: scene index {index} out of range [0, {len(cache)})")
    maps, scene = batch_scenes(gather_batch(cache, np.array([index]), grid, [theta]), grid)
    return np.asarray(maps[0]), jax.tree.map(lambda x: np.asarray(x[0]), scene)


def local_rows(sharding, batch_size: int) -> slice:
    """The rows of a global batch of `batch_size` sharded by `sharding` (along its first
    axis) that this process's devices hold: all of them with one process. A process loads
    only these (`gather_batch`) and `to_device` assembles the global batch from every
    process's part."""
    devices = len(sharding.device_set)
    if batch_size % devices:
        raise ValueError(f"batch_size {batch_size} is not divisible by {devices} devices")
    spans = sorted(
        idx[0].indices(batch_size)[:2]
        for idx in sharding.addressable_devices_indices_map((batch_size,)).values()
    )
    lo, hi = spans[0][0], spans[-1][1]
    if any(a[1] != b[0] and a != b for a, b in itertools.pairwise(spans)):
        raise ValueError(f"this process's rows of the batch are not contiguous: {spans}")
    return slice(lo, hi)


def to_device(batch: Batch, sharding=None, batch_size: int | None = None) -> Batch:
    """Puts a host batch on device(s), sharded along the batch axis if `sharding` is given.

    With several processes, `batch` holds this process's `local_rows` of a global batch of
    `batch_size` scenes, and every process calls this with its own part.
    """
    if sharding is None or sharding.is_fully_addressable:
        return jax.tree.map(lambda x: jax.device_put(x, sharding), batch)
    return jax.tree.map(
        lambda x: jax.make_array_from_process_local_data(
            sharding, np.asarray(x), (batch_size,) + x.shape[1:]
        ),
        batch,
    )


def check_batch(batch: Batch, scene_ids: list[str]) -> None:
    """Host-side guard: raises ValueError naming the scene and field on NaN/inf input. The
    maps are not read back: they are drawn from map points the cache checked finite when it
    was loaded, and reading them would wait for the device."""
    fields = {
        "actors.position": batch.actors.position,
        "actors.size": batch.actors.size,
        "actors.heading": batch.actors.heading,
        "actors.velocity": batch.actors.velocity,
        "ego.velocity": batch.ego.velocity,
        "ego.size": batch.ego.size,
    }
    for name, value in fields.items():
        value = np.asarray(value)
        bad = ~np.isfinite(value.reshape(value.shape[0], -1)).all(axis=1)
        if bad.any():
            i = int(np.flatnonzero(bad)[0])
            raise ValueError(f"scene {scene_ids[i]}: field {name}: NaN or inf in the batch")


@functools.partial(jax.jit, static_argnames="grid")
def batch_scenes(batch: Batch, grid: GridConfig):
    """(maps [B,H,W,C], scenes): each cached scene's actors rotated by its theta and kept to
    the grid's region (`scene_from_cached`).

    Jitted: called outside a compiled program, its operations would each compile on their
    own."""
    scene, _ = jax.vmap(lambda a, e, t: scene_from_cached(a, e, t, grid))(
        batch.actors, batch.ego, batch.thetas
    )
    return batch.maps, scene
