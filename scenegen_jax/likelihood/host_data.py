"""Whole caches as host arrays, for the small models beside SceneGen (the forecaster of the
Features MMD, LayoutVAE): every scene's map raster at rotation 0 (`cache_maps`) and
LayoutVAE's per-scene sequences (`layout_data`)."""

from __future__ import annotations

import sys

import numpy as np
from tqdm import tqdm

from scenegen_jax.config import GridConfig
from scenegen_jax.data.cache import cached_actors
from scenegen_jax.model.layout_vae import layout_arrays
from scenegen_jax.raster.jax_map import draw_maps

# Scenes drawn per compiled call.
DRAW_CHUNK = 32


def cache_maps(cache, grid: GridConfig, indices=None, progress: bool = True,
               desc: str = "draw maps") -> np.ndarray:
    """float32 [S, G, G, C] the map rasters of the scenes `indices` (default: all) of a
    cache or `CacheUnion`, at rotation 0 and `grid`."""
    indices = np.arange(len(cache)) if indices is None else np.asarray(indices)
    out = []
    for start in tqdm(range(0, len(indices), DRAW_CHUNK), desc=desc, unit="chunk",
                      file=sys.stderr, disable=not progress):
        idx = indices[start : start + DRAW_CHUNK]
        maps = draw_maps([cache.map_store.frame_map(int(i)) for i in idx],
                         np.zeros(len(idx), np.float32), grid)
        out.append(np.asarray(maps))
    size = grid.grid_size
    return (np.concatenate(out) if out
            else np.zeros((0, size, size, len(grid.map_channels)), np.float32))


def layout_data(cache, grid: GridConfig, indices=None, progress: bool = True,
                desc: str = "draw maps") -> dict:
    """LayoutVAE's arrays of the scenes `indices` (default: all): `layout_arrays` of each,
    stacked, with the maps (`cache_maps`) and the egos' velocities."""
    indices = np.arange(len(cache)) if indices is None else np.asarray(indices)
    rows = [layout_arrays(cached_actors(cache, int(i)), grid) for i in indices]
    out = {k: np.stack([r[k] for r in rows]) for k in rows[0]} if rows else {}
    out["maps"] = cache_maps(cache, grid, indices, progress, desc)
    out["ego_velocity"] = np.asarray(cache.ego_velocity[indices], np.float32)
    return out
