"""Synthetic scenes of a fixed size for timing (shapes, not learning, set the cost)."""

from __future__ import annotations

import jax
import numpy as np

from scenegen_jax.likelihood.batch import Batch
from scenegen_jax.scene import Actors, canonical_order, make_ego


def synthetic_batch(cfg, b: int, n_actors: int, seed: int = 0) -> Batch:
    """b unrotated scenes with n_actors random actors each and a random binary map."""
    rng = np.random.default_rng(seed)
    h = cfg.grid.grid_size
    maps = (rng.random((b, h, h, len(cfg.grid.map_channels))) < 0.3).astype(np.float32)
    slots = max(cfg.grid.max_actors, n_actors)
    half = cfg.grid.region_m / 2 - 1
    actors = []
    for _ in range(b):
        a = Actors(
            cls=rng.integers(0, 3, slots).astype(np.int32),
            position=rng.uniform(-half, half, (slots, 2)).astype(np.float32),
            size=np.tile(np.float32([1.9, 4.6]), (slots, 1)),
            heading=rng.uniform(0, 2 * np.pi, slots).astype(np.float32),
            velocity=rng.normal(0, 3, (slots, 2)).astype(np.float32),
            valid=np.arange(slots) < n_actors,
        )
        actors.append(jax.tree.map(np.asarray, canonical_order(a, cfg.grid)))
    stacked = jax.tree.map(lambda *x: np.stack(x), *actors)
    egos = jax.tree.map(lambda *x: np.stack(x), *[make_ego(cfg.grid.ego_size_m)] * b)
    return Batch(maps=maps, thetas=np.zeros(b, np.float32), actors=stacked, ego=egos)
