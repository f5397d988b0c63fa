"""A batch of cached scenes as the unroll reads it: gathered on the host, checked, put on
device(s), rotated and cropped."""

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
from scenegen_jax.raster.transform import scene_from_cached
from scenegen_jax.scene import Actors


class Batch(NamedTuple):
    """A batch as read from the cache (before rotation and cropping).

    canvas: float16 [B, S, S, C_all] map canvases; actors: Actors [B, A]; ego: Actors [B].
    """

    canvas: Any
    actors: Actors
    ego: Actors


def gather_batch(cache: Cache | CacheUnion, indices: np.ndarray, grid: GridConfig) -> Batch:
    """Host arrays of the scenes `indices` (canvas kept in float16)."""
    indices = np.asarray(indices)
    actors = Actors(**{k: np.asarray(getattr(cache.actors, k)[indices]) for k in ACTOR_FIELDS})
    canvas = np.stack([np.asarray(cache.maps[i]) for i in indices])
    return Batch(canvas=canvas, actors=actors, ego=cache.ego(indices))


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
            sharding, x, (batch_size,) + x.shape[1:]
        ),
        batch,
    )


def check_batch(batch: Batch, scene_ids: list[str]) -> None:
    """Host-side guard: raises ValueError naming the scene and field on NaN/inf input."""
    fields = {
        "canvas": batch.canvas,
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
def crop_batch(batch: Batch, thetas, grid: GridConfig):
    """Rotates each cached scene by thetas [B] rad and crops it: (maps [B,H,W,C], scene).

    Jitted: called outside a compiled program, its operations would each compile on their
    own."""
    maps, scene, _ = jax.vmap(lambda c, a, e, t: scene_from_cached(c, a, e, t, grid))(
        batch.canvas, batch.actors, batch.ego, thetas
    )
    return maps, scene
