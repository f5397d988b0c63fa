"""Batches from a cache, in an order that is a pure function of (seed, step)."""

from __future__ import annotations

import jax
import numpy as np

from scenegen_jax.config import Config
from scenegen_jax.data.cache import ACTOR_FIELDS, Cache
from scenegen_jax.scene import Actors
from scenegen_jax.train.step import Batch


def batch_indices(num_scenes: int, batch_size: int, seed: int, step: int) -> np.ndarray:
    """Scene indices of batch `step`: consecutive slices of per-epoch permutations."""
    pos = step * batch_size + np.arange(batch_size)
    epochs, offsets = np.divmod(pos, num_scenes)
    out = np.empty(batch_size, np.int64)
    for epoch in np.unique(epochs):
        perm = np.random.default_rng([seed, int(epoch)]).permutation(num_scenes)
        sel = epochs == epoch
        out[sel] = perm[offsets[sel]]
    return out


def gather_batch(cache: Cache, indices: np.ndarray, cfg: Config) -> Batch:
    """Host arrays of the scenes `indices` (canvas kept in float16)."""
    indices = np.asarray(indices)
    actors = Actors(**{k: np.asarray(getattr(cache.actors, k)[indices]) for k in ACTOR_FIELDS})
    n = len(indices)
    ego = Actors(
        cls=np.zeros(n, np.int32),
        position=np.zeros((n, 2), np.float32),
        size=cache.ego_size[indices],
        heading=np.zeros(n, np.float32),
        velocity=cache.ego_velocity[indices],
        valid=np.ones(n, bool),
    )
    canvas = np.stack([np.asarray(cache.maps[i]) for i in indices])
    return Batch(canvas=canvas, actors=actors, ego=ego)


def to_device(batch: Batch, sharding=None) -> Batch:
    """Puts a host batch on device(s), sharded along the batch axis if `sharding` is given."""
    return jax.tree.map(lambda x: jax.device_put(x, sharding), batch)
