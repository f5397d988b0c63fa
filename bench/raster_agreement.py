"""Per-channel agreement of the map rasters drawn where the model runs (`raster.jax_map`)
with the shapely reference (`raster.map`), over every frame of a cache: the share of pixels
equal (binary channels) or within 0.05 (directions), unrotated or at a random rotation per
frame, at the cache's grid.

    .venv/bin/python bench/raster_agreement.py CACHE [--rotate]
"""

from __future__ import annotations

import argparse
import json

import numpy as np

from scenegen_jax.config import ALL_LAYER_GROUPS, Config
from scenegen_jax.data.cache import load_cache
from scenegen_jax.raster.jax_map import draw_maps
from scenegen_jax.raster.map import ALL_MAP_CHANNELS, rasterize_map
from scenegen_jax.vector_map import rotation_matrix

BATCH = 16


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("cache")
    p.add_argument("--rotate", action="store_true", help="a random rotation per frame")
    args = p.parse_args()
    cache = load_cache(args.cache)
    grid = Config().replace(grid_size=int(cache.meta["grid_size"]),
                            m_per_px=float(cache.meta["m_per_px"]),
                            map_layers=ALL_LAYER_GROUPS).grid
    rng = np.random.default_rng(0)
    hits, pixels = np.zeros(len(ALL_MAP_CHANNELS)), 0
    for lo in range(0, len(cache), BATCH):
        maps = [cache.map_store.frame_map(i) for i in range(lo, min(lo + BATCH, len(cache)))]
        thetas = rng.uniform(0, 2 * np.pi, len(maps)) if args.rotate else np.zeros(len(maps))
        got = np.asarray(draw_maps(maps, thetas, grid, channels=ALL_MAP_CHANNELS))
        for drawn, vmap, theta in zip(got, maps, thetas, strict=True):
            want = rasterize_map(vmap.transform(rotation_matrix(theta), np.zeros(2)),
                                 grid.grid_size, grid.m_per_px)
            hits += (np.abs(drawn - want) <= 0.05).sum(axis=(0, 1))
            pixels += grid.grid_size**2
    share = hits / pixels
    print(json.dumps({"cache": args.cache, "frames": len(cache), "rotate": args.rotate,
                      "least": round(float(share.min()), 4),
                      "by_channel": {c: round(float(s), 4)
                                     for c, s in zip(ALL_MAP_CHANNELS, share, strict=True)}}))


if __name__ == "__main__":
    main()
