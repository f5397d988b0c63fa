"""A batch of cached scenes as the unroll reads it: gathered on the host, checked, put on
device(s), rotated and cropped."""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.cache import ACTOR_FIELDS, Cache
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


def gather_batch(cache: Cache | CacheUnion, indices: np.ndarray, cfg: Config) -> Batch:
    """Host arrays of the scenes `indices` (canvas kept in float16)."""
    indices = np.asarray(indices)
    actors = Actors(**{k: np.asarray(getattr(cache.actors, k)[indices]) for k in ACTOR_FIELDS})
    canvas = np.stack([np.asarray(cache.maps[i]) for i in indices])
    return Batch(canvas=canvas, actors=actors, ego=cache.ego(indices))


def to_device(batch: Batch, sharding=None) -> Batch:
    """Puts a host batch on device(s), sharded along the batch axis if `sharding` is given."""
    return jax.tree.map(lambda x: jax.device_put(x, sharding), batch)


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


def crop_batch(batch: Batch, thetas, cfg: Config):
    """Rotates each cached scene by thetas [B] rad and crops it: (maps [B,H,W,C], scene)."""
    maps, scene, _ = jax.vmap(lambda c, a, e, t: scene_from_cached(c, a, e, t, cfg))(
        batch.canvas, batch.actors, batch.ego, thetas
    )
    return maps, scene
